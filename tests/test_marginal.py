"""Marginal DR-MMSE solver (Chen et al. 2025, problem (16); jdrkf/sets/_marginal.py)
against an independent CVXPY/Clarabel SDP (tests/marginal_oracle.py) and closed forms.

Compilation dominates (≈10–20 s per (set kind, n, dims) structure), so the default tier
uses two structures (moment and KL, n = 2, three scalar sensors) plus p = 1; the `slow`
tier sweeps the other sizes (p ∈ {1, 2, 3}, sensor dims 1–2, n 1–3).
"""

import functools

import jax
import jax.numpy as jnp
import marginal_oracle as O
import numpy as np
import pytest

from jdrkf.sets._marginal import MarginalKL, MarginalMoment, marginal_mmse

VALUE_RTOL = 1e-6  # barrier bias is ~1e-8 relative (μ = 1e-8), Clarabel ~1e-9
FEAS_TOL = 1e-9
FAST = [("moment", 2, (1, 1, 1)), ("kl", 2, (1, 1, 1))]
SLOW = [("moment", 3, (2, 1)), ("kl", 3, (2, 1)), ("moment", 1, (1, 2)), ("kl", 1, (2, 1, 1)),
        ("moment", 2, (2, 2, 1)), ("kl", 2, (1,)), ("moment", 3, (1,))]


@functools.cache
def _case(kind, n, dims, idx):
    rng = np.random.default_rng([sum(map(ord, kind)), n, *dims, idx])
    cov = O.random_cov(rng, n, dims)
    p = len(dims)
    if kind == "moment":
        params = (rng.uniform(0.3, 1.0, p), rng.uniform(1.0, 2.0, p))
    else:
        params = (rng.uniform(0.02, 0.6, p),)
    value, _ = O.solve_marginal_sdp(cov, n, dims, kind, params)
    return cov, params, value


def _set(kind, params):
    return MarginalMoment(*params) if kind == "moment" else MarginalKL(*params)


def _check_feasible(res, cov, n, dims, kind, params):
    S = np.asarray(res.cov)
    assert np.linalg.eigvalsh(S).min() >= -FEAS_TOL * np.abs(S).max()
    for i, idx in enumerate(O.block_indices(n, dims)):
        sig = cov[np.ix_(idx, idx)]
        L = np.linalg.cholesky(sig)
        W = np.linalg.solve(L, np.linalg.solve(L, S[np.ix_(idx, idx)]).T)  # L⁻¹ S_B L⁻ᵀ
        lam = np.linalg.eigvalsh(0.5 * (W + W.T))
        if kind == "moment":
            assert lam.min() >= params[0][i] - FEAS_TOL and lam.max() <= params[1][i] + FEAS_TOL
        else:
            kl = 0.5 * np.sum(lam - 1.0 - np.log(lam))
            assert kl <= params[0][i] + FEAS_TOL


def _run_against_oracle(kind, n, dims, idx):
    cov, params, value = _case(kind, n, dims, idx)
    res = marginal_mmse(cov, n, dims, _set(kind, params))
    assert bool(res.converged)
    np.testing.assert_allclose(float(res.value), value, rtol=VALUE_RTOL)
    _check_feasible(res, cov, n, dims, kind, params)
    # internal consistency of the outputs with S* (NumPy)
    S = np.asarray(res.cov)
    K = np.linalg.solve(S[n:, n:], S[n:, :n]).T
    np.testing.assert_allclose(np.asarray(res.gain), K, rtol=1e-6, atol=1e-8)
    np.testing.assert_allclose(np.asarray(res.posterior_cov), S[:n, :n] - K @ S[n:, :n], atol=1e-8)
    # a worst case is at least as bad as the nominal with min γ2 scaling (moment)
    f_kf, _ = O.kalman_value(cov, n)
    if kind == "moment":
        assert float(res.value) >= np.min(params[1]) * f_kf * (1 - VALUE_RTOL)


@pytest.mark.parametrize("idx", range(10))
@pytest.mark.parametrize("structure", FAST, ids=str)
def test_against_sdp(structure, idx):
    _run_against_oracle(*structure, idx)


@pytest.mark.slow
@pytest.mark.parametrize("idx", range(4))
@pytest.mark.parametrize("structure", SLOW, ids=str)
def test_against_sdp_sizes(structure, idx):
    _run_against_oracle(*structure, idx)


def test_single_sensor_closed_form():
    """p = 1: the worst case is γ2 Σ in value, gain and posterior (S* itself is not unique)."""
    rng = np.random.default_rng(3)
    n, dims = 2, (1,)
    for g1, g2 in [(0.5, 1.7), (1.0, 1.0), (0.9, 1.0)]:
        cov = O.random_cov(rng, n, dims)
        res = marginal_mmse(cov, n, dims, MarginalMoment(np.array([g1]), np.array([g2])))
        f_kf, K = O.kalman_value(cov, n)
        np.testing.assert_allclose(float(res.value), g2 * f_kf, rtol=1e-7)
        np.testing.assert_allclose(np.asarray(res.gain), K, rtol=1e-6, atol=1e-9)
        P = cov[:n, :n] - K @ cov[n:, :n]
        np.testing.assert_allclose(np.asarray(res.posterior_cov), g2 * P, rtol=1e-6, atol=1e-9)


