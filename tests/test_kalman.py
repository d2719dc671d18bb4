"""KalmanFilter and SteadyStateKalmanFilter against independent oracles."""

import functools

import equinox as eqx
import filterpy.kalman as filterpy_kalman
import hypothesis
import hypothesis.strategies as st
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg

import jdrkf
from oracles import numpy_dare_filter, numpy_kalman_filter, numpy_simulate_lgssm


def _random_spd(rng, d, scale=1.0):
    a = rng.normal(size=(d, d))
    return scale * (a @ a.T / d + 0.5 * np.eye(d))


def _random_stable(rng, n, radius=0.95):
    a = rng.normal(size=(n, n))
    return radius * a / np.max(np.abs(np.linalg.eigvals(a)))


def _time_varying_problem(rng, n=3, m=2, q=2, p=1, T=40, missing=True):
    F = np.stack([_random_stable(rng, n) for _ in range(T)])
    H = rng.normal(size=(m, n))
    Q = _random_spd(rng, q)
    R = np.stack([_random_spd(rng, m, 0.5) for _ in range(T)])
    G = rng.normal(size=(n, q))
    B = rng.normal(size=(n, p))
    u = rng.normal(size=(T, p))
    mu_w = rng.normal(size=q)
    mu_v = rng.normal(size=(T, m))
    m0, P0 = rng.normal(size=n), _random_spd(rng, n)
    ys = rng.normal(size=(T, m)) * 3
    if missing:
        ys[3, 0] = np.nan  # one missing component
        ys[7, :] = np.nan  # a whole missing vector
        ys[10:12, 1] = np.nan
    return dict(F=F, H=H, Q=Q, R=R, G=G, B=B, process_mean=mu_w, noise_mean=mu_v), u, m0, P0, ys


def test_matches_numpy_oracle_time_varying_controls_missing(rng):
    fields, u, m0, P0, ys = _time_varying_problem(rng)
    flt = jdrkf.KalmanFilter(outputs="all")
    res = flt(jdrkf.LinearModel(**fields), jdrkf.Gaussian(m0, P0), ys, inputs=u, observed=~np.isnan(ys))
    ref = numpy_kalman_filter(m0, P0, ys, inputs=u, **fields)
    for name in ["filtered_means", "filtered_covariances", "predicted_means", "predicted_covariances", "loglik_increments"]:
        np.testing.assert_allclose(getattr(res, name), ref[name], rtol=0, atol=1e-10, err_msg=name)
    np.testing.assert_allclose(res.marginal_loglik, ref["marginal_loglik"], rtol=1e-12)
    assert res.loglik_increments[7] == 0.0  # the whole-vector NaN step is skipped
    assert res.result == jdrkf.RESULTS.successful


def test_matches_filterpy(rng):
    n, m, T = 3, 2, 60
    F, H, Q, R = _random_stable(rng, n), rng.normal(size=(m, n)), _random_spd(rng, n), _random_spd(rng, m)
    m0, P0 = rng.normal(size=n), _random_spd(rng, n)
    _, ys = numpy_simulate_lgssm(rng, m0, P0, F, H, Q, R, T)
    kf = filterpy_kalman.KalmanFilter(dim_x=n, dim_z=m)
    kf.F, kf.H, kf.Q, kf.R, kf.x, kf.P = F, H, Q, R, m0.copy(), P0.copy()
    means, covs, lls = [], [], []
    for y in ys:
        kf.predict()
        kf.update(y)
        means.append(kf.x.copy())
        covs.append(kf.P.copy())
        lls.append(kf.log_likelihood)
    res = jdrkf.KalmanFilter(outputs="all")(jdrkf.LinearModel(F, H, Q, R), jdrkf.Gaussian(m0, P0), ys)
    np.testing.assert_allclose(res.filtered_means, np.array(means), atol=1e-10)
    np.testing.assert_allclose(res.filtered_covariances, np.array(covs), atol=1e-10)
    np.testing.assert_allclose(res.loglik_increments, np.array(lls), atol=1e-10)


