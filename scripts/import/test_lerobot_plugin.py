#!/usr/bin/env python3
"""Checks of the `lerobot_policy_vdd` plugin (crates/vdd-py/lerobot_policy_vdd). Not part of CI: it
needs PyTorch, lerobot 0.6.1, the `vdd` wheel and the plugin installed, plus a student file and
its LeRobot teacher directory:

    VDD_STUDENT=path/to/vdd-lerobot-s0.safetensors VDD_TEACHER_DIR=path/to/lerobot_teacher \
        python scripts/import/test_lerobot_plugin.py      # or: python -m pytest <this file>

Without the two variables every check is skipped.
"""

import os
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch

STUDENT = os.environ.get("VDD_STUDENT")
TEACHER = os.environ.get("VDD_TEACHER_DIR")


class Skip(Exception):
    pass


def _need_files():
    if not (STUDENT and TEACHER):
        try:
            import pytest

            pytest.skip("set VDD_STUDENT and VDD_TEACHER_DIR")
        except ImportError:
            raise Skip("set VDD_STUDENT and VDD_TEACHER_DIR") from None


def _raises(exc, fragment, fn, *args, **kwargs):
    try:
        fn(*args, **kwargs)
    except exc as e:
        assert fragment in str(e), f"{fragment!r} not in {e!r}"
        return
    raise AssertionError(f"no {exc.__name__} raised")


def _converted(tmp: Path, seed: int = 0):
    from lerobot_policy_vdd.convert import convert

    out = tmp / f"vdd-s{seed}"
    convert(STUDENT, TEACHER, out, seed=seed)
    return out


def _load(directory: Path):
    from lerobot.configs import PreTrainedConfig
    from lerobot.policies.factory import get_policy_class, make_pre_post_processors

    cfg = PreTrainedConfig.from_pretrained(directory)
    policy = get_policy_class(cfg.type).from_pretrained(directory)
    pre, post = make_pre_post_processors(cfg, pretrained_path=str(directory))
    return policy, pre, post


def _obs(rng, b=1):
    c = rng.uniform(0.3, 0.7, size=(b, 2)).astype(np.float32)
    lag = rng.normal(0, 0.003, size=(b, 2)).astype(np.float32)
    return {"observation.state": torch.from_numpy(c), "observation.environment_state": torch.from_numpy(lag)}


def test_the_plugin_registers_through_lerobots_discovery():
    from lerobot.configs import PreTrainedConfig
    from lerobot.policies.factory import get_policy_class, make_pre_post_processors
    from lerobot.utils.import_utils import register_third_party_plugins

    register_third_party_plugins()
    assert "vdd" in PreTrainedConfig.get_known_choices()
    from lerobot_policy_vdd import VddConfig, VddPolicy

    assert get_policy_class("vdd") is VddPolicy
    # `--policy.type=vdd` as LeRobot's command lines parse it (draccus).
    from dataclasses import dataclass

    import draccus

    @dataclass
    class Cli:
        policy: PreTrainedConfig | None = None

    cli = draccus.parse(Cli, args=["--policy.type=vdd", "--policy.seed=3", "--policy.device=cpu"])
    assert isinstance(cli.policy, VddConfig) and cli.policy.seed == 3
    from lerobot.configs.types import FeatureType, PolicyFeature

    cfg = VddConfig(
        input_features={
            "observation.state": PolicyFeature(FeatureType.STATE, (2,)),
            "observation.environment_state": PolicyFeature(FeatureType.ENV, (2,)),
        },
        output_features={"action": PolicyFeature(FeatureType.ACTION, (2,))},
        device="cpu",
    )
    keys = ["observation.state", "observation.environment_state", "action"]
    stats = {k: {"min": torch.zeros(2), "max": torch.ones(2)} for k in keys}
    pre, post = make_pre_post_processors(cfg, dataset_stats=stats)  # make_vdd_pre_post_processors
    out = pre({"observation.state": torch.full((2,), 0.5), "observation.environment_state": torch.ones(2)})
    assert torch.allclose(out["observation.state"], torch.zeros(1, 2))
    # A fresh policy has no student: a clear error, not a traceback from None.
    _raises(RuntimeError, "no student loaded", VddPolicy(cfg).select_action, out)
    _raises(ValueError, "features =", VddConfig, features="bogus v1", device="cpu")
    _raises(ValueError, "n_action_steps = 16", VddConfig, n_action_steps=16, device="cpu")


def test_save_load_round_trip_acts_as_vdd_policy():
    _need_files()
    import vdd

    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        out = _converted(tmp)
        policy, pre, post = _load(out)
        # save_pretrained again: the same mixture bytes, loadable again.
        again = tmp / "again"
        policy.save_pretrained(again)
        from safetensors.torch import load_file

        a, b = load_file(out / "model.safetensors"), load_file(again / "model.safetensors")
        assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
        assert Path(STUDENT).read_bytes() == a["vdd.mixture"].numpy().tobytes()

        ref = vdd.Policy.load(STUDENT)
        ref.seed(0)
        rng = np.random.default_rng(1)
        from lerobot_policy_vdd.modeling_vdd import raw_observation

        policy.reset()
        for _ in range(20):
            obs = _obs(rng, b=3)
            got = post(policy.select_action(pre(dict(obs)))).numpy()
            per_step = torch.cat([obs["observation.state"], obs["observation.environment_state"]], -1).numpy()
            want = ref.act_batch(raw_observation(per_step, ref.features))
            assert np.abs(got - want).max() <= 1e-5, np.abs(got - want).max()
        # A different seed draws other experts: the seeding is what makes the two agree.
        other, pre2, post2 = _load(_converted(tmp, seed=7))
        rng = np.random.default_rng(1)
        ref = vdd.Policy.load(STUDENT)
        ref.seed(0)
        diffs = []
        for _ in range(20):
            obs = _obs(rng, b=3)
            got = post2(other.select_action(pre2(dict(obs)))).numpy()
            per_step = torch.cat([obs["observation.state"], obs["observation.environment_state"]], -1).numpy()
            diffs.append(np.abs(got - ref.act_batch(raw_observation(per_step, ref.features))).max())
        assert max(diffs) > 1e-5

        chunk = policy.predict_action_chunk(
            {
                k: v.unsqueeze(1).repeat(1, 2, 1)
                for k, v in pre(dict(_obs(rng, b=4))).items()
                if k.startswith("observation")
            }
        )
        assert tuple(chunk.shape) == (4, 8, 2)


