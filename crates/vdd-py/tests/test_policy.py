"""vdd.Policy: loading, acting, components, likelihood, errors."""

import numpy as np
import pytest

import vdd


def mixture_log_density(log_gating, means, scale_tril, actions):
    """log Σ_z q(z|s) N(a; μ_z, L_z L_zᵀ), in float64, from the components."""
    n, z, d = means.shape
    out = np.empty(n)
    for i in range(n):
        terms = []
        for k in range(z):
            L = scale_tril[i, k].astype(np.float64)
            y = np.linalg.solve(L, (actions[i] - means[i, k]).astype(np.float64))
            log_n = -0.5 * y @ y - np.log(np.diag(L)).sum() - 0.5 * d * np.log(2 * np.pi)
            terms.append(log_gating[i, k] + log_n)
        terms = np.array(terms)
        m = terms.max()
        out[i] = m + np.log(np.exp(terms - m).sum())
    return out


def test_load_reports_its_dimensions(saved_policy):
    p = vdd.Policy.load(str(saved_policy))
    assert (p.obs_dim, p.action_dim, p.num_experts) == (1, 2, 8)
    assert (p.obs_window, p.action_chunk, p.features) == (1, 1, "identity v1")
    assert "num_experts=8" in repr(p)


def test_components_have_the_documented_shapes_and_a_normalised_gating(saved_policy):
    p = vdd.Policy.load(saved_policy)
    obs = np.zeros((3, 1), dtype=np.float32)
    lg, mu, L = p.components(obs)
    assert lg.shape == (3, 8) and mu.shape == (3, 8, 2) and L.shape == (3, 8, 2, 2)
    assert lg.dtype == mu.dtype == L.dtype == np.float32
    np.testing.assert_allclose(np.exp(lg).sum(axis=1), 1.0, rtol=1e-6)
    assert np.all(np.triu(L, k=1) == 0.0)
    assert np.all(np.diagonal(L, axis1=2, axis2=3) > 0.0)


def test_act_returns_an_experts_mean(saved_policy):
    p = vdd.Policy.load(saved_policy)
    _, mu, _ = p.components(np.zeros((1, 1), dtype=np.float32))
    for _ in range(20):
        a = p.act(np.zeros(1, dtype=np.float32))
        assert a.shape == (2,) and a.dtype == np.float32
        assert np.min(np.abs(mu[0] - a).max(axis=1)) < 1e-5
    batch = p.act_batch(np.zeros((5, 1)))  # float64 in: converted
    assert batch.shape == (5, 2)
    p.reset()
    p.seed(3)
    first = p.act_batch(np.zeros((50, 1), dtype=np.float32))
    p.seed(3)
    np.testing.assert_array_equal(first, p.act_batch(np.zeros((50, 1), dtype=np.float32)))


def test_log_likelihood_is_the_mixture_density_of_the_components(saved_policy):
    p = vdd.Policy.load(saved_policy)
    obs = np.zeros((4, 1), dtype=np.float32)
    actions = np.array([[2.0, 2.0], [-1.9, 2.1], [0.0, 0.0], [2.2, -1.7]], dtype=np.float32)
    ll = p.log_likelihood(obs, actions)
    assert ll.shape == (4,) and ll.dtype == np.float32
    want = mixture_log_density(*p.components(obs), actions)
    np.testing.assert_allclose(ll, want, rtol=1e-4, atol=1e-4)
    # A mode of the teacher is far more likely than the empty centre.
    assert ll[0] > ll[2] + 5.0


def test_save_and_load_keep_the_components(four_modes_policy, tmp_path):
    path = tmp_path / "again.safetensors"
    four_modes_policy.save(path)
    obs = np.linspace(-1, 1, 6, dtype=np.float32)[:, None]
    for a, b in zip(four_modes_policy.components(obs), vdd.Policy.load(path).components(obs)):
        np.testing.assert_array_equal(a, b)


def test_bad_input_raises_value_error_and_bad_files_raise_vdd_error(saved_policy, tmp_path):
    p = vdd.Policy.load(saved_policy)
    with pytest.raises(ValueError, match=r"expected shape \(1,\)"):
        p.act(np.zeros(3, dtype=np.float32))
    with pytest.raises(ValueError, match=r"\(n, 1\)"):
        p.components(np.zeros((2, 2), dtype=np.float32))
    with pytest.raises(ValueError, match="non-finite"):
        p.act(np.array([np.nan], dtype=np.float32))
    with pytest.raises(ValueError, match="rows"):
        p.log_likelihood(np.zeros((2, 1)), np.zeros((3, 2)))
    with pytest.raises(vdd.VddError, match="missing.safetensors"):
        vdd.Policy.load(tmp_path / "missing.safetensors")
    junk = tmp_path / "junk.safetensors"
    junk.write_bytes(b"not a model")
    with pytest.raises(vdd.VddError):
        vdd.Policy.load(junk)
    with pytest.raises(vdd.VddError):
        vdd.load_teacher(saved_policy)  # a student, not a teacher


def test_a_batch_over_the_row_limit_is_a_value_error_raised_before_allocating(saved_policy):
    # Before, 10^7 rows raised PanicException (an unwrapped faer allocation).
    import time

    p = vdd.Policy.load(saved_policy)
    obs = np.zeros((10**7, 1), dtype=np.float32)
    start = time.perf_counter()
    for call in (
        lambda: p.act_batch(obs),
        lambda: p.components(obs),
        lambda: p.log_likelihood(obs, np.zeros((10**7, 2), dtype=np.float32)),
    ):
        with pytest.raises(ValueError, match="rows per call"):
            call()
    assert time.perf_counter() - start < 5.0, "refused before allocating"
    # The policy still works afterwards.
    assert p.act_batch(np.zeros((3, 1), dtype=np.float32)).shape == (3, 2)