def test_predict_update_public_and_consistent(rng):
    fields, u, m0, P0, ys = _time_varying_problem(rng, missing=False)
    model, prior = jdrkf.LinearModel(**fields), jdrkf.Gaussian(m0, P0)
    res = jdrkf.KalmanFilter()(model, prior, ys, inputs=u)
    belief = prior
    for t in range(3):
        pred = jdrkf.predict(model, belief, t, u[t])
        belief, _, failed = jdrkf.update(model, pred, ys[t], t)
        assert not failed
    np.testing.assert_allclose(belief.mean, res.filtered_means[2], atol=1e-12)


def _loglik_of(q_and_r, F, H, m0, P0, ys):
    q, r = q_and_r
    return jdrkf.KalmanFilter()(jdrkf.LinearModel(F, H, q, r), jdrkf.Gaussian(m0, P0), ys).marginal_loglik


def test_jit_vmap_grad_against_finite_differences(rng):
    n, m, T, runs = 2, 1, 50, 4
    F, H = _random_stable(rng, n), rng.normal(size=(m, n))
    Q, R = _random_spd(rng, n), _random_spd(rng, m)
    m0, P0 = np.zeros(n), np.eye(n)
    ys = np.stack([numpy_simulate_lgssm(rng, m0, P0, F, H, Q, R, T)[1] for _ in range(runs)])

    def total(q_and_r):
        lls = jax.vmap(lambda y: _loglik_of(q_and_r, F, H, m0, P0, y))(ys)
        return jnp.sum(lls)

    grad_q, grad_r = jax.jit(jax.grad(total))((jnp.asarray(Q), jnp.asarray(R)))

    def oracle(q, r):
        return sum(numpy_kalman_filter(m0, P0, y, F, H, q, r)["marginal_loglik"] for y in ys)

    eps = 1e-6
    for (i, j) in [(0, 0), (0, 1), (1, 1)]:
        e = np.zeros((n, n))
        e[i, j] = e[j, i] = eps
        fd = (oracle(Q + e, R) - oracle(Q - e, R)) / (2 * eps)
        ad = grad_q[i, j] + (grad_q[j, i] if i != j else 0.0)
        np.testing.assert_allclose(ad, fd, rtol=1e-6, atol=1e-8)
    fd_r = (oracle(Q, R + eps) - oracle(Q, R - eps)) / (2 * eps)
    np.testing.assert_allclose(grad_r[0, 0], fd_r, rtol=1e-6)


def test_vmap_equals_loop_and_no_retrace(rng):
    n, m, T = 2, 1, 30
    model = jdrkf.LinearModel(_random_stable(rng, n), rng.normal(size=(m, n)), _random_spd(rng, n), _random_spd(rng, m))
    prior = jdrkf.Gaussian(np.zeros(n), np.eye(n))
    traces = []

    @jax.jit
    def batched(ys):
        traces.append(1)
        return jax.vmap(jdrkf.KalmanFilter(), in_axes=(None, None, 0))(model, prior, ys)

    ys1, ys2 = rng.normal(size=(5, T, m)), rng.normal(size=(5, T, m))
    out1 = batched(ys1)
    batched(ys2)
    assert len(traces) == 1
    for r in range(5):
        single = jdrkf.KalmanFilter()(model, prior, ys1[r])
        np.testing.assert_allclose(out1.filtered_means[r], single.filtered_means, atol=1e-13)


def test_vmap_over_models_time_varying(rng):
    # Per-run true transition matrices, as TMKF uses them.
    n, m, T, runs = 2, 1, 20, 3
    Fs = np.stack([np.stack([_random_stable(rng, n) for _ in range(T)]) for _ in range(runs)])
    base = jdrkf.LinearModel(Fs[0], rng.normal(size=(m, n)), np.eye(n), np.eye(m))
    ys = rng.normal(size=(runs, T, m))
    prior = jdrkf.Gaussian(np.zeros(n), np.eye(n))

    def run(F, y):
        return jdrkf.KalmanFilter()(eqx.tree_at(lambda mm: mm.F, base, F), prior, y).filtered_means

    out = jax.vmap(run)(Fs, ys)
    for r in range(runs):
        ref = numpy_kalman_filter(np.zeros(n), np.eye(n), ys[r], Fs[r], base.H, np.eye(n), np.eye(m))
        np.testing.assert_allclose(out[r], ref["filtered_means"], atol=1e-12)


