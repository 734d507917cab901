#!/usr/bin/env python3
"""Trains a small LeRobot DiffusionPolicy on our Avoiding demonstrations, on CPU, in minutes.

The end-to-end check of docs/import.md ("End to end"): a policy trained by LeRobot's own code in
PyTorch, saved as LeRobot saves it, then imported (`cargo xtask import lerobot`), rolled out and
distilled by the Rust crates.

Input: the training episodes written by

    cargo xtask demos avoiding --export results/e2e/avoiding_train.npz

(`observations_seq` N x T x 4, `actions_seq` N x T x 2, `existence_mask` N x T: the recipe's
demonstrations, data seed and train/validation split, observations already through the recipe's
`position_and_lag` feature map, i.e. (c, d - c): the current position c and the tracking lag
d - c, where d is the previous desired position). Nothing is downloaded.

State-only LeRobot diffusion policies need `observation.state` and, without images,
`observation.environment_state`. We feed

    observation.state             = c      (the end effector's position, 2-D)
    observation.environment_state = d - c  (the tracking lag, 2-D)

so the policy's per-step observation, [state, environment_state], is exactly the
`position_and_lag` feature of the task's observation (d, c). Both are normalised MIN_MAX (ENV is
added to `normalization_mapping`; LeRobot would otherwise leave it unnormalised, and the lag is
a few millimetres). The script writes `vdd_features.json` ({"name": "position_and_lag",
"version": 1}) beside LeRobot's files; the importer records it, so the imported teacher applies
that registered feature map to raw observations when it acts.

Samples are built as LeRobot's dataset builds them with `delta_timestamps`: for frame t the
observations t - n_obs_steps + 1 .. t and the actions t - n_obs_steps + 1 .. t - n_obs_steps +
horizon, indices clamped to the episode (padding repeats the first/last frame;
`do_mask_loss_for_padding` is off, LeRobot's default), the last `drop_n_last_frames` frames of
each episode not used as anchors. The loop calls the policy's own `forward` (its diffusion loss)
with the preprocessor's normalised batch; `save_pretrained` of the policy and of the
pre/post-processors writes the directory LeRobot itself writes.

    python scripts/import/train_lerobot_avoiding.py --data results/e2e/avoiding_train.npz \
        --out results/e2e/lerobot_avoiding

Versions: scripts/import/requirements-fixtures.txt (Python 3.12).
"""

import argparse
import json
import os
import time

import numpy as np
import torch


