"""RTS smoother (`jdrkf.smooth`, `RTSSmoother`, `rts_backward`) against a NumPy RTS written
here, dynamax's `lgssm_smoother`, the filter's own (worst-case) moments for DR filters,
missing data, jit × vmap × grad and the shared covariance path under `vmap`."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from oracles import numpy_kalman_filter
from test_shared_covariance import _carry_shapes, _loops

import jdrkf
from jdrkf.sets import KL, Moment, Wasserstein


# ----------------------------------------------------------------------------------
# NumPy oracle: the Kalman filter of tests/oracles.py (NaN = missing, the update uses the
# observed rows only) and an RTS backward pass with explicit inverses, in jdrkf's time
# convention (the prior is the law of x_0, Fs[t] drives x_t → x_{t+1})
# ----------------------------------------------------------------------------------


def np_rts(Fs, m0, P0, mf, Pf, mp, Pp):
    """RTS backward pass; returns smoothed x_1..x_T, Cov(x_k, x_{k-1} | y) for k = 1..T and the
    smoothed law of x_0."""
    T = mf.shape[0]
    fm = [m0, *mf]  # x_0..x_T
    fP = [P0, *Pf]
    sm, sP = [None] * (T + 1), [None] * (T + 1)
    sm[T], sP[T] = fm[T], fP[T]
    cross = [None] * T
    for k in range(T - 1, -1, -1):
        G = fP[k] @ Fs[k].T @ np.linalg.inv(Pp[k])
        sm[k] = fm[k] + G @ (sm[k + 1] - mp[k])
        sP[k] = fP[k] + G @ (sP[k + 1] - Pp[k]) @ G.T
        cross[k] = sP[k + 1] @ G.T
    return np.array(sm[1:]), np.array(sP[1:]), np.array(cross), sm[0], sP[0]


def _assert_smoothed(res, want, rtol=1e-9, atol=1e-11):
    means, covs, cross, m0, P0 = want
    np.testing.assert_allclose(res.smoothed_means, means, rtol=rtol, atol=atol)
    np.testing.assert_allclose(res.smoothed_covariances, covs, rtol=rtol, atol=atol)
    np.testing.assert_allclose(res.smoothed_cross_covariances, cross, rtol=rtol, atol=atol)
    np.testing.assert_allclose(res.smoothed_initial_mean, m0, rtol=rtol, atol=atol)
    np.testing.assert_allclose(res.smoothed_initial_covariance, P0, rtol=rtol, atol=atol)


def _random_problem(seed, T=12, n=3, m=2, p=2, time_varying=True):
    rng = np.random.default_rng(seed)
    shape = (T, n, n) if time_varying else (n, n)
    F = 0.9 * rng.normal(size=shape) / np.sqrt(n) + 0.5 * np.eye(n)
    G = rng.normal(size=(n, n)) / np.sqrt(n) + np.eye(n)
    c = rng.normal(size=(n, n))
    Q = c @ c.T / n + 0.2 * np.eye(n)
    e = rng.normal(size=(m, m))
    R = e @ e.T / m + 0.3 * np.eye(m)
    H = rng.normal(size=(m, n))
    B = rng.normal(size=(n, p))
    inputs = rng.normal(size=(T, p))
    mu_w, mu_v = 0.2 * rng.normal(size=n), 0.3 * rng.normal(size=m)
    model = jdrkf.LinearModel(F, H, Q, R, G=G, B=B, process_mean=mu_w, noise_mean=mu_v)
    c0 = rng.normal(size=(n, n))
    prior = jdrkf.Gaussian(rng.normal(size=n), c0 @ c0.T / n + 0.5 * np.eye(n))
    ys = np.asarray(jdrkf.simulate(jax.random.key(seed), model, prior, T, 1, inputs=inputs).observations[0])
    oracle = dict(Fs=np.broadcast_to(F, (T, n, n)), m0=np.asarray(prior.mean), P0=np.asarray(prior.cov),
                  kf=dict(F=F, H=H, Q=Q, R=R, G=G, B=B, inputs=inputs, process_mean=mu_w, noise_mean=mu_v))
    return model, prior, ys, inputs, oracle


_MOMENTS = ("filtered_means", "filtered_covariances", "predicted_means", "predicted_covariances")


def _oracle(o, ys):
    """NumPy Kalman filter + NumPy RTS (NaN entries of `ys` are missing)."""
    filt = numpy_kalman_filter(o["m0"], o["P0"], ys, **o["kf"])
    return filt, np_rts(o["Fs"], o["m0"], o["P0"], *(filt[k] for k in _MOMENTS))


def _oracle_from_filter(oracle, res):
    """The NumPy backward pass fed with the filter's own moments."""
    moments = [np.asarray(getattr(res.filter_result, f)) for f in _MOMENTS]
    return np_rts(oracle["Fs"], oracle["m0"], oracle["P0"], *moments)