def test_failure_becomes_result_code_or_error():
    # Zero measurement noise on a zero-variance state: H P Hᵀ + R = 0 is not positive definite.
    model = jdrkf.LinearModel(np.eye(1), np.eye(1), np.zeros((1, 1)), np.zeros((1, 1)))
    prior = jdrkf.Gaussian(np.zeros(1), np.zeros((1, 1)))
    ys = np.ones((3, 1))
    res = jdrkf.KalmanFilter(throw=False)(model, prior, ys)
    assert res.result == jdrkf.RESULTS.nonpositive_innovation
    with pytest.raises(Exception, match="not numerically positive definite"):
        jax.block_until_ready(jdrkf.KalmanFilter()(model, prior, ys).filtered_means)


@pytest.mark.parametrize("n,m", [(1, 1), (2, 1), (3, 2), (6, 6)])
def test_entrywise_step_equals_array_step(rng, n, m):
    """Small states (n, m ≤ linalg.UNROLL_MAX) run the step on matrix entries
    (`filters/_entrywise.py`); under `linalg.lapack_only()` the filter runs the array
    `predict`/`update`/`step_result` instead. Both must agree on every output and code."""
    fields, u, m0, P0, ys = _time_varying_problem(rng, n=n, m=m, q=min(n, 2), T=25, missing=False)
    observed = rng.random(ys.shape) > 0.2
    observed[5] = False  # a whole missing vector
    model, prior = jdrkf.LinearModel(**fields), jdrkf.Gaussian(m0, P0)
    flt = jdrkf.KalmanFilter(outputs="all", throw=False)
    run = lambda y, o: flt(model, prior, y, inputs=u, observed=o)  # noqa: E731
    entrywise = jax.jit(run)(ys, observed)
    with jdrkf.linalg.lapack_only():
        arrays = jax.jit(run)(ys, observed)
    for name in ["filtered_means", "filtered_covariances", "predicted_means", "predicted_covariances", "loglik_increments"]:
        np.testing.assert_allclose(getattr(entrywise, name), getattr(arrays, name), rtol=1e-11, atol=1e-11, err_msg=name)
    assert entrywise.result == arrays.result == jdrkf.RESULTS.successful
    # the public step is the same step
    state, out = flt.step(model, prior, jnp.asarray(ys[0]), 0, jnp.asarray(u[0]), observed=jnp.asarray(observed[0]))
    np.testing.assert_allclose(out.filtered.cov, entrywise.filtered_covariances[0], rtol=1e-12)
    np.testing.assert_allclose(state.mean, entrywise.filtered_means[0], rtol=1e-12)
    # failures give the same codes (the bad matrices arrive traced, past the eager checks):
    # a non-positive innovation covariance, an indefinite filtered covariance
    def codes(r, p0, h):
        res = jdrkf.KalmanFilter(throw=False)(jdrkf.LinearModel(np.eye(n), h, np.zeros((n, n)), r),
                                              jdrkf.Gaussian(np.zeros(n), p0), np.ones((3, m)))
        return res.result._value

    cases = [(-np.eye(m), np.eye(n), np.eye(m, n), jdrkf.RESULTS.nonpositive_innovation),
             (np.eye(m), np.diag(np.r_[1.0, -np.ones(n - 1)]) if n > 1 else -np.eye(1), np.zeros((m, n)),
              jdrkf.RESULTS.indefinite_covariance)]
    for r, p0, h, code in cases:
        with jdrkf.linalg.lapack_only():
            want = jax.jit(codes)(r, p0, h)
        assert jax.jit(codes)(r, p0, h) == want == code._value


# --- steady state --------------------------------------------------------------------------


def test_solve_dare_matches_scipy(rng):
    for n, m in [(1, 1), (2, 1), (4, 2), (6, 3)]:
        F, H, Q, R = _random_stable(rng, n, 0.99), rng.normal(size=(m, n)), _random_spd(rng, n), _random_spd(rng, m)
        p = jdrkf.linalg.solve_dare(F, H, Q, R)
        ref = scipy.linalg.solve_discrete_are(F.T, H.T, Q, R)
        np.testing.assert_allclose(p, ref, rtol=1e-10, atol=1e-10)


