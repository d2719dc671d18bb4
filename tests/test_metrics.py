"""Error metrics and confidence intervals (`jdrkf.metrics`) against NumPy/SciPy."""

import jax.numpy as jnp
import numpy as np
import pytest
import scipy.stats

from jdrkf import metrics


def _pair(rng, shape):
    return rng.normal(size=shape), rng.normal(size=shape)


def _spd_batch(rng, batch, n):
    a = rng.normal(size=batch + (n, n))
    return a @ np.swapaxes(a, -1, -2) + 0.3 * np.eye(n)


@pytest.mark.parametrize("shape", [(7, 3), (5, 7, 3), (2, 4, 6, 1)])
def test_squared_error_and_rmse(rng, shape):
    x, xh = _pair(rng, shape)
    se = np.asarray(metrics.squared_error(x, xh))
    want = np.array([[np.sum((x[idx + (t,)] - xh[idx + (t,)]) ** 2) for t in range(shape[-2])]
                     for idx in np.ndindex(*shape[:-2])]).reshape(shape[:-1])
    np.testing.assert_allclose(se, want, rtol=1e-13)
    r = np.asarray(metrics.rmse(x, xh))
    assert r.shape == shape[:-2]
    np.testing.assert_allclose(r, np.sqrt(want.mean(axis=-1)), rtol=1e-13)
    # rtamse is the very same function
    assert metrics.rtamse is metrics.rmse
    np.testing.assert_array_equal(metrics.rtamse(x, xh), r)


def test_rmse_closed_form():
    # constant error vector (3, 4) at every step: ‖e‖ = 5, so RMSE = 5 whatever T
    x = np.zeros((2, 9, 2))
    xh = np.broadcast_to(np.array([3.0, 4.0]), x.shape)
    np.testing.assert_allclose(metrics.rmse(x, xh), [5.0, 5.0], rtol=1e-15)
    np.testing.assert_allclose(metrics.squared_error(x, xh), np.full((2, 9), 25.0), rtol=1e-15)
    # errors 1 and 3 at two steps: sqrt((1 + 9) / 2)
    x2 = np.array([[[1.0], [3.0]]])
    np.testing.assert_allclose(metrics.rmse(x2, np.zeros_like(x2)), [np.sqrt(5.0)], rtol=1e-15)


def test_rmse_accepts_jax_arrays(rng):
    x, xh = _pair(rng, (3, 5, 2))
    np.testing.assert_allclose(metrics.rmse(jnp.asarray(x), jnp.asarray(xh)), metrics.rmse(x, xh), rtol=1e-15)


def test_mse_per_step(rng):
    runs, T, n = 11, 6, 4
    x, xh = _pair(rng, (runs, T, n))
    m = np.asarray(metrics.mse_per_step(x, xh))
    assert m.shape == (T,)
    want = np.array([np.mean([np.sum((x[r, t] - xh[r, t]) ** 2) for r in range(runs)]) for t in range(T)])
    np.testing.assert_allclose(m, want, rtol=1e-13)
    for comps in ([0, 2], [3], (1, 2, 3)):
        got = np.asarray(metrics.mse_per_step(x, xh, components=comps))
        c = list(comps)
        want_c = np.mean(np.sum((x[..., c] - xh[..., c]) ** 2, axis=-1), axis=0)
        np.testing.assert_allclose(got, want_c, rtol=1e-13)
    # all components = no selection
    np.testing.assert_allclose(metrics.mse_per_step(x, xh, components=[0, 1, 2, 3]), m, rtol=1e-14)


def test_mse_per_step_relates_to_rmse(rng):
    # mean over steps of the per-step MSE = mean over runs of RMSE²
    x, xh = _pair(rng, (8, 5, 3))
    lhs = float(np.mean(metrics.mse_per_step(x, xh)))
    rhs = float(np.mean(np.asarray(metrics.rmse(x, xh)) ** 2))
    np.testing.assert_allclose(lhs, rhs, rtol=1e-13)


@pytest.mark.parametrize("batch", [(6,), (3, 6), (2, 3, 4)])
def test_nees_against_numpy_solve(rng, batch):
    n = 3
    x, xh = _pair(rng, batch + (n,))
    P = _spd_batch(rng, batch, n)
    got = np.asarray(metrics.nees(x, xh, P))
    assert got.shape == batch
    want = np.empty(batch)
    for idx in np.ndindex(*batch):
        e = x[idx] - xh[idx]
        want[idx] = e @ np.linalg.solve(P[idx], e)
    np.testing.assert_allclose(got, want, rtol=1e-10)