# ----------------------------------------------------------------------------------
# Tests
# ----------------------------------------------------------------------------------


def test_kalman_smoother_matches_numpy_rts():
    """Time-varying F, controls, noise means: filter and backward pass both from NumPy."""
    model, prior, ys, inputs, o = _random_problem(0)
    res = jdrkf.smooth(jdrkf.KalmanFilter(), model, prior, ys, inputs=inputs)
    filt, want = _oracle(o, ys)
    _assert_smoothed(res, want)
    assert res.result == jdrkf.RESULTS.successful
    np.testing.assert_allclose(res.marginal_loglik, filt["marginal_loglik"], rtol=1e-10)
    # The last smoothed law is the last filtered one; earlier ones are tighter.
    pf = filt["filtered_covariances"]
    np.testing.assert_allclose(res.smoothed_covariances[-1], pf[-1], rtol=1e-10)
    assert np.all(np.trace(res.smoothed_covariances[:-1], axis1=1, axis2=2) < np.trace(pf[:-1], axis1=1, axis2=2))


def test_matches_dynamax_lgssm_smoother(monkeypatch):
    dynamax = pytest.importorskip("dynamax.linear_gaussian_ssm")
    # dynamax adds 1e-9·I to every matrix it solves with (a 1e-9 relative bias): switch it off.
    boosted = dynamax.inference.psd_solve
    monkeypatch.setattr(dynamax.inference, "psd_solve", lambda A, b, diagonal_boost=0.0: boosted(A, b, diagonal_boost))
    rng = np.random.default_rng(1)
    n, m, T = 3, 2, 20
    F = 0.9 * rng.normal(size=(n, n)) / np.sqrt(n)
    H = rng.normal(size=(m, n))
    c = rng.normal(size=(n, n))
    Q = c @ c.T / n + 0.1 * np.eye(n)
    R = np.array([[0.5, 0.1], [0.1, 0.3]])
    model = jdrkf.LinearModel(F, H, Q, R)
    prior = jdrkf.Gaussian(rng.normal(size=n), np.eye(n))
    ys = np.asarray(jdrkf.simulate(jax.random.key(1), model, prior, T, 1).observations[0])
    res = jdrkf.smooth(jdrkf.KalmanFilter(), model, prior, ys)
    # dynamax's `initial` is the law of its first state, which y_1 measures: our x_1 | nothing,
    # i.e. the prior of x_0 mapped through one prediction.
    m1 = F @ np.asarray(prior.mean)
    P1 = F @ np.asarray(prior.cov) @ F.T + Q
    params = dynamax.inference.make_lgssm_params(jnp.asarray(m1), jnp.asarray(P1), jnp.asarray(F), jnp.asarray(Q), jnp.asarray(H), jnp.asarray(R))
    post = dynamax.lgssm_smoother(params, jnp.asarray(ys))
    np.testing.assert_allclose(res.smoothed_means, post.smoothed_means, rtol=1e-9, atol=1e-11)
    np.testing.assert_allclose(res.smoothed_covariances, post.smoothed_covariances, rtol=1e-9, atol=1e-11)
    np.testing.assert_allclose(res.marginal_loglik, post.marginal_loglik, rtol=1e-10)
    # dynamax: E[z_t z_{t+1}ᵀ | y] (T-1 pairs); ours: Cov(x_k, x_{k-1} | y), entry 0 pairing x_1 with x_0.
    sm = np.asarray(post.smoothed_means)
    dyn_cov = np.asarray(post.smoothed_cross_covariances) - sm[:-1, :, None] * sm[1:, None, :]
    np.testing.assert_allclose(res.smoothed_cross_covariances[1:], np.swapaxes(dyn_cov, 1, 2), rtol=1e-9, atol=1e-11)