def test_solve_dare_unstable_detectable(rng):
    # An unstable but observable system still has a stabilizing DARE solution.
    F = np.array([[1.2, 1.0], [0.0, 1.1]])
    H, Q, R = np.array([[1.0, 0.0]]), np.eye(2), np.eye(1)
    np.testing.assert_allclose(
        jdrkf.linalg.solve_dare(F, H, Q, R), scipy.linalg.solve_discrete_are(F.T, H.T, Q, R), rtol=1e-10
    )


def test_solve_dare_gradient_matches_finite_differences(rng):
    n, m = 3, 2
    F, H, Q, R = _random_stable(rng, n), rng.normal(size=(m, n)), _random_spd(rng, n), _random_spd(rng, m)
    w = rng.normal(size=(n, n))

    def f(F, R):
        return jnp.sum(w * jdrkf.linalg.solve_dare(F, H, Q, R))

    def f_ref(F, R):
        return np.sum(w * scipy.linalg.solve_discrete_are(F.T, H.T, Q, R))

    gF, gR = jax.grad(f, argnums=(0, 1))(jnp.asarray(F), jnp.asarray(R))
    eps = 1e-6
    for (i, j) in [(0, 0), (1, 2), (2, 1)]:
        e = np.zeros_like(F)
        e[i, j] = eps
        np.testing.assert_allclose(gF[i, j], (f_ref(F + e, R) - f_ref(F - e, R)) / (2 * eps), rtol=1e-6, atol=1e-8)
    e = np.zeros_like(R)
    e[0, 1] = e[1, 0] = eps
    np.testing.assert_allclose(gR[0, 1] + gR[1, 0], (f_ref(F, R + e) - f_ref(F, R - e)) / (2 * eps), rtol=1e-6, atol=1e-8)


def test_steady_state_gain_is_limit_of_time_varying_gain(rng):
    n, m, q = 3, 2, 2
    F, H = _random_stable(rng, n, 0.9), rng.normal(size=(m, n))
    Q, R, G = _random_spd(rng, q), _random_spd(rng, m), rng.normal(size=(n, q))
    model = jdrkf.LinearModel(F, H, Q, R, G=G)
    ss = jdrkf.SteadyStateKalmanFilter.solve(model)
    P_ref, K_ref = numpy_dare_filter(F, H, Q, R, G)
    np.testing.assert_allclose(ss.predicted_cov, P_ref, atol=1e-10)
    np.testing.assert_allclose(ss.gain, K_ref, atol=1e-10)
    prior = jdrkf.Gaussian(np.zeros(n), 10 * np.eye(n))
    res = jdrkf.KalmanFilter(outputs="all")(model, prior, rng.normal(size=(300, m)))
    P_last = res.predicted_covariances[-1]
    K_last = P_last @ H.T @ np.linalg.inv(H @ P_last @ H.T + R)
    np.testing.assert_allclose(K_last, ss.gain, atol=1e-10)
    np.testing.assert_allclose(res.filtered_covariances[-1], ss.filtered_cov, atol=1e-10)


def test_steady_state_filter_tracks_kalman_filter_after_transient(rng):
    n, m = 2, 1
    F, H, Q, R = _random_stable(rng, n, 0.8), rng.normal(size=(m, n)), _random_spd(rng, n), _random_spd(rng, m)
    model = jdrkf.LinearModel(F, H, Q, R)
    _, ys = numpy_simulate_lgssm(rng, np.zeros(n), np.eye(n), F, H, Q, R, 200)
    ys[50, 0] = np.nan
    prior = jdrkf.Gaussian(np.zeros(n), np.eye(n))
    kf = jdrkf.KalmanFilter(outputs="all")(model, prior, ys, observed=~np.isnan(ys))
    ss = jdrkf.SteadyStateKalmanFilter(outputs="all")(model, prior, ys, observed=~np.isnan(ys))
    np.testing.assert_allclose(ss.filtered_means[100:], kf.filtered_means[100:], atol=1e-8)
    np.testing.assert_allclose(ss.loglik_increments[100:], kf.loglik_increments[100:], atol=1e-8)
    assert ss.loglik_increments[50] == 0.0


