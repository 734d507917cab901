"""A distilled policy drives gymnasium's Pendulum-v1: the loop is Python's, the actions Rust's.

    python crates/vdd-py/examples/gym_pendulum.py [--episodes 3] [--iterations 400]
    python crates/vdd-py/examples/gym_pendulum.py --model results/avoiding/<run>/models/vdd-beso-s0.safetensors

Without --model, a teacher written in NumPy (a swing-up controller with Gaussian action noise,
known by its score) is distilled by the Rust trainer through ``vdd.distill``, and the student
drives Pendulum-v1. With --model, a saved policy (e.g. the Avoiding student of
``cargo xtask experiment avoiding --quick --methods vdd-beso``) is timed on random
observations instead (its environment is Rust's, not gymnasium's).

Either way it prints the µs per ``act`` call measured from Python beside Rust's own figure
for the same policy and observations (``Policy.rust_us_per_act``: ``vdd_tasks::timing``, the
recipes' measurement), and the difference: what the Python binding costs per call.
"""

import argparse
import statistics
import time

import numpy as np

import vdd

ACTION_STD = 0.2
MAX_TORQUE = 2.0


def controller(obs):
    """A swing-up controller: PD near the top, energy pumping elsewhere (θ = 0 is upright)."""
    cos, sin, vel = obs[:, 0], obs[:, 1], obs[:, 2]
    theta = np.arctan2(sin, cos)
    pd = -(10.0 * theta + 2.0 * vel)
    energy = 0.5 * vel**2 + 10.0 * (cos - 1.0)  # 0 at the top, at rest
    pump = -np.sign(vel * cos + 1e-6) * np.sign(energy) * MAX_TORQUE
    u = np.where(cos > 0.85, pd, pump)
    return np.clip(u, -MAX_TORQUE, MAX_TORQUE)[:, None]


def teacher_score(actions, states, sigma):
    """∇_a log N(a; controller(s), ACTION_STD² + σ²): the teacher's score at noise level σ."""
    var = ACTION_STD**2 + sigma[:, None].astype(np.float64) ** 2
    return ((controller(states) - actions) / var).astype(np.float32)


def python_us_per_act(policy, observations, rounds=5, min_round_s=0.02):
    """µs per ``policy.act`` call from Python: the median of ``rounds`` timed loops over the
    observations (each at least ``min_round_s`` long), as Rust's figure is taken."""
    for o in observations[:100]:
        policy.act(o)
    per_round = []
    for _ in range(rounds):
        calls, t0 = 0, time.perf_counter()
        while True:
            for o in observations:
                policy.act(o)
            calls += len(observations)
            elapsed = time.perf_counter() - t0
            if elapsed >= min_round_s:
                break
        per_round.append(elapsed * 1e6 / calls)
    return statistics.median(per_round)


def report(policy, observations, in_loop_us=None):
    obs = np.ascontiguousarray(observations, dtype=np.float32)
    py_us = python_us_per_act(policy, list(obs))
    rust_us = policy.rust_us_per_act(obs)
    if in_loop_us is not None:
        print(f"act from Python inside the env loop: {in_loop_us:.2f} µs per call (mean)")
    print(f"act from Python: {py_us:.2f} µs per call (median of 5 rounds)")
    print(f"act in Rust    : {rust_us:.2f} µs per call (vdd_tasks::timing, median of 5 rounds)")
    print(f"Python binding overhead: {py_us - rust_us:+.2f} µs per call")


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", help="time a saved policy instead of distilling one")
    parser.add_argument("--episodes", type=int, default=3)
    parser.add_argument("--iterations", type=int, default=400)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    if args.model:
        policy = vdd.Policy.load(args.model)
        print(policy)
        rng = np.random.default_rng(args.seed)
        observations = rng.uniform(-0.5, 0.5, size=(200, policy.obs_dim))
        report(policy, observations)
        return

    import gymnasium as gym

    rng = np.random.default_rng(args.seed)
    theta = rng.uniform(-np.pi, np.pi, 512)
    vel = rng.uniform(-8.0, 8.0, 512)
    states = np.stack([np.cos(theta), np.sin(theta), vel], axis=1).astype(np.float32)
    t0 = time.perf_counter()
    policy = vdd.distill(teacher_score, states, action_dim=1, experts=4,
                         iterations=args.iterations, seed=args.seed, vi_samples=16)
    print(f"distilled {policy} in {time.perf_counter() - t0:.1f} s")

    env = gym.make("Pendulum-v1")
    seen, act_ns, calls = [], 0, 0
    for episode in range(args.episodes):
        obs, _ = env.reset(seed=args.seed + episode)
        policy.reset()
        total, done = 0.0, False
        while not done:
            t = time.perf_counter_ns()
            action = policy.act(obs)
            act_ns += time.perf_counter_ns() - t
            calls += 1
            seen.append(obs)
            obs, reward, terminated, truncated, _ = env.step(np.clip(action, -2.0, 2.0))
            total += reward
            done = terminated or truncated
        print(f"episode {episode}: return {total:.1f}")
    env.close()
    report(policy, np.array(seen), in_loop_us=act_ns / calls / 1e3)


if __name__ == "__main__":
    main()
