#!/usr/bin/env python3
"""Fixtures for the BESO/D3IL importer (vdd-import), made with the packages' own model code.

Usage (python 3.11, the versions in requirements-beso.txt):

    python scripts/import/beso_fixtures.py --d3il PATH/TO/d3il --beso PATH/TO/beso \
        --out tests/fixtures/import

PATH/TO/d3il is a checkout of ALRhub/d3il and PATH/TO/beso one of intuitive-robots/beso; neither
is committed here. The script imports their modules unchanged: `DiffusionGPT` (score_gpts.py),
`GCDenoiser` (score_wrappers.py), the samplers and schedules (gc_sampling.py) from D3IL, and
`GCTimeScoreNetwork` (D3IL's score_plan_mlp.py, which imports `ResidualMLPNetwork` from BESO).

For each small, randomly initialised model it writes `<name>.safetensors` (the GCDenoiser's
state dict, keys as in `model_state_dict.pth`) and `<name>.json`: the constructor arguments,
inputs, the inner network's outputs and the denoiser's outputs at several sigmas, one full
sampling run with its noise recorded, package versions, and `torch_rows_per_s` (the denoiser's
forward at batch 1024 with `torch.set_num_threads(1)`).
"""

import argparse
import importlib.util
import json
import os
import platform
import sys
import time

import numpy as np
import torch
from omegaconf import OmegaConf
from safetensors.torch import save_file


def load_modules(d3il, beso):
    sys.path.insert(0, beso)
    sys.path.insert(0, d3il)
    from agents.models.beso.agents.diffusion_agents.k_diffusion import (  # noqa: E402
        gc_sampling,
        score_wrappers,
    )

    path = os.path.join(
        d3il, "agents/models/beso/agents/lmp_agents/lmp_modules/plan_encoders/score_plan_mlp.py"
    )
    spec = importlib.util.spec_from_file_location("score_plan_mlp", path)
    mlp = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mlp)
    sys.modules["score_plan_mlp"] = mlp
    return score_wrappers, gc_sampling, mlp


def randomise(model, gen):
    """Replaces every parameter and float buffer (but masks) with N(0, 0.3²) noise, LayerNorm
    weights with 1 + noise, so no weight is at its trivial initial value."""
    with torch.no_grad():
        for name, t in model.state_dict().items():
            if name.endswith("attn.mask"):
                continue
            noise = torch.randn(t.shape, generator=gen) * 0.3
            if ("ln" in name or "normalizer" in name) and name.endswith("weight"):
                noise = noise + 1.0
            t.copy_(noise)


GPT_CASES = {
    # D3IL's configuration: no goal, linear head; sampled as D3IL's agent does (euler_ancestral,
    # linear sigmas).
    "beso_gpt": dict(
        net=dict(state_dim=4, action_dim=2, embed_dim=16, n_layers=2, n_heads=2, obs_seq_len=3,
                 goal_seq_len=0, goal_conditioned=False, linear_output=True),
        sampling=dict(sampler="euler_ancestral", schedule="linear", steps=4),
    ),
    # BESO's goal-conditioned variant with the MLP head, sampled with DDIM on exponential sigmas.
    "beso_gpt_goal": dict(
        net=dict(state_dim=3, action_dim=2, embed_dim=12, n_layers=1, n_heads=3, obs_seq_len=2,
                 goal_seq_len=1, goal_conditioned=True, linear_output=False),
        sampling=dict(sampler="ddim", schedule="exponential", steps=5),
    ),
}

MLP_CASES = {
    "beso_resmlp": dict(
        net=dict(obs_dim=4, action_dim=2, hidden_dim=32, num_hidden_layers=4, time_embed_dim=8,
                 embedding="FourierFeatures", activation="Mish", norm="LayerNorm"),
        window=2,
        sampling=dict(sampler="euler", schedule="exponential", steps=5),
    ),
    "beso_resmlp_sin": dict(
        net=dict(obs_dim=3, action_dim=3, hidden_dim=24, num_hidden_layers=2, time_embed_dim=6,
                 embedding="Sinusoidal", activation="GELU", norm="None"),
        window=1,
        sampling=dict(sampler="euler_ancestral", schedule="linear", steps=3),
    ),
}

SIGMA_DATA = 0.5
SIGMA_MIN, SIGMA_MAX, RHO = 0.1, 1.0, 5.0


def build_gpt(score_wrappers, net):
    inner = dict(
        _target_="agents.models.beso.agents.diffusion_agents.k_diffusion.score_gpts.DiffusionGPT",
        device="cpu", embed_pdrob=0.0, attn_pdrop=0.0, resid_pdrop=0.0, sigma_vocab_size=8,
        time_embedding_fn=None, goal_drop=0.0, **net,
    )
    return score_wrappers.GCDenoiser(OmegaConf.create(inner), sigma_data=SIGMA_DATA)


