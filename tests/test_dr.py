"""DRKF (Wang & Ye 2022, Algorithm 1) and its special cases (Theorem 10), HuberKF and
WassersteinKF, against independent NumPy / cvxpy oracles."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.optimize
import scipy.stats
from hypothesis import given, settings, strategies as st

import jdrkf
from jdrkf.experiments import wang_ye
from jdrkf.sets import KL, EpsContamination, EpsNormal, Moment, Wasserstein

from oracles import numpy_kalman_filter
from sdp_oracles import joint_wasserstein_sdp


# One compilation per filter structure and data shape (filters and data are traced
# arguments), so hypothesis examples and repeated calls do not recompile.
run = eqx.filter_jit(lambda flt, model, prior, ys: flt(model, prior, ys))


def _data(getkey, runs=1, steps=40, alpha=1.0, outliers=True):
    traj = wang_ye.scenario(getkey(), runs, alpha, outliers, steps)
    return wang_ye.nominal_model(), wang_ye.prior(), traj


def _random_model(rng, n=3, m=2):
    a = rng.normal(size=(n, n))
    f = 0.9 * a / max(1.0, np.max(np.abs(np.linalg.eigvals(a))))
    b = rng.normal(size=(n, n))
    c = rng.normal(size=(m, m))
    return jdrkf.LinearModel(F=f, H=rng.normal(size=(m, n)), Q=b @ b.T / n + 0.1 * np.eye(n), R=c @ c.T / m + 0.2 * np.eye(m))


@pytest.mark.parametrize(
    "flt",
    [
        jdrkf.DRKF(),
        jdrkf.DRKF(state_set=Wasserstein(0.0), noise_set=Wasserstein(0.0)),
        jdrkf.DRKF(state_set=KL(0.0), noise_set=Moment(1.0)),
        jdrkf.DRKF(joint_set=Wasserstein(0.0)),
        jdrkf.DRKF(joint_set=KL(0.0)),
        jdrkf.WassersteinKF(0.0),
    ],
)
def test_zero_radius_is_kalman_filter(flt, rng):
    # Theorem 10, case 1; oracle: NumPy KF.
    model = _random_model(rng)
    prior = jdrkf.Gaussian(jnp.zeros(3), jnp.eye(3))
    ys = rng.normal(size=(15, 2))
    res = run(flt, model, prior, ys)
    ref = numpy_kalman_filter(prior.mean, prior.cov, ys, model.F, model.H, model.Q, model.R)
    np.testing.assert_allclose(res.filtered_means, ref["filtered_means"], rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(res.filtered_covariances, ref["filtered_covariances"], rtol=1e-10, atol=1e-10)


def test_equal_moment_radii_is_fading_memory_kf(rng):
    # Theorem 10, case 2: Σx = θM, Σv = θR ⇒ the KF gain and P* = θ P (NumPy oracle).
    model = _random_model(rng)
    theta = 1.07
    ys = rng.normal(size=(12, 2))
    res = run(jdrkf.DRKF(state_set=Moment(theta), noise_set=Moment(theta)), model, jdrkf.Gaussian(jnp.zeros(3), jnp.eye(3)), ys)
    f, h, q, r = (np.asarray(x) for x in (model.F, model.H, model.Q, model.R))
    x, p = np.zeros(3), np.eye(3)
    for k, y in enumerate(ys):
        m = f @ p @ f.T + q
        gain = m @ h.T @ np.linalg.inv(h @ m @ h.T + r)
        x = f @ x + gain @ (y - h @ f @ x)
        p = theta * (m - gain @ h @ m)
        np.testing.assert_allclose(res.filtered_means[k], x, rtol=1e-10, atol=1e-10)
        np.testing.assert_allclose(res.filtered_covariances[k], p, rtol=1e-10, atol=1e-10)


def _numpy_huber_mkf(model, prior, ys, theta2, eps, k):
    """Wang & Ye's Huber.m / MKF.m (m = 1), written from their code (Spratm-Asleaf/DRSE-Outlier)."""
    f, h, q, r = (np.asarray(x) for x in (model.F, model.H, model.Q, model.R))
    x, p = np.asarray(prior.mean), np.asarray(prior.cov)
    i_min = (1 - eps) * (1 - 2 * scipy.stats.norm.cdf(-k))
    means = []
    for y in ys:
        sx = theta2 * (f @ p @ f.T + q)
        s = h @ sx @ h.T + theta2 * r
        x = f @ x
        w = 1 / np.sqrt(s[0, 0])
        x = x + (sx @ h.T)[:, 0] * w * np.clip(w * (y[0] - h[0] @ x), -k, k)
        p = sx - sx @ h.T @ np.linalg.inv(s) @ h @ sx * i_min
        means.append(x)
    return np.array(means), p


