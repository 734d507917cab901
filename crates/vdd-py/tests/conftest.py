"""Fixtures: a four-mode 2-D Gaussian mixture teacher and a policy distilled from it."""

import numpy as np
import pytest

import vdd

MODES = np.array([[2.0, 2.0], [-2.0, 2.0], [-2.0, -2.0], [2.0, -2.0]])
MODE_STD = 0.3


def four_modes_score(actions, states, sigma):
    """The exact score of an equal mixture of N(mode, MODE_STD² I), smoothed by N(0, σ² I)."""
    var = MODE_STD**2 + sigma.astype(np.float64)[:, None] ** 2  # (n, 1)
    diff = MODES[None, :, :] - actions[:, None, :]  # (n, 4, 2)
    logits = -(diff**2).sum(-1) / (2.0 * var)
    w = np.exp(logits - logits.max(axis=1, keepdims=True))
    w /= w.sum(axis=1, keepdims=True)
    return ((w[:, :, None] * diff).sum(axis=1) / var).astype(np.float32)


@pytest.fixture(scope="session")
def four_modes_policy():
    states = np.zeros((16, 1), dtype=np.float32)
    return vdd.distill(
        four_modes_score,
        states,
        action_dim=2,
        experts=8,
        iterations=300,
        seed=0,
        batch_size=16,
        vi_samples=32,
    )


@pytest.fixture(scope="session")
def saved_policy(four_modes_policy, tmp_path_factory):
    path = tmp_path_factory.mktemp("policy") / "policy.safetensors"
    four_modes_policy.save(str(path))
    return path
