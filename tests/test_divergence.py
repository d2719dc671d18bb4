"""TauKF (τ-divergence / KL robust KF) and RiskSensitiveKF against independent oracles."""

from decimal import Decimal, localcontext

import equinox as eqx
import hypothesis
import hypothesis.strategies as st
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.optimize
from oracles import numpy_kalman_filter, numpy_simulate_lgssm

import jdrkf
from jdrkf.filters._divergence import (
    RiskSensitiveKF,
    TauKF,
    _phi,
    robustify_covariance,
)


def _random_spd(rng, d, scale=1.0):
    a = rng.normal(size=(d, d))
    return scale * (a @ a.T / d + 0.5 * np.eye(d))


def _random_stable(rng, n, radius=0.95):
    a = rng.normal(size=(n, n))
    return radius * a / np.max(np.abs(np.linalg.eigvals(a)))


@jax.jit
def _run_filter(filt, model, prior, ys, observed=None):
    return filt(model, prior, ys, observed=observed)


# --- independent NumPy oracle of the published predictor (Zorzi 2017) ----------------------


def _phi_table(s, tau):
    """φ_τ(s) exactly as in the published table."""
    if tau == 0:
        return 1 / (1 - s) - 1 + np.log(1 - s)
    if tau == 1:
        return s * np.exp(s) - np.exp(s) + 1
    u = 1 - (1 - tau) * s
    return -u ** (tau / (tau - 1)) / (tau * (1 - tau)) + u ** (1 / (tau - 1)) / (1 - tau) + 1 / tau


def _g_table(s, tau):
    return np.exp(s) if tau == 1 else (1 - (1 - tau) * s) ** (-1 / (1 - tau))


def _theta_brentq(p, tau, c):
    """θ > 0 with Σ φ_τ(θ p_i) = c (scipy brentq)."""
    p = np.atleast_1d(p)
    if c == 0:
        return 0.0

    def h(theta):
        return sum(_phi_table(theta * pi, tau) for pi in p) - c

    hi = (1 - 1e-9) / ((1 - tau) * p.max()) if tau < 1 else 1 / p.max()
    while tau == 1 and h(hi) < 0:
        hi *= 2
    return scipy.optimize.brentq(h, 0.0, hi, xtol=1e-300, rtol=4 * np.finfo(float).eps, maxiter=1000)


def _robustify_np(P, tau, c):
    p, U = np.linalg.eigh(P)
    theta = _theta_brentq(p, tau, c)
    return theta, U @ np.diag(p * _g_table(theta * p, tau)) @ U.T


def published_tau_predictor(m0, P0, ys, A, C, Q, R, tau, c):
    """Zorzi's one-step predictor, steps 1–3 of docs/math/divergence.md, started from the prior's
    prediction: x̂_1 = A m0, V_1 = robustify(A P0 Aᵀ + Q). Returns x̂_t, V_t, θ_t, P_t for
    t = 1..T (x̂_t uses y_1..y_{t-1}; ys[t-1] = y_t)."""
    x = A @ m0
    P = A @ P0 @ A.T + Q
    theta, V = _robustify_np(P, tau, c)
    out = {"means": [], "V": [], "theta": [], "P": []}
    for y in ys:
        out["means"].append(x)
        out["V"].append(V)
        out["theta"].append(theta)
        out["P"].append(P)
        S = C @ V @ C.T + R
        G = A @ V @ C.T @ np.linalg.inv(S)
        x = A @ x + G @ (y - C @ x)
        P = A @ V @ A.T - G @ S @ G.T + Q
        P = 0.5 * (P + P.T)
        theta, V = _robustify_np(P, tau, c)
    return {k: np.array(v) for k, v in out.items()}


def _seed000_system():
    F = np.array([[0.9802, 0.0196], [0.0, 0.9802]])
    H = np.array([[1.0, -1.0]])
    Q = np.array([[1.9608, 0.0195], [0.0195, 1.9605]])
    R = np.array([[1.0]])
    return F, H, Q, R


def _random_system(rng, n=3, m=2):
    return _random_stable(rng, n, 0.9), rng.normal(size=(m, n)), _random_spd(rng, n), _random_spd(rng, m, 0.5)


