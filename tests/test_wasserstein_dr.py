"""Jang, Hakobyan & Yang (2025): the time-varying Wasserstein DRKF and the
steady-state DRKF, against the cvxpy SDP (14), a NumPy DR Riccati recursion driven by
a certified Frank–Wolfe, the steady-state Kalman filter and finite differences."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jdrkf
from jdrkf.sets import Wasserstein

from sdp_oracles import bures_distance
from stationary_oracle import dr_riccati, stationary_sdp, step_fw


solve = eqx.filter_jit(lambda flt, model: flt.solve(model))
run = eqx.filter_jit(lambda flt, model, prior, ys, observed=None: flt(model, prior, ys, observed=observed))

# The 3-state system of the issue: SDP (14) gives 3.4271, the recursion 3.4154.
A3 = np.array([[0.7, 0.3, 0.0], [0.0, 0.8, 0.2], [0.1, 0.0, 0.6]])
C3 = np.array([[1.0, 0.0, 0.5], [0.0, 1.0, -1.0]])
W3 = np.diag([0.3, 0.2, 0.4])
V3 = np.array([[0.5, 0.1], [0.1, 0.4]])
# The paper's 2-D benchmark (Section 5.1.2).
A2 = np.array([[0.1, 1.0], [0.0, 1.2]])
C2 = np.array([[1.0, -1.0]])


def _model(a, c, w, v, **kw):
    return jdrkf.LinearModel(F=a, H=c, Q=w, R=v, **kw)


def _random_system(rng, n, m):
    a = rng.normal(size=(n, n))
    a = a / np.max(np.abs(np.linalg.eigvals(a))) * rng.uniform(0.5, 1.2)
    b = rng.normal(size=(n, n))
    c = rng.normal(size=(m, m))
    return a, rng.normal(size=(m, n)), b @ b.T / n + 0.1 * np.eye(n), c @ c.T / m + 0.2 * np.eye(m)


def test_issue_example_sdp_and_recursion_differ():
    model = _model(A3, C3, W3, V3)
    sol = solve(jdrkf.SteadyStateDRKF(0.5, 0.0), model)
    ref = stationary_sdp(A3, C3, W3, V3, 0.5, 0.0)
    assert bool(sol.converged)
    np.testing.assert_allclose(float(sol.value), ref["value"], rtol=1e-6)
    np.testing.assert_allclose(float(sol.value), 3.4271, atol=1e-4)
    rec = jdrkf.WassersteinDRKF(0.5, 0.0).covariance_recursion(model, W3, 60)
    ref_rec = dr_riccati(A3, C3, W3, V3, 0.5, 0.0, W3, 60)
    np.testing.assert_allclose(np.trace(rec.posterior_cov, axis1=1, axis2=2), ref_rec["traces"], rtol=1e-8)
    np.testing.assert_allclose(ref_rec["traces"][-1], 3.4154, atol=1e-4)
    # The optimum of (14) is not the limit of the recursion, and the SDP's Σ⁻* is not the
    # per-step maximiser for its own pseudo-nominal prior.
    assert float(sol.value) - ref_rec["traces"][-1] > 1e-2
    own = step_fw(np.asarray(sol.nominal_prior_cov), C3, V3, 0.5, 0.0)
    assert np.max(np.abs(own["prior_cov"] - np.asarray(sol.prior_cov))) > 1e-3


@pytest.mark.parametrize("seed", range(13))
def test_steady_state_matches_sdp(seed):
    rng = np.random.default_rng(seed)
    n, m = [(2, 1), (3, 2), (3, 1), (4, 2)][seed % 4]
    a, c, w, v = _random_system(rng, n, m)
    theta_x, theta_v = rng.uniform(0.0, 1.5, size=2)
    if seed % 3 == 0:
        theta_v = 0.0
    sol = solve(jdrkf.SteadyStateDRKF(theta_x, theta_v), _model(a, c, w, v))
    ref = stationary_sdp(a, c, w, v, theta_x, theta_v)
    assert bool(sol.converged)
    # Clarabel ends "optimal_inaccurate" on a few instances (seed 5): compare those loosely.
    np.testing.assert_allclose(float(sol.value), ref["value"], rtol=1e-6 if ref["accurate"] else 1e-4)
    # Feasibility of our solution for (13), checked with NumPy.
    nominal = a @ np.asarray(sol.posterior_cov) @ a.T + w
    assert bures_distance(np.asarray(sol.prior_cov), nominal) ** 2 <= theta_x**2 + 1e-9
    assert bures_distance(np.asarray(sol.noise_cov), v) ** 2 <= theta_v**2 + 1e-9
    k = np.asarray(sol.prior_cov) @ c.T @ np.linalg.inv(c @ np.asarray(sol.prior_cov) @ c.T + np.asarray(sol.noise_cov))
    np.testing.assert_allclose(np.asarray(sol.gain), k, rtol=1e-8, atol=1e-10)


def test_zero_radii_is_steady_state_kalman_filter():
    rng = np.random.default_rng(3)
    model = _model(*_random_system(rng, 3, 2))
    sol = solve(jdrkf.SteadyStateDRKF(0.0, 0.0), model)
    kf = jdrkf.SteadyStateKalmanFilter.solve(model)
    np.testing.assert_allclose(sol.gain, kf.gain, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(sol.prior_cov, kf.predicted_cov, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(sol.posterior_cov, kf.filtered_cov, rtol=1e-10, atol=1e-12)


def test_recursion_limit_vs_sdp_under_corollary_1():
    # θv = 0, θx = θ_max: the recursion converges (Theorem 2), and its limit is within
    # a few 1e-6 of the SDP optimum — but not equal to it, although Corollary 1 says so.
    model = _model(A2, C2, np.eye(2), np.eye(1))
    theta = float(jdrkf.theta_max(A2, C2, np.eye(2), np.eye(1), N=8, q=20).theta_max)
    rec = jdrkf.WassersteinDRKF(theta, 0.0).covariance_recursion(model, np.eye(2), 40)
    traces = np.trace(np.asarray(rec.posterior_cov), axis1=1, axis2=2)
    assert abs(traces[-1] - traces[-2]) <= 1e-10 * traces[-1]
    sol = solve(jdrkf.SteadyStateDRKF(theta, 0.0), model)
    ref = stationary_sdp(A2, C2, np.eye(2), np.eye(1), theta, 0.0)
    np.testing.assert_allclose(float(sol.value), ref["value"], rtol=1e-6)
    gap = (float(sol.value) - traces[-1]) / float(sol.value)
    assert 1e-7 < gap < 1e-5


@pytest.mark.parametrize("theta_x,theta_v", [(0.3, 0.0), (0.4, 0.2)])
def test_time_varying_filter_converges_to_recursion_fixed_point(theta_x, theta_v, getkey):
    # The filter on data (with nominal means) has the data-independent covariance recursion;
    # its last posterior covariance is the fixed point of the NumPy recursion.
    model = _model(A3, C3, W3, V3, process_mean=[0.1, 0.0, -0.2], noise_mean=[0.3, -0.1])
    traj = jdrkf.simulate(getkey(), model, jdrkf.Gaussian(jnp.zeros(3), jnp.eye(3)), 60, 1)
    res = run(jdrkf.WassersteinDRKF(theta_x, theta_v), model, jdrkf.Gaussian(jnp.zeros(3), jnp.eye(3)), traj.observations[0])
    ref = dr_riccati(A3, C3, W3, V3, theta_x, theta_v, A3 @ A3.T + W3, 60)
    # The NumPy worst case is certified in value to 1e-14, hence in its matrices to ~1e-7.
    np.testing.assert_allclose(res.filtered_covariances[-1], ref["posterior_cov"], rtol=1e-6, atol=1e-7)
    assert abs(ref["traces"][-1] - ref["traces"][-2]) < 1e-9 * ref["traces"][-1]


def test_time_varying_filter_means_vs_numpy(getkey):
    # Theorem 1 with non-zero nominal means (eqs. 7, 10), against a NumPy loop whose worst
    # case comes from the certified Frank–Wolfe.
    model = _model(A3, C3, W3, V3, process_mean=[0.1, 0.0, -0.2], noise_mean=[0.3, -0.1])
    prior = jdrkf.Gaussian(jnp.array([1.0, -1.0, 0.5]), jnp.eye(3))
    ys = np.asarray(jdrkf.simulate(getkey(), model, prior, 15, 1).observations[0])
    res = run(jdrkf.WassersteinDRKF(0.4, 0.2, outputs="all"), model, prior, ys)
    mean, cov = np.array([1.0, -1.0, 0.5]), np.eye(3)
    for k in range(15):
        mean = A3 @ mean + np.array([0.1, 0.0, -0.2])
        step = step_fw(A3 @ cov @ A3.T + W3, C3, V3, 0.4, 0.2)
        mean = mean + step["gain"] @ (ys[k] - C3 @ mean - np.array([0.3, -0.1]))
        cov = step["posterior_cov"]
        np.testing.assert_allclose(res.filtered_means[k], mean, rtol=1e-6, atol=1e-7)
        np.testing.assert_allclose(res.predicted_covariances[k], step["prior_cov"], rtol=1e-6, atol=1e-7)
    same = run(jdrkf.DRKF(state_set=Wasserstein(0.4), noise_set=Wasserstein(0.2)), model, prior, ys)
    np.testing.assert_allclose(res.filtered_means, same.filtered_means, rtol=0, atol=0)


def test_steady_state_filter_is_constant_gain(getkey):
    model = _model(A3, C3, W3, V3, process_mean=[0.1, 0.0, -0.2], noise_mean=[0.3, -0.1])
    prior = jdrkf.Gaussian(jnp.array([1.0, -1.0, 0.5]), jnp.eye(3))
    ys = np.array(jdrkf.simulate(getkey(), model, prior, 20, 1).observations[0])
    ys[4, 1] = np.nan
    flt = jdrkf.SteadyStateDRKF(0.5, 0.2, outputs="all")
    res = run(flt, model, prior, ys, ~np.isnan(ys))
    sol = solve(flt, model)
    gain = np.asarray(sol.gain)
    mean = np.array([1.0, -1.0, 0.5])
    for k in range(20):
        mean = A3 @ mean + np.array([0.1, 0.0, -0.2])
        innov = np.nan_to_num(ys[k] - C3 @ mean - np.array([0.3, -0.1]))
        mean = mean + gain @ innov
        np.testing.assert_allclose(res.filtered_means[k], mean, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(res.predicted_covariances[0], sol.prior_cov)
    np.testing.assert_allclose(res.filtered_covariances[-1], sol.posterior_cov)
    assert bool(jnp.all(jnp.isfinite(res.loglik_increments)))
    assert res.result == jdrkf.RESULTS.successful


def test_value_monotone_in_radii():
    model = _model(A3, C3, W3, V3)
    values = [float(solve(jdrkf.SteadyStateDRKF(t, 0.5 * t), model).value) for t in (0.0, 0.2, 0.5, 1.0, 2.0)]
    assert all(b > a for a, b in zip(values, values[1:], strict=False))


@pytest.mark.slow  # DRKF(Wasserstein, Wasserstein) = WassersteinDRKF is tested, and its θx, θv gradients are in test_tuning
@pytest.mark.parametrize("which", ["radius_x", "radius_v"])
def test_gradients_vs_finite_differences(which):
    model = _model(A3, C3, W3, V3)

    def value(theta):
        kw = {"radius_x": 0.5, "radius_v": 0.3, which: theta}
        sol = jdrkf.SteadyStateDRKF(**kw).solve(model)
        return sol.value, sol.gain[0, 0]

    theta, h = 0.4, 1e-5
    grads = jax.jacfwd(lambda t: jnp.stack(value(t)))(jnp.asarray(theta))
    rev = jax.grad(lambda t: value(t)[0])(jnp.asarray(theta))
    fd = (np.array(jax.jit(value)(theta + h)) - np.array(jax.jit(value)(theta - h))) / (2 * h)
    np.testing.assert_allclose(grads, fd, rtol=1e-6, atol=1e-9)
    np.testing.assert_allclose(rev, grads[0], rtol=1e-10)


def test_bad_input():
    with pytest.raises(ValueError, match="radius_x"):
        jdrkf.SteadyStateDRKF(-0.1, 0.0)
    with pytest.raises(ValueError, match="radius_v"):
        jdrkf.WassersteinDRKF(0.1, float("nan"))
    tv = jdrkf.LinearModel(F=np.stack([A3] * 4), H=C3, Q=W3, R=V3)
    with pytest.raises(ValueError, match="time-invariant"):
        jdrkf.SteadyStateDRKF(0.1, 0.1).solve(tv)
    with pytest.raises(ValueError, match="nominal_prior_cov"):
        jdrkf.WassersteinDRKF(0.1, 0.1).covariance_recursion(_model(A3, C3, W3, V3), np.eye(2), 3)


def test_drkf_positional_sets_as_documented():
    flt = jdrkf.DRKF(Wasserstein(0.4), Wasserstein(0.2))
    assert isinstance(flt.state_set, Wasserstein) and flt.throw is True


# EM nominals of Jang, Hakobyan & Yang's LQR study (5 outputs; eigenvalues lifted to 1e-4): the optimality
# system also has a root with an indefinite adjoint Λ and a lower value (an unstable gain);
# the solver must stay on the branch of the convex problem's KKT point.
Q_EM = [[0.0007789979017225235, -0.001767063591106396, 3.308166160106838e-05, 0.0002085791437367776],
        [-0.001767063591106396, 0.0070733447052783276, -0.0001718648209080409, -0.0006557940825710237],
        [3.308166160106838e-05, -0.0001718648209080409, 0.00010485834570302319, 1.6686792182533556e-05],
        [0.0002085791437367776, -0.0006557940825710237, 1.6686792182533556e-05, 0.00020965854526602552]]
R_EM = [[0.010489965641882659, -0.0007295540456303367], [-0.0007295540456303367, 0.00015122722478985484]]


def test_ill_conditioned_em_nominal_stays_on_the_convex_branch():
    a = np.array([[1, 0.2, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0.2], [0, 0, 0, 1]], float)
    c = np.array([[1.0, 0, 0, 0], [0, 0, 1.0, 0]])
    q, r = np.array(Q_EM), np.array(R_EM)
    sol = solve(jdrkf.SteadyStateDRKF(0.2, 0.2), _model(a, c, q, r))
    ref = stationary_sdp(a, c, q, r, 0.2, 0.2)
    assert bool(sol.converged)
    np.testing.assert_allclose(float(sol.value), ref["value"], rtol=1e-6)
    assert np.min(np.linalg.eigvalsh(np.asarray(sol.adjoint))) > 0
    assert np.max(np.abs(np.linalg.eigvals(a @ (np.eye(4) - np.asarray(sol.gain) @ c)))) < 1


@pytest.mark.slow  # ~20 s (compiles jit x vmap x grad); gradients are also checked by test_gradients_vs_finite_differences
def test_time_varying_filter_jit_vmap_grad(getkey):
    # vmap over runs (n = 3: unrolled solves, no batched LAPACK) equals single runs, and the
    # gradient of the mean filtered trace in θx matches central finite differences.
    model = _model(A3, C3, W3, V3)
    prior = jdrkf.Gaussian(jnp.zeros(3), jnp.eye(3))
    ys = jdrkf.simulate(getkey(), model, prior, 8, 3).observations
    flt = jdrkf.WassersteinDRKF(0.3, 0.1)
    batch = jax.vmap(lambda y: run(flt, model, prior, y).filtered_means)(ys)
    np.testing.assert_allclose(batch[1], run(flt, model, prior, ys[1]).filtered_means, rtol=1e-10, atol=1e-12)

    def loss(theta):
        res = jdrkf.WassersteinDRKF(theta, 0.1)(model, prior, ys[0])
        return jnp.mean(jnp.trace(res.filtered_covariances, axis1=1, axis2=2))

    g = jax.jit(jax.grad(loss))(0.3)
    fd = (jax.jit(loss)(0.3 + 1e-5) - jax.jit(loss)(0.3 - 1e-5)) / 2e-5
    np.testing.assert_allclose(g, fd, rtol=1e-5)


def test_steady_state_worst_case_function_matches_the_sdp_and_checks_its_arguments():
    """`jdrkf.sets.steady_state_worst_case` is the solver behind `SteadyStateDRKF.solve`:
    the Clarabel SDP of (14) gives its value; bad radii and counts raise, naming them."""
    sol = jdrkf.sets.steady_state_worst_case(A3, C3, W3, V3, radius_x=0.5, radius_v=0.2)
    ref = stationary_sdp(A3, C3, W3, V3, 0.5, 0.2)
    assert bool(sol.converged)
    np.testing.assert_allclose(float(sol.value), ref["value"], rtol=1e-6)
    same = solve(jdrkf.SteadyStateDRKF(0.5, 0.2), _model(A3, C3, W3, V3))
    np.testing.assert_allclose(np.asarray(sol.gain), np.asarray(same.gain), rtol=0, atol=1e-12)
    with pytest.raises(ValueError, match="radius_x"):
        jdrkf.sets.steady_state_worst_case(A3, C3, W3, V3, -0.1, 0.2)
    with pytest.raises(ValueError, match="max_iter"):
        jdrkf.sets.steady_state_worst_case(A3, C3, W3, V3, 0.5, 0.2, max_iter=0)