@pytest.mark.parametrize(
    "flt",
    [
        jdrkf.WassersteinDRKF(0.1, 0.1, outputs="all"),
        jdrkf.DRKF(state_set=KL(0.05), noise_set=Moment(1.1)),
        jdrkf.DRKF(state_set=Wasserstein(0.1), noise_set=Wasserstein(0.1)),
    ],
    ids=["W-DRKF", "DRKF-KL", "DRKF-W"],
)
def test_dr_smoother_uses_the_filters_worst_case_moments(flt):
    model, prior, ys, inputs, o = _random_problem(2, time_varying=False)
    res = jdrkf.smooth(flt, model, prior, ys, inputs=inputs)
    assert res.result == jdrkf.RESULTS.successful
    _assert_smoothed(res, _oracle_from_filter(o, res))
    # The worst-case predicted covariances are not the nominal F P Fᵀ + G Q Gᵀ, so an RTS
    # pass with the nominal prediction (what a KF smoother would use) gives other answers.
    fr = res.filter_result
    Pf = np.asarray(fr.filtered_covariances)
    nominal = np.concatenate([[o["P0"]], Pf[:-1]])
    kf = o["kf"]
    nominal = o["Fs"] @ nominal @ np.swapaxes(o["Fs"], 1, 2) + kf["G"] @ kf["Q"] @ kf["G"].T
    assert np.max(np.abs(np.asarray(fr.predicted_covariances) - nominal)) > 1e-2
    naive = np_rts(o["Fs"], o["m0"], o["P0"], np.asarray(fr.filtered_means), Pf, np.asarray(fr.predicted_means), nominal)
    assert np.max(np.abs(np.asarray(res.smoothed_covariances) - naive[1])) > 1e-3


def test_zero_radius_dr_smoother_is_the_kalman_smoother():
    model, prior, ys, inputs, _ = _random_problem(3)
    kf = jdrkf.smooth(jdrkf.KalmanFilter(), model, prior, ys, inputs=inputs)
    dr = jdrkf.smooth(jdrkf.DRKF(state_set=Wasserstein(0.0), noise_set=Wasserstein(0.0)), model, prior, ys, inputs=inputs)
    for field in ("smoothed_means", "smoothed_covariances", "smoothed_cross_covariances", "smoothed_initial_covariance"):
        np.testing.assert_allclose(getattr(dr, field), getattr(kf, field), rtol=1e-8, atol=1e-10, err_msg=field)


def test_missing_data_matches_oracle_that_skips_updates():
    model, prior, ys, inputs, o = _random_problem(4, T=15)
    mask = np.ones(ys.shape, bool)
    mask[3] = False  # a step with nothing observed
    mask[7, 0] = mask[8, 1] = mask[14, 0] = False  # partial observations, the last step included
    ys_nan = np.where(mask, ys, np.nan)
    res = jdrkf.smooth(jdrkf.KalmanFilter(), model, prior, ys_nan, inputs=inputs, observed=jnp.asarray(mask))
    _assert_smoothed(res, _oracle(o, ys_nan)[1])
    full = jdrkf.smooth(jdrkf.KalmanFilter(), model, prior, ys, inputs=inputs)
    assert np.abs(np.asarray(res.smoothed_covariances[3] - full.smoothed_covariances[3])).max() > 1e-3


def test_multisensor_fusion_filter():
    model = jdrkf.MultiSensorModel([[0.9, 0.1], [0.0, 0.95]], [[[1.0, 0.0]], [[0.0, 1.0]]], [[0.3, 0.0], [0.0, 0.2]], [[[1.0]], [[2.0]]])
    prior = jdrkf.Gaussian(np.zeros(2), np.eye(2))
    ys = np.asarray(jax.random.normal(jax.random.key(5), (10, 2)))
    got = jdrkf.smooth(jdrkf.CKF(), model, prior, ys)
    F, H, Q, R = (np.asarray(a) for a in (model.F, model.H, model.Q, model.noise_cov()))
    o = dict(Fs=np.broadcast_to(F, (10, 2, 2)), m0=np.zeros(2), P0=np.eye(2), kf=dict(F=F, H=H, Q=Q, R=R))
    _assert_smoothed(got, _oracle(o, ys)[1])