@pytest.mark.parametrize("system", ["random", "seed000"])
@pytest.mark.parametrize("tau", [0.0, 0.5, 1.0])
def test_matches_published_predictor(rng, system, tau):
    if system == "random":
        F, H, Q, R = _random_system(rng)
        c, T = 0.05, 40
    else:
        F, H, Q, R = _seed000_system()
        c, T = 1.5e-4, 200
    n = F.shape[0]
    m0, P0 = np.zeros(n), np.eye(n)
    _, ys = numpy_simulate_lgssm(rng, m0, P0, F, H, Q, R, T)
    ys[::17] += 30.0  # a few outliers: the means then depend visibly on the gains
    ref = published_tau_predictor(m0, P0, ys, F, H, Q, R, tau, c)
    res = _run_filter(TauKF(tau, c, outputs="all"), jdrkf.LinearModel(F, H, Q, R), jdrkf.Gaussian(m0, P0), ys)
    assert res.result == jdrkf.RESULTS.successful
    assert np.all(ref["theta"] > 0)
    np.testing.assert_allclose(res.info["theta"], ref["theta"], rtol=1e-9)
    np.testing.assert_allclose(res.predicted_covariances, ref["V"], rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(res.info["nominal_predicted_cov"], ref["P"], rtol=1e-9, atol=1e-9)
    scale = np.max(np.abs(ref["means"]))
    np.testing.assert_allclose(res.predicted_means, ref["means"], rtol=0, atol=1e-9 * scale)
    # The robustification is not negligible here (else the test could not fail).
    assert np.max(np.abs(ref["V"] - ref["P"])) > 1e-3 * np.max(np.abs(ref["P"]))


def test_published_riccati_identity(rng):
    # Zorzi's step 2: P_{t+1} = A V Aᵀ − G (C V Cᵀ + R) Gᵀ + Q = A Π Aᵀ + Q,
    # with Π the filtered covariance of the update from V.
    F, H, Q, R = _random_system(rng)
    n = F.shape[0]
    ys = rng.normal(size=(40, H.shape[0]))
    res = _run_filter(TauKF(0.3, 0.1, outputs="all"), jdrkf.LinearModel(F, H, Q, R), jdrkf.Gaussian(np.zeros(n), np.eye(n)), ys)
    for k in range(len(ys) - 1):
        V, Pi = res.predicted_covariances[k], res.filtered_covariances[k]
        S = H @ V @ H.T + R
        G = F @ V @ H.T @ np.linalg.inv(S)
        published = F @ V @ F.T - G @ S @ G.T + Q
        nominal_next = res.info["nominal_predicted_cov"][k + 1]
        np.testing.assert_allclose(nominal_next, published, atol=1e-12)
        np.testing.assert_allclose(nominal_next, F @ Pi @ F.T + Q, atol=1e-12)


# --- limits and structure --------------------------------------------------------------------


def _kf_problem(rng, n=3, m=2, T=40):
    F, H, Q, R = _random_system(rng, n, m)
    model = jdrkf.LinearModel(F, H, Q, R)
    prior = jdrkf.Gaussian(rng.normal(size=n), _random_spd(rng, n))
    _, ys = numpy_simulate_lgssm(rng, np.zeros(n), np.eye(n), F, H, Q, R, T)
    return model, prior, ys


_FIELDS = ["filtered_means", "filtered_covariances", "predicted_means", "predicted_covariances", "loglik_increments"]


@pytest.mark.parametrize("tau", [0.0, 0.5, 1.0])
def test_zero_tolerance_is_the_kalman_filter(rng, tau):
    model, prior, ys = _kf_problem(rng)
    kf = _run_filter(jdrkf.KalmanFilter(outputs="all"), model, prior, ys)
    exact = _run_filter(TauKF(tau, 0.0, outputs="all"), model, prior, ys)
    for name in _FIELDS:  # round-off: the KF runs its step entry by entry (filters/_entrywise.py)
        np.testing.assert_allclose(getattr(exact, name), getattr(kf, name), rtol=1e-12, atol=1e-13, err_msg=name)
    np.testing.assert_array_equal(exact.info["theta"], 0.0)
    near = _run_filter(TauKF(tau, 1e-12, outputs="all"), model, prior, ys)
    assert np.all(near.info["theta"] > 0)
    for name in _FIELDS:
        np.testing.assert_allclose(getattr(near, name), getattr(kf, name), rtol=1e-5, atol=1e-6, err_msg=name)


@pytest.mark.parametrize("tau", [0.0, 0.3, 1.0])
def test_least_favourable_covariance_dominates_nominal(rng, tau):
    model, prior, ys = _kf_problem(rng)
    res = _run_filter(TauKF(tau, 0.2, outputs="all"), model, prior, ys)
    gap = np.linalg.eigvalsh(res.predicted_covariances - res.info["nominal_predicted_cov"])
    assert np.all(gap > 0)  # strictly: every eigenvalue of P is inflated when c > 0
    # and the filtered covariance exceeds the KF update of the same nominal prediction
    H, R = np.asarray(model.H), np.asarray(model.R)
    for P, Pi in zip(np.asarray(res.info["nominal_predicted_cov"]), np.asarray(res.filtered_covariances)):
        kf_filtered = P - P @ H.T @ np.linalg.solve(H @ P @ H.T + R, H @ P)
        assert np.min(np.linalg.eigvalsh(Pi - kf_filtered)) > -1e-12


def test_continuous_in_tau_at_the_ends(rng):
    P = _random_spd(rng, 3)
    for tau_end, tau_near in [(0.0, 1e-6), (1.0, 1 - 1e-6)]:
        for c in [1e-4, 0.5]:
            th_end, V_end = robustify_covariance(P, tau_end, c)
            th_near, V_near = robustify_covariance(P, tau_near, c)
            np.testing.assert_allclose(th_near, th_end, rtol=1e-5)
            np.testing.assert_allclose(V_near, V_end, rtol=1e-5)
            assert th_near != th_end  # the interior formula was used, not the end point's


@pytest.mark.parametrize("tau", [0.0, 0.5, 1.0])
def test_scalar_closed_form(tau):
    p, c = 2.5, 0.3
    theta_ref = _theta_brentq(np.array([p]), tau, c)
    v_ref = p / (1 - theta_ref * p) if tau == 0 else p * _g_table(theta_ref * p, tau)
    theta, v = robustify_covariance(np.array([[p]]), tau, c)
    np.testing.assert_allclose(theta, theta_ref, rtol=1e-12)
    np.testing.assert_allclose(v[0, 0], v_ref, rtol=1e-12)


def test_static_kl_check(rng):
    # ½ Σ φ_0(θ p_i) = KL(N(0, V) ‖ N(0, P)) = c/2, and V = (P⁻¹ − θ I)⁻¹.
    n, c = 3, 0.2
    P = _random_spd(rng, n)
    theta, V = robustify_covariance(P, 0.0, c)
    V = np.asarray(V)
    p = np.linalg.eigvalsh(P)
    np.testing.assert_allclose(0.5 * sum(_phi_table(theta * pi, 0) for pi in p), c / 2, rtol=1e-12)
    kl = 0.5 * (np.trace(np.linalg.solve(P, V)) - n + np.linalg.slogdet(P)[1] - np.linalg.slogdet(V)[1])
    np.testing.assert_allclose(kl, c / 2, rtol=1e-10)
    np.testing.assert_allclose(V, np.linalg.inv(np.linalg.inv(P) - theta * np.eye(n)), rtol=1e-10)
    kl_jdrkf = jdrkf.Gaussian(np.zeros(n), V).kl_divergence(jdrkf.Gaussian(np.zeros(n), P))
    np.testing.assert_allclose(kl_jdrkf, c / 2, rtol=1e-10)


def _phi_decimal(s, tau):
    """φ_τ(s) from the published table in 60-digit decimal arithmetic."""
    with localcontext() as ctx:
        ctx.prec = 60
        s, tau = Decimal(s), Decimal(tau)
        if tau == 0:
            return float(1 / (1 - s) - 1 + (1 - s).ln())
        if tau == 1:
            return float(s * s.exp() - s.exp() + 1)
        lu = (1 - (1 - tau) * s).ln()
        return float(-(lu * tau / (tau - 1)).exp() / (tau * (1 - tau)) + (lu / (tau - 1)).exp() / (1 - tau) + 1 / tau)


def test_phi_is_accurate_everywhere():
    # Including tiny s and τ near 0, where the published form cancels catastrophically.
    taus = [0.0, 1e-9, 1e-4, 0.1, 0.5, 0.7, 1 - 1e-6, 1.0]
    ss = np.array([1e-8, 1e-4, 0.1, 0.25, 0.26, 0.6, 0.99, 1.0, 1.3, 4.0, -0.01, -0.4])
    phi = jax.jit(_phi)
    for tau in taus:
        values = np.asarray(phi(ss, jnp.asarray(tau)))
        for s, value in zip(ss, values):
            if tau < 1 and (1 - tau) * s >= 1:
                assert value == np.inf
            else:
                np.testing.assert_allclose(value, _phi_decimal(s, tau), rtol=1e-13, err_msg=f"tau={tau}, s={s}")


# --- risk-sensitive filter -------------------------------------------------------------------


def test_risk_sensitive_zero_theta_is_the_kalman_filter(rng):
    model, prior, ys = _kf_problem(rng)
    kf = _run_filter(jdrkf.KalmanFilter(outputs="all"), model, prior, ys)
    rs = _run_filter(RiskSensitiveKF(0.0, outputs="all"), model, prior, ys)
    for name in _FIELDS:  # round-off: the KF runs its step entry by entry (filters/_entrywise.py)
        np.testing.assert_allclose(getattr(rs, name), getattr(kf, name), rtol=1e-12, atol=1e-13, err_msg=name)
    assert np.all(rs.info["valid"])


def test_risk_sensitive_with_tau_kf_multipliers_is_tau_kf(rng):
    model, prior, ys = _kf_problem(rng)
    tau_kf = _run_filter(TauKF(0.0, 0.1, outputs="all"), model, prior, ys)
    state = prior
    step = jax.jit(lambda theta, state, y, t: RiskSensitiveKF(theta).step(model, state, y, t))
    for t in range(len(ys)):
        state, out = step(tau_kf.info["theta"][t], state, ys[t], t)
        assert out.result == jdrkf.RESULTS.successful and out.info["valid"]
        np.testing.assert_allclose(out.predicted.cov, tau_kf.predicted_covariances[t], rtol=1e-11)
        np.testing.assert_allclose(out.filtered.cov, tau_kf.filtered_covariances[t], rtol=1e-11)
        np.testing.assert_allclose(out.filtered.mean, tau_kf.filtered_means[t], rtol=1e-11, atol=1e-12)
    # and the update form matches (P⁻¹ − θ I)⁻¹ with explicit inverses
    theta, P = 0.05, _random_spd(rng, 3)
    state = jdrkf.Gaussian(np.zeros(3), P)
    one_step = jdrkf.LinearModel(np.eye(3), np.eye(1, 3), np.zeros((3, 3)), np.eye(1))
    _, out = RiskSensitiveKF(theta).step(one_step, state, jnp.full(1, jnp.nan), 0, observed=jnp.zeros(1, bool))
    np.testing.assert_allclose(out.predicted.cov, np.linalg.inv(np.linalg.inv(P) - theta * np.eye(3)), rtol=1e-12)


def test_risk_sensitive_breakdown_is_reported(rng):
    model, prior, ys = _kf_problem(rng)
    lam_max = np.linalg.eigvalsh(jdrkf.predict(model, prior, 0).cov).max()
    ok = _run_filter(RiskSensitiveKF(0.5 / lam_max, throw=False, outputs="all"), model, prior, ys)
    assert ok.result == jdrkf.RESULTS.successful and np.all(ok.info["valid"])
    bad = _run_filter(RiskSensitiveKF(1.01 / lam_max, throw=False, outputs="all"), model, prior, ys)
    assert bad.result == jdrkf.RESULTS.risk_sensitive_breakdown
    assert not bad.info["valid"][0]
    # No pretence of a finite answer after the breakdown.
    assert np.all(np.isnan(bad.filtered_means)) and np.all(np.isnan(bad.predicted_covariances))
    with pytest.raises(Exception, match="non-finite|risk"):
        jax.block_until_ready(_run_filter(RiskSensitiveKF(1.01 / lam_max), model, prior, ys).filtered_means)


def test_innovation_failure_code():
    # Zero noise and a zero prior covariance: H V Hᵀ + R = 0 is not positive definite.
    model = jdrkf.LinearModel(np.eye(3), np.eye(2, 3), np.zeros((3, 3)), np.zeros((2, 2)))
    prior = jdrkf.Gaussian(np.zeros(3), np.zeros((3, 3)))
    res = _run_filter(TauKF(0.5, 0.1, throw=False), model, prior, np.ones((40, 2)))
    assert res.result == jdrkf.RESULTS.nonpositive_innovation


# --- differentiability -----------------------------------------------------------------------


def _grad_problem(rng, runs=3, T=30):
    F, H, Q, R = _random_system(rng, 2, 1)
    model = jdrkf.LinearModel(F, H, Q, R)
    prior = jdrkf.Gaussian(np.zeros(2), np.eye(2))
    sims = [numpy_simulate_lgssm(rng, np.zeros(2), np.eye(2), F, H, Q, R, T) for _ in range(runs)]
    xs = np.stack([s[0] for s in sims])
    ys = np.stack([s[1] for s in sims])
    ys[:, 5] += 20.0
    return model, prior, xs, ys


@jax.jit
@jax.value_and_grad
def _mse_and_grad(filt, model, prior, xs, ys):
    """Mean squared error of the filtered means over a batch of runs, and its gradient
    with respect to the filter's hyper-parameters (jit × vmap × grad)."""
    out = jax.vmap(filt, in_axes=(None, None, 0))(model, prior, ys)
    return jnp.mean((out.filtered_means - xs) ** 2)


def _central_fd(f, x, h):
    return (f(x + h) - f(x - h)) / (2 * h)


def test_jit_vmap_grad_tau_kf_against_finite_differences(rng):
    model, prior, xs, ys = _grad_problem(rng)
    tau, c = 0.3, 0.05
    _, grad = _mse_and_grad(TauKF(tau, c), model, prior, xs, ys)
    fd_tau = _central_fd(lambda t: _mse_and_grad(TauKF(t, c), model, prior, xs, ys)[0], tau, 1e-5)
    fd_c = _central_fd(lambda x: _mse_and_grad(TauKF(tau, x), model, prior, xs, ys)[0], c, 1e-6)
    np.testing.assert_allclose(grad.tau, fd_tau, rtol=1e-5)
    np.testing.assert_allclose(grad.radius, fd_c, rtol=1e-5)
    assert abs(grad.tau) > 1e-6 and abs(grad.radius) > 1e-4  # non-trivial dependence


def test_jit_vmap_grad_risk_sensitive_against_finite_differences(rng):
    model, prior, xs, ys = _grad_problem(rng)
    theta = 0.05
    _, grad = _mse_and_grad(RiskSensitiveKF(theta), model, prior, xs, ys)
    fd = _central_fd(lambda x: _mse_and_grad(RiskSensitiveKF(x), model, prior, xs, ys)[0], theta, 1e-6)
    np.testing.assert_allclose(grad.theta, fd, rtol=1e-5)
    assert abs(grad.theta) > 1e-4


def _one_sided_fd(f, x, h):
    # second-order one-sided difference (for τ at the ends of [0, 1])
    return (-3 * f(x) + 4 * f(x + h) - f(x + 2 * h)) / (2 * h)


def _robustify_objective(P, tau, c, W):
    theta, V = robustify_covariance(P, tau, c)
    return jnp.sum(W * V) + 3 * theta


_robustify_value_and_grad = jax.jit(jax.value_and_grad(_robustify_objective, argnums=(0, 1, 2)))


@pytest.mark.parametrize("tau", [0.0, 0.5, 1.0])
@pytest.mark.parametrize("spectrum", ["2I", "repeated", "distinct"])
def test_robustify_gradients_with_repeated_eigenvalues(rng, tau, spectrum):
    n, c = 3, 0.3
    if spectrum == "2I":
        P = 2 * np.eye(n)
    elif spectrum == "repeated":
        U = np.linalg.qr(rng.normal(size=(n, n)))[0]
        P = U @ np.diag([1.0, 2.0, 2.0]) @ U.T
    else:
        P = _random_spd(rng, n)
    W = rng.normal(size=(n, n))

    def f(P, tau, c):
        return _robustify_value_and_grad(*(jnp.asarray(x, jnp.float64) for x in (P, tau, c, W)))[0]

    _, (gP, gtau, gc) = _robustify_value_and_grad(*(jnp.asarray(x, jnp.float64) for x in (P, tau, c, W)))
    assert np.all(np.isfinite(gP))
    E = rng.normal(size=(n, n))
    E = E + E.T
    np.testing.assert_allclose(np.sum(gP * E), _central_fd(lambda h: f(P + h * E, tau, c), 0.0, 1e-6), rtol=1e-7)
    np.testing.assert_allclose(gc, _central_fd(lambda x: f(P, tau, x), c, 1e-6), rtol=1e-7)
    if tau == 0.5:
        fd_tau = _central_fd(lambda x: f(P, x, c), tau, 1e-6)
    else:
        sign = 1.0 if tau == 0 else -1.0
        fd_tau = sign * _one_sided_fd(lambda x: f(P, tau + sign * x, c), 0.0, 1e-5)
    np.testing.assert_allclose(gtau, fd_tau, rtol=1e-6)


# --- dtype, missing data, properties, validation ---------------------------------------------


def test_float32_runs_and_matches_float64(rng):
    model, prior, ys = _kf_problem(rng)
    ref = _run_filter(TauKF(0.5, 0.1, outputs="all"), model, prior, ys)
    f32 = lambda x: jnp.asarray(x, jnp.float32)
    model32 = jax.tree_util.tree_map(f32, model)
    prior32 = jdrkf.Gaussian(f32(prior.mean), f32(prior.cov))
    for filt in [TauKF(0.5, 0.1), RiskSensitiveKF(0.01)]:
        res = _run_filter(filt, model32, prior32, f32(ys))
        assert res.filtered_means.dtype == jnp.float32 and res.filtered_covariances.dtype == jnp.float32
        assert res.result == jdrkf.RESULTS.successful
    res = _run_filter(TauKF(0.5, 0.1, outputs="all"), model32, prior32, f32(ys))
    np.testing.assert_allclose(res.filtered_means, ref.filtered_means, rtol=1e-3, atol=1e-3)
    np.testing.assert_allclose(res.info["theta"], ref.info["theta"], rtol=1e-3)


def test_missing_observations(rng):
    model, prior, ys = _kf_problem(rng)
    ys[4, :] = np.nan
    ys[7, 0] = np.nan
    res = _run_filter(TauKF(0.0, 0.1, outputs="all"), model, prior, ys, ~np.isnan(ys))
    assert res.result == jdrkf.RESULTS.successful
    np.testing.assert_array_equal(res.filtered_means[4], res.predicted_means[4])
    np.testing.assert_allclose(res.filtered_covariances[4], res.predicted_covariances[4], atol=1e-14)
    assert res.loglik_increments[4] == 0.0
    # the partially observed step equals the update with only the observed row
    nominal = jdrkf.Gaussian(res.predicted_means[7], res.predicted_covariances[7])
    H, R = np.asarray(model.H), np.asarray(model.R)
    ref = numpy_kalman_filter(nominal.mean, nominal.cov, ys[7:8, 1:], np.eye(3), H[1:], np.zeros((3, 3)), R[1:, 1:])
    np.testing.assert_allclose(res.filtered_means[7], ref["filtered_means"][0], atol=1e-12)


def test_nominal_covariance_shared_under_vmap_without_a_mask(rng):
    model, prior, _ = _kf_problem(rng, T=10)
    ys = rng.normal(size=(4, 10, 2))

    def carry_shapes(fn, *args):
        jaxpr = jax.make_jaxpr(fn)(*args)
        scan = next(e for e in jaxpr.jaxpr.eqns if e.primitive.name == "scan")
        return [v.aval.shape for v in scan.outvars[: scan.params["num_carry"]]]

    shapes = carry_shapes(jax.vmap(TauKF(0.5, 0.1), in_axes=(None, None, 0)), model, prior, ys)
    assert (3, 3) in shapes and (4, 3, 3) not in shapes
    # a mask shared by all runs keeps the recursion shared; a per-run mask does not
    mask = np.ones((10, 2), bool)
    mask[3, 0] = False
    shapes = carry_shapes(jax.vmap(lambda y: TauKF(0.5, 0.1)(model, prior, y, observed=mask)), ys)
    assert (3, 3) in shapes and (4, 3, 3) not in shapes
    shapes = carry_shapes(jax.vmap(lambda y, o: TauKF(0.5, 0.1)(model, prior, y, observed=o)), ys, np.stack([mask] * 4))
    assert (4, 3, 3) in shapes


@st.composite
def _systems(draw):
    # One shape (n = 3, m = 2, T = 40) so that the jitted filter compiles once.
    seed = draw(st.integers(0, 2**31 - 1))
    radius = draw(st.floats(0.1, 1.05))
    q_rank = draw(st.integers(1, 3))
    scale = draw(st.sampled_from([1e-3, 1.0, 1e3]))
    tau = draw(st.sampled_from([0.0, 0.25, 0.5, 0.9, 1.0]))
    c = draw(st.floats(1e-6, 2.0))
    rng = np.random.default_rng(seed)
    G = rng.normal(size=(3, q_rank))
    Q = scale * (G @ G.T + 1e-6 * np.eye(3))  # possibly near-singular process noise
    return _random_stable(rng, 3, radius), rng.normal(size=(2, 3)), Q, _random_spd(rng, 2, 0.1), tau, c, seed


@hypothesis.settings(max_examples=20, deadline=None, derandomize=True)
@hypothesis.given(_systems())
def test_filtered_covariances_symmetric_psd(system):
    F, H, Q, R, tau, c, seed = system
    model = jdrkf.LinearModel(F, H, Q, R)
    prior = jdrkf.Gaussian(np.zeros(3), np.eye(3))
    ys = np.random.default_rng(seed).normal(size=(40, 2)) * 3
    res = _run_filter(TauKF(tau, c, throw=False, outputs="all"), model, prior, ys)
    assert res.result == jdrkf.RESULTS.successful
    covs = np.asarray(res.filtered_covariances)
    np.testing.assert_array_equal(covs, np.swapaxes(covs, -1, -2))
    assert np.min(np.linalg.eigvalsh(covs)) >= -1e-10 * np.max(np.abs(covs))
    theta = np.asarray(res.info["theta"])
    nominal = np.asarray(res.info["nominal_predicted_cov"])
    assert np.all(theta > 0)
    if tau < 1:
        assert np.all(theta * np.linalg.eigvalsh(nominal)[:, -1] * (1 - tau) < 1)
    gap = np.linalg.eigvalsh(np.asarray(res.predicted_covariances) - nominal)
    assert np.min(gap) >= -1e-10 * np.max(np.abs(nominal))


@pytest.mark.parametrize(
    "make, name",
    [
        (lambda: TauKF(1.5, 0.1), "tau"),
        (lambda: TauKF(-0.1, 0.1), "tau"),
        (lambda: TauKF(float("nan"), 0.1), "tau"),
        (lambda: TauKF(0.5, -1.0), "radius"),
        (lambda: TauKF(0.5, np.ones(2)), "radius"),
        (lambda: RiskSensitiveKF(-1.0), "theta"),
    ],
)
def test_bad_hyperparameters_raise(make, name):
    with pytest.raises(ValueError, match=f"^{name} "):
        make()


def test_hyperparameters_are_differentiable_leaves():
    filt = TauKF(0.5, 0.1)
    leaves = jax.tree_util.tree_leaves(eqx.filter(filt, eqx.is_inexact_array))
    assert len(leaves) == 2
    assert jax.tree_util.tree_leaves(eqx.filter(RiskSensitiveKF(0.1), eqx.is_inexact_array))[0] == 0.1
