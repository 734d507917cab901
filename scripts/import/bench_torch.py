#!/usr/bin/env python3
"""Times PyTorch's forward of every committed import fixture at batch 1024 on one thread
(`torch.set_num_threads(1)`), the figure `cargo xtask bench import` reports as
`torch_rows_per_s`, and optionally writes it into the fixtures. The fixtures' tensors and
weights are never touched: only the recorded rate (and a note of how it was measured) changes.

Measure (python 3.11, the versions in requirements-beso.txt; model code from the checkouts the
fixture scripts name):

    python scripts/import/bench_torch.py --d3il PATH/TO/d3il --beso PATH/TO/beso \
        --dp PATH/TO/diffusion_policy --json run1.json

Write the per-fixture median of several such runs into the fixtures:

    python scripts/import/bench_torch.py --write run1.json run2.json run3.json

Run it alternately with `cargo xtask bench import` on the same machine, so both sides see the
same load. Each network is rebuilt by its package's own code from the fixture's constructor
arguments and loaded with the fixture's weights. Timing mirrors our side of the bench: the U-Nets
take the best of 5 forwards after one warm-up, the BESO/D3IL and transformer fixtures the mean
rate over 2 s after 3 warm-ups. The LeRobot fixtures are timed on diffusion_policy's
`ConditionalUnet1D` built with the same arguments (LeRobot's `DiffusionConditionalUnet1d` is that
network under other parameter names; LeRobot 0.6.1 needs python >= 3.12).
"""

import argparse
import json
import os
import statistics
import struct
import sys
import time

import torch
from safetensors.torch import load_file

HERE = os.path.dirname(os.path.abspath(__file__))
BATCH = 1024
UNETS = ("diffusion_policy_unet", "lerobot_unet_ddim", "lerobot_unet_ddpm")


def best_of(fn, reps=5):
    fn()
    best = float("inf")
    for _ in range(reps):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return BATCH / best


def mean_rate(fn, secs=2.0):
    for _ in range(3):
        fn()
    reps, start = 0, time.perf_counter()
    while time.perf_counter() - start < secs:
        fn()
        reps += 1
    return BATCH * reps / (time.perf_counter() - start)


def read_safetensors_header(path):
    with open(path, "rb") as f:
        n = struct.unpack("<Q", f.read(8))[0]
        return json.loads(f.read(n))


def unet_from_fixture(fixtures, name, dp):
    """diffusion_policy's ConditionalUnet1D with the fixture's arguments and weights."""
    sys.path.insert(0, dp)
    from diffusion_policy.model.diffusion.conditional_unet1d import ConditionalUnet1D

    d = os.path.join(fixtures, name)
    with open(os.path.join(d, "config.json")) as f:
        cfg = json.load(f)
    weights = load_file(os.path.join(d, "model.safetensors"))
    if "policy" in cfg:  # diffusion_policy's hydra cfg
        m = cfg["policy"]["model"]
        args = dict(input_dim=m["input_dim"], global_cond_dim=m["global_cond_dim"],
                    diffusion_step_embed_dim=m["diffusion_step_embed_dim"],
                    down_dims=m["down_dims"], kernel_size=m["kernel_size"],
                    n_groups=m["n_groups"], cond_predict_scale=m["cond_predict_scale"])
        horizon = cfg["horizon"]
        sd = {k[len("model."):]: v for k, v in weights.items() if k.startswith("model.")}
    else:  # LeRobot's DiffusionConfig
        obs = sum(f["shape"][0] for f in cfg["input_features"].values())
        act = cfg["output_features"]["action"]["shape"][0]
        args = dict(input_dim=act, global_cond_dim=obs * cfg["n_obs_steps"],
                    diffusion_step_embed_dim=cfg["diffusion_step_embed_dim"],
                    down_dims=cfg["down_dims"], kernel_size=cfg["kernel_size"],
                    n_groups=cfg["n_groups"],
                    cond_predict_scale=cfg["use_film_scale_modulation"])
        horizon = cfg["horizon"]
        sd = {}
        for k, v in weights.items():
            if not k.startswith("diffusion.unet."):
                continue
            k = k[len("diffusion.unet."):].replace(".conv1.", ".blocks.0.")
            k = k.replace(".conv2.", ".blocks.1.")
            parts = k.split(".")
            if parts[0] in ("down_modules", "up_modules") and parts[2] == "2":
                k = ".".join(parts[:3] + ["conv"] + parts[3:])
            sd[k] = v
    model = ConditionalUnet1D(**args)
    model.load_state_dict(sd)
    return model.eval(), horizon, args["input_dim"], args["global_cond_dim"]


def bench_unet(fixtures, name, dp):
    model, h, ad, gd = unet_from_fixture(fixtures, name, dp)
    gen = torch.Generator().manual_seed(0)
    x = torch.randn((BATCH, h, ad), generator=gen)
    t = torch.randint(0, 100, (BATCH,), generator=gen)
    g = torch.randn((BATCH, gd), generator=gen)
    with torch.no_grad():
        return best_of(lambda: model(x, t, global_cond=g))


