#!/usr/bin/env python3
"""Converts a BESO/D3IL run directory's PyTorch checkpoint for `cargo xtask import beso`.

    python scripts/import/beso_pth.py RUN_DIR [--weights model_state_dict.pth] [--scaler FILE]

RUN_DIR is what BESO/D3IL training leaves (the official VDD code loads its BESO teachers from
it): `model_state_dict.pth` (the GCDenoiser's state dict) beside hydra's `.hydra/config.yaml`
(or `config.yaml`). The script writes, into RUN_DIR:

* `model_state_dict.safetensors`: every tensor of the state dict, same names, float32;
* `scaler.json` (with --scaler): D3IL's `Scaler` statistics, which the checkpoint does not hold
  (D3IL recomputes them from the training data). FILE is an `.npz` or a torch-saved dict with
  `x_mean`, `x_std`, `y_mean`, `y_std`, `y_bounds` (2 x action_dim, in the scaled space) and
  optionally `scale_data` (default true). From a D3IL agent:

      s = agent.scaler
      np.savez("scaler.npz", x_mean=s.x_mean.cpu(), x_std=s.x_std.cpu(), y_mean=s.y_mean.cpu(),
               y_std=s.y_std.cpu(), y_bounds=s.y_bounds, scale_data=s.scale_data)

The Rust side then reads only safetensors, JSON and YAML. Needs torch, numpy and safetensors.
"""

import argparse
import json
import os
import sys

import numpy as np
import torch
from safetensors.torch import save_file


def load_scaler(path):
    if path.endswith(".npz"):
        data = dict(np.load(path))
    else:
        data = torch.load(path, map_location="cpu", weights_only=False)
    out = {}
    for key in ("x_mean", "x_std", "y_mean", "y_std", "y_bounds"):
        if key not in data:
            sys.exit(f"{path}: missing key `{key}`")
        out[key] = np.asarray(torch.as_tensor(data[key]).double()).tolist()
    out["scale_data"] = bool(np.asarray(data.get("scale_data", True)))
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("run_dir")
    ap.add_argument("--weights", default="model_state_dict.pth")
    ap.add_argument("--scaler", default=None)
    args = ap.parse_args()
    src = os.path.join(args.run_dir, args.weights)
    state = torch.load(src, map_location="cpu", weights_only=True)
    if not isinstance(state, dict):
        sys.exit(f"{src}: expected a state dict, got {type(state).__name__}")
    tensors = {}
    for name, value in state.items():
        if not torch.is_tensor(value):
            sys.exit(f"{src}: entry `{name}` is not a tensor")
        tensors[name] = value.detach().to(torch.float32).contiguous()
    out = os.path.join(args.run_dir, "model_state_dict.safetensors")
    save_file(tensors, out)
    print(f"wrote {out} ({len(tensors)} tensors)")
    if args.scaler:
        scaler_out = os.path.join(args.run_dir, "scaler.json")
        with open(scaler_out, "w") as f:
            json.dump(load_scaler(args.scaler), f)
        print(f"wrote {scaler_out}")


if __name__ == "__main__":
    main()