def test_select_action_follows_lerobots_queues():
    """Each executed block of `n_action_steps` actions is, for one expert, the mean chunk at
    indices `n_obs_steps - 1 ..` of the window LeRobot's own `populate_queues` holds when its
    action queue runs empty (the first observation repeated at the start)."""
    _need_files()
    from collections import deque

    from lerobot.policies.utils import populate_queues
    from lerobot_policy_vdd.modeling_vdd import raw_observation

    with tempfile.TemporaryDirectory() as tmp:
        policy, pre, post = _load(_converted(Path(tmp)))
        cfg = policy.config
        rng = np.random.default_rng(3)
        keys = ["observation.state", "observation.environment_state"]
        queues = {k: deque(maxlen=cfg.n_obs_steps) for k in keys}
        policy.reset()
        b, checked = 3, 0
        for block in range(4):
            for step in range(cfg.n_action_steps):
                obs = _obs(rng, b=b)
                populate_queues(queues, obs)
                if step == 0:
                    window = torch.cat([torch.stack(list(queues[k]), dim=1) for k in keys], -1).numpy()
                    raw = raw_observation(window, policy.student.features).reshape(b, -1)
                    _, means, _ = policy.student.components(raw)
                    chunks = means.reshape(b, means.shape[1], cfg.horizon, -1)
                    start = cfg.n_obs_steps - 1
                    candidates = chunks[:, :, start : start + cfg.n_action_steps]
                    executed = []
                executed.append(post(policy.select_action(pre(dict(obs)))).numpy())
            executed = np.stack(executed, 1)  # (b, n_action_steps, action_dim)
            for row in range(b):
                err = np.abs(candidates[row] - executed[row][None]).max(axis=(1, 2)).min()
                assert err <= 1e-5, (block, row, err)
                checked += 1
        assert checked == 12


def test_bad_input_gets_clear_errors():
    _need_files()
    from lerobot_policy_vdd import VddPolicy

    with tempfile.TemporaryDirectory() as tmp:
        tmp = Path(tmp)
        policy, pre, _ = _load(_converted(tmp))
        rng = np.random.default_rng(2)
        batch = pre(dict(_obs(rng, b=2)))
        only_state = {"observation.state": batch["observation.state"]}
        _raises(ValueError, "lacks 'observation.environment_state'", policy.select_action, only_state)
        bad = dict(batch, **{"observation.state": torch.zeros(2, 3)})
        _raises(ValueError, "expected (B, 2)", policy.select_action, bad)
        bad = dict(batch, **{"observation.state": torch.full((2, 2), float("nan"))})
        _raises(ValueError, "non-finite", policy.select_action, bad)
        policy.select_action(batch)
        _raises(ValueError, "batch size changed from 2 to 1", policy.select_action, pre(dict(_obs(rng, b=1))))
        policy.reset()
        policy.select_action(pre(dict(_obs(rng, b=1))))
        _raises(NotImplementedError, "not trained in PyTorch", policy.forward, batch)
        # The teacher's own model.safetensors is not a vdd policy.
        load = VddPolicy._load_as_safetensor
        teacher_model = str(Path(TEACHER) / "model.safetensors")
        _raises(ValueError, "not a vdd policy", load, policy, teacher_model, "cpu", False)
        missing = str(tmp / "model.safetensors")
        _raises(FileNotFoundError, "no model.safetensors", load, policy, missing, "cpu", False)
        from lerobot_policy_vdd.convert import convert, main

        missing = tmp / "missing.safetensors"
        _raises(FileNotFoundError, "no student file", convert, missing, TEACHER, tmp / "x")
        _raises(FileNotFoundError, "no LeRobot teacher directory", convert, STUDENT, tmp, tmp / "x")
        assert main(["--student", str(tmp / "missing"), "--teacher", TEACHER, "--out", str(tmp / "x")]) == 2
        # A configuration that does not fit the student is refused, naming the fields.
        policy.config.n_action_steps = 4
        want = "execute_steps (n_action_steps): student 8, config 4"
        _raises(ValueError, want, policy.load_mixture, STUDENT)


if __name__ == "__main__":
    failed = 0
    for name, fn in list(globals().items()):
        if name.startswith("test_") and callable(fn):
            try:
                fn()
                print(f"ok    {name}")
            except Skip as e:
                print(f"skip  {name}: {e}")
            except Exception as e:  # noqa: BLE001
                failed += 1
                print(f"FAIL  {name}: {type(e).__name__}: {e}")
    sys.exit(1 if failed else 0)
