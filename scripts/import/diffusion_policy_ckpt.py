"""Converts a real-stanford/diffusion_policy `.ckpt` (a dill/torch pickle) to files the Rust
importer reads: `model.safetensors` (the policy's state_dict, EMA weights when the run used
EMA) and `config.json` (the run's resolved hydra config).

    python scripts/import/diffusion_policy_ckpt.py RUN/checkpoints/latest.ckpt --out DIR
    cargo xtask import diffusion-policy DIR --out teacher.safetensors

Needs torch, dill and omegaconf (the packages diffusion_policy itself uses); not
diffusion_policy's code. Unpickling runs code from the file: convert only checkpoints you trust.
"""

import argparse
import json
import os

import dill
import torch
from omegaconf import OmegaConf
from safetensors.torch import save_file


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("ckpt")
    ap.add_argument("--out", required=True, help="output directory")
    ap.add_argument("--weights", choices=["auto", "ema_model", "model"], default="auto")
    a = ap.parse_args()
    if not OmegaConf.has_resolver("eval"):
        OmegaConf.register_new_resolver("eval", eval, replace=True)
    with open(a.ckpt, "rb") as f:
        payload = torch.load(f, pickle_module=dill, map_location="cpu", weights_only=False)
    cfg = OmegaConf.to_container(payload["cfg"], resolve=True)
    sds = payload["state_dicts"]
    which = a.weights
    if which == "auto":
        use_ema = cfg.get("training", {}).get("use_ema", False)
        which = "ema_model" if use_ema and "ema_model" in sds else "model"
    sd = sds[which]
    tensors = {k: v.detach().float().contiguous() for k, v in sd.items() if torch.is_tensor(v) and v.is_floating_point()}
    os.makedirs(a.out, exist_ok=True)
    save_file(tensors, os.path.join(a.out, "model.safetensors"), metadata={"weights": which})
    with open(os.path.join(a.out, "config.json"), "w") as f:
        json.dump(cfg, f, indent=2, default=str)
    print(f"wrote {len(tensors)} tensors ({which}) and config.json to {a.out}")


if __name__ == "__main__":
    main()
