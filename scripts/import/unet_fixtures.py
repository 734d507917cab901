"""Fixtures for the U-Net teacher importers (issue #20), made with the real packages.

Builds small randomly initialised diffusion policies with LeRobot (PyPI) and with
real-stanford/diffusion_policy's model code (a checkout whose path you pass; its code is not
committed here), records their U-Net outputs at several diffusion steps and one full sampling
run with fixed noise, and times the U-Net at batch 1024 on one thread. Writes, per fixture,
the package's own files (LeRobot `save_pretrained` directory, or a diffusion_policy `.ckpt`
converted by `diffusion_policy_ckpt.py`) and `expected.safetensors`.

    python scripts/import/unet_fixtures.py --out tests/fixtures/import \
        --diffusion-policy /path/to/diffusion_policy-checkout

Versions used for the committed fixtures: see requirements-fixtures.txt beside this file.
"""

import argparse
import json
import os
import subprocess
import sys
import time
import types

import torch
from safetensors.torch import save_file

torch.set_num_threads(1)

ROWS_BENCH = 1024


def bench_rows_per_s(fn, batch, reps=5):
    fn(batch)
    best = float("inf")
    for _ in range(reps):
        t0 = time.perf_counter()
        fn(batch)
        best = min(best, time.perf_counter() - t0)
    return batch / best


def versions():
    import diffusers
    out = {"torch": torch.__version__, "diffusers": diffusers.__version__, "python": sys.version.split()[0]}
    try:
        import lerobot
        out["lerobot"] = getattr(lerobot, "__version__", "unknown")
    except ImportError:
        pass
    return out


def record_noise(seed, shape, steps):
    """The variance noises DDPMScheduler.step draws from the global generator, in order."""
    torch.manual_seed(seed)
    return torch.stack([torch.randn(shape) for _ in range(steps)]) if steps else torch.zeros((0, *shape))


# ---------------------------------------------------------------- LeRobot
def lerobot_fixture(out_dir, name, seed, keep_init=False, bench_batch=ROWS_BENCH, **kw):
    """`keep_init`: PyTorch's own initialisation (the scaled normal draws below would overflow a
    wide network); `bench_batch`: the batch the U-Net is timed at (recorded as `bench_batch`)."""
    from importlib.metadata import version as pkg_version

    from lerobot.configs.types import FeatureType, NormalizationMode, PolicyFeature
    from lerobot.policies.diffusion.configuration_diffusion import DiffusionConfig
    from lerobot.policies.diffusion.modeling_diffusion import DiffusionPolicy
    from lerobot.policies.factory import make_pre_post_processors

    torch.manual_seed(seed)
    sd, ed, ad = 4, 3, 2
    norm = kw.pop("norm", {"STATE": NormalizationMode.MIN_MAX, "ACTION": NormalizationMode.MIN_MAX})
    cfg = DiffusionConfig(
        input_features={
            "observation.state": PolicyFeature(type=FeatureType.STATE, shape=(sd,)),
            "observation.environment_state": PolicyFeature(type=FeatureType.ENV, shape=(ed,)),
        },
        output_features={"action": PolicyFeature(type=FeatureType.ACTION, shape=(ad,))},
        normalization_mapping={"VISUAL": NormalizationMode.MEAN_STD, **norm},
        device="cpu",
        push_to_hub=False,
        **kw,
    )
    pol = DiffusionPolicy(cfg).eval()
    # Random non-trivial weights everywhere (GroupNorm affine included).
    if not keep_init:
        with torch.no_grad():
            for p in pol.parameters():
                p.copy_(torch.randn_like(p) * (0.3 if p.ndim > 1 else 0.2))
    stats = {
        "observation.state": {"min": torch.tensor([-1.0, 0.0, 0.5, -3.0]), "max": torch.tensor([1.0, 2.0, 0.7, 3.0]),
                              "mean": torch.tensor([0.1, 1.0, 0.6, -0.5]), "std": torch.tensor([0.5, 0.7, 0.05, 2.0])},
        "observation.environment_state": {"min": torch.zeros(ed), "max": torch.ones(ed),
                                          "mean": torch.full((ed,), 0.5), "std": torch.full((ed,), 0.3)},
        "action": {"min": torch.tensor([-0.5, 0.0]), "max": torch.tensor([0.5, 4.0]),
                   "mean": torch.tensor([0.0, 2.0]), "std": torch.tensor([0.2, 1.5])},
    }
    pre, post = make_pre_post_processors(cfg, dataset_stats=stats)
    d = os.path.join(out_dir, name)
    os.makedirs(d, exist_ok=True)
    pol.save_pretrained(d)
    pre.save_pretrained(d)
    post.save_pretrained(d)

    unet = pol.diffusion.unet
    h, no = cfg.horizon, cfg.n_obs_steps
    gdim = (sd + ed) * no
    steps = torch.tensor([0, 1, 10, 50, 98, 99])
    b = len(steps)
    x = torch.randn(b, h, ad)
    g = torch.randn(b, gdim)
    with torch.no_grad():
        y = unet(x, steps, global_cond=g)

    # One full sampling run through the package's own pipeline, fixed noise.
    b2 = 3
    state = torch.rand(b2, no, sd) * 2.0 - 0.5
    env = torch.rand(b2, no, ed)
    batch = pre({"observation.state": state, "observation.environment_state": env})
    noise = torch.randn(b2, h, ad)
    sched = pol.diffusion.noise_scheduler
    n_inf = pol.diffusion.num_inference_steps
    stochastic = cfg.noise_scheduler_type == "DDPM"
    step_noise = record_noise(1234, (b2, h, ad), n_inf - 1 if stochastic else 0)
    torch.manual_seed(1234)
    with torch.no_grad():
        gc = pol.diffusion._prepare_global_conditioning(batch)
        acts = pol.diffusion.generate_actions(batch, noise=noise.clone())
    acts_raw = post(acts)

    with torch.no_grad():
        rate = bench_rows_per_s(
            lambda n: unet(torch.randn(n, h, ad), torch.randint(0, 100, (n,)), global_cond=torch.randn(n, gdim)),
            bench_batch,
        )
    tensors = {
        "unet.x": x, "unet.t": steps.float(), "unet.global_cond": g, "unet.out": y,
        "sample.observation.state": state, "sample.observation.environment_state": env,
        "sample.global_cond": gc, "sample.noise": noise, "sample.step_noise": step_noise,
        "sample.actions": acts_raw.contiguous(),
    }
    meta = {"torch_rows_per_s": f"{rate:.1f}", "versions": json.dumps({**versions(), "lerobot": pkg_version("lerobot")}),
            "architecture": "lerobot_unet1d", "bench_batch": str(bench_batch)}
    save_file({k: v.contiguous().float() for k, v in tensors.items()}, os.path.join(d, "expected.safetensors"), metadata=meta)
    print(name, "torch rows/s", round(rate), "params", sum(p.numel() for p in pol.parameters()))