def build_mlp(score_wrappers, net):
    embed = dict(
        _target_="agents.models.beso.agents.diffusion_agents.k_diffusion.utils."
                 "return_time_sigma_embedding_model",
        embedding_type=net["embedding"], time_embed_dim=net["time_embed_dim"], device="cpu",
    )
    inner = dict(
        _target_="score_plan_mlp.GCTimeScoreNetwork", _recursive_=False,
        obs_dim=net["obs_dim"], plan_dim=net["action_dim"], hidden_dim=net["hidden_dim"],
        goal_dim=0, embed_fn=embed, cond_mask_prob=0.0,
        num_hidden_layers=net["num_hidden_layers"], output_dim=net["action_dim"], dropout=0.0,
        activation=net["activation"], model_style=True, use_norm=net["norm"] != "None",
        norm_style="LayerNorm", use_spectral_norm=False, device="cpu", goal_conditional=False,
    )
    model = score_wrappers.GCDenoiser(OmegaConf.create(inner), sigma_data=SIGMA_DATA)
    return model


# The agents' hard-wired schedules: D3IL's BesoAgent samples on linear sigmas, BESO's on
# exponential ones; the run config names the agent.
AGENTS = {"linear": "agents.beso_agent.BesoAgent",
          "exponential": "beso.agents.diffusion_agents.beso_agent.BesoAgent"}


def hydra_config(arch, net, case, t):
    """The run's `config.yaml` as hydra saves it (interpolations unresolved)."""
    if arch == "diffusion_gpt":
        inner = {"_target_": "agents.models.beso.agents.diffusion_agents.k_diffusion.score_gpts"
                             ".DiffusionGPT", **net, "obs_seq_len": "${window_size}",
                 "state_dim": "${obs_dim}", "action_dim": "${action_dim}",
                 "device": "${device}", "embed_pdrob": 0, "attn_pdrop": 0.2, "resid_pdrop": 0.1,
                 "sigma_vocab_size": 8,
                 "time_embedding_fn": {"_target_": "x.return_time_sigma_embedding_model",
                                       "embedding_type": "Linear", "time_embed_dim": 8}}
        obs, act = net["state_dim"], net["action_dim"]
    else:
        inner = {"_target_": "score_plan_mlp.GCTimeScoreNetwork", "obs_dim": "${obs_dim}",
                 "plan_dim": "${action_dim}", "hidden_dim": net["hidden_dim"], "goal_dim": 0,
                 "embed_fn": {"_target_": "x.return_time_sigma_embedding_model",
                              "embedding_type": net["embedding"],
                              "time_embed_dim": net["time_embed_dim"], "device": "cpu"},
                 "cond_mask_prob": 0.0, "num_hidden_layers": net["num_hidden_layers"],
                 "output_dim": "${action_dim}", "dropout": 0.0, "activation": net["activation"],
                 "model_style": True, "use_norm": net["norm"] != "None",
                 "norm_style": "LayerNorm", "use_spectral_norm": False, "device": "cpu",
                 "goal_conditional": False}
        obs, act = net["obs_dim"], net["action_dim"]
    sampling = case["sampling"]
    return {
        "obs_dim": obs, "action_dim": act, "window_size": t, "device": "cpu",
        "scale_data": False,
        "agents": {"_target_": AGENTS[sampling["schedule"]], "_recursive_": False,
                   "model": {"_target_": "agents.models.beso.agents.diffusion_agents.k_diffusion"
                                         ".score_wrappers.GCDenoiser",
                             "_recursive_": False, "sigma_data": SIGMA_DATA,
                             "inner_model": inner},
                   "sampler_type": sampling["sampler"],
                   "num_sampling_steps": sampling["steps"], "sigma_data": SIGMA_DATA,
                   "rho": RHO, "sigma_min": SIGMA_MIN, "sigma_max": SIGMA_MAX,
                   "window_size": "${window_size}", "goal_window_size": 1,
                   "scale_data": "${scale_data}", "use_ema": True},
    }


def sigmas_for(gc_sampling, kind, steps):
    if kind == "linear":
        return gc_sampling.get_sigmas_linear(steps, SIGMA_MIN, SIGMA_MAX)
    if kind == "exponential":
        return gc_sampling.get_sigmas_exponential(steps, SIGMA_MIN, SIGMA_MAX)
    return gc_sampling.get_sigmas_karras(steps, SIGMA_MIN, SIGMA_MAX, RHO)