def lerobot_samples(obs_seq, act_seq, mask, n_obs, horizon, drop_last):
    """Indices of LeRobot-style samples: (episode, observation frames, action frames)."""
    lengths = mask.sum(axis=1).astype(int)
    ep, o_idx, a_idx = [], [], []
    for e, n in enumerate(lengths):
        for t in range(max(n - drop_last, 1)):
            ep.append(e)
            o_idx.append(np.clip(np.arange(t - n_obs + 1, t + 1), 0, n - 1))
            a_idx.append(np.clip(np.arange(t - n_obs + 1, t - n_obs + 1 + horizon), 0, n - 1))
    ep = np.array(ep)
    return ep, np.stack(o_idx), np.stack(a_idx), lengths


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", required=True, help="npz of `cargo xtask demos avoiding --export`")
    ap.add_argument("--out", required=True, help="directory to save_pretrained into")
    # The teacher of docs/import.md, "Distilling an imported policy": 4,000 steps of 256 at a
    # U-Net of 64/128/256 channels (about 24 minutes on 2 CPU threads).
    ap.add_argument("--steps", type=int, default=4000)
    ap.add_argument("--batch", type=int, default=256)
    ap.add_argument("--down-dims", type=int, nargs="+", default=[64, 128, 256])
    ap.add_argument("--lr", type=float, default=1e-3)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=1)
    a = ap.parse_args()

    from importlib.metadata import version as pkg_version

    from lerobot.configs.types import FeatureType, NormalizationMode, PolicyFeature
    from lerobot.policies.diffusion.configuration_diffusion import DiffusionConfig
    from lerobot.policies.diffusion.modeling_diffusion import DiffusionPolicy
    from lerobot.policies.factory import make_pre_post_processors

    torch.manual_seed(a.seed)
    np.random.seed(a.seed)
    torch.set_num_threads(a.threads)

    z = np.load(a.data)
    obs_seq = z["observations_seq"].astype(np.float32)  # N x T x 4: (c, d - c)
    act_seq = z["actions_seq"].astype(np.float32)  # N x T x 2
    mask = z["existence_mask"] > 0.5
    assert obs_seq.shape[-1] == 4 and act_seq.shape[-1] == 2, (obs_seq.shape, act_seq.shape)

    n_obs, horizon, n_act = 2, 16, 8
    cfg = DiffusionConfig(
        input_features={
            "observation.state": PolicyFeature(type=FeatureType.STATE, shape=(2,)),
            "observation.environment_state": PolicyFeature(type=FeatureType.ENV, shape=(2,)),
        },
        output_features={"action": PolicyFeature(type=FeatureType.ACTION, shape=(2,))},
        normalization_mapping={
            "VISUAL": NormalizationMode.MEAN_STD,
            "STATE": NormalizationMode.MIN_MAX,
            "ENV": NormalizationMode.MIN_MAX,
            "ACTION": NormalizationMode.MIN_MAX,
        },
        n_obs_steps=n_obs,
        horizon=horizon,
        n_action_steps=n_act,
        drop_n_last_frames=horizon - n_act - n_obs + 1,
        down_dims=tuple(a.down_dims),
        kernel_size=5,
        n_groups=8,
        diffusion_step_embed_dim=32,
        use_film_scale_modulation=True,
        noise_scheduler_type="DDIM",
        num_train_timesteps=100,
        num_inference_steps=10,
        beta_schedule="squaredcos_cap_v2",
        prediction_type="epsilon",
        clip_sample=True,
        clip_sample_range=1.0,
        optimizer_lr=a.lr,
        device="cpu",
        push_to_hub=False,
    )
    policy = DiffusionPolicy(cfg)

    # Per-frame statistics over every valid frame, as LeRobot's dataset statistics.
    frames_obs = obs_seq[mask]
    frames_act = act_seq[mask]

    def stats(x):
        x = torch.from_numpy(x)
        return {"min": x.min(0).values, "max": x.max(0).values, "mean": x.mean(0), "std": x.std(0)}

    dataset_stats = {
        "observation.state": stats(frames_obs[:, :2]),
        "observation.environment_state": stats(frames_obs[:, 2:]),
        "action": stats(frames_act),
    }
    pre, post = make_pre_post_processors(cfg, dataset_stats=dataset_stats)

    ep, o_idx, a_idx, _ = lerobot_samples(obs_seq, act_seq, mask, n_obs, horizon, cfg.drop_n_last_frames)
    obs_windows = torch.from_numpy(obs_seq[ep[:, None], o_idx])  # S x n_obs x 4
    act_chunks = torch.from_numpy(act_seq[ep[:, None], a_idx])  # S x horizon x 2
    n = len(ep)
    print(f"{n} samples from {mask.shape[0]} episodes; {sum(p.numel() for p in policy.parameters())} parameters")

    opt = torch.optim.AdamW(policy.parameters(), lr=a.lr, betas=cfg.optimizer_betas, eps=cfg.optimizer_eps,
                            weight_decay=cfg.optimizer_weight_decay)
    warmup = min(cfg.scheduler_warmup_steps, a.steps // 10)

    def lr_at(step):
        if step < warmup:
            return (step + 1) / warmup
        p = (step - warmup) / max(1, a.steps - warmup)
        return 0.5 * (1.0 + np.cos(np.pi * p))

    sched = torch.optim.lr_scheduler.LambdaLR(opt, lr_at)
    gen = torch.Generator().manual_seed(a.seed)
    policy.train()
    t0 = time.time()
    losses = []
    for step in range(a.steps):
        idx = torch.randint(0, n, (a.batch,), generator=gen)
        w, c = obs_windows[idx], act_chunks[idx]
        batch = pre({
            "observation.state": w[..., :2],
            "observation.environment_state": w[..., 2:],
            "action": c,
        })
        batch["action_is_pad"] = torch.zeros(a.batch, horizon, dtype=torch.bool)
        loss, _ = policy.forward(batch)
        opt.zero_grad()
        loss.backward()
        torch.nn.utils.clip_grad_norm_(policy.parameters(), 10.0)
        opt.step()
        sched.step()
        losses.append(loss.item())
        if step % 250 == 0 or step + 1 == a.steps:
            print(f"step {step:5d}  loss {np.mean(losses[-250:]):.4f}  {time.time() - t0:.0f} s", flush=True)
    train_seconds = time.time() - t0
    policy.eval()

    os.makedirs(a.out, exist_ok=True)
    policy.save_pretrained(a.out)
    pre.save_pretrained(a.out)
    post.save_pretrained(a.out)
    with open(os.path.join(a.out, "vdd_features.json"), "w") as f:
        json.dump({"name": "position_and_lag", "version": 1}, f)
    info = {
        "train_seconds": train_seconds,
        "steps": a.steps,
        "batch": a.batch,
        "lr": a.lr,
        "down_dims": a.down_dims,
        "seed": a.seed,
        "threads": a.threads,
        "samples": n,
        "final_loss": float(np.mean(losses[-250:])),
        "versions": {"lerobot": pkg_version("lerobot"), "torch": torch.__version__, "numpy": np.__version__},
    }
    with open(os.path.join(a.out, "training.json"), "w") as f:
        json.dump(info, f, indent=1)
    print(json.dumps(info))


if __name__ == "__main__":
    main()