def test_nees_closed_form_and_consistency(rng):
    # diagonal covariance: Σ e_i² / σ_i²
    e = np.array([[1.0, -2.0, 0.5]])
    P = np.diag([4.0, 1.0, 0.25])[None]
    np.testing.assert_allclose(metrics.nees(e, np.zeros_like(e), P), [0.25 + 4.0 + 1.0], rtol=1e-14)
    # errors drawn from N(0, P): NEES ~ chi²(n), mean n
    n, num = 3, 20_000
    L = np.linalg.cholesky(_spd_batch(rng, (), n))
    P = L @ L.T
    err = rng.normal(size=(num, n)) @ L.T
    vals = np.asarray(metrics.nees(err, np.zeros_like(err), np.broadcast_to(P, (num, n, n))))
    assert abs(vals.mean() - n) <= 6 * np.sqrt(2 * n / num)


@pytest.mark.parametrize("n", [2, 3, 7, 30, 1000])
@pytest.mark.parametrize("level", [0.5, 0.9, 0.95, 0.99])
def test_mean_ci_matches_scipy(rng, n, level):
    v = rng.normal(loc=3.0, scale=2.0, size=n)
    mean, (lo, hi) = metrics.mean_ci(v, level)
    assert isinstance(mean, float) and isinstance(lo, float) and isinstance(hi, float)
    want_lo, want_hi = scipy.stats.t.interval(level, n - 1, loc=v.mean(), scale=scipy.stats.sem(v))
    np.testing.assert_allclose(mean, v.mean(), rtol=1e-14)
    half = 0.5 * (want_hi - want_lo)
    np.testing.assert_allclose(0.5 * (hi - lo), half, rtol=1e-8)
    np.testing.assert_allclose([lo, hi], [want_lo, want_hi], rtol=0, atol=1e-8 * half)


def test_mean_ci_default_level_and_shapes(rng):
    v = rng.exponential(size=(4, 5))  # any shape: flattened
    mean, (lo, hi) = metrics.mean_ci(v)
    want = scipy.stats.t.interval(0.95, 19, loc=v.mean(), scale=scipy.stats.sem(v.ravel()))
    np.testing.assert_allclose([mean, lo, hi], [v.mean(), *want], rtol=1e-10)
    # a plain list and a jax array work the same
    m2, ci2 = metrics.mean_ci(list(v.ravel()))
    m3, ci3 = metrics.mean_ci(jnp.asarray(v))
    np.testing.assert_allclose([m2, *ci2], [mean, lo, hi], rtol=1e-14)
    np.testing.assert_allclose([m3, *ci3], [mean, lo, hi], rtol=1e-14)


def test_mean_ci_closed_form_n2():
    # n = 2: half-width = t_{0.975, 1} * |a - b| / 2 with t_{0.975, 1} = tan(0.475 π)
    mean, (lo, hi) = metrics.mean_ci([1.0, 3.0], 0.95)
    half = np.tan(0.475 * np.pi) * np.sqrt(2.0) / np.sqrt(2.0)
    np.testing.assert_allclose(mean, 2.0)
    np.testing.assert_allclose([lo, hi], [2.0 - half, 2.0 + half], rtol=1e-10)
    # constant data: zero-width interval
    mean, (lo, hi) = metrics.mean_ci(np.full(10, 4.0))
    assert mean == 4.0 and lo == 4.0 and hi == 4.0


@pytest.mark.parametrize(
    "values, level, match",
    [
        ([1.0, np.nan, 2.0], 0.95, "non-finite"),
        ([1.0, np.inf], 0.95, "non-finite"),
        ([], 0.95, "empty"),
        (np.zeros((0, 3)), 0.95, "empty"),
        ([1.0, 2.0, 3.0], 0.0, "level"),
        ([1.0, 2.0, 3.0], 1.0, "level"),
        ([1.0, 2.0, 3.0], 1.5, "level"),
        ([1.0, 2.0, 3.0], -0.2, "level"),
        ([1.0, 2.0, 3.0], 95, "level"),
    ],
)
def test_mean_ci_errors(values, level, match):
    with pytest.raises(ValueError, match=match):
        metrics.mean_ci(values, level)