def sample(gc_sampling, model, state, goal, x, spec):
    sigmas = sigmas_for(gc_sampling, spec["schedule"], spec["steps"])
    recorded = []
    original = torch.randn_like

    def recording(t, *a, **k):
        z = original(t, *a, **k)
        recorded.append(z.clone())
        return z

    torch.randn_like = recording
    try:
        fn = {"euler_ancestral": gc_sampling.sample_euler_ancestral,
              "ddim": gc_sampling.sample_ddim, "euler": gc_sampling.sample_euler}[spec["sampler"]]
        out = fn(model, state, x, goal, sigmas, disable=True)
    finally:
        torch.randn_like = original
    return sigmas, recorded, out


def flat(t):
    return t.detach().reshape(t.shape[0], -1).double().numpy().tolist()


def rows_per_s(model, make_inputs):
    torch.set_num_threads(1)
    state, action, goal, sigma = make_inputs(1024)
    with torch.no_grad():
        for _ in range(3):
            model(state, action, goal, sigma)
        reps, start = 0, time.perf_counter()
        while time.perf_counter() - start < 2.0:
            model(state, action, goal, sigma)
            reps += 1
    return 1024 * reps / (time.perf_counter() - start)


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("--d3il", required=True)
    ap.add_argument("--beso", required=True)
    ap.add_argument("--out", required=True)
    args = ap.parse_args()
    score_wrappers, gc_sampling, _ = load_modules(args.d3il, args.beso)
    os.makedirs(args.out, exist_ok=True)
    versions = {"python": platform.python_version(), "torch": torch.__version__,
                "numpy": np.__version__}
    cases = [(k, "diffusion_gpt", v) for k, v in GPT_CASES.items()]
    cases += [(k, "resmlp", v) for k, v in MLP_CASES.items()]
    for i, (name, arch, case) in enumerate(cases):
        gen = torch.Generator().manual_seed(100 + i)
        torch.manual_seed(200 + i)
        net = case["net"]
        if arch == "diffusion_gpt":
            model = build_gpt(score_wrappers, net)
            t, sd, ad = net["obs_seq_len"], net["state_dim"], net["action_dim"]
            g = net["goal_seq_len"] if net["goal_conditioned"] else 0
        else:
            model = build_mlp(score_wrappers, net)
            t, sd, ad, g = case["window"], net["obs_dim"], net["action_dim"], 0
        randomise(model, gen)
        model.eval()

        def make_inputs(n, gen=gen, t=t, sd=sd, ad=ad, g=g):
            state = torch.randn((n, t, sd), generator=gen)
            action = torch.randn((n, t, ad), generator=gen)
            goal = torch.randn((n, g, sd), generator=gen) if g > 0 else None
            sigma = torch.exp(torch.empty(n).uniform_(-3.0, 1.5, generator=gen))
            return state, action, goal, sigma

        n = 6
        state, action, goal, _ = make_inputs(n)
        levels = [0.05, 0.1, 0.5, 1.0, 3.0, 20.0]
        sigma = torch.tensor(levels, dtype=torch.float32)
        with torch.no_grad():
            inner = model.inner_model(state, action, goal, sigma)
            denoised = model(state, action, goal, sigma)
            x = torch.randn((n, t, ad), generator=gen) * SIGMA_MAX
            sigmas, noise, result = sample(gc_sampling, model, state, goal, x.clone(),
                                           case["sampling"])
        record = {
            "arch": arch, "network": net, "window": t, "sigma_data": SIGMA_DATA,
            "states": flat(state), "actions": flat(action),
            "goals": flat(goal) if goal is not None else None,
            "sigma": levels, "inner": flat(inner), "denoised": flat(denoised),
            "sampling": {**case["sampling"], "sigma_min": SIGMA_MIN, "sigma_max": SIGMA_MAX,
                         "rho": RHO, "sigmas": sigmas.double().tolist(), "x_init": flat(x),
                         "noise": [flat(z) for z in noise], "result": flat(result)},
            "torch_rows_per_s": rows_per_s(model, make_inputs),
            "versions": versions,
        }
        tensors = {k: v.contiguous() for k, v in model.state_dict().items()}
        save_file(tensors, os.path.join(args.out, f"{name}.safetensors"))
        OmegaConf.save(OmegaConf.create(hydra_config(arch, net, case, t)),
                       os.path.join(args.out, f"{name}.yaml"))
        with open(os.path.join(args.out, f"{name}.json"), "w") as f:
            json.dump(record, f)
        print(f"{name}: torch_rows_per_s {record['torch_rows_per_s']:.0f}")


if __name__ == "__main__":
    main()