def test_nominal_radii_are_not_the_kf_for_several_sensors():
    """γ1 = γ2 = 1 (or c = 0) fixes every marginal block but not the cross-sensor
    correlations: with p ≥ 2 the adversary correlates the sensor errors, so the value
    exceeds the centralized KF with independent sensors (it equals the SDP)."""
    rng = np.random.default_rng(5)
    n, dims = 2, (1, 1, 1)
    cov = O.random_cov(rng, n, dims, independent=True)
    f_kf, _ = O.kalman_value(cov, n)
    ones = np.ones(3)
    for kind, params in [("moment", (ones, ones)), ("kl", (0.0 * ones,))]:
        value, _ = O.solve_marginal_sdp(cov, n, dims, kind, params)
        res = marginal_mmse(cov, n, dims, _set(kind, params))
        np.testing.assert_allclose(float(res.value), value, rtol=VALUE_RTOL)
        assert float(res.value) > f_kf * (1 + 1e-3)
        _check_feasible(res, cov, n, dims, kind, params)


def _fd(fun, x, h):
    return (fun(x + h) - fun(x - h)) / (2 * h)


@pytest.mark.parametrize("kind", ["moment", pytest.param("kl", marks=pytest.mark.slow)])
def test_gradients_vs_finite_differences(kind):
    """Reverse-mode gradient of value + gain[0, 1] + posterior_cov[0, 1] w.r.t. every
    radius and the nominal covariance, against central differences (one compile)."""
    n, dims = 2, (1, 1, 1)
    cov, params, _ = _case(kind, n, dims, 0)
    cov = jnp.asarray(cov)
    params = tuple(jnp.asarray(p) for p in params)

    def loss(cov, params):
        r = marginal_mmse(cov, n, dims, _set(kind, params))
        return r.value + r.gain[0, 1] + r.posterior_cov[0, 1]

    g_cov, g_par = jax.grad(loss, argnums=(0, 1))(cov, params)
    h = 1e-5
    for k in range(len(params)):
        for i in range(3):
            e = jnp.zeros(3).at[i].set(1.0)

            def f(t, k=k, e=e):
                return loss(cov, tuple(p + t * e if j == k else p for j, p in enumerate(params)))

            np.testing.assert_allclose(float(g_par[k][i]), float(_fd(f, 0.0, h)), rtol=1e-5, atol=1e-7)
    # one x–y¹ cross-covariance entry and one state variance (symmetric perturbations)
    for E in (jnp.zeros_like(cov).at[0, n].set(1.0).at[n, 0].set(1.0), jnp.zeros_like(cov).at[1, 1].set(1.0)):
        fd = _fd(lambda t, E=E: loss(cov + t * E, params), 0.0, h)
        np.testing.assert_allclose(float(jnp.sum(g_cov * E)), float(fd), rtol=1e-5, atol=1e-7)


@pytest.mark.slow
def test_degenerate_radii_one_sided_derivative():
    """γ1 = γ2 = 1 (no interior): projected-gradient solution, derivative from the
    barrier problem widened by 1e-6 ≈ the one-sided finite difference along γ2 = 1 + t."""
    n, dims = 2, (1, 1, 1)
    cov = O.random_cov(np.random.default_rng(5), n, dims, independent=True)
    ones = jnp.ones(3)

    def f(g2):
        return marginal_mmse(cov, n, dims, MarginalMoment(ones, g2)).value

    # At this kink only the derivative along the widening direction (all γ2 together) is
    # consistent; single-sensor one-sided derivatives differ (the others stay pinned).
    g = jax.grad(f)(ones)
    h = 1e-4
    fd = (f(ones + h) - f(ones)) / h
    np.testing.assert_allclose(float(jnp.sum(g)), float(fd), rtol=1e-2)


@pytest.mark.slow
def test_jit_and_vmap():
    """jit and a small vmap, on the one-sensor structure (closed form γ2 f_KF)."""
    n, dims = 2, (1,)
    cov = O.random_cov(np.random.default_rng(11), n, dims)
    f_kf, _ = O.kalman_value(cov, n)

    @jax.jit
    def val(g2):
        return marginal_mmse(cov, n, dims, MarginalMoment(jnp.asarray([0.8]), g2)).value

    g2s = jnp.asarray([[1.2], [1.5]])
    np.testing.assert_allclose(float(val(g2s[0])), 1.2 * f_kf, rtol=1e-7)
    np.testing.assert_allclose(np.asarray(jax.vmap(val)(g2s)), np.asarray(g2s[:, 0]) * f_kf, rtol=1e-7)


def test_bad_inputs():
    cov = np.eye(4)
    with pytest.raises(ValueError, match="gamma1"):
        MarginalMoment(0.0, 1.5)
    with pytest.raises(ValueError, match="gamma1"):
        MarginalMoment(1.2, 1.5)
    with pytest.raises(ValueError, match="gamma2"):
        MarginalMoment(0.5, 0.9)
    with pytest.raises(ValueError, match="radius must"):
        MarginalKL(-0.1)
    with pytest.raises(ValueError, match="cov has shape"):
        marginal_mmse(cov, 2, (1, 2), MarginalKL(0.1))
    with pytest.raises(ValueError, match="n must"):
        marginal_mmse(cov, 0, (1, 1, 1, 1), MarginalKL(0.1))
    with pytest.raises(ValueError, match="dims"):
        marginal_mmse(cov, 2, (1, 0), MarginalKL(0.1))
    with pytest.raises(ValueError, match="sensors"):
        marginal_mmse(cov, 2, (1, 1), MarginalKL(np.array([0.1, 0.2, 0.3])))
    with pytest.raises(ValueError, match="set must"):
        marginal_mmse(cov, 2, (1, 1), 0.1)