@pytest.mark.parametrize("theta2", [1.0, 1.02])
def test_huber_and_moment_filters_match_reference_code(getkey, theta2):
    # Theorem 10, case 5 (θ2 = 1: HKF) and the paper's MKF, vs a NumPy port of the authors' filters.
    model, prior, traj = _data(getkey)
    ys = traj.observations[0]
    flt = (jdrkf.HuberKF(0.05, 1.4) if theta2 == 1.0
           else jdrkf.DRKF(state_set=Moment(theta2), noise_set=Moment(theta2), outliers=EpsContamination(0.05, k=1.4)))
    res = run(flt, model, prior, ys)
    ref, p_last = _numpy_huber_mkf(model, prior, np.asarray(ys), theta2, 0.05, 1.4)
    np.testing.assert_allclose(res.filtered_means, ref, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(res.filtered_covariances[-1], p_last, rtol=1e-9)
    if theta2 == 1.0:
        drkf = run(jdrkf.DRKF(outliers=EpsContamination(0.05, k=1.4)), model, prior, ys)
        np.testing.assert_allclose(drkf.filtered_means, res.filtered_means, rtol=1e-12)


def test_outliers_move_robust_filters_less_than_kf(rng):
    model = _random_model(rng, 2, 1)
    prior = jdrkf.Gaussian(jnp.zeros(2), jnp.eye(2))
    ys = np.zeros((5, 1))
    ys_out = ys.copy()
    ys_out[2, 0] = 100.0
    for flt in [jdrkf.HuberKF(0.05), jdrkf.DRKF(state_set=Wasserstein(0.1), noise_set=Wasserstein(0.1), outliers=EpsNormal(0.03))]:
        move = np.abs(run(flt, model, prior, ys_out).filtered_means[2] - run(flt, model, prior, ys).filtered_means[2]).max()
        kf_move = np.abs(run(jdrkf.KalmanFilter(), model, prior, ys_out).filtered_means[2]).max()
        assert move < 0.1 * kf_move


def test_wasserstein_kf_matches_sdp_recursion(getkey):
    # Theorem 10, case 6: DRKF(joint_set=Wasserstein(ρ)) ≡ WassersteinKF(ρ), and both follow the
    # WKF recursion with the worst case of each step from an SDP solver (cvxpy + Clarabel).
    model, prior, traj = _data(getkey, steps=4, outliers=False)
    ys = np.asarray(traj.observations[0])
    rho = 0.3
    res = run(jdrkf.WassersteinKF(rho), model, prior, ys)
    res2 = run(jdrkf.DRKF(joint_set=Wasserstein(rho)), model, prior, ys)
    np.testing.assert_allclose(res.filtered_means, res2.filtered_means, rtol=1e-12)
    f, h, q, r = (np.asarray(x) for x in (model.F, model.H, model.Q, model.R))
    x, v = np.zeros(2), np.eye(2)
    for k, y in enumerate(ys):
        a = np.vstack([f, h @ f])
        b = np.block([[q, q @ h.T], [h @ q, h @ q @ h.T + r]])
        sdp = joint_wasserstein_sdp(a @ v @ a.T + b, 2, rho)
        s = sdp["cov"]
        gain = s[:2, 2:] @ np.linalg.inv(s[2:, 2:])
        x = f @ x + gain @ (y - h @ f @ x)
        v = s[:2, :2] - gain @ s[2:, :2]
        np.testing.assert_allclose(res.filtered_means[k], x, rtol=1e-5, atol=1e-5)
        np.testing.assert_allclose(res.filtered_covariances[k], v, rtol=1e-5, atol=1e-5)


def test_joint_kl_is_relative_entropy_update(rng):
    # Theorem 10, case 7 (static form, Levy & Nikoukhah 2013): with a joint KL ball of budget c the
    # worst-case posterior is (P⁻¹ − θI)⁻¹, P the nominal posterior, ½ Σ φ₀(θ pᵢ) = c, and the
    # estimate is the nominal one.
    model = _random_model(rng)
    prior = jdrkf.Gaussian(jnp.zeros(3), jnp.eye(3))
    ys = rng.normal(size=(1, 2))
    c = 0.05
    res = run(jdrkf.DRKF(joint_set=KL(c)), model, prior, ys)
    kf = run(jdrkf.KalmanFilter(), model, prior, ys)
    p = np.asarray(kf.filtered_covariances[0])
    lam = np.linalg.eigvalsh(p)

    def phi(theta):
        s = theta * lam
        return 0.5 * np.sum(1 / (1 - s) - 1 + np.log(1 - s)) - c

    theta = scipy.optimize.brentq(phi, 0.0, (1 - 1e-12) / lam.max(), xtol=1e-15)
    np.testing.assert_allclose(res.filtered_covariances[0], np.linalg.inv(np.linalg.inv(p) - theta * np.eye(3)), rtol=1e-8)
    np.testing.assert_allclose(res.filtered_means[0], kf.filtered_means[0], rtol=1e-8, atol=1e-10)


FILTERS = {
    "dr-wasserstein": jdrkf.DRKF(state_set=Wasserstein(0.2), noise_set=Wasserstein(0.1), outliers=EpsContamination(0.05)),
    "dr-kl-moment": jdrkf.DRKF(state_set=KL(0.01), noise_set=Moment(1.05), outliers=EpsNormal(0.02)),
    "mkf": jdrkf.DRKF(state_set=Moment(1.02), noise_set=Moment(1.02), outliers=EpsContamination(0.05, k=1.4)),
    "huber": jdrkf.HuberKF(0.05, 1.4),
    "wkf": jdrkf.WassersteinKF(0.1),
}


@pytest.mark.parametrize("name", [pytest.param(n, marks=pytest.mark.slow) if n == "dr-kl-moment" else n for n in sorted(FILTERS)])
def test_jit_vmap_agree_and_are_finite(name, getkey):
    flt = FILTERS[name]
    model, prior, traj = _data(getkey, runs=3, steps=25)
    batch = jax.jit(jax.vmap(lambda y: flt(model, prior, y)))(traj.observations)
    single = run(flt, model, prior, traj.observations[1])
    np.testing.assert_allclose(batch.filtered_means[1], single.filtered_means, rtol=1e-9, atol=1e-9)
    assert np.all(batch.result == jdrkf.RESULTS.successful)
    assert np.all(np.isfinite(batch.filtered_covariances))


def test_missing_components_match_reduced_model(rng):
    # NaN components drop out of the DR update exactly like observing only the other rows.
    model = _random_model(rng, 3, 2)
    prior = jdrkf.Gaussian(jnp.zeros(3), jnp.eye(3))
    ys = rng.normal(size=(1, 2))
    ys_nan = ys.copy()
    ys_nan[0, 1] = np.nan
    reduced = jdrkf.LinearModel(F=model.F, H=model.H[:1], Q=model.Q, R=model.R[:1, :1])
    flt = jdrkf.DRKF(state_set=Wasserstein(0.2), noise_set=Wasserstein(0.1))
    full = eqx.filter_jit(lambda y: flt(model, prior, y, observed=~jnp.isnan(y)))(ys_nan)
    red = run(flt, reduced, prior, ys[:, :1])
    np.testing.assert_allclose(full.filtered_means, red.filtered_means, rtol=1e-8)
    np.testing.assert_allclose(full.filtered_covariances, red.filtered_covariances, rtol=1e-8)


def test_bad_arguments():
    with pytest.raises(ValueError, match="joint_set"):
        jdrkf.DRKF(joint_set=Wasserstein(0.1), outliers=EpsContamination(0.05))
    with pytest.raises(ValueError, match="state_set"):
        jdrkf.DRKF(state_set=0.1)
    with pytest.raises(ValueError, match="radius"):
        jdrkf.WassersteinKF(-1.0)
    with pytest.raises(ValueError, match="theta2"):
        Moment(0.5)


@settings(max_examples=15, deadline=None)
@given(seed=st.integers(0, 10_000), theta_x=st.floats(0.0, 2.0), theta_v=st.floats(0.0, 2.0))
def test_covariances_stay_psd(seed, theta_x, theta_v):
    rng = np.random.default_rng(seed)
    model = _random_model(rng, 3, 2)
    ys = rng.normal(size=(8, 2)) * 3
    flt = jdrkf.DRKF(state_set=Wasserstein(theta_x), noise_set=Wasserstein(theta_v), outliers=EpsContamination(0.1),
                     outputs="all")
    res = run(flt, model, jdrkf.Gaussian(jnp.zeros(3), jnp.eye(3)), ys)
    covs = np.asarray(res.filtered_covariances)
    np.testing.assert_allclose(covs, np.swapaxes(covs, 1, 2), atol=1e-12)
    assert np.all(np.linalg.eigvalsh(covs) > 0)
    # The worst-case prior keeps the nominal's smallest eigenvalue (T ⪰ I in the Gelbrich oracle).
    lo = np.linalg.eigvalsh(res.info["nominal_prior_cov"])[:, 0]
    assert np.all(np.linalg.eigvalsh(res.predicted_covariances)[:, 0] >= lo * (1 - 1e-9))


def test_float32_matches_float64(getkey):
    model, prior, traj = _data(getkey, steps=30)
    flt = jdrkf.DRKF(state_set=Wasserstein(0.2), noise_set=Wasserstein(0.1), outliers=EpsContamination(0.05))
    ref = run(flt, model, prior, traj.observations[0])
    f32 = lambda tree: jax.tree.map(lambda a: a.astype(jnp.float32) if eqx.is_inexact_array(a) else a, tree)  # noqa: E731
    res = run(f32(flt), f32(model), f32(prior), traj.observations[0].astype(jnp.float32))
    assert res.filtered_means.dtype == jnp.float32 and res.result == jdrkf.RESULTS.successful
    np.testing.assert_allclose(res.filtered_means, ref.filtered_means, rtol=1e-3, atol=1e-3 * np.abs(ref.filtered_means).max())