def test_jit_vmap_grad_against_finite_differences():
    model, prior, _, inputs, _ = _random_problem(6, T=10, time_varying=False)
    runs = 4
    traj = jdrkf.simulate(jax.random.key(6), model, prior, 10, runs, inputs=inputs)  # states: x_1..x_T
    flt = jdrkf.DRKF(state_set=Moment(1.1), noise_set=Moment(1.05))  # worst case θ P: cheap to compile

    def smoothed(scale, ys_runs):
        mdl = eqx.tree_at(lambda m: m.F, model, scale * model.F)
        return jax.vmap(lambda y: jdrkf.smooth(flt, mdl, prior, y, inputs=inputs))(ys_runs)

    @jax.jit
    def loss(scale):
        res = smoothed(scale, traj.observations)
        return jnp.mean((res.smoothed_means - traj.states) ** 2) + jnp.mean(res.smoothed_cross_covariances ** 2)

    batched = jax.jit(smoothed)(1.0, traj.observations)
    one = jax.jit(lambda y: jdrkf.smooth(flt, model, prior, y, inputs=inputs))
    for b in (0, runs - 1):
        want = one(traj.observations[b])
        np.testing.assert_allclose(batched.smoothed_means[b], want.smoothed_means, rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(batched.smoothed_cross_covariances[b], want.smoothed_cross_covariances, rtol=1e-10, atol=1e-12)
    grad = jax.jit(jax.grad(loss))(0.97)
    h = 1e-5
    fd = (loss(0.97 + h) - loss(0.97 - h)) / (2 * h)
    assert abs(float(fd)) > 1e-3
    np.testing.assert_allclose(grad, fd, rtol=1e-6)


B_RUNS, T_SHARED = 7, 13


def _backward_loop(jaxpr):
    loops = [e for e in _loops(jaxpr) if e.primitive.name == "scan" and e.params["reverse"] and e.params["length"] == T_SHARED]
    assert len(loops) == 1, loops
    return loops[0]


@pytest.mark.parametrize("flt", [jdrkf.KalmanFilter(), jdrkf.WassersteinDRKF(0.2, 0.1)], ids=["KF", "W-DRKF"])
def test_vmap_shares_the_backward_covariance_path(flt):
    model, prior, _, _, _ = _random_problem(7, T=T_SHARED, time_varying=False)
    model = jdrkf.LinearModel(model.F, model.H, model.Q, model.R)
    ys = jdrkf.simulate(jax.random.key(7), model, prior, T_SHARED, B_RUNS).observations
    n = model.state_dim
    jaxpr = jax.make_jaxpr(jax.vmap(lambda y: jdrkf.smooth(flt, model, prior, y)))(ys)
    carry = _carry_shapes(_backward_loop(jaxpr))
    assert (n, n) in carry and (B_RUNS, n, n) not in carry, carry  # covariances once for all runs
    assert (B_RUNS, n) in carry, carry  # means per run
    # A per-run mask makes the covariances (and the backward pass's) per run.
    mask = np.ones(ys.shape, bool)
    mask[0, 2, 0] = False
    per_run = jax.make_jaxpr(jax.vmap(lambda y, o: jdrkf.smooth(flt, model, prior, y, observed=o)))(ys, mask)
    carry = _carry_shapes(_backward_loop(per_run))
    assert (B_RUNS, n, n) in carry and (n, n) not in carry, carry


def test_nonpositive_predicted_covariance_gives_a_result_code():
    # F = 0 and Q = 0 make the predicted covariance of x_2 zero: no smoother gain exists.
    model = jdrkf.LinearModel([[0.0]], [[1.0]], [[0.0]], [[1.0]])
    prior = jdrkf.Gaussian(np.zeros(1), np.eye(1))
    ys = np.ones((4, 1))
    res = jdrkf.smooth(jdrkf.KalmanFilter(throw=False), model, prior, ys)
    assert res.filter_result.result == jdrkf.RESULTS.successful
    assert res.result == jdrkf.RESULTS.nonpositive_predicted_covariance
    with pytest.raises(Exception, match="not numerically positive"):
        jdrkf.smooth(jdrkf.KalmanFilter(), model, prior, ys)
    # The filter's own failure keeps its code.
    bad = jdrkf.smooth(jdrkf.KalmanFilter(throw=False), model, prior, jnp.full((4, 1), jnp.inf))
    assert bad.result == jdrkf.RESULTS.nonfinite_state


def test_inconsistent_worst_case_prediction_gives_a_result_code(rng):
    """A Wasserstein worst-case prior need not dominate F P Fᵀ: on this constant-velocity model
    at θ = 0.1 the implied process noise is indefinite and the backward pass would return an
    indefinite smoothed covariance; it must say so, while a smaller radius and moment sets
    (which inflate) are fine. The oracle is the implied noise computed here in NumPy."""
    dt = 0.2
    f = np.array([[1, 0, dt, 0], [0, 1, 0, dt], [0, 0, 1, 0], [0, 0, 0, 1.0]])
    model = jdrkf.LinearModel(F=f, H=np.eye(2, 4), Q=0.01 * np.eye(4), R=0.01 * np.eye(2))
    prior = jdrkf.Gaussian(np.zeros(4), np.eye(4))
    ys = rng.normal(size=(30, 2))
    for flt, consistent in [
        (jdrkf.WassersteinDRKF(0.1, 0.1, throw=False), False),
        (jdrkf.WassersteinDRKF(0.02, 0.02, throw=False), True),
        (jdrkf.DRKF(state_set=Moment(1.5), noise_set=Moment(1.5), throw=False), True),
    ]:
        res = jdrkf.smooth(flt, model, prior, ys)
        fr = res.filter_result
        filt = np.concatenate([[np.eye(4)], np.asarray(fr.filtered_covariances)[:-1]])
        implied = np.asarray(fr.predicted_covariances) - f @ filt @ f.T
        oracle = np.linalg.eigvalsh(0.5 * (implied + np.swapaxes(implied, 1, 2))).min() > -1e-10
        assert oracle == consistent
        assert fr.result == jdrkf.RESULTS.successful
        expected = jdrkf.RESULTS.successful if consistent else jdrkf.RESULTS.inconsistent_predicted_covariance
        assert res.result == expected
        if consistent:
            assert np.linalg.eigvalsh(np.asarray(res.smoothed_covariances)).min() > 0


def test_rejects_non_gaussian_filters_and_models():
    for flt, name in ((jdrkf.BootstrapPF(10), "BootstrapPF"), (jdrkf.DRParticleFilter(10), "DRParticleFilter"),
                      (jdrkf.EnsembleKF(10), "EnsembleKF"), (jdrkf.UnscentedKF(), "UnscentedKF")):
        with pytest.raises(ValueError, match=name):
            jdrkf.RTSSmoother(flt)
    with pytest.raises(ValueError, match="filter must be a jdrkf filter"):
        jdrkf.RTSSmoother(lambda *a: None)
    nonlinear = jdrkf.NonlinearModel(lambda x, t: x, lambda x, t: x, np.eye(1), np.eye(1))
    with pytest.raises(ValueError, match="model must be a jdrkf.LinearModel"):
        jdrkf.smooth(jdrkf.KalmanFilter(), nonlinear, jdrkf.Gaussian(np.zeros(1), np.eye(1)), np.zeros((3, 1)))
    model, prior, ys, inputs, _ = _random_problem(8, time_varying=False)
    partial = jdrkf.KalmanFilter()(model, prior, ys, inputs=inputs)
    with pytest.raises(ValueError, match="predicted_means, predicted_covariances: run the filter with outputs='all'"):
        jdrkf.rts_backward(model, prior, partial)


def test_rts_backward_on_a_stored_filter_result_equals_smooth():
    model, prior, ys, inputs, _ = _random_problem(9)
    flt = jdrkf.KalmanFilter(outputs="all")
    fr = flt(model, prior, ys, inputs=inputs)
    got = jdrkf.rts_backward(model, prior, fr)
    want = jdrkf.smooth(flt, model, prior, ys, inputs=inputs)
    np.testing.assert_array_equal(got.smoothed_means, want.smoothed_means)
    np.testing.assert_array_equal(got.smoothed_covariances, want.smoothed_covariances)
    short = eqx.tree_at(lambda r: [getattr(r, f) for f in _MOMENTS], fr, [getattr(fr, f)[:5] for f in _MOMENTS])
    with pytest.raises(ValueError, match="time-varying with 12 steps"):
        jdrkf.rts_backward(model, prior, short)