def test_steady_state_rejects_time_varying_model(rng):
    model = jdrkf.LinearModel(np.stack([np.eye(2)] * 3), np.ones((1, 2)), np.eye(2), np.eye(1))
    with pytest.raises(ValueError, match="time-invariant"):
        jdrkf.SteadyStateKalmanFilter.solve(model)


# --- property test ---------------------------------------------------------------------------


@st.composite
def stable_systems(draw):
    n = draw(st.integers(1, 4))
    m = draw(st.integers(1, 3))
    seed = draw(st.integers(0, 2**31 - 1))
    radius = draw(st.floats(0.1, 0.999))
    rng = np.random.default_rng(seed)
    return _random_stable(rng, n, radius), rng.normal(size=(m, n)), _random_spd(rng, n), _random_spd(rng, m, 0.1), seed


@hypothesis.settings(max_examples=8, deadline=None, derandomize=True)
@hypothesis.given(stable_systems())
def test_float32_long_run_covariances_stay_symmetric_psd(system):
    F, H, Q, R, seed = system
    f32 = functools.partial(np.asarray, dtype=np.float32)
    model = jdrkf.LinearModel(f32(F), f32(H), f32(Q), f32(R))
    n, m = F.shape[0], H.shape[0]
    prior = jdrkf.Gaussian(np.zeros(n, np.float32), np.eye(n, dtype=np.float32))
    ys = np.random.default_rng(seed).normal(size=(10_000, m)).astype(np.float32) * 5
    res = jax.jit(jdrkf.KalmanFilter())(model, prior, ys)
    covs = np.asarray(res.filtered_covariances)
    assert covs.dtype == np.float32
    assert np.all(np.isfinite(covs)) and np.all(np.isfinite(np.asarray(res.filtered_means)))
    np.testing.assert_array_equal(covs, np.swapaxes(covs, -1, -2))
    assert np.min(np.linalg.eigvalsh(covs.astype(np.float64))) >= -1e-5 * np.max(np.abs(covs))
    assert res.result == jdrkf.RESULTS.successful


def test_default_equals_all_observed_mask_and_fails_loudly_on_nan(rng):
    fields, u, m0, P0, ys = _time_varying_problem(rng, missing=False)
    model, prior = jdrkf.LinearModel(**fields), jdrkf.Gaussian(m0, P0)
    a = jdrkf.KalmanFilter()(model, prior, ys, inputs=u, observed=np.ones(ys.shape, bool))
    b = jdrkf.KalmanFilter()(model, prior, ys, inputs=u)
    np.testing.assert_allclose(b.filtered_means, a.filtered_means, atol=1e-12)
    np.testing.assert_allclose(b.filtered_covariances, a.filtered_covariances, atol=1e-12)
    np.testing.assert_allclose(b.marginal_loglik, a.marginal_loglik, rtol=1e-12)
    ys[4, 0] = np.nan
    with pytest.raises(ValueError, match=r"ys\[4, 0\] is NaN.*observed"):
        jdrkf.KalmanFilter(throw=False)(model, prior, ys, inputs=u)
    res = jax.jit(lambda y: jdrkf.KalmanFilter(throw=False)(model, prior, y, inputs=u))(ys)
    assert res.result == jdrkf.RESULTS.nan_observation


