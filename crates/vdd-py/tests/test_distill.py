"""vdd.distill: a NumPy teacher drives the Rust trainer; its errors surface in Python."""

import traceback

import numpy as np
import pytest

import vdd
from conftest import MODES, four_modes_score


def test_distilling_four_gaussians_covers_all_four_modes(four_modes_policy):
    lg, mu, L = four_modes_policy.components(np.zeros((1, 1), dtype=np.float32))
    # Every mode has an expert whose mean sits on it.
    dist = np.linalg.norm(mu[0][:, None, :] - MODES[None, :, :], axis=2)  # (experts, modes)
    assert np.all(dist.min(axis=0) < 0.3), dist.min(axis=0)
    # And the policy's actions land on every mode.
    four_modes_policy.seed(0)
    actions = four_modes_policy.act_batch(np.zeros((2000, 1), dtype=np.float32))
    nearest = np.linalg.norm(actions[:, None, :] - MODES[None], axis=2).argmin(axis=1)
    share = np.bincount(nearest, minlength=4) / len(actions)
    assert np.all(share > 0.1), share


def test_an_exception_in_score_fn_surfaces_with_its_traceback():
    def broken_teacher(actions, states, sigma):
        raise KeyError("the teacher's server is down")

    with pytest.raises(KeyError, match="server is down") as info:
        vdd.distill(broken_teacher, np.zeros((4, 1)), action_dim=2, iterations=3)
    frames = [f.name for f in traceback.extract_tb(info.value.__traceback__)]
    assert "broken_teacher" in frames, frames


def test_a_score_of_the_wrong_shape_is_a_value_error():
    with pytest.raises(ValueError, match=r"score_fn returned shape \(.*, 3\)"):
        vdd.distill(
            lambda a, s, sig: np.zeros((len(a), 3)), np.zeros((4, 1)), action_dim=2, iterations=1
        )


def test_settings_map_onto_the_configurations_and_unknown_ones_are_named():
    p = vdd.distill(
        four_modes_score,
        np.zeros((4, 1)),
        action_dim=2,
        experts=2,
        iterations=2,
        expert_kind="full",
        noise={"kind": "fixed", "level": 0.1},
        experts_network={"hidden_dim": 8, "num_blocks": 1, "activation": "relu"},
    )
    assert p.num_experts == 2
    with pytest.raises(ValueError, match="unknown setting `hidden`"):
        vdd.distill(four_modes_score, np.zeros((4, 1)), action_dim=2, hidden=3)
    with pytest.raises(ValueError, match="give it as experts="):
        vdd.distill(four_modes_score, np.zeros((4, 1)), action_dim=2, num_experts=2)
    with pytest.raises(ValueError, match="invalid student setting: unknown variant `round`"):
        vdd.distill(four_modes_score, np.zeros((4, 1)), action_dim=2, expert_kind="round")


def test_the_score_fn_gets_float32_arrays_of_the_documented_shapes():
    seen = []

    def teacher(actions, states, sigma):
        seen.append((actions.shape, states.shape, sigma.shape, actions.dtype))
        return four_modes_score(actions, states, sigma)

    vdd.distill(teacher, np.zeros((4, 3)), action_dim=2, experts=2, iterations=1, batch_size=4,
                vi_samples=5)
    (a, s, sig, dtype) = seen[0]
    assert a[1] == 2 and s[1] == 3 and a[0] == s[0] == sig[0] and dtype == np.float32


def test_toy_defaults_stay_reachable_and_trainer_settings_are_accepted():
    toy = vdd.distill(four_modes_score, np.zeros((4, 1)), action_dim=2, experts=2, iterations=2,
                      defaults="toy")
    assert toy.num_experts == 2
    auto = vdd.distill(four_modes_score, np.zeros((4, 1)), action_dim=2, experts=2,
                       iterations=2, noise_anneal_until=0.5, batch_size=4)
    assert auto.num_experts == 2
    # Settings that a default configuration leaves out of its serialised form.
    both = vdd.distill(four_modes_score, np.zeros((4, 1)), action_dim=2, experts=2,
                       iterations=2, score_at="noised_sample",
                       state_noise={"share": 0.5, "std": 0.1}, experts_per_state=1)
    assert both.num_experts == 2
    with pytest.raises(ValueError, match="setting `defaults`: expected 'auto' or 'toy'"):
        vdd.distill(four_modes_score, np.zeros((4, 1)), action_dim=2, defaults="paper")


def test_noise_range_bounds_the_levels_a_python_teacher_is_asked_at():
    """`noise_range=(min, max)` states the levels a score_fn is trustworthy at: the automatic
    plan anneals down to `min` (without it, further), and a noise setting outside is refused (`VddError`)."""
    rng = np.random.default_rng(0)

    def sample_fn(states):
        return MODES[rng.integers(4, size=len(states))] + 0.1 * rng.standard_normal(
            (len(states), 2)
        )

    def lowest_level(**settings):
        seen = []

        def score(actions, states, sigma):
            seen.append(float(sigma.min()))
            return four_modes_score(actions, states, sigma)

        vdd.distill(score, np.zeros((8, 1)), action_dim=2, experts=4, iterations=40,
                    sample_fn=sample_fn, **settings)
        return min(seen)

    assert lowest_level(noise_range=(0.3, 5.0)) >= 0.3 - 1e-6
    assert lowest_level() < 0.3
    with pytest.raises(vdd.VddError, match="outside the teacher's range"):
        vdd.distill(four_modes_score, np.zeros((4, 1)), action_dim=2, iterations=2,
                    noise={"kind": "fixed", "level": 0.1}, noise_range=(0.3, 5.0))
    with pytest.raises(ValueError, match="setting `noise_range`"):
        vdd.distill(four_modes_score, np.zeros((4, 1)), action_dim=2, noise_range=(1.0, 0.5))
