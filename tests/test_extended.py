"""`ExtendedKF`: the extended, iterated extended and DR-by-linearisation Kalman filters.

Oracles: filterpy's `ExtendedKalmanFilter` with hand-derived Jacobians; a NumPy (iterated)
EKF with hand-derived Jacobians (non-additive noise, missing data); the first-order
optimality condition of the MAP problem that the iterated EKF solves by Gauss–Newton;
`KalmanFilter` / `DRKF` / `WassersteinKF` on the equivalent `LinearModel`; central finite
differences for gradients.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from filterpy.kalman import ExtendedKalmanFilter
from scipy.stats import multivariate_normal

import jdrkf
from jdrkf.filters._base import with_outputs
from jdrkf.sets import KL, EpsContamination, Moment, Wasserstein

run = eqx.filter_jit(lambda flt, model, prior, ys, observed=None: flt(model, prior, ys, observed=observed))
TOL = {"rtol": 1e-10, "atol": 1e-10}

# --------------------------------------------------------------------------- models

# Target with quadratic drag, range and bearing from the origin (additive noise).
DT, DRAG = 0.1, 0.05


def drag_f(x, t):
    v = x[2:]
    return jnp.concatenate([x[:2] + DT * v, v - DT * DRAG * jnp.sqrt(v @ v) * v])


def rb_h(x, t):
    return jnp.stack([jnp.sqrt(x[0] ** 2 + x[1] ** 2), jnp.arctan2(x[1], x[0])])


def np_drag_f(x):
    v = x[2:]
    return np.concatenate([x[:2] + DT * v, v - DT * DRAG * np.linalg.norm(v) * v])


def np_drag_F(x):
    v = x[2:]
    s = np.linalg.norm(v)
    F = np.eye(4)
    F[:2, 2:] = DT * np.eye(2)
    F[2:, 2:] = np.eye(2) - DT * DRAG * (s * np.eye(2) + np.outer(v, v) / s)
    return F


def np_rb_h(x):
    return np.array([np.hypot(x[0], x[1]), np.arctan2(x[1], x[0])])


def np_rb_H(x):
    r2 = x[0] ** 2 + x[1] ** 2
    r = np.sqrt(r2)
    return np.array([[x[0] / r, x[1] / r, 0.0, 0.0], [-x[1] / r2, x[0] / r2, 0.0, 0.0]])


Q_RB = np.diag([1e-3, 1e-3, 1e-2, 1e-2])
R_RB = np.diag([0.1**2, 0.01**2])
RB = jdrkf.NonlinearModel(drag_f, rb_h, Q_RB, R_RB)
RB_PRIOR = jdrkf.Gaussian(jnp.array([10.0, 5.0, 1.0, 0.5]), jnp.diag(jnp.array([1.0, 1.0, 0.1, 0.1])))


# Pendulum with a multiplicative process noise and non-additive measurement noise, noise means nonzero.
MU_W, MU_V = np.array([0.1]), np.array([0.05, -0.02])


def pend_f(x, w, t):
    return jnp.stack([x[0] + DT * x[1], x[1] - DT * jnp.sin(x[0]) + DT * w[0] * (1.0 + 0.5 * x[1] ** 2)])


def pend_h(x, v, t):
    return jnp.stack([x[0] * jnp.exp(v[0]), jnp.cos(x[0]) + x[1] + v[1] * jnp.sqrt(1.0 + x[0] ** 2)])


def np_pend(x, mu_w, mu_v):
    """Value and Jacobians of the pendulum model at the noise means: (f, F, G) and (h, H, D) callables."""
    f = np.array([x[0] + DT * x[1], x[1] - DT * np.sin(x[0]) + DT * mu_w[0] * (1.0 + 0.5 * x[1] ** 2)])
    F = np.array([[1.0, DT], [-DT * np.cos(x[0]), 1.0 + DT * mu_w[0] * x[1]]])
    G = np.array([[0.0], [DT * (1.0 + 0.5 * x[1] ** 2)]])
    return f, F, G


def np_pend_h(x, mu_v):
    s = np.sqrt(1.0 + x[0] ** 2)
    h = np.array([x[0] * np.exp(mu_v[0]), np.cos(x[0]) + x[1] + mu_v[1] * s])
    H = np.array([[np.exp(mu_v[0]), 0.0], [-np.sin(x[0]) + mu_v[1] * x[0] / s, 1.0]])
    D = np.array([[x[0] * np.exp(mu_v[0]), 0.0], [0.0, s]])
    return h, H, D


Q_P, R_P = np.array([[0.2]]), np.diag([0.01, 0.04])
PEND = jdrkf.NonlinearModel(
    pend_f, pend_h, Q_P, R_P, additive=False, state_dim=2, obs_dim=2,
    process_noise=jdrkf.Gaussian(MU_W, Q_P), measurement_noise=jdrkf.Gaussian(MU_V, R_P),
)
PEND_PRIOR = jdrkf.Gaussian(jnp.array([0.8, 0.0]), 0.05 * jnp.eye(2))


def numpy_ekf(m0, P0, ys, trans, obs, Q, R, iterations=1, observed=None):
    """NumPy (iterated) EKF: `trans(m) -> (f, F, G)`, `obs(x) -> (h, H, D)`; Joseph update
    with the rows of `observed` only; x⁽ⁱ⁺¹⁾ = m⁻ + K_i (y − h(x⁽ⁱ⁾) − H_i (m⁻ − x⁽ⁱ⁾))."""
    m, P = np.asarray(m0, float), np.asarray(P0, float)
    out = {k: [] for k in ("filtered_means", "filtered_covariances", "predicted_means", "predicted_covariances", "loglik_increments")}
    for t, y in enumerate(np.asarray(ys)):
        f, F, G = trans(m)
        mp, Pp = f, F @ P @ F.T + G @ Q @ G.T
        rows = np.ones(len(y), bool) if observed is None else np.asarray(observed[t])
        x = mp
        for _ in range(iterations):
            h, H, D = obs(x)
            H, Rt = H[rows], (D @ R @ D.T)[np.ix_(rows, rows)]
            S = H @ Pp @ H.T + Rt
            K = Pp @ H.T @ np.linalg.inv(S)
            innov = y[rows] - h[rows] - H @ (mp - x)
            x = mp + K @ innov
        A = np.eye(len(m)) - K @ H
        m, P = x, A @ Pp @ A.T + K @ Rt @ K.T
        ll = multivariate_normal.logpdf(innov, np.zeros(rows.sum()), S) if rows.any() else 0.0
        for k, v in zip(out, (m, P, mp, Pp, ll)):
            out[k].append(v)
    return {k: np.array(v) for k, v in out.items()}


def rb_obs(x):
    return np_rb_h(x), np_rb_H(x), np.eye(2)


def rb_trans(m):
    return np_drag_f(m), np_drag_F(m), np.eye(4)


@pytest.fixture(scope="module")
def rb_data():
    return jdrkf.simulate(jax.random.key(3), RB, RB_PRIOR, num_steps=40, num_runs=3).observations


@pytest.fixture(scope="module")
def pend_data():
    return jdrkf.simulate(jax.random.key(4), PEND, PEND_PRIOR, num_steps=40, num_runs=3).observations


def assert_matches(res, ref):
    for name in ("filtered_means", "filtered_covariances", "predicted_means", "predicted_covariances", "loglik_increments"):
        np.testing.assert_allclose(getattr(res, name), ref[name], **TOL, err_msg=name)


# --------------------------------------------------------------------------- the EKF


def test_matches_filterpy_range_bearing(rb_data):
    ys = np.asarray(rb_data[0])
    ekf = ExtendedKalmanFilter(dim_x=4, dim_z=2)

    def predict_x(u=0):
        ekf.x = np_drag_f(ekf.x)

    ekf.predict_x = predict_x
    ekf.x, ekf.P, ekf.Q, ekf.R = np.array(RB_PRIOR.mean), np.array(RB_PRIOR.cov), Q_RB, R_RB
    ref = {k: [] for k in ("filtered_means", "filtered_covariances", "predicted_means", "predicted_covariances", "loglik_increments")}
    for y in ys:
        ekf.F = np_drag_F(ekf.x)
        ekf.predict()
        ref["predicted_means"].append(ekf.x.copy())
        ref["predicted_covariances"].append(ekf.P.copy())
        ekf.update(y, np_rb_H, np_rb_h)
        ref["filtered_means"].append(ekf.x.copy())
        ref["filtered_covariances"].append(ekf.P.copy())
        ref["loglik_increments"].append(ekf.log_likelihood)
    res = run(jdrkf.ExtendedKF(outputs="all"), RB, RB_PRIOR, ys)
    assert res.result == jdrkf.RESULTS.successful
    assert_matches(res, {k: np.array(v) for k, v in ref.items()})
    np.testing.assert_allclose(res.marginal_loglik, np.sum(ref["loglik_increments"]), rtol=1e-10)
    # the Jacobians of the last step, as reported in info
    np.testing.assert_allclose(res.info["observation_jacobian"][-1], np_rb_H(ref["predicted_means"][-1]), **TOL)
    np.testing.assert_allclose(res.info["transition_jacobian"][0], np_drag_F(np.asarray(RB_PRIOR.mean)), **TOL)


def pend_trans(m):
    return np_pend(m, MU_W, MU_V)


def pend_obs(x):
    return np_pend_h(x, MU_V)


def test_non_additive_noise_with_noise_means_vs_numpy(pend_data):
    ys = pend_data[0]
    res = run(jdrkf.ExtendedKF(outputs="all"), PEND, PEND_PRIOR, ys)
    ref = numpy_ekf(PEND_PRIOR.mean, PEND_PRIOR.cov, ys, pend_trans, pend_obs, Q_P, R_P)
    assert_matches(res, ref)


def test_missing_data_vs_numpy(pend_data):
    ys = np.array(pend_data[1])
    observed = np.ones(ys.shape, bool)
    observed[5:9, 0] = False
    observed[12, :] = False
    observed[20:23, 1] = False
    ys[~observed] = np.nan
    for iterations in (1, 3):
        res = run(jdrkf.ExtendedKF(iterations=iterations, outputs="all"), PEND, PEND_PRIOR, jnp.asarray(ys), jnp.asarray(observed))
        ref = numpy_ekf(PEND_PRIOR.mean, PEND_PRIOR.cov, ys, pend_trans, pend_obs, Q_P, R_P, iterations, observed)
        assert_matches(res, ref)


def test_non_additive_form_of_an_additive_model_is_the_same_filter(rb_data):
    model = jdrkf.NonlinearModel(lambda x, w, t: drag_f(x, t) + w, lambda x, v, t: rb_h(x, t) + v, Q_RB, R_RB,
                                 additive=False, state_dim=4, obs_dim=2)
    a = run(jdrkf.ExtendedKF(), RB, RB_PRIOR, rb_data[0])
    b = run(jdrkf.ExtendedKF(), model, RB_PRIOR, rb_data[0])
    np.testing.assert_allclose(a.filtered_means, b.filtered_means, **TOL)
    np.testing.assert_allclose(a.filtered_covariances, b.filtered_covariances, **TOL)
    np.testing.assert_allclose(a.marginal_loglik, b.marginal_loglik, **TOL)


# --------------------------------------------------------------------------- iterated EKF


@pytest.mark.parametrize("iterations", [2, 4])
def test_iterated_ekf_vs_numpy(rb_data, iterations):
    res = run(jdrkf.ExtendedKF(iterations=iterations, outputs="all"), RB, RB_PRIOR, rb_data[0])
    ref = numpy_ekf(RB_PRIOR.mean, RB_PRIOR.cov, rb_data[0], rb_trans, rb_obs, Q_RB, R_RB, iterations)
    assert_matches(res, ref)


def test_iterated_ekf_converges_to_the_map_estimate(rb_data):
    # A fixed point of the iteration makes the gradient of the MAP objective
    # ½ (x − m⁻)ᵀ P⁻⁻¹ (x − m⁻) + ½ (y − h(x))ᵀ R⁻¹ (y − h(x)) vanish (Bell & Cathey 1993).
    prior = jdrkf.Gaussian(RB_PRIOR.mean, 4.0 * RB_PRIOR.cov)  # a wide prior: a visibly nonlinear update
    ys = rb_data[0][:3]
    one = run(jdrkf.ExtendedKF(outputs="all"), RB, prior, ys)
    many = run(jdrkf.ExtendedKF(iterations=30, outputs="all"), RB, prior, ys)
    R_inv = np.linalg.inv(R_RB)
    for t in range(3):
        mp, Pp, x = (np.asarray(a[t]) for a in (many.predicted_means, many.predicted_covariances, many.filtered_means))
        y = np.asarray(ys[t])
        grad = lambda z, mp=mp, Pp=Pp, y=y: np.linalg.solve(Pp, z - mp) - np_rb_H(z).T @ R_inv @ (y - np_rb_h(z))
        scale = np.linalg.norm(np.linalg.solve(Pp, x - mp))
        assert np.linalg.norm(grad(x)) < 1e-8 * scale
    # the one-step EKF mean is not the MAP estimate here
    mp, Pp = np.asarray(one.predicted_means[0]), np.asarray(one.predicted_covariances[0])
    x = np.asarray(one.filtered_means[0])
    grad = np.linalg.solve(Pp, x - mp) - np_rb_H(x).T @ R_inv @ (np.asarray(ys[0]) - np_rb_h(x))
    assert np.linalg.norm(grad) > 1e-3 * np.linalg.norm(np.linalg.solve(Pp, x - mp))


def test_iterations_checked():
    for bad in (0, -1, 1.5, True):
        with pytest.raises(ValueError, match="iterations"):
            jdrkf.ExtendedKF(iterations=bad)


# --------------------------------------------------------------------------- linear models: the KF and DR filters


F_LIN = np.array([[0.9, 0.2, 0.0], [0.0, 0.95, 0.1], [0.05, 0.0, 0.8]])
G_LIN = np.array([[1.0, 0.0], [0.3, 1.0], [0.0, 0.5]])
H_LIN = np.array([[1.0, 0.0, 0.5], [0.0, 1.0, -1.0]])
D_LIN = np.array([[1.0, 0.2], [0.0, 0.7]])
Q_LIN, R_LIN = np.array([[0.3, 0.05], [0.05, 0.2]]), np.array([[0.5, 0.1], [0.1, 0.4]])
MW_LIN, MV_LIN = np.array([0.2, -0.1]), np.array([0.3, 0.1])

LIN_NL = jdrkf.NonlinearModel(
    lambda x, w, t: jnp.asarray(F_LIN) @ x + jnp.asarray(G_LIN) @ w,
    lambda x, v, t: jnp.asarray(H_LIN) @ x + jnp.asarray(D_LIN) @ v,
    Q_LIN, R_LIN, additive=False, state_dim=3, obs_dim=2,
    process_noise=jdrkf.Gaussian(MW_LIN, Q_LIN), measurement_noise=jdrkf.Gaussian(MV_LIN, R_LIN),
)
LIN = jdrkf.LinearModel(F_LIN, H_LIN, Q_LIN, D_LIN @ R_LIN @ D_LIN.T, G=G_LIN, process_mean=MW_LIN, noise_mean=D_LIN @ MV_LIN)
LIN_PRIOR = jdrkf.Gaussian(jnp.array([1.0, -1.0, 0.5]), jnp.eye(3))


@pytest.fixture(scope="module")
def lin_data():
    return jdrkf.simulate(jax.random.key(5), LIN, LIN_PRIOR, num_steps=25, num_runs=2).observations


def assert_same_filter(a, b):
    for name in ("filtered_means", "filtered_covariances", "predicted_means", "predicted_covariances", "loglik_increments"):
        np.testing.assert_allclose(getattr(a, name), getattr(b, name), **TOL, err_msg=name)


@pytest.mark.parametrize("iterations", [1, 8])
def test_linear_model_equals_kalman_filter(lin_data, iterations):
    ys = lin_data[0]
    observed = jnp.ones(ys.shape, bool).at[3:6, 1].set(False)
    ekf = run(jdrkf.ExtendedKF(iterations=iterations, outputs="all"), LIN_NL, LIN_PRIOR, ys, observed)
    kf = run(jdrkf.KalmanFilter(outputs="all"), LIN, LIN_PRIOR, ys, observed)
    assert_same_filter(ekf, kf)


DR_FILTERS = {
    "wasserstein": jdrkf.DRKF(state_set=Wasserstein(0.2), noise_set=Wasserstein(0.1), rtol=1e-12),
    "kl+outliers": jdrkf.DRKF(state_set=KL(0.05), noise_set=KL(0.02), outliers=EpsContamination(0.05, k=1.4), rtol=1e-12),
    "moment": jdrkf.DRKF(state_set=Moment(1.05), noise_set=Moment(1.02)),
    "wasserstein-joint": jdrkf.WassersteinKF(0.1, rtol=1e-12),
}
SLOW = {"kl+outliers", "wasserstein-joint"}  # about a minute of compilation each on a busy 2-core machine


@pytest.mark.parametrize("name", [pytest.param(n, marks=[pytest.mark.slow] if n in SLOW else []) for n in DR_FILTERS])
def test_dr_ekf_on_a_linear_model_equals_the_linear_dr_filter(lin_data, name):
    flt = DR_FILTERS[name]
    ys = lin_data[1]
    ekf = run(jdrkf.ExtendedKF(flt, outputs="all"), LIN_NL, LIN_PRIOR, ys)
    ref = run(with_outputs(flt, "all"), LIN, LIN_PRIOR, ys)
    assert ekf.result == jdrkf.RESULTS.successful
    assert_same_filter(ekf, ref)


def test_dr_ekf_is_robust_on_a_nonlinear_model(rb_data):
    # Moment sets inflate the predicted and noise covariances: the DR-EKF's filtered covariances dominate the EKF's
    # at the first step (same linearisation point) and its mean differs.
    ekf = run(jdrkf.ExtendedKF(), RB, RB_PRIOR, rb_data[0])
    dr = run(jdrkf.ExtendedKF(jdrkf.DRKF(state_set=Moment(1.2), noise_set=Moment(1.2))), RB, RB_PRIOR, rb_data[0])
    assert dr.result == jdrkf.RESULTS.successful
    assert np.linalg.eigvalsh(np.asarray(dr.filtered_covariances[0] - ekf.filtered_covariances[0])).min() > 0
    assert not np.allclose(dr.filtered_means, ekf.filtered_means)


# --------------------------------------------------------------------------- jit × vmap × grad


def _loglik(scale, flt, ys):
    model = jdrkf.NonlinearModel(pend_f, pend_h, scale * jnp.asarray(Q_P), jnp.asarray(R_P), additive=False, state_dim=2,
                                 obs_dim=2, process_noise=jdrkf.Gaussian(MU_W, Q_P), measurement_noise=jdrkf.Gaussian(MU_V, R_P))
    return flt(model, PEND_PRIOR, ys).marginal_loglik


@pytest.mark.parametrize("flt", [jdrkf.ExtendedKF(),
                                 pytest.param(jdrkf.ExtendedKF(jdrkf.DRKF(state_set=Moment(1.1)), iterations=2), marks=pytest.mark.slow)],
                         ids=["ekf", "dr-iekf"])
def test_jit_vmap_grad_vs_finite_differences(pend_data, flt):
    scale = jnp.asarray(1.3)
    grads = eqx.filter_jit(jax.vmap(jax.grad(_loglik), in_axes=(None, None, 0)))(scale, flt, pend_data)
    value = eqx.filter_jit(jax.vmap(_loglik, in_axes=(None, None, 0)))
    eps = 1e-5
    fd = (value(scale + eps, flt, pend_data) - value(scale - eps, flt, pend_data)) / (2 * eps)
    np.testing.assert_allclose(grads, fd, rtol=1e-5)
    # vmap over runs = one run at a time
    np.testing.assert_allclose(value(jnp.asarray(1.0), flt, pend_data)[2], run(flt, PEND, PEND_PRIOR, pend_data[2]).marginal_loglik, **TOL)


# --------------------------------------------------------------------------- failures


def test_nonfinite_jacobian_is_reported():
    # sqrt has an infinite derivative at 0: the predicted mean reaches 0 at step t = 2.
    model = jdrkf.NonlinearModel(lambda x, t: jnp.where(t == 2, 0.0, 1.0) * x, lambda x, t: jnp.sqrt(jnp.abs(x)), jnp.eye(1), jnp.eye(1))
    prior = jdrkf.Gaussian(jnp.ones(1), jnp.eye(1))
    ys = jnp.ones((5, 1))
    res = run(jdrkf.ExtendedKF(throw=False), model, prior, ys)
    assert res.result == jdrkf.RESULTS.nonfinite_jacobian
    assert np.all(np.isfinite(res.filtered_means[:2]))
    with pytest.raises(Exception, match="Jacobian"):
        run(jdrkf.ExtendedKF(), model, prior, ys)
    # a concrete prior at which the Jacobians are not finite raises at once
    with pytest.raises(ValueError, match="prior"):
        jdrkf.ExtendedKF().init(model, jdrkf.Gaussian(jnp.zeros(1), jnp.eye(1)))


def test_bad_filters_and_models_raise(rb_data):
    with pytest.raises(ValueError, match="filter"):
        jdrkf.ExtendedKF(jdrkf.UnscentedKF())
    with pytest.raises(ValueError, match="filter"):
        jdrkf.ExtendedKF(jdrkf.BootstrapPF(10))
    with pytest.raises(ValueError, match="filter"):
        jdrkf.ExtendedKF(jdrkf.SteadyStateKalmanFilter())(RB, RB_PRIOR, rb_data[0])
    with pytest.raises(ValueError, match="NonlinearModel"):
        jdrkf.ExtendedKF()(LIN, LIN_PRIOR, jnp.zeros((3, 2)))
    with pytest.raises(ValueError, match="NaN"):
        jdrkf.ExtendedKF()(RB, RB_PRIOR, rb_data[0].at[3, 0].set(jnp.nan))