def test_default_shares_covariance_under_vmap(rng):
    # Without a mask the covariance recursion does not depend on the data, so vmap
    # leaves it unbatched: the time loop of the batched filter carries it once.
    model = jdrkf.LinearModel(_random_stable(rng, 2), rng.normal(size=(1, 2)), np.eye(2), np.eye(1))
    prior = jdrkf.Gaussian(np.zeros(2), np.eye(2))
    ys = rng.normal(size=(4, 10, 1))
    observed = np.ones(ys.shape, bool)
    shared = jax.vmap(jdrkf.KalmanFilter(), in_axes=(None, None, 0))(model, prior, ys)
    masked = jax.vmap(lambda y, o: jdrkf.KalmanFilter()(model, prior, y, observed=o))(ys, observed)
    np.testing.assert_allclose(shared.filtered_means, masked.filtered_means, atol=1e-12)
    np.testing.assert_allclose(shared.filtered_covariances, masked.filtered_covariances, atol=1e-12)

    def cov_carry_shapes(fn, *args):
        jaxpr = jax.make_jaxpr(fn)(*args)
        scan = next(e for e in jaxpr.jaxpr.eqns if e.primitive.name == "scan")
        return [v.aval.shape for v in scan.outvars[: scan.params["num_carry"]] if jnp.issubdtype(v.aval.dtype, jnp.inexact)]

    # n = 2: the filter carries the covariance's 4 entries (scalars; (4,) arrays when per run)
    cov_carry = cov_carry_shapes(jax.vmap(jdrkf.KalmanFilter(), in_axes=(None, None, 0)), model, prior, ys)
    assert cov_carry.count(()) >= 4 and cov_carry.count((4,)) <= 3, cov_carry  # 2 mean entries + log-likelihood
    # a per-run mask makes the covariance recursion per run
    per_run = cov_carry_shapes(jax.vmap(lambda y, o: jdrkf.KalmanFilter()(model, prior, y, observed=o)), ys, observed)
    assert per_run.count((4,)) >= 2 + 4, per_run


def test_steady_state_default_matches_all_observed_mask_on_complete_data(rng):
    n, m = 3, 2
    F, H, Q, R = _random_stable(rng, n, 0.8), rng.normal(size=(m, n)), _random_spd(rng, n), _random_spd(rng, m)
    model, prior = jdrkf.LinearModel(F, H, Q, R), jdrkf.Gaussian(np.zeros(n), np.eye(n))
    _, ys = numpy_simulate_lgssm(rng, np.zeros(n), np.eye(n), F, H, Q, R, 50)
    flt = jdrkf.SteadyStateKalmanFilter(outputs="all")
    a = flt(model, prior, ys, observed=np.ones(ys.shape, bool))
    b = flt(model, prior, ys)
    np.testing.assert_allclose(b.filtered_means, a.filtered_means, atol=1e-12)
    np.testing.assert_allclose(b.loglik_increments, a.loglik_increments, atol=1e-12)
    ys[5, 1] = np.nan
    with pytest.raises(ValueError, match="observed"):
        jdrkf.SteadyStateKalmanFilter(throw=False)(model, prior, ys)
    res = jax.jit(lambda y: jdrkf.SteadyStateKalmanFilter(throw=False)(model, prior, y))(ys)
    assert res.result == jdrkf.RESULTS.nan_observation


# --- explicit missing-data mask (`observed`) and requested outputs (`outputs`) ----------------

_ALL_FIELDS = (
    "filtered_means",
    "filtered_covariances",
    "predicted_means",
    "predicted_covariances",
    "loglik_increments",
    "marginal_loglik",
    "info",
)


def test_observed_mask_ignores_masked_values_and_matches_nan_oracle(rng):
    fields, u, m0, P0, ys = _time_varying_problem(rng)  # NaN at the missing entries
    model, prior = jdrkf.LinearModel(**fields), jdrkf.Gaussian(m0, P0)
    observed = ~np.isnan(ys)
    flt = jdrkf.KalmanFilter(outputs="all")
    res = flt(model, prior, ys, inputs=u, observed=observed)
    assert res.result == jdrkf.RESULTS.successful
    # The values at masked entries are ignored: finite garbage there gives the same run.
    garbage = np.where(observed, ys, 1e3 * rng.normal(size=ys.shape))
    assert np.all(np.isfinite(garbage))
    res_g = flt(model, prior, garbage, inputs=u, observed=observed)
    for name in ["filtered_means", "filtered_covariances", "predicted_means", "predicted_covariances", "loglik_increments"]:
        np.testing.assert_array_equal(getattr(res_g, name), getattr(res, name), err_msg=name)
    np.testing.assert_array_equal(res_g.marginal_loglik, res.marginal_loglik)
    # ... and equals the old NaN-as-missing semantics (the NumPy oracle skips NaN components).
    ref = numpy_kalman_filter(m0, P0, ys, inputs=u, **fields)
    for name in ["filtered_means", "filtered_covariances", "predicted_means", "predicted_covariances", "loglik_increments"]:
        np.testing.assert_allclose(getattr(res_g, name), ref[name], rtol=0, atol=1e-10, err_msg=name)
    np.testing.assert_allclose(res_g.marginal_loglik, ref["marginal_loglik"], rtol=1e-12)
    # The mask, not the data, decides: hiding finite entries equals the oracle with NaN there.
    hidden = observed.copy()
    hidden[0, 1] = hidden[20, 0] = False
    res_h = jax.jit(lambda y, o: flt(model, prior, y, inputs=u, observed=o))(garbage, hidden)
    ys_h = np.where(hidden, ys, np.nan)
    ref_h = numpy_kalman_filter(m0, P0, ys_h, inputs=u, **fields)
    for name in ["filtered_means", "filtered_covariances", "loglik_increments"]:
        np.testing.assert_allclose(getattr(res_h, name), ref_h[name], rtol=0, atol=1e-10, err_msg=name)
    assert not np.allclose(res_h.filtered_means, res.filtered_means, atol=1e-6)


