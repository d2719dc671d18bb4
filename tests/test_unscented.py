"""`UnscentedKF` and `EnsembleKF` (the Gaussian-approximation filters of Wang 2022).

Oracles: filterpy's `UnscentedKalmanFilter` + `MerweScaledSigmaPoints`; a NumPy
re-implementation of the authors' `UKF.m` (Simon 2006, eqs. (14.57)–(14.67)); the
NumPy Kalman filter of `tests/oracles.py`; a NumPy closed form of the
no-redraw recursion on linear models; statistical tolerances for the EnKF.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg
from filterpy.kalman import MerweScaledSigmaPoints, UnscentedKalmanFilter

import jdrkf
from jdrkf._nonlinear import NonlinearModel, _simulate_nonlinear
from jdrkf.experiments.wang_nonlinear import growth_f, growth_h
from jdrkf.filters._unscented import EnsembleKF, UnscentedKF, merwe_weights, sigma_points

from oracles import numpy_kalman_filter


run = eqx.filter_jit(lambda flt, model, prior, ys, observed=None: flt(model, prior, ys, observed=observed))
run_key = eqx.filter_jit(lambda flt, model, prior, ys, key: flt(model, prior, ys, key))


# --------------------------------------------------------------------------- models


def np_growth_f(x, t):
    return x / 2 + 25 * x / (1 + x**2) + 8 * np.cos(1.2 * (t + 1))


GROWTH = NonlinearModel(growth_f, growth_h, 10.0 * jnp.eye(1), jnp.eye(1))
GROWTH_PRIOR = jdrkf.Gaussian(jnp.zeros(1), jnp.eye(1))

# Wang (2022), Section V-B: CV target, range/bearing from a sensor moving along +y.
DT = 0.5
F_CV = np.kron(np.eye(2), np.array([[1.0, DT], [0.0, 1.0]]))
G_CV = np.kron(np.eye(2), np.array([[DT**2 / 2], [DT]]))
Q_CV = G_CV @ np.diag([5.0, 5.0]) @ G_CV.T
R_RB = np.diag([1.0, 0.001])


def rb_h(x, t):
    sy = DT * (t + 1).astype(x.dtype)
    dx, dy = x[0], x[2] - sy
    return jnp.stack([jnp.sqrt(dx**2 + dy**2), jnp.arctan(dy / dx)])


def np_rb_h(x, t):
    sy = DT * (t + 1)
    dx, dy = x[0], x[2] - sy
    return np.array([np.sqrt(dx**2 + dy**2), np.arctan(dy / dx)])


TRACK = NonlinearModel(lambda x, t: jnp.asarray(F_CV) @ x, rb_h, Q_CV, R_RB)
TRACK_PRIOR = jdrkf.Gaussian(jnp.array([5.0, 0.0, 5.0, 0.0]), 0.1 * jnp.eye(4))


def _data(model, prior, T=50, runs=1, seed=0):
    return _simulate_nonlinear(jax.random.key(seed), model, prior, T, runs)


# --------------------------------------------------------------------------- oracles


def filterpy_ukf(f, h, Q, R, m0, P0, ys, alpha, beta, kappa):
    n, m = len(m0), ys.shape[1]
    pts = MerweScaledSigmaPoints(n, alpha, beta, kappa)
    ukf = UnscentedKalmanFilter(n, m, 1.0, lambda x, t: h(x, t), lambda x, dt, t: f(x, t), pts)
    ukf.x, ukf.P, ukf.Q, ukf.R = np.array(m0, float), np.array(P0, float), np.array(Q), np.array(R)
    means, covs, pmeans, lls = [], [], [], []
    for t, y in enumerate(ys):
        ukf.predict(t=t)
        pmeans.append(ukf.x.copy())
        ukf.update(y, t=t)
        means.append(ukf.x.copy())
        covs.append(ukf.P.copy())
        lls.append(ukf.log_likelihood)
    return np.array(means), np.array(covs), np.array(pmeans), np.array(lls)


def authors_ukf(f, h, Q, R, m0, P0, ys):
    """NumPy transcription of the authors' `UKF.m` (2n points, rows of the upper
    Cholesky factor of nP, no redraw for the measurement update)."""
    n = len(m0)
    mu, P = np.array(m0, float), np.array(P0, float)
    means, covs = [], []
    for t, y in enumerate(ys):
        U = scipy.linalg.cholesky(n * P, lower=False)
        z = np.concatenate([mu + U, mu - U])  # rows: mu ± U[i, :]
        x = np.array([f(zi, t) for zi in z])
        mu_x = x.mean(axis=0)
        P_xx = (x - mu_x).T @ (x - mu_x) / (2 * n) + Q
        yh = np.array([h(xi, t) for xi in x])
        mu_y = yh.mean(axis=0)
        P_yy = (yh - mu_y).T @ (yh - mu_y) / (2 * n) + R
        P_xy = (x - mu_x).T @ (yh - mu_y) / (2 * n)
        K = P_xy @ np.linalg.inv(P_yy)
        mu = mu_x + K @ (y - mu_y)
        P = P_xx - K @ P_yy @ K.T
        means.append(mu)
        covs.append(P)
    return np.array(means), np.array(covs)


def no_redraw_linear(F, H, Q, R, m0, P0, ys):
    """Closed-form limit of the reuse-the-propagated-points filters on a linear model:
    `P_yy = H F P Fᵀ Hᵀ + R`, `P_xy = F P Fᵀ Hᵀ`, `P⁻ = F P Fᵀ + Q`."""
    m, P = np.array(m0, float), np.array(P0, float)
    means, covs = [], []
    for y in ys:
        FPF = F @ P @ F.T
        P_yy = H @ FPF @ H.T + R
        K = FPF @ H.T @ np.linalg.inv(P_yy)
        m = F @ m + K @ (y - H @ F @ m)
        P = FPF + Q - K @ P_yy @ K.T
        means.append(m)
        covs.append(P)
    return np.array(means), np.array(covs)


# --------------------------------------------------------------------------- sigma points


@pytest.mark.parametrize("alpha, beta, kappa", [(1.0, 2.0, 0.0), (1e-3, 2.0, 0.0), (0.5, 2.0, 3.0 - 3), (0.3, 0.0, 1.0)])
def test_merwe_weights_vs_filterpy(alpha, beta, kappa):
    for d in (1, 3):
        wm, wc = merwe_weights(d, alpha, beta, kappa, jnp.float64)
        pts = MerweScaledSigmaPoints(d, alpha, beta, kappa)
        np.testing.assert_allclose(wm, pts.Wm, rtol=1e-12)
        np.testing.assert_allclose(wc, pts.Wc, rtol=1e-12)
        np.testing.assert_allclose(np.sum(wm), 1.0, rtol=1e-9)


def test_sigma_points_vs_filterpy_and_moments(rng):
    a = rng.normal(size=(3, 3))
    P, m = a @ a.T + 0.5 * np.eye(3), rng.normal(size=3)
    pts, wm, wc, ok = sigma_points(jnp.asarray(m), jnp.asarray(P), "merwe", 0.5, 2.0, 1.0)
    assert bool(ok)
    np.testing.assert_allclose(pts, MerweScaledSigmaPoints(3, 0.5, 2.0, 1.0).sigma_points(m, P), rtol=1e-12)
    for kind in ("merwe", "simon"):
        pts, wm, wc, ok = sigma_points(jnp.asarray(m), jnp.asarray(P), kind, 1.0, 0.0, 0.0)
        pts, wm, wc = np.asarray(pts), np.asarray(wm), np.asarray(wc)
        assert pts.shape[0] == (7 if kind == "merwe" else 6)
        np.testing.assert_allclose(wm.sum(), 1.0, rtol=1e-14)
        np.testing.assert_allclose(wm @ pts, m, rtol=1e-12, atol=1e-12)
        dev = pts - m
        np.testing.assert_allclose((dev * wc[:, None]).T @ dev, P, rtol=1e-12)
    _, _, _, ok = sigma_points(jnp.asarray(m), -jnp.asarray(P), "simon")
    assert not bool(ok)


# --------------------------------------------------------------------------- vs filterpy


@pytest.mark.parametrize("alpha, beta, kappa", [(1.0, 2.0, 0.0), (0.5, 2.0, 1.0), (0.1, 2.0, 0.0)])
def test_matches_filterpy_growth_model(alpha, beta, kappa):
    ys = _data(GROWTH, GROWTH_PRIOR).observations[0]
    res = run(UnscentedKF(alpha, beta, kappa, outputs="all"), GROWTH, GROWTH_PRIOR, ys)
    f = lambda x, t: np_growth_f(x, t)  # noqa: E731
    means, covs, pmeans, lls = filterpy_ukf(f, lambda x, t: x**2 / 20, 10.0 * np.eye(1), np.eye(1), [0.0], np.eye(1), np.asarray(ys), alpha, beta, kappa)
    np.testing.assert_allclose(res.filtered_means, means, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(res.filtered_covariances, covs, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(res.predicted_means, pmeans, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(res.loglik_increments, lls, rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("alpha, beta, kappa", [(1.0, 2.0, 0.0), (1e-3, 2.0, 0.0), (0.5, 2.0, -1.0)])
def test_matches_filterpy_range_bearing(alpha, beta, kappa):
    ys = _data(TRACK, TRACK_PRIOR).observations[0]
    res = run(UnscentedKF(alpha, beta, kappa, outputs="all"), TRACK, TRACK_PRIOR, ys)
    means, covs, _, lls = filterpy_ukf(
        lambda x, t: F_CV @ x, np_rb_h, Q_CV, R_RB, [5.0, 0.0, 5.0, 0.0], 0.1 * np.eye(4), np.asarray(ys), alpha, beta, kappa
    )
    scale = np.max(np.abs(means))
    np.testing.assert_allclose(res.filtered_means, means, rtol=1e-9, atol=1e-9 * scale)
    np.testing.assert_allclose(res.filtered_covariances, covs, rtol=1e-7, atol=1e-9 * np.max(np.abs(covs)))
    # α = 1e-3: weights ~1e6 of both signs cancel; the two codes agree to ~1e-7 there.
    ll_tol = 1e-9 if alpha >= 0.1 else 1e-6
    np.testing.assert_allclose(res.loglik_increments, lls, rtol=ll_tol, atol=ll_tol)


def test_simon_variant_matches_authors_code():
    ys = _data(TRACK, TRACK_PRIOR, seed=1).observations[0]
    res = run(UnscentedKF(sigma_points="simon", redraw=False), TRACK, TRACK_PRIOR, ys)
    means, covs = authors_ukf(lambda x, t: F_CV @ x, np_rb_h, Q_CV, R_RB, np.array([5.0, 0.0, 5.0, 0.0]), 0.1 * np.eye(4), np.asarray(ys))
    np.testing.assert_allclose(res.filtered_means, means, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(res.filtered_covariances, covs, rtol=1e-8, atol=1e-10)
    ys = _data(GROWTH, GROWTH_PRIOR, seed=1).observations[0]
    res = run(UnscentedKF(sigma_points="simon", redraw=False), GROWTH, GROWTH_PRIOR, ys)
    means, covs = authors_ukf(np_growth_f, lambda x, t: x**2 / 20, 10.0 * np.eye(1), np.eye(1), np.zeros(1), np.eye(1), np.asarray(ys))
    np.testing.assert_allclose(res.filtered_means, means, rtol=1e-9, atol=1e-9)


# --------------------------------------------------------------------------- linear models


F2 = np.array([[0.9, 0.2], [-0.1, 0.8]])
H2 = np.array([[1.0, 0.5], [0.0, 1.0], [0.3, -0.2]])
Q2 = np.array([[0.5, 0.1], [0.1, 0.3]])
R2 = np.diag([0.2, 0.4, 0.3])
LIN = NonlinearModel(lambda x, t: jnp.asarray(F2) @ x, lambda x, t: jnp.asarray(H2) @ x, Q2, R2)
# The same system in the general form, with w of dimension 3 through G (q = 3 ≠ n).
G3 = np.array([[1.0, 0.0, 0.5], [0.0, 1.0, -0.3]])
Q3 = np.diag([0.4, 0.2, 0.3])
LIN_GEN = NonlinearModel(
    lambda x, w, t: jnp.asarray(F2) @ x + jnp.asarray(G3) @ w,
    lambda x, v, t: jnp.asarray(H2) @ x + v,
    Q3,
    R2,
    additive=False,
    state_dim=2,
    obs_dim=3,
)
LIN_PRIOR = jdrkf.Gaussian(jnp.array([1.0, -1.0]), jnp.array([[1.0, 0.2], [0.2, 0.5]]))


def _lin_data(T=30, runs=1):
    return _simulate_nonlinear(jax.random.key(5), LIN, LIN_PRIOR, T, runs).observations


@pytest.mark.parametrize(
    "flt",
    [
        UnscentedKF(outputs="all"),
        UnscentedKF(1e-3, 2.0, 0.0, outputs="all"),
        UnscentedKF(0.5, 0.0, 0.0, outputs="all"),  # λ < 0, n + λ > 0
        UnscentedKF(1.0, 2.0, 3.0 - 2, outputs="all"),
        UnscentedKF(sigma_points="simon", outputs="all"),
    ],
)
def test_linear_model_equals_kalman_filter(flt):
    ys = np.array(_lin_data()[0])
    ys[3, 1] = np.nan  # a missing component
    ys[7] = np.nan  # a missing step
    ref = numpy_kalman_filter(LIN_PRIOR.mean, LIN_PRIOR.cov, ys, F2, H2, Q2, R2)
    res = run(flt, LIN, LIN_PRIOR, jnp.asarray(ys), jnp.asarray(~np.isnan(ys)))
    for name in ("filtered_means", "filtered_covariances", "predicted_means", "predicted_covariances", "loglik_increments"):
        np.testing.assert_allclose(getattr(res, name), ref[name], rtol=1e-7, atol=1e-8, err_msg=name)


@pytest.mark.parametrize("redraw", [True, False])
@pytest.mark.parametrize("kind", ["merwe", "simon"])
def test_augmented_linear_model_equals_kalman_filter(redraw, kind):
    ys = _lin_data()[0]
    ref = numpy_kalman_filter(LIN_PRIOR.mean, LIN_PRIOR.cov, np.asarray(ys), F2, H2, Q3, R2, G=G3)
    res = run(UnscentedKF(sigma_points=kind, redraw=redraw, outputs="all"), LIN_GEN, LIN_PRIOR, ys)
    for name in ("filtered_means", "filtered_covariances", "loglik_increments"):
        np.testing.assert_allclose(getattr(res, name), ref[name], rtol=1e-7, atol=1e-8, err_msg=name)


def test_no_redraw_linear_closed_form():
    ys = _lin_data()[0]
    means, covs = no_redraw_linear(F2, H2, Q2, R2, LIN_PRIOR.mean, LIN_PRIOR.cov, np.asarray(ys))
    for flt in (UnscentedKF(redraw=False), UnscentedKF(sigma_points="simon", redraw=False)):
        res = run(flt, LIN, LIN_PRIOR, ys)
        np.testing.assert_allclose(res.filtered_means, means, rtol=1e-9, atol=1e-10)
        np.testing.assert_allclose(res.filtered_covariances, covs, rtol=1e-9, atol=1e-10)


# --------------------------------------------------------------------------- EnKF


@pytest.mark.slow
def test_enkf_large_ensemble_tends_to_its_limits():
    """N = 4000: errors O(sqrt(P / N)) ≈ 2e-2 per step; tolerance 0.1 absolute
    on O(1) quantities (means of a stable system, covariances ≤ 1)."""
    ys = _lin_data(T=10)[0]
    kf = numpy_kalman_filter(LIN_PRIOR.mean, LIN_PRIOR.cov, np.asarray(ys), F2, H2, Q2, R2)
    nr_means, nr_covs = no_redraw_linear(F2, H2, Q2, R2, LIN_PRIOR.mean, LIN_PRIOR.cov, np.asarray(ys))
    for flt, means, covs in (
        (EnsembleKF(4000, redraw=True), kf["filtered_means"], kf["filtered_covariances"]),
        (EnsembleKF(4000), nr_means, nr_covs),
    ):
        res = run_key(flt, LIN, LIN_PRIOR, ys, jax.random.key(11))
        np.testing.assert_allclose(res.filtered_means, means, atol=0.1)
        np.testing.assert_allclose(res.filtered_covariances, covs, atol=0.05)
    # The two limits differ by more than the tolerance (the test can tell them apart).
    assert np.max(np.abs(kf["filtered_covariances"] - nr_covs)) > 0.05
    # General-noise form (augmented samples): tends to the Kalman filter.
    kf3 = numpy_kalman_filter(LIN_PRIOR.mean, LIN_PRIOR.cov, np.asarray(ys), F2, H2, Q3, R2, G=G3)
    res = run_key(EnsembleKF(4000), LIN_GEN, LIN_PRIOR, ys, jax.random.key(12))
    np.testing.assert_allclose(res.filtered_means, kf3["filtered_means"], atol=0.1)
    np.testing.assert_allclose(res.filtered_covariances, kf3["filtered_covariances"], atol=0.05)


# --------------------------------------------------------------------------- batching, results, errors


def test_jit_vmap_over_runs():
    traj = _data(TRACK, TRACK_PRIOR, T=20, runs=3, seed=2)
    ys = traj.observations
    flt = UnscentedKF(sigma_points="simon", redraw=False)
    batch = eqx.filter_jit(lambda f, m, p, y: jax.vmap(f, in_axes=(None, None, 0))(m, p, y))(flt, TRACK, TRACK_PRIOR, ys)
    for r in range(3):
        means, _ = authors_ukf(lambda x, t: F_CV @ x, np_rb_h, Q_CV, R_RB, np.array([5.0, 0.0, 5.0, 0.0]), 0.1 * np.eye(4), np.asarray(ys[r]))
        np.testing.assert_allclose(batch.filtered_means[r], means, rtol=1e-9, atol=1e-9)
    enkf = EnsembleKF(50, throw=False)
    keys = jax.random.split(jax.random.key(0), 3)
    eb = eqx.filter_jit(lambda f, m, p, y, k: jax.vmap(f, in_axes=(None, None, 0, 0))(m, p, y, k))(enkf, TRACK, TRACK_PRIOR, ys, keys)
    one = run_key(enkf, TRACK, TRACK_PRIOR, ys[1], keys[1])
    np.testing.assert_allclose(eb.filtered_means[1], one.filtered_means, rtol=1e-9, atol=1e-9)
    assert np.all(np.asarray(eb.result == jdrkf.RESULTS.successful))


def test_result_codes():
    ys = jnp.ones((3, 1))
    flat = NonlinearModel(lambda x, t: x, lambda x, t: jnp.zeros(1, x.dtype), np.eye(1), np.zeros((1, 1)))
    res = run(UnscentedKF(throw=False), flat, GROWTH_PRIOR, ys)
    assert res.result == jdrkf.RESULTS.nonpositive_innovation
    with pytest.raises(Exception, match="innovation"):
        run(UnscentedKF(), flat, GROWTH_PRIOR, ys)
    singular = jdrkf.Gaussian(jnp.zeros(2), jnp.zeros((2, 2)))
    res = run(UnscentedKF(throw=False), LIN_GEN, singular, jnp.ones((3, 3)))
    assert res.result == jdrkf.RESULTS.nonfinite_state


def test_errors():
    ys = jnp.ones((3, 1))
    lin = jdrkf.LinearModel(np.eye(1), np.eye(1), np.eye(1), np.eye(1))
    with pytest.raises(ValueError, match="model must be a jdrkf.NonlinearModel"):
        UnscentedKF()(lin, GROWTH_PRIOR, ys)
    with pytest.raises(ValueError, match="sigma_points must be one of"):
        UnscentedKF(sigma_points="julier")
    with pytest.raises(ValueError, match="alpha must be positive"):
        UnscentedKF(0.0)
    with pytest.raises(ValueError, match="need κ > −1"):
        UnscentedKF(1.0, 2.0, -1.0)(GROWTH, GROWTH_PRIOR, ys)
    with pytest.raises(ValueError, match="num_samples must be an int >= 2"):
        EnsembleKF(1)
    with pytest.raises(ValueError, match="EnsembleKF is stochastic: pass a PRNG key"):
        EnsembleKF(10)(GROWTH, GROWTH_PRIOR, ys)
    with pytest.raises(ValueError, match="takes no controls"):
        UnscentedKF()(GROWTH, GROWTH_PRIOR, ys, inputs=jnp.ones((3, 1)))
    with pytest.raises(ValueError, match=r"ys has shape \(3, 2\)"):
        UnscentedKF()(GROWTH, GROWTH_PRIOR, jnp.ones((3, 2)))


# --------------------------------------------------------------------------- gradients


def _central_fd(fn, x, h=1e-5):
    return np.array([(fn(x + h * e) - fn(x - h * e)) / (2 * h) for e in np.eye(len(x))])


@pytest.mark.parametrize("kind", ["ukf", "enkf"])
def test_grad_of_mse_wrt_noise_scales_matches_finite_differences(kind):
    """d MSE / d (Q-scale, R-scale) through the whole filter: the UKF is a smooth
    function of the model; the EnKF is too for a fixed key (reparametrized draws)."""
    traj = _data(GROWTH, GROWTH_PRIOR, T=15, runs=1, seed=4)
    ys, xs = traj.observations[0], traj.states[0]
    flt = UnscentedKF() if kind == "ukf" else EnsembleKF(40)
    key = jax.random.key(7)

    @jax.jit
    def mse(s):
        model = NonlinearModel(growth_f, growth_h, s[0] * GROWTH.Q, s[1] * GROWTH.R)
        res = flt(model, GROWTH_PRIOR, ys, key)
        return jnp.mean((res.filtered_means - xs) ** 2)

    s0 = jnp.array([1.3, 0.8])
    grad = jax.jit(jax.grad(mse))(s0)
    fd = _central_fd(lambda s: float(mse(s)), np.asarray(s0))
    assert np.all(np.abs(fd) > 1e-4)  # both scales matter
    np.testing.assert_allclose(grad, fd, rtol=1e-6)
