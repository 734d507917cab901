#!/usr/bin/env python3
"""Fixtures for diffusion_policy's TransformerForDiffusion (vdd_torch::TransformerForDiffusion),
made with the package's own module.

    python scripts/import/dp_transformer_fixtures.py --dp PATH/TO/diffusion_policy \
        --out tests/fixtures/import

PATH/TO/diffusion_policy is a checkout of real-stanford/diffusion_policy (not committed); the
script imports diffusion_policy/model/diffusion/transformer_for_diffusion.py unchanged. For each
small randomly initialised model it writes `<name>.safetensors` (the module's state dict) and
`<name>.json`: constructor arguments, inputs (sample, timesteps, cond), the noise predictions,
package versions, and `torch_rows_per_s` (forward at batch 1024, torch.set_num_threads(1)).
Versions: requirements-beso.txt.
"""

import argparse
import json
import os
import platform
import sys
import time

import numpy as np
import torch
from safetensors.torch import save_file

CASES = {
    # diffusion_policy's low-dim transformer setting: obs as cond, causal, MLP cond encoder.
    "dp_transformer": dict(input_dim=2, output_dim=2, horizon=6, n_obs_steps=2, cond_dim=5,
                           n_layer=2, n_head=2, n_emb=16, p_drop_emb=0.0, p_drop_attn=0.0,
                           causal_attn=True, time_as_cond=True, n_cond_layers=0),
    # A transformer cond encoder, no causal masks.
    "dp_transformer_enc": dict(input_dim=3, output_dim=3, horizon=4, n_obs_steps=3, cond_dim=4,
                               n_layer=1, n_head=4, n_emb=16, p_drop_emb=0.0, p_drop_attn=0.0,
                               causal_attn=False, time_as_cond=True, n_cond_layers=1),
    # Encoder only (BERT): time is the first token, no observation conditioning.
    "dp_transformer_bert": dict(input_dim=2, output_dim=2, horizon=5, n_obs_steps=5, cond_dim=0,
                                n_layer=2, n_head=2, n_emb=8, p_drop_emb=0.0, p_drop_attn=0.0,
                                causal_attn=True, time_as_cond=False, n_cond_layers=0),
}


def flat(t):
    return t.detach().reshape(t.shape[0], -1).double().numpy().tolist()


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--dp", required=True)
    ap.add_argument("--out", required=True)
    args = ap.parse_args()
    sys.path.insert(0, args.dp)
    from diffusion_policy.model.diffusion.transformer_for_diffusion import (  # noqa: E402
        TransformerForDiffusion,
    )

    versions = {"python": platform.python_version(), "torch": torch.__version__,
                "numpy": np.__version__}
    for i, (name, cfg) in enumerate(CASES.items()):
        torch.manual_seed(300 + i)
        gen = torch.Generator().manual_seed(400 + i)
        model = TransformerForDiffusion(**cfg)
        with torch.no_grad():
            for key, t in model.state_dict().items():
                if key in ("mask", "memory_mask"):
                    continue
                noise = torch.randn(t.shape, generator=gen) * 0.3
                if "norm" in key and key.endswith("weight"):
                    noise = noise + 1.0
                t.copy_(noise)
        model.eval()

        def inputs(n, cfg=cfg, gen=gen):
            sample = torch.randn((n, cfg["horizon"], cfg["input_dim"]), generator=gen)
            steps = torch.randint(0, 100, (n,), generator=gen).float()
            cond = (torch.randn((n, cfg["n_obs_steps"], cfg["cond_dim"]), generator=gen)
                    if cfg["cond_dim"] > 0 else None)
            return sample, steps, cond

        sample, steps, cond = inputs(6)
        steps = torch.tensor([0.0, 1.0, 10.0, 37.0, 75.0, 99.0])
        with torch.no_grad():
            out = model(sample, steps, cond)
            torch.set_num_threads(1)
            s, t, c = inputs(1024)
            for _ in range(3):
                model(s, t, c)
            reps, start = 0, time.perf_counter()
            while time.perf_counter() - start < 2.0:
                model(s, t, c)
                reps += 1
            rate = 1024 * reps / (time.perf_counter() - start)
        record = {"arch": "transformer_for_diffusion",
                  "network": {k: v for k, v in cfg.items() if not k.startswith("p_drop")},
                  "sample": flat(sample), "timestep": steps.tolist(),
                  "cond": flat(cond) if cond is not None else None, "output": flat(out),
                  "torch_rows_per_s": rate, "versions": versions}
        save_file({k: v.contiguous() for k, v in model.state_dict().items()},
                  os.path.join(args.out, f"{name}.safetensors"))
        with open(os.path.join(args.out, f"{name}.json"), "w") as f:
            json.dump(record, f)
        print(f"{name}: torch_rows_per_s {rate:.0f}")


if __name__ == "__main__":
    main()
