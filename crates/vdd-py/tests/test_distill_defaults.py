"""`vdd.distill`'s defaults (`Vdd::auto`) on a user-written teacher: a 16-D mixture of four
well-separated Gaussians with scales from 0.05 to 2, given only as a NumPy score function (no
sampler), on three seeds. Every component must be covered and the reverse KL from the
student to the mixture at most 0.01 (issue 34, item 5)."""

import numpy as np
import pytest

import vdd

D, K = 16, 4
_rng = np.random.default_rng(20240)
MEANS = (6.0 * _rng.standard_normal((K, D))).astype(np.float32)  # pairwise ~ 34 apart
STDS = np.exp(_rng.uniform(np.log(0.05), np.log(2.0), size=(K, D))).astype(np.float32)
LOG_W = np.log(np.full(K, 1.0 / K))


def _log_components(actions, sigma):
    """log w_k + log N(a; μ_k, diag(s_k² + σ²)) `(n, K)` and the terms `(μ_k − a) / var`."""
    var = STDS[None] ** 2 + (sigma.astype(np.float32) ** 2)[:, None, None]  # (n, K, D)
    diff = MEANS[None] - actions[:, None, :]
    g = diff / var
    logits = LOG_W[None] - 0.5 * ((diff * g).sum(-1) + np.log(2 * np.pi * var).sum(-1))
    return logits, g


def mixture_score(actions, states, sigma):
    """The exact score of the mixture smoothed by N(0, σ² I): each covariance plus σ²."""
    logits, g = _log_components(actions.astype(np.float32), sigma)
    r = np.exp(logits - logits.max(axis=1, keepdims=True))
    r /= r.sum(axis=1, keepdims=True)
    return np.einsum("nk,nkd->nd", r, g).astype(np.float32)


def mixture_log_density(actions):
    """log p(a) `(n,)` of the clean mixture and each action's most likely component."""
    logits, _ = _log_components(actions.astype(np.float64), np.zeros(len(actions)))
    m = logits.max(axis=1)
    return m + np.log(np.exp(logits - m[:, None]).sum(axis=1)), logits.argmax(axis=1)


def reverse_kl_and_shares(policy, n=20000, seed=0):
    """KL(q || p) by sampling the student's mixture (`components`), with `log q` from
    `log_likelihood`; and the share of samples on each of the mixture's components."""
    obs = np.zeros((1, 1), dtype=np.float32)
    log_gating, means, scale_tril = policy.components(obs)
    rng = np.random.default_rng(seed)
    weights = np.exp(log_gating[0].astype(np.float64))
    z = rng.choice(len(weights), size=n, p=weights / weights.sum())
    eps = rng.standard_normal((n, D))
    a = (means[0][z] + np.einsum("nij,nj->ni", scale_tril[0][z], eps)).astype(np.float32)
    log_q = policy.log_likelihood(np.zeros((n, 1), dtype=np.float32), a).astype(np.float64)
    log_p, component = mixture_log_density(a)
    return float(np.mean(log_q - log_p)), np.bincount(component, minlength=K) / n


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_default_distill_recovers_a_16d_mixture_from_its_score_alone(seed):
    policy = vdd.distill(mixture_score, np.zeros((16, 1)), action_dim=D, experts=K, seed=seed)
    kl, shares = reverse_kl_and_shares(policy, seed=seed)
    print(f"seed {seed}: reverse KL {kl:.5f}, component shares {np.round(shares, 3)}")
    assert np.all(shares > 0.05), (kl, shares)
    assert kl <= 0.01, (kl, shares)


def test_a_sample_fn_is_used_and_checked():
    calls = []

    def sample_fn(states):
        calls.append(states.shape)
        z = np.random.default_rng(len(calls)).integers(K, size=len(states))
        eps = np.random.default_rng(len(calls) + 1).standard_normal((len(states), D))
        return MEANS[z] + STDS[z] * eps

    policy = vdd.distill(mixture_score, np.zeros((16, 1)), action_dim=D, experts=K,
                         iterations=60, sample_fn=sample_fn)
    assert calls and calls[0][1] == 1
    assert policy.num_experts == K
    with pytest.raises(ValueError, match=r"sample_fn returned shape \(.*, 3\)"):
        vdd.distill(mixture_score, np.zeros((4, 1)), action_dim=D, experts=K, iterations=2,
                    sample_fn=lambda s: np.zeros((len(s), 3)))
    with pytest.raises(ValueError, match="sample_fn returned a non-finite action"):
        vdd.distill(mixture_score, np.zeros((4, 1)), action_dim=D, experts=K, iterations=2,
                    sample_fn=lambda s: np.full((len(s), D), np.nan))
    with pytest.raises(TypeError, match="sample_fn must be callable"):
        vdd.distill(mixture_score, np.zeros((4, 1)), action_dim=D, sample_fn=3)