def bench_beso(fixtures, name, d3il, beso):
    sys.path.insert(0, HERE)
    import beso_fixtures as bf

    score_wrappers, _, _ = bf.load_modules(d3il, beso)
    if name in bf.GPT_CASES:
        net = bf.GPT_CASES[name]["net"]
        model = bf.build_gpt(score_wrappers, net)
        t, sd, ad = net["obs_seq_len"], net["state_dim"], net["action_dim"]
        g = net["goal_seq_len"] if net["goal_conditioned"] else 0
    else:
        case = bf.MLP_CASES[name]
        net = case["net"]
        model = bf.build_mlp(score_wrappers, net)
        t, sd, ad, g = case["window"], net["obs_dim"], net["action_dim"], 0
    model.load_state_dict(load_file(os.path.join(fixtures, f"{name}.safetensors")))
    model.eval()
    gen = torch.Generator().manual_seed(0)
    state = torch.randn((BATCH, t, sd), generator=gen)
    action = torch.randn((BATCH, t, ad), generator=gen)
    goal = torch.randn((BATCH, g, sd), generator=gen) if g > 0 else None
    sigma = torch.exp(torch.empty(BATCH).uniform_(-3.0, 1.5, generator=gen))
    with torch.no_grad():
        return mean_rate(lambda: model(state, action, goal, sigma))


def bench_dp_transformer(fixtures, name, dp):
    sys.path.insert(0, dp)
    sys.path.insert(0, HERE)
    import dp_transformer_fixtures as tf
    from diffusion_policy.model.diffusion.transformer_for_diffusion import (
        TransformerForDiffusion,
    )

    cfg = tf.CASES[name]
    model = TransformerForDiffusion(**cfg)
    model.load_state_dict(load_file(os.path.join(fixtures, f"{name}.safetensors")))
    model.eval()
    gen = torch.Generator().manual_seed(0)
    sample = torch.randn((BATCH, cfg["horizon"], cfg["input_dim"]), generator=gen)
    steps = torch.randint(0, 100, (BATCH,), generator=gen).float()
    cond = (torch.randn((BATCH, cfg["n_obs_steps"], cfg["cond_dim"]), generator=gen)
            if cfg["cond_dim"] > 0 else None)
    with torch.no_grad():
        return mean_rate(lambda: model(sample, steps, cond))


def measure(a):
    sys.path.insert(0, HERE)
    import beso_fixtures as bf
    import dp_transformer_fixtures as tf

    torch.set_num_threads(1)
    rates = {}
    want = set(a.only or []) or None
    for name in UNETS:
        if want is None or name in want:
            rates[name] = bench_unet(a.fixtures, name, a.dp)
    for name in list(bf.GPT_CASES) + list(bf.MLP_CASES):
        if want is None or name in want:
            rates[name] = bench_beso(a.fixtures, name, a.d3il, a.beso)
    for name in tf.CASES:
        if want is None or name in want:
            rates[name] = bench_dp_transformer(a.fixtures, name, a.dp)
    for name, r in rates.items():
        print(f"{name:24} torch_rows_per_s {r:>10.0f}")
    record = {"torch": torch.__version__, "python": sys.version.split()[0], "rates": rates}
    if a.json:
        with open(a.json, "w") as f:
            json.dump(record, f, indent=1)


def set_safetensors_metadata(path, updates):
    """Rewrites only the header's `__metadata__` of a safetensors file; tensor bytes stay."""
    with open(path, "rb") as f:
        n = struct.unpack("<Q", f.read(8))[0]
        header = json.loads(f.read(n))
        data = f.read()
    header.setdefault("__metadata__", {}).update(updates)
    raw = json.dumps(header, separators=(",", ":")).encode()
    raw += b" " * (-len(raw) % 8)
    with open(path, "wb") as f:
        f.write(struct.pack("<Q", len(raw)))
        f.write(raw)
        f.write(data)


def write(a):
    runs = []
    for p in a.write:
        with open(p) as f:
            runs.append(json.load(f))
    names = sorted(set().union(*(r["rates"] for r in runs)))
    how = (f"median of {len(runs)} runs of scripts/import/bench_torch.py, torch "
           f"{runs[0]['torch']}, python {runs[0]['python']}")
    for name in names:
        rate = statistics.median(r["rates"][name] for r in runs if name in r["rates"])
        if name in UNETS:
            path = os.path.join(a.fixtures, name, "expected.safetensors")
            set_safetensors_metadata(path, {"torch_rows_per_s": f"{rate:.1f}",
                                            "torch_rows_per_s_measured_by": how})
        else:
            path = os.path.join(a.fixtures, f"{name}.json")
            with open(path) as f:
                record = json.load(f)
            record["torch_rows_per_s"] = rate
            record["torch_rows_per_s_measured_by"] = how
            with open(path, "w") as f:
                json.dump(record, f)
        print(f"{name:24} torch_rows_per_s {rate:>10.0f} -> {path}")


def main():
    ap = argparse.ArgumentParser(description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--fixtures", default=os.path.join(HERE, "..", "..", "tests", "fixtures",
                                                       "import"))
    ap.add_argument("--d3il", help="checkout of ALRhub/d3il")
    ap.add_argument("--beso", help="checkout of intuitive-robots/beso")
    ap.add_argument("--dp", help="checkout of real-stanford/diffusion_policy")
    ap.add_argument("--json", help="where to save this run's rates")
    ap.add_argument("--only", nargs="+", metavar="FIXTURE", help="time only these fixtures")
    ap.add_argument("--write", nargs="+", metavar="RUN_JSON",
                    help="write the median of these runs into the fixtures (no timing)")
    a = ap.parse_args()
    if a.write:
        write(a)
    elif a.d3il and a.beso and a.dp:
        measure(a)
    else:
        ap.error("give --d3il, --beso and --dp to measure, or --write RUN_JSON...")


if __name__ == "__main__":
    main()
