"""Multi-sensor model and fusion filters (Chen et al. 2025): MultiSensorModel,
CKF, covariance intersection and the marginal DRKF, against independent NumPy / SciPy /
CVXPY oracles (tests/fusion_oracle.py)."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg

import jdrkf
from jdrkf._multisensor import MultiSensorModel, _simulate_multisensor
from jdrkf.filters._fusion import CKF, CovarianceIntersection, MarginalDRKF
from jdrkf.sets import covariance_intersection
from jdrkf.sets._marginal import MarginalKL, MarginalMoment

import fusion_oracle as fo
from oracles import numpy_kalman_filter


run = eqx.filter_jit(lambda flt, model, prior, ys: flt(model, prior, ys))
ci_fuse = eqx.filter_jit(covariance_intersection)


def _spd(rng, d, floor=0.3):
    a = rng.normal(size=(d, d))
    return a @ a.T / d + floor * np.eye(d)


def _random_model(rng, n=3, dims=(1, 2), q=2, beta=False, cross=False):
    a = rng.normal(size=(n, n))
    F = 0.95 * a / max(1.0, np.max(np.abs(np.linalg.eigvals(a))))
    G = rng.normal(size=(n, q))
    H = [rng.normal(size=(d, n)) for d in dims]
    R = [_spd(rng, d) for d in dims]
    kw = {}
    if beta:
        kw["beta"] = [0.5 * rng.normal(size=(d, q)) for d in dims]
    if cross:
        kw["cross_cov"] = {(0, 1): 0.1 * rng.normal(size=(dims[0], dims[1]))}
    return MultiSensorModel(F, H, _spd(rng, q), R, G=G, **kw)


def _np(model):
    return tuple(np.asarray(x) for x in (model.F, model.G, model.Q, model.H, model.R))


# ------------------------------------------------------------------ model


def test_model_validation():
    F, Q = np.eye(2), np.eye(2)
    H, R = [np.ones((1, 2)), np.ones((2, 2))], [np.eye(1), np.eye(2)]
    with pytest.raises(ValueError, match="H\\[1\\]"):
        MultiSensorModel(F, [np.ones((1, 2)), np.ones((2, 3))], Q, R)
    with pytest.raises(ValueError, match="R\\[1\\]"):
        MultiSensorModel(F, H, Q, [np.eye(1), np.eye(3)])
    with pytest.raises(ValueError, match="equal length"):
        MultiSensorModel(F, H, Q, [np.eye(1)])
    with pytest.raises(ValueError, match="sequences"):
        MultiSensorModel(F, np.ones((3, 2)), Q, np.eye(3))
    with pytest.raises(ValueError, match="F"):
        MultiSensorModel(np.ones((2, 3)), H, Q, R)
    with pytest.raises(ValueError, match="G"):
        MultiSensorModel(F, H, np.eye(3), R)
    with pytest.raises(ValueError, match="cross_cov"):
        MultiSensorModel(F, H, Q, R, cross_cov={(0, 1): np.ones((2, 1))})
    with pytest.raises(ValueError, match="cross_cov"):
        MultiSensorModel(F, H, Q, R, cross_cov={(0, 0): np.ones((1, 1))})
    with pytest.raises(ValueError, match="positive semidefinite"):
        MultiSensorModel(F, H, Q, R, cross_cov={(0, 1): 5 * np.ones((1, 2))})
    with pytest.raises(ValueError, match="cross_cov"):
        MultiSensorModel(F, H, Q, R, cross_cov=np.eye(2))
    with pytest.raises(ValueError, match="beta\\[0\\]"):
        MultiSensorModel(F, H, Q, R, beta=[np.ones((1, 3)), np.ones((2, 2))])
    with pytest.raises(ValueError, match="beta\\[0\\] is a scalar"):
        MultiSensorModel(F, H, Q, R, beta=[0.5, np.ones((2, 2))])
    with pytest.raises(ValueError, match="one entry per sensor"):
        MultiSensorModel(F, H, Q, R, beta=[0.5])
    model = MultiSensorModel(F, H, Q, R)
    with pytest.raises(ValueError, match="sensor index"):
        model.sensor(2)
    prior = jdrkf.Gaussian(jnp.zeros(2), jnp.eye(2))
    with pytest.raises(ValueError, match="ys has shape"):
        CKF()(model, prior, np.zeros((4, 2)))
    with pytest.raises(ValueError, match="MultiSensorModel"):
        CKF()(model.as_linear(), prior, np.zeros((4, 3)))
    with pytest.raises(ValueError, match="criterion"):
        CovarianceIntersection("max")
    with pytest.raises(ValueError, match="set must be a marginal set"):
        MarginalDRKF(jdrkf.sets.Moment(1.1))
    with pytest.raises(ValueError, match="model must be"):
        MarginalDRKF(MarginalKL(0.1))(model.as_linear(), prior, np.zeros((4, 3)))


def test_model_views_match_numpy(rng):
    model = _random_model(rng, beta=True, cross=True)
    assert model.dims == (1, 2) and model.num_sensors == 2 and model.state_dim == 3 and model.obs_dim == 3
    F, G, Q, H, R_bd = _np(model)
    lin = model.as_linear()
    cc = np.asarray(model.cross_cov)
    np.testing.assert_array_equal(np.asarray(lin.H), H)
    np.testing.assert_allclose(np.asarray(lin.R), R_bd + cc, rtol=0, atol=0)
    assert np.all(cc[:1, :1] == 0) and np.all(cc[1:, 1:] == 0) and np.allclose(cc, cc.T)
    s1 = model.sensor(1)
    np.testing.assert_array_equal(np.asarray(s1.H), H[1:])
    np.testing.assert_array_equal(np.asarray(s1.R), R_bd[1:, 1:])
    # Full-matrix cross_cov gives the same model.
    full = np.asarray(lin.R)
    m2 = MultiSensorModel(F, [H[:1], H[1:]], Q, [R_bd[:1, :1], R_bd[1:, 1:]], G=G, cross_cov=full, beta=np.asarray(model.beta))
    np.testing.assert_array_equal(np.asarray(m2.cross_cov), cc)
    P = _spd(rng, 3)
    np.testing.assert_allclose(model.joint_nominal_cov(P), fo.joint_nominal(F, G, Q, H, R_bd, P), rtol=1e-12, atol=1e-12)
    zc = np.asarray(model.joint_nominal_cov(P, zero_cross=True))
    assert np.all(zc[3:4, 4:] == 0)
    np.testing.assert_allclose(zc[:4, :4], fo.joint_nominal(F, G, Q, H, R_bd, P)[:4, :4], rtol=1e-12)
    beta = np.asarray(model.beta)
    np.testing.assert_allclose(model.true_noise_cov(), beta @ Q @ beta.T + R_bd + cc, rtol=1e-12)


def test_paper_noise_covariance():
    # the authors' MATLAB code (lylechan42/MDRKF): b_i b_j q1 + diag(q1i), diagonal 5.25 / 8.64 / 10.16.
    model = MultiSensorModel(np.eye(3), [np.eye(3)[i:i + 1] for i in range(3)], [[1.0]], [[[5.0]], [[8.0]], [[10.0]]],
                             G=np.ones((3, 1)), beta=[0.5, 0.8, 0.4])
    b = np.array([0.5, 0.8, 0.4])
    np.testing.assert_allclose(model.true_noise_cov(), np.outer(b, b) + np.diag([5.0, 8.0, 10.0]), rtol=1e-14)


def test_simulated_noise_covariance(rng, getkey):
    model = _random_model(rng, n=2, dims=(1, 2), q=2, beta=True, cross=True)
    model = MultiSensorModel(model.F, [model.H[:1], model.H[1:]], model.Q, [model.R[:1, :1], model.R[1:, 1:]],
                             cross_cov=model.cross_cov + model.R, beta=model.beta)  # G = I: w recoverable from x
    prior = jdrkf.Gaussian(jnp.ones(2), jnp.eye(2))
    traj = _simulate_multisensor(getkey(), model, prior, 5, 3000)
    F, _, Q, H, _ = _np(model)
    x = np.concatenate([np.asarray(traj.initial_states)[:, None], np.asarray(traj.states)], axis=1)  # x_0..x_T
    v = np.asarray(traj.observations) - np.einsum("ij,rtj->rti", H, x[:, 1:])
    w = x[:, 1:] - np.einsum("ij,rtj->rti", F, x[:, :-1])  # w_1..w_T
    v_, w_prev = v[:, 1:].reshape(-1, 3), w[:, :-1].reshape(-1, 2)
    n_samp = v_.shape[0]
    joint = np.concatenate([v_, w_prev], axis=1)
    emp = joint.T @ joint / n_samp  # zero-mean noises
    true = np.block([[np.asarray(model.true_noise_cov()), np.asarray(model.true_noise_process_cross_cov())],
                     [np.asarray(model.true_noise_process_cross_cov()).T, Q]])
    sd = np.sqrt((np.outer(np.diag(true), np.diag(true)) + true**2) / n_samp)
    assert np.all(np.abs(emp - true) < 5 * sd), np.max(np.abs(emp - true) / sd)
    # The first step uses w_0 (an independent draw), with the same law.
    assert np.all(np.abs(v[:, 0].T @ v[:, 0] / v.shape[0] - true[:3, :3]) < 5 * np.sqrt(n_samp / v.shape[0]) * sd[:3, :3])


# ------------------------------------------------------------------ CKF and single-sensor KF


def test_ckf_and_single_sensor_kf_match_numpy(rng):
    model = _random_model(rng, cross=True)
    F, G, Q, H, R_bd = _np(model)
    R = np.asarray(model.noise_cov())
    prior = jdrkf.Gaussian(jnp.asarray(rng.normal(size=3)), jnp.asarray(_spd(rng, 3)))
    ys = rng.normal(size=(15, 3))
    res = run(CKF(outputs="all"), model, prior, ys)
    ref = numpy_kalman_filter(prior.mean, prior.cov, ys, F, H, Q, R, G=G)
    for key in ("filtered_means", "filtered_covariances", "predicted_means", "predicted_covariances"):
        np.testing.assert_allclose(getattr(res, key), ref[key], rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(res.marginal_loglik, ref["marginal_loglik"], rtol=1e-10)
    res1 = run(jdrkf.KalmanFilter(), model.sensor(0), prior, ys[:, :1])
    ref1 = numpy_kalman_filter(prior.mean, prior.cov, ys[:, :1], F, H[:1], Q, R_bd[:1, :1], G=G)
    np.testing.assert_allclose(res1.filtered_means, ref1["filtered_means"], rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(res1.filtered_covariances, ref1["filtered_covariances"], rtol=1e-10, atol=1e-10)


# ------------------------------------------------------------------ covariance intersection


@pytest.mark.parametrize("criterion", ["det", "trace"])
def test_ci_identical_inputs_unchanged(rng, criterion):
    x, P = rng.normal(size=3), _spd(rng, 3)
    fused, sol = ci_fuse(jnp.stack([x] * 3), jnp.stack([P] * 3), criterion)
    np.testing.assert_allclose(fused.mean, x, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(fused.cov, P, rtol=1e-10, atol=1e-12)
    assert bool(sol.converged)


@pytest.mark.parametrize("criterion", ["det", "trace"])
def test_ci_scalar_all_weight_on_smallest_variance(criterion):
    var = np.array([3.0, 0.7, 2.0])
    fused, sol = ci_fuse(jnp.asarray([[1.0], [2.0], [3.0]]), jnp.asarray(var[:, None, None]), criterion)
    np.testing.assert_allclose(sol.weights, [0.0, 1.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(fused.mean, [2.0], rtol=1e-12)
    np.testing.assert_allclose(fused.cov, [[0.7]], rtol=1e-12)


@pytest.mark.parametrize("criterion", ["det", "trace"])
@pytest.mark.parametrize("p", [2, 3])
def test_ci_weights_optimal_vs_scipy(rng, criterion, p):
    for _ in range(3):
        Ps = [_spd(rng, 3, floor=0.1) for _ in range(p)]
        xs = rng.normal(size=(p, 3))
        fused, sol = ci_fuse(jnp.asarray(xs), jnp.asarray(np.stack(Ps)), criterion)
        w_ref, val_ref = fo.ci_weights(Ps, criterion)
        assert bool(sol.converged)
        # Never worse than SciPy's best (multi-start SLSQP and vertices), and equal to it.
        val = fo.ci_objective(np.asarray(sol.weights), Ps, criterion)
        assert val <= val_ref + 1e-9 * (1 + abs(val_ref))
        np.testing.assert_allclose(val, val_ref, rtol=1e-8, atol=1e-10)
        np.testing.assert_allclose(sol.weights, w_ref, atol=2e-4)
        x_ref, P_ref = fo.ci_fuse(xs, Ps, np.asarray(sol.weights))
        np.testing.assert_allclose(fused.mean, x_ref, rtol=1e-9, atol=1e-10)
        np.testing.assert_allclose(fused.cov, P_ref, rtol=1e-9, atol=1e-10)
    if p == 2:  # fine grid
        grid = np.linspace(0, 1, 20001)
        vals = [fo.ci_objective([a, 1 - a], Ps, criterion) for a in grid]
        assert float(sol.value) <= min(vals) + 1e-12 * (1 + abs(min(vals)))


def test_ci_consistent_for_any_cross_correlation(rng):
    # Errors e_i with ANY joint covariance C (diagonal blocks P_i): the fused error
    # Σ A_i e_i, A_i = ω_i P_CI P_i⁻¹, has covariance A C Aᵀ ⪯ P_CI (closed form).
    n, p = 3, 3
    for criterion in ("det", "trace"):
        for k in range(6):
            L = rng.normal(size=(n * p, n * p if k % 2 else 2))  # also rank-deficient (fully correlated)
            C = L @ L.T + (0.05 * np.eye(n * p) if k % 2 == 0 else 0.0)
            Ps = [C[i * n:(i + 1) * n, i * n:(i + 1) * n] + 1e-3 * np.eye(n) for i in range(p)]
            C = C + 1e-3 * np.eye(n * p)
            _, sol = ci_fuse(jnp.zeros((p, n)), jnp.asarray(np.stack(Ps)), criterion)
            w, P_ci = np.asarray(sol.weights), np.asarray(sol.cov)
            A = np.hstack([w[i] * P_ci @ np.linalg.inv(Ps[i]) for i in range(p)])
            np.testing.assert_allclose(A @ np.vstack([np.eye(n)] * p), np.eye(n), atol=1e-9)  # unbiased
            assert np.min(np.linalg.eigvalsh(P_ci - A @ C @ A.T)) > -1e-9


@pytest.mark.parametrize("criterion", ["det", pytest.param("trace", marks=pytest.mark.slow)])
def test_ci_filter_matches_numpy(rng, criterion):
    model = _random_model(rng, dims=(1, 1, 2))
    F, G, Q, H, R_bd = _np(model)
    prior = jdrkf.Gaussian(jnp.zeros(3), jnp.asarray(_spd(rng, 3)))
    ys = rng.normal(size=(8, 4))
    res = run(CovarianceIntersection(criterion, outputs="all"), model, prior, ys)
    Hb = [H[:1], H[1:2], H[2:]]
    Rb = [R_bd[:1, :1], R_bd[1:2, 1:2], R_bd[2:, 2:]]
    means, covs, weights = fo.ci_filter(np.zeros(3), np.asarray(prior.cov), ys, F, G, Q, Hb, Rb, criterion)
    np.testing.assert_allclose(res.info["weights"], weights, atol=2e-4)
    np.testing.assert_allclose(res.filtered_means, means, rtol=1e-6, atol=1e-6)
    np.testing.assert_allclose(res.filtered_covariances, covs, rtol=1e-6, atol=1e-8)
    assert bool(jnp.all(res.info["converged"]))


# ------------------------------------------------------------------ marginal DRKF
# The worst-case solver compiles slowly (tens of seconds per set type): marked slow.


@pytest.mark.slow
def test_mdrkf_one_sensor_is_fading_memory(rng):
    # p = 1: S* = γ2 Σ ⇒ KF gain and V = γ2 (M − K H M); γ1 = γ2 = 1 ⇒ the KF.
    model = _random_model(rng, n=2, dims=(2,), q=2)
    F, G, Q, H, R_bd = _np(model)
    prior = jdrkf.Gaussian(jnp.zeros(2), jnp.eye(2))
    ys = rng.normal(size=(6, 2))
    for g1, g2 in ((1.0, 1.0), (0.6, 1.3)):
        res = run(MarginalDRKF(MarginalMoment(g1, g2)), model, prior, ys)
        means, covs = fo.fading_memory_filter(np.zeros(2), np.eye(2), ys, F, G, Q, H, R_bd, g2)
        np.testing.assert_allclose(res.filtered_means, means, rtol=1e-7, atol=1e-8)
        np.testing.assert_allclose(res.filtered_covariances, covs, rtol=1e-7, atol=1e-8)


@pytest.mark.slow
def test_mdrkf_vmap_equals_single_runs(rng, getkey):
    model = _random_model(rng, n=2, dims=(1, 1), q=2, beta=True)
    prior = jdrkf.Gaussian(jnp.zeros(2), jnp.eye(2))
    ys = _simulate_multisensor(getkey(), model, prior, 5, 3).observations
    flt = MarginalDRKF(MarginalMoment(0.7, 1.2))
    batched = eqx.filter_jit(lambda f, m, p, y: jax.vmap(f, in_axes=(None, None, 0))(m, p, y))(flt, model, prior, ys)
    for r in range(3):
        single = run(flt, model, prior, ys[r])
        np.testing.assert_allclose(batched.filtered_means[r], single.filtered_means, rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(batched.filtered_covariances[r], single.filtered_covariances, rtol=1e-10, atol=1e-12)
    # The covariance path is data independent: identical across runs.
    np.testing.assert_array_equal(batched.filtered_covariances[0], batched.filtered_covariances[2])


@pytest.mark.slow
@pytest.mark.parametrize("kind", ["moment", "kl"])
def test_mdrkf_matches_cvxpy_sdp_loop(rng, kind):
    model = _random_model(rng, n=2, dims=(1, 1), q=2)
    F, G, Q, H, R_bd = _np(model)
    prior = jdrkf.Gaussian(jnp.zeros(2), jnp.eye(2))
    ys = rng.normal(size=(3, 2))
    radius = (0.6, 1.4) if kind == "moment" else 0.1
    s = MarginalMoment(*radius) if kind == "moment" else MarginalKL(radius)
    res = run(MarginalDRKF(s), model, prior, ys)
    means, covs = fo.mdrkf_sdp_filter(np.zeros(2), np.eye(2), ys, F, G, Q, H, R_bd, model.dims, kind, radius)
    np.testing.assert_allclose(res.filtered_covariances, covs, rtol=1e-5, atol=1e-7)
    np.testing.assert_allclose(res.filtered_means, means, rtol=1e-3, atol=1e-4)


@pytest.mark.slow
def test_mdrkf_equal_gammas_is_worst_cross_correlation_not_ckf(rng):
    # γ1 = γ2 = 1 fixes every marginal block; the cross-sensor blocks stay free, so for
    # p > 1 the filter is NOT the CKF (which assumes independent sensors): it is never
    # more optimistic than the CKF, and it matches the SDP with fixed marginals.
    model = _random_model(rng, n=2, dims=(1, 1), q=2)
    F, G, Q, H, R_bd = _np(model)
    prior = jdrkf.Gaussian(jnp.zeros(2), jnp.eye(2))
    ys = rng.normal(size=(3, 2))
    res = run(MarginalDRKF(MarginalMoment(1.0, 1.0)), model, prior, ys)
    ckf = run(CKF(), model, prior, ys)
    assert np.all(np.trace(res.filtered_covariances, axis1=1, axis2=2) >= np.trace(ckf.filtered_covariances, axis1=1, axis2=2) - 1e-9)
    _, covs = fo.mdrkf_sdp_filter(np.zeros(2), np.eye(2), ys, F, G, Q, H, R_bd, model.dims, "moment", (1.0, 1.0))
    np.testing.assert_allclose(res.filtered_covariances, covs, rtol=1e-5, atol=1e-7)


def test_scipy_block_diag_sanity():
    # fusion_oracle.stacked is the NumPy twin of as_linear (guards the oracle itself).
    H, R = fo.stacked([np.ones((1, 2)), np.zeros((2, 2))], [np.eye(1), 2 * np.eye(2)])
    np.testing.assert_array_equal(R, scipy.linalg.block_diag(np.eye(1), 2 * np.eye(2)))
    assert H.shape == (3, 2)


@pytest.mark.slow
def test_mdrkf_grad_through_filter_matches_finite_differences(rng, getkey):
    """d MSE / d (γ1, γ2) through the whole MarginalDRKF (the solver's implicit
    derivatives chained over time steps) against central finite differences. The lower
    bound γ1 is inactive here (the worst case sits on the upper bounds): its derivative
    is ~0, which the gradient must reproduce too."""
    model = _random_model(rng, n=2, dims=(1, 1), q=2, beta=True)
    prior = jdrkf.Gaussian(jnp.zeros(2), jnp.eye(2))
    traj = _simulate_multisensor(getkey(), model, prior, 6, 1)
    ys, xs = traj.observations[0], traj.states[0]

    @jax.jit
    def mse(g):
        res = MarginalDRKF(MarginalMoment(g[0], g[1]))(model, prior, ys)
        return jnp.mean((res.filtered_means - xs) ** 2)

    g0 = np.array([0.8, 1.3])
    grad = jax.jit(jax.grad(mse))(jnp.asarray(g0))
    h = 1e-3  # the barrier solver's round-off makes smaller steps noisy (FD error ~1e-12 / h)
    fd = np.array([(float(mse(g0 + h * e)) - float(mse(g0 - h * e))) / (2 * h) for e in np.eye(2)])
    assert abs(fd[1]) > 1e-3
    np.testing.assert_allclose(grad, fd, rtol=1e-6, atol=1e-8)