# ---------------------------------------------------------------- diffusion_policy
def dp_fixture(out_dir, name, seed, checkout):
    sys.path.insert(0, checkout)
    if "zarr" not in sys.modules:  # normalizer.py imports zarr only for a type hint
        z = types.ModuleType("zarr")
        z.Array = type("Array", (), {})
        sys.modules["zarr"] = z
    import dill
    from diffusers.schedulers.scheduling_ddpm import DDPMScheduler
    from omegaconf import OmegaConf

    from diffusion_policy.model.diffusion.conditional_unet1d import ConditionalUnet1D
    from diffusion_policy.policy.diffusion_unet_lowdim_policy import DiffusionUnetLowdimPolicy

    torch.manual_seed(seed)
    obs_dim, act_dim, h, no, na = 5, 2, 16, 2, 8
    cfg = OmegaConf.create({
        "name": "train_diffusion_unet_lowdim", "horizon": h, "n_obs_steps": no, "n_action_steps": na,
        "n_latency_steps": 0, "obs_as_global_cond": True, "obs_as_local_cond": False,
        "pred_action_steps_only": False, "obs_dim": obs_dim, "action_dim": act_dim,
        "policy": {
            "_target_": "diffusion_policy.policy.diffusion_unet_lowdim_policy.DiffusionUnetLowdimPolicy",
            "model": {"_target_": "diffusion_policy.model.diffusion.conditional_unet1d.ConditionalUnet1D",
                      "input_dim": act_dim, "local_cond_dim": None, "global_cond_dim": obs_dim * no,
                      "diffusion_step_embed_dim": 32, "down_dims": [16, 32, 48], "kernel_size": 5,
                      "n_groups": 8, "cond_predict_scale": True},
            "noise_scheduler": {"_target_": "diffusers.schedulers.scheduling_ddpm.DDPMScheduler",
                                "num_train_timesteps": 100, "beta_start": 0.0001, "beta_end": 0.02,
                                "beta_schedule": "squaredcos_cap_v2", "variance_type": "fixed_small",
                                "clip_sample": True, "prediction_type": "epsilon"},
            "horizon": "${horizon}", "obs_dim": "${obs_dim}", "action_dim": "${action_dim}",
            "n_action_steps": "${eval:'${n_action_steps}+${n_latency_steps}'}", "n_obs_steps": "${n_obs_steps}",
            "num_inference_steps": 100, "obs_as_local_cond": "${obs_as_local_cond}",
            "obs_as_global_cond": "${obs_as_global_cond}", "pred_action_steps_only": "${pred_action_steps_only}",
            "oa_step_convention": True,
        },
        "training": {"use_ema": True},
    })
    mc = dict(cfg.policy.model)
    mc.pop("_target_")
    model = ConditionalUnet1D(**mc)
    sc = dict(cfg.policy.noise_scheduler)
    sc.pop("_target_")
    policy = DiffusionUnetLowdimPolicy(
        model=model, noise_scheduler=DDPMScheduler(**sc), horizon=h, obs_dim=obs_dim, action_dim=act_dim,
        n_action_steps=na, n_obs_steps=no, num_inference_steps=100, obs_as_global_cond=True,
        oa_step_convention=True).eval()
    with torch.no_grad():
        for p in policy.model.parameters():
            p.copy_(torch.randn_like(p) * (0.3 if p.ndim > 1 else 0.2))
    data = {"obs": torch.randn(200, obs_dim) * torch.tensor([1.0, 2.0, 0.5, 3.0, 0.1]) + 1.0,
            "action": torch.rand(200, act_dim) * torch.tensor([2.0, 5.0]) - 1.0}
    policy.normalizer.fit(data, last_n_dims=1, mode="limits")
    d = os.path.join(out_dir, name)
    os.makedirs(d, exist_ok=True)
    ckpt = os.path.join(d, "..", f"{name}.ckpt")
    payload = {"cfg": cfg, "state_dicts": {"model": policy.state_dict(), "ema_model": policy.state_dict()},
               "pickles": {}}
    with open(ckpt, "wb") as f:
        torch.save(payload, f, pickle_module=dill)
    here = os.path.dirname(os.path.abspath(__file__))
    subprocess.run([sys.executable, os.path.join(here, "diffusion_policy_ckpt.py"), ckpt, "--out", d], check=True)
    os.remove(ckpt)

    steps = torch.tensor([0, 1, 10, 50, 98, 99])
    b = len(steps)
    x = torch.randn(b, h, act_dim)
    g = torch.randn(b, obs_dim * no)
    with torch.no_grad():
        y = model(x, steps, global_cond=g)
    b2 = 3
    obs = torch.randn(b2, no, obs_dim) + 1.0
    torch.manual_seed(77)
    noise = torch.randn(b2, h, act_dim)  # conditional_sample's first draw
    step_noise = torch.stack([torch.randn(b2, h, act_dim) for _ in range(99)])
    torch.manual_seed(77)
    with torch.no_grad():
        res = policy.predict_action({"obs": obs})
    rate = bench_rows_per_s(
        lambda n: model(torch.randn(n, h, act_dim), torch.randint(0, 100, (n,)), global_cond=torch.randn(n, obs_dim * no)),
        ROWS_BENCH,
    )
    tensors = {"unet.x": x, "unet.t": steps.float(), "unet.global_cond": g, "unet.out": y,
               "sample.obs": obs, "sample.noise": noise, "sample.step_noise": step_noise,
               "sample.actions": res["action"], "sample.action_pred": res["action_pred"]}
    meta = {"torch_rows_per_s": f"{rate:.1f}", "versions": json.dumps(versions()),
            "architecture": "diffusion_policy_unet1d"}
    save_file({k: v.contiguous().float() for k, v in tensors.items()}, os.path.join(d, "expected.safetensors"), metadata=meta)
    print(name, "torch rows/s", round(rate), "params", sum(p.numel() for p in model.parameters()))


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", required=True)
    ap.add_argument("--diffusion-policy", help="path to a real-stanford/diffusion_policy checkout")
    ap.add_argument("--default-scale", action="store_true",
                    help="only write lerobot_unet_default: LeRobot's DiffusionConfig defaults (down_dims "
                         "512/1024/2048, 248M parameters, about 1 GB; too large to commit), timed at batch 32")
    a = ap.parse_args()
    from lerobot.configs.types import NormalizationMode as N
    if a.default_scale:
        # Every U-Net and scheduler setting at DiffusionConfig's default; PyTorch's initialisation.
        lerobot_fixture(a.out, "lerobot_unet_default", 3, keep_init=True, bench_batch=32)
        return
    lerobot_fixture(a.out, "lerobot_unet_ddpm", 0, n_obs_steps=2, horizon=16, n_action_steps=8,
                    down_dims=(16, 32, 48), kernel_size=5, n_groups=8, diffusion_step_embed_dim=32,
                    use_film_scale_modulation=True)
    lerobot_fixture(a.out, "lerobot_unet_ddim", 1, n_obs_steps=1, horizon=8, n_action_steps=4,
                    down_dims=(16, 32), kernel_size=3, n_groups=4, diffusion_step_embed_dim=16,
                    use_film_scale_modulation=False, noise_scheduler_type="DDIM", beta_schedule="linear",
                    prediction_type="sample", num_inference_steps=10, clip_sample_range=1.5,
                    norm={"STATE": N.MEAN_STD, "ACTION": N.MEAN_STD})
    if a.diffusion_policy:
        dp_fixture(a.out, "diffusion_policy_unet", 2, a.diffusion_policy)


if __name__ == "__main__":
    main()
