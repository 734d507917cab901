#!/usr/bin/env python3
"""The student goes back to LeRobot: load a distilled VDD student through LeRobot (the
`lerobot_policy_vdd` plugin, `--policy.type=vdd`) beside its LeRobot teacher, feed both the same
observation sequences, and compare the plugin's actions with the Rust `vdd.Policy`'s.

Not part of CI (it needs PyTorch and LeRobot). Needs Python 3.12 with lerobot 0.6.1, the `vdd`
wheel (crates/vdd-py) and the plugin (`pip install -e crates/vdd-py/lerobot_policy_vdd`).

    python scripts/import/lerobot_roundtrip.py --teacher results/e2e/lerobot_avoiding \
        --student results/e2e/run-s0/models/vdd-lerobot.safetensors \
        --out results/e2e/vdd_lerobot --data results/e2e/avoiding_train.npz

Steps:
1. `lerobot_policy_vdd.convert.convert` writes `--out`, a LeRobot directory of the student
   (config.json, model.safetensors, the teacher's processor files) -- skipped with
   `--no-convert` when `--out` already holds one.
2. LeRobot's plugin discovery (`register_third_party_plugins`) registers the `vdd` type; both
   policies load through LeRobot's own `get_policy_class(type).from_pretrained(dir)` and
   `make_pre_post_processors(config, pretrained_path=dir)`.
3. For each of `--episodes` demonstrations of the npz (observations already through the
   `position_and_lag` map, i.e. per step `(c, d - c)` = `(observation.state,
   observation.environment_state)`), every step is fed to
   * the plugin: `postprocessor(policy.select_action(preprocessor(batch)))`,
   * the Rust student: `vdd.Policy.load(student).act(raw)`, `raw = (d, c)` the task's raw
     observation, seeded as the plugin's (`config.seed`),
   * the teacher: LeRobot's `DiffusionPolicy.select_action` (torch seeded with `--seed`),
   each reset at the episode's start. Then the same episodes again as one batch (one row per
   episode, `act_batch` on the Rust side) over the steps all of them have.
Prints the max abs difference plugin vs `vdd.Policy` (the acceptance bar: <= 1e-5), the
teacher's actions beside the student's, and the wall time per action of each (batch 1, one
torch thread; the LeRobot ones include their processors).
"""

from __future__ import annotations

import argparse
import logging
import sys
import time
from pathlib import Path

import numpy as np
import torch


def load_through_lerobot(directory: Path):
    """A policy and its processors, as LeRobot's scripts load them."""
    from lerobot.configs import PreTrainedConfig
    from lerobot.policies.factory import get_policy_class, make_pre_post_processors

    cfg = PreTrainedConfig.from_pretrained(directory)
    cfg.device = "cpu"
    policy = get_policy_class(cfg.type).from_pretrained(directory, config=cfg)
    pre, post = make_pre_post_processors(cfg, pretrained_path=str(directory))
    return cfg, policy, pre, post


def lerobot_batch(obs: np.ndarray) -> dict[str, torch.Tensor]:
    """`(B, 4)` featured observations `(c, d - c)` as LeRobot's observation batch."""
    obs = torch.from_numpy(np.ascontiguousarray(obs, dtype=np.float32))
    return {"observation.state": obs[:, :2], "observation.environment_state": obs[:, 2:]}