def test_nan_without_mask_raises_or_reports_nan_observation(rng):
    fields, u, m0, P0, ys = _time_varying_problem(rng, missing=False)
    model, prior = jdrkf.LinearModel(**fields), jdrkf.Gaussian(m0, P0)
    ys[6, 1] = np.nan
    # Concrete data: an eager error that points at `observed`.
    with pytest.raises(ValueError, match=r"ys\[6, 1\] is NaN.*observed=~jnp\.isnan\(ys\)"):
        jdrkf.KalmanFilter(throw=False)(model, prior, ys, inputs=u)
    # Traced data: a result code (it takes precedence over the NaN state it causes) ...
    res = jax.jit(lambda y: jdrkf.KalmanFilter(throw=False)(model, prior, y, inputs=u))(ys)
    assert res.result == jdrkf.RESULTS.nan_observation
    # ... and with throw=True a run-time error.
    with pytest.raises(Exception, match="told to use is NaN"):
        jax.block_until_ready(jax.jit(lambda y: jdrkf.KalmanFilter()(model, prior, y, inputs=u))(ys).filtered_means)
    # A NaN at an entry the mask marks observed is the same error.
    observed = np.ones(ys.shape, bool)
    observed[2, 0] = False
    with pytest.raises(ValueError, match=r"ys\[6, 1\] is NaN.*observed"):
        jdrkf.KalmanFilter(throw=False)(model, prior, ys, inputs=u, observed=observed)
    run = jax.jit(lambda y, o: jdrkf.KalmanFilter(throw=False)(model, prior, y, inputs=u, observed=o))
    assert run(ys, observed).result == jdrkf.RESULTS.nan_observation
    # Masking the NaN entry makes the run succeed.
    observed[6, 1] = False
    assert run(ys, observed).result == jdrkf.RESULTS.successful
    # Under vmap the code is per run: only the run with the NaN reports it.
    runs = np.stack([np.nan_to_num(ys), ys, np.nan_to_num(ys) + 1.0])
    codes = jax.vmap(lambda y: jdrkf.KalmanFilter(throw=False)(model, prior, y, inputs=u).result)(runs)
    np.testing.assert_array_equal(
        np.asarray(codes == jdrkf.RESULTS.nan_observation), [False, True, False]
    )
    np.testing.assert_array_equal(np.asarray(codes == jdrkf.RESULTS.successful), [True, False, True])


