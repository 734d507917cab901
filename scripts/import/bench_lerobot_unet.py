#!/usr/bin/env python3
"""Times a LeRobot `DiffusionPolicy` fixture's U-Net with LeRobot's own code, one thread, the
figure `cargo xtask bench import` reports as `torch_rows_per_s` for it: the best of 5 forwards
after one warm-up at the fixture's `bench_batch` (its `expected.safetensors` metadata), as our
side of the bench times it. Meant for fixtures too large to commit (the default-scale U-Net of
`unet_fixtures.py --default-scale`), run alternately with our bench on the same machine:

    python scripts/import/bench_lerobot_unet.py DIR/lerobot_unet_default [--write]

`--write` stores the rate in the fixture's `expected.safetensors` metadata (tensors untouched).
Python 3.12, lerobot 0.6.1 (requirements-fixtures.txt).
"""

import argparse
import os
import sys
import time

import torch

HERE = os.path.dirname(os.path.abspath(__file__))


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("fixture")
    ap.add_argument("--write", action="store_true")
    a = ap.parse_args()
    sys.path.insert(0, HERE)
    from bench_torch import read_safetensors_header, set_safetensors_metadata
    from lerobot.policies.diffusion.modeling_diffusion import DiffusionPolicy

    torch.set_num_threads(1)
    expected = os.path.join(a.fixture, "expected.safetensors")
    meta = read_safetensors_header(expected).get("__metadata__", {})
    batch = int(meta.get("bench_batch", 1024))
    pol = DiffusionPolicy.from_pretrained(a.fixture).eval()
    cfg = pol.config
    unet = pol.diffusion.unet
    ad = cfg.output_features["action"].shape[0]
    gd = sum(f.shape[0] for f in cfg.input_features.values()) * cfg.n_obs_steps
    gen = torch.Generator().manual_seed(0)
    x = torch.randn((batch, cfg.horizon, ad), generator=gen)
    t = torch.randint(0, 100, (batch,), generator=gen)
    g = torch.randn((batch, gd), generator=gen)
    with torch.no_grad():
        unet(x, t, global_cond=g)
        best = float("inf")
        for _ in range(5):
            t0 = time.perf_counter()
            unet(x, t, global_cond=g)
            best = min(best, time.perf_counter() - t0)
    rate = batch / best
    print(f"{os.path.basename(os.path.normpath(a.fixture)):24} torch_rows_per_s {rate:.2f} (batch {batch}, torch {torch.__version__})")
    if a.write:
        set_safetensors_metadata(expected, {"torch_rows_per_s": f"{rate:.2f}"})


if __name__ == "__main__":
    main()