def main() -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--teacher", type=Path, required=True, help="LeRobot DiffusionPolicy directory")
    p.add_argument("--student", type=Path, required=True, help="the distilled mixture file")
    p.add_argument("--out", type=Path, required=True, help="the student's LeRobot directory")
    p.add_argument("--no-convert", action="store_true", help="--out already holds the student")
    p.add_argument("--data", type=Path, required=True, help="exported demonstrations (npz)")
    p.add_argument("--episodes", type=int, default=10)
    p.add_argument("--steps", type=int, default=100, help="steps per episode (at most)")
    p.add_argument("--seed", type=int, default=0, help="torch seed of the teacher's sampling")
    p.add_argument("--show", type=int, default=10, help="steps of the first episode to print")
    args = p.parse_args()
    logging.basicConfig(level=logging.WARNING)
    torch.set_num_threads(1)

    for path, what in ((args.teacher, "teacher directory"), (args.data, "npz")):
        if not path.exists():
            print(f"error: no {what} at {path}", file=sys.stderr)
            return 2

    from lerobot.configs import PreTrainedConfig
    from lerobot.utils.import_utils import register_third_party_plugins

    register_third_party_plugins()
    if "vdd" not in PreTrainedConfig.get_known_choices():
        print("error: the `vdd` policy type is not registered: pip install -e crates/vdd-py/lerobot_policy_vdd",
              file=sys.stderr)
        return 2
    import vdd
    from lerobot_policy_vdd.convert import convert
    from lerobot_policy_vdd.modeling_vdd import raw_observation

    if not args.no_convert:
        convert(args.student, args.teacher, args.out)
        print(f"converted {args.student} -> {args.out}: {sorted(x.name for x in args.out.iterdir())}")

    s_cfg, student, s_pre, s_post = load_through_lerobot(args.out)
    t_cfg, teacher, t_pre, t_post = load_through_lerobot(args.teacher)
    print(f"student: {type(student).__module__}.{type(student).__name__} (type {s_cfg.type}), "
          f"features {s_cfg.features}, n_obs_steps {s_cfg.n_obs_steps}, horizon {s_cfg.horizon}, "
          f"n_action_steps {s_cfg.n_action_steps}, seed {s_cfg.seed}")
    print(f"teacher: {type(teacher).__name__} (type {t_cfg.type}), "
          f"{t_cfg.noise_scheduler_type} {t_cfg.num_inference_steps} steps")
    reference = vdd.Policy.load(args.student)
    reference.seed(s_cfg.seed)
    print(f"vdd.Policy: {reference.num_experts} experts, window {reference.obs_window}, "
          f"chunk {reference.action_chunk}, features {reference.features}")

    data = np.load(args.data)
    obs_seq, mask = data["observations_seq"], data["existence_mask"]
    if obs_seq.ndim != 3 or obs_seq.shape[2] != 4:
        print(f"error: observations_seq has shape {obs_seq.shape}, expected (N, T, 4)", file=sys.stderr)
        return 2
    episodes = list(range(min(args.episodes, obs_seq.shape[0])))
    lengths = [min(int(mask[e].sum()), args.steps) for e in episodes]

    def run(rows: list[np.ndarray], steps: int):
        """Lockstep over `steps` steps of `rows` (each `(T, 4)`): plugin, Rust, teacher."""
        student.reset(), reference.reset(), teacher.reset()
        plug, rust, teach = [], [], []
        for t in range(steps):
            obs = np.stack([r[t] for r in rows])
            batch = lerobot_batch(obs)
            t0 = time.perf_counter()
            plug.append(s_post(student.select_action(s_pre(dict(batch)))).numpy())
            t1 = time.perf_counter()
            rust.append(reference.act_batch(raw_observation(obs, reference.features)))
            t2 = time.perf_counter()
            with torch.no_grad():
                teach.append(t_post(teacher.select_action(t_pre(dict(batch)))).numpy())
            t3 = time.perf_counter()
            if len(rows) == 1:
                clock["plugin"] += t1 - t0
                clock["vdd.Policy"] += t2 - t1
                clock["teacher"] += t3 - t2
        return np.stack(plug, 1), np.stack(rust, 1), np.stack(teach, 1)

    torch.manual_seed(args.seed)
    clock = {"plugin": 0.0, "vdd.Policy": 0.0, "teacher": 0.0}
    worst, calls, scale, t0 = 0.0, 0, 0.0, time.time()
    print("\nepisode  steps  max|plugin - vdd.Policy|  max|plugin - teacher|")
    first = None
    for e, n in zip(episodes, lengths):
        plug, rust, teach = run([obs_seq[e]], n)
        d = float(np.abs(plug - rust).max())
        worst, calls = max(worst, d), calls + n
        scale = max(scale, float(np.abs(rust).max()))
        print(f"{e:7d}  {n:5d}  {d:24.3e}  {float(np.abs(plug - teach).max()):21.3e}")
        if first is None:
            first = (plug[0], rust[0], teach[0])
    n = min(lengths)
    plug, rust, teach = run([obs_seq[e] for e in episodes], n)
    d = float(np.abs(plug - rust).max())
    worst, calls = max(worst, d), calls + n * len(episodes)
    print(f"batched  {len(episodes)}x{n:<3d}  {d:24.3e}  {float(np.abs(plug - teach).max()):21.3e}")

    plug, rust, teach = first
    print(f"\nfirst episode, first {args.show} steps (actions: plugin | vdd.Policy | teacher):")
    for t in range(min(args.show, len(plug))):
        fmt = lambda a: "(" + ", ".join(f"{x:+.6f}" for x in a) + ")"  # noqa: E731
        print(f"  t={t:3d}  {fmt(plug[t])} | {fmt(rust[t])} | {fmt(teach[t])}")
    single = sum(lengths)
    print(f"\nwall time per action, batch 1 ({single} actions; processors included for LeRobot's): "
          + ", ".join(f"{k} {1e6 * v / single:.0f} us" for k, v in clock.items()))
    ok = worst <= 1e-5
    print(f"\nmax abs diff plugin vs vdd.Policy over {calls} actions: {worst:.3e} "
          f"({'within' if ok else 'ABOVE'} 1e-5; largest |action| {scale:.3e}); {time.time() - t0:.1f} s")
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