def test_observed_validation(rng):
    fields, u, m0, P0, ys = _time_varying_problem(rng, missing=False)
    model, prior = jdrkf.LinearModel(**fields), jdrkf.Gaussian(m0, P0)
    T, m = ys.shape
    bad = [
        np.ones((T, m + 1), bool),  # wrong shape
        np.ones((T - 1, m), bool),
        np.ones(T * m, bool),
        np.ones((T, m)),  # float, not bool
        np.ones((T, m), np.int32),
    ]
    for observed in bad:
        with pytest.raises(ValueError, match="observed"):
            jdrkf.KalmanFilter()(model, prior, ys, inputs=u, observed=observed)
    with pytest.raises(ValueError, match="observed"):
        jdrkf.SteadyStateKalmanFilter()(
            jdrkf.LinearModel(fields["F"][0], fields["H"], fields["Q"], fields["R"][0], G=fields["G"]),
            prior, ys, observed=np.ones((T, m), np.float64),
        )
    # CovarianceIntersection does not support missing data.
    ms = jdrkf.MultiSensorModel(np.eye(2) * 0.9, [np.ones((1, 2)), np.eye(2)], np.eye(2), [np.eye(1), np.eye(2)])
    ys3 = rng.normal(size=(5, 3))
    ci = jdrkf.CovarianceIntersection()
    assert ci(ms, jdrkf.Gaussian(np.zeros(2), np.eye(2)), ys3).result == jdrkf.RESULTS.successful
    with pytest.raises(ValueError, match="observed"):
        ci(ms, jdrkf.Gaussian(np.zeros(2), np.eye(2)), ys3, observed=np.ones((5, 3), bool))


@pytest.mark.slow  # ~30 s: compiles every output subset
def test_outputs_default_all_and_subsets(rng):
    fields, u, m0, P0, ys = _time_varying_problem(rng)
    model, prior = jdrkf.LinearModel(**fields), jdrkf.Gaussian(m0, P0)
    observed = ~np.isnan(ys)
    default = jdrkf.KalmanFilter()(model, prior, ys, inputs=u, observed=observed)
    filled = {"filtered_means", "filtered_covariances", "marginal_loglik"}
    for name in _ALL_FIELDS:
        assert (getattr(default, name) is not None) == (name in filled), name
    assert default.result == jdrkf.RESULTS.successful
    full = jdrkf.KalmanFilter(outputs="all")(model, prior, ys, inputs=u, observed=observed)
    for name in _ALL_FIELDS[:-1]:  # KalmanFilter has no diagnostics (info is None)
        assert getattr(full, name) is not None, name
    for name in filled:
        np.testing.assert_array_equal(getattr(default, name), getattr(full, name), err_msg=name)
    np.testing.assert_allclose(full.marginal_loglik, jnp.sum(full.loglik_increments), rtol=1e-12)
    assert full.loglik_increments.shape == (ys.shape[0],) and full.predicted_covariances.shape == (ys.shape[0], 3, 3)
    # A filter with diagnostics fills `info` with "all" and only then.
    huber_all = jdrkf.HuberKF(0.05, 1.4, outputs="all")(model, prior, ys, inputs=u, observed=observed)
    assert all(getattr(huber_all, name) is not None for name in _ALL_FIELDS)
    assert jdrkf.HuberKF(0.05, 1.4)(model, prior, ys, inputs=u, observed=observed).info is None
    np.testing.assert_allclose(huber_all.marginal_loglik, jnp.sum(huber_all.loglik_increments), rtol=1e-12)
    # Requested fields equal those of "all"; the others are None (a name or a sequence, jit or not).
    for outputs in ["predicted_means", ("loglik_increments",), ("marginal_loglik", "predicted_covariances"), ["info", "filtered_means"]]:
        requested = {outputs} if isinstance(outputs, str) else set(outputs)
        for call in (lambda f: f(model, prior, ys, inputs=u, observed=observed),
                     jax.jit(lambda f: f(model, prior, ys, inputs=u, observed=observed))):
            for flt, cls in ((jdrkf.KalmanFilter(outputs=outputs), jdrkf.KalmanFilter), (jdrkf.HuberKF(0.05, 1.4, outputs=outputs), functools.partial(jdrkf.HuberKF, 0.05, 1.4))):
                res, ref = call(flt), call(cls(outputs="all"))
                for name in _ALL_FIELDS:
                    if name in requested:
                        jax.tree.map(np.testing.assert_array_equal, getattr(res, name), getattr(ref, name))
                    else:
                        assert getattr(res, name) is None, (outputs, name)
    # Unknown names are rejected, naming `outputs`.
    for outputs in ["filtered_mean", ("filtered_means", "bogus"), 3]:
        with pytest.raises(ValueError, match="outputs"):
            jdrkf.KalmanFilter(outputs=outputs)
        with pytest.raises(ValueError, match="outputs"):
            jdrkf.HuberKF(0.05, 1.4, outputs=outputs)
