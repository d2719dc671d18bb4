"""Closed-loop simulation (filter + LQR in one scan, Jang et al. 2025) against independent NumPy
re-implementations that replay the returned noise draws, and scipy's DARE."""

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg

import jdrkf
from jdrkf._closed_loop import ClosedLoopResult, LQRController, closed_loop
from jdrkf.sets import Moment


# --- the system of Jang, Hakobyan & Yang (2025), Sec. 5.2 ------------------------------------

DT = 0.2
A4 = np.array([[1, DT, 0, 0], [0, 1, 0, 0], [0, 0, 1, DT], [0, 0, 0, 1]], dtype=np.float64)
B4 = np.array([[0.02, 0], [0.2, 0], [0, 0.02], [0, 0.2]])
C4 = np.array([[1.0, 0, 0, 0], [0, 0, 1, 0]])
Q_LQR = np.diag([10.0, 1.0, 10.0, 1.0])
R_LQR = 0.1 * np.eye(2)


@functools.cache
def _lqr004():
    return LQRController.design(A4, B4, Q_LQR, R_LQR)


def _seed004():
    model = jdrkf.LinearModel(F=A4, H=C4, Q=0.01 * np.eye(4), R=0.01 * np.eye(2), B=B4)
    prior = jdrkf.Gaussian(jnp.zeros(4), 0.01 * jnp.eye(4))
    t = np.arange(0.0, 10.0 + 1e-9, DT)
    ref = np.stack([5 * np.sin(0.5 * t), 2.5 * np.cos(0.5 * t), t, np.ones_like(t)], axis=1)
    return model, prior, ref


# --- independent NumPy oracles ---------------------------------------------------------------


def _np_lqr_gain(A, B, Q, R):
    P = scipy.linalg.solve_discrete_are(A, B, Q, R)
    return np.linalg.solve(R + B.T @ P @ B, B.T @ P @ A)


def _at(a, t, ndim):
    a = np.asarray(a, dtype=np.float64)
    return a[t] if a.ndim == ndim + 1 else a


def _np_closed_loop(x0, w, v, ref, K, nominal, true, m0, P0, measure_initial, gain_fn=None):
    """Replay: true system with draws (x0, w, v), a NumPy KF (standard form, no Joseph) or,
    with `gain_fn(t, P) -> (gain, posterior factor)`, a modified one; LQR u = −K(x̂ − r)."""
    T = ref.shape[0] - 1

    def mats(mdl, t):
        return {k: _at(getattr(mdl, k), t, 1 if k in ("process_mean", "noise_mean") else 2)
                for k in ("F", "H", "Q", "R", "G", "B", "process_mean", "noise_mean")}

    def kf_update(mean, P, y, nm, t):
        S = nm["H"] @ P @ nm["H"].T + nm["R"]
        Kf = P @ nm["H"].T @ np.linalg.inv(S)
        mean = mean + Kf @ (y - nm["H"] @ mean - nm["noise_mean"])
        P = P - Kf @ nm["H"] @ P
        return mean, P

    update = kf_update if gain_fn is None else gain_fn
    xs, ests, us, ys = [], [], [], []
    x = np.asarray(x0, dtype=np.float64)
    tm0 = mats(true, 0)
    y = tm0["H"] @ x + v[0]
    mean, P = np.asarray(m0, dtype=np.float64), np.asarray(P0, dtype=np.float64)
    if measure_initial:
        mean, P = update(mean, P, y, mats(nominal, 0), 0)
    xs.append(x), ests.append(mean), ys.append(y)
    for t in range(T):
        u = -K @ (mean - ref[t])
        us.append(u)
        tm, nm = mats(true, t), mats(nominal, t)
        x = tm["F"] @ x + tm["B"] @ u + tm["G"] @ w[t]
        y = tm["H"] @ x + v[t + 1]
        mean = nm["F"] @ mean + nm["B"] @ u + nm["G"] @ nm["process_mean"]
        P = nm["F"] @ P @ nm["F"].T + nm["G"] @ nm["Q"] @ nm["G"].T
        mean, P = update(mean, P, y, nm, t)
        xs.append(x), ests.append(mean), ys.append(y)
    us.append(-K @ (mean - ref[T]))
    return np.array(xs), np.array(ests), np.array(us), np.array(ys)


def _np_cost(xs, us, ref, Q, R):
    e = xs - ref
    return sum(e[t] @ Q @ e[t] + us[t] @ R @ us[t] for t in range(xs.shape[0]))


def _random_system(rng, n=3, m=2, p=2, q=2, time_varying=False, T=12):
    a = rng.normal(size=(n, n))
    F = 1.05 * a / np.max(np.abs(np.linalg.eigvals(a)))  # mildly unstable open loop
    H = rng.normal(size=(m, n))
    b = rng.normal(size=(q, q))
    c = rng.normal(size=(m, m))
    kw = dict(
        F=F, H=H, Q=b @ b.T / q + 0.1 * np.eye(q), R=c @ c.T / m + 0.2 * np.eye(m),
        G=rng.normal(size=(n, q)), B=rng.normal(size=(n, p)),
        process_mean=0.1 * rng.normal(size=q), noise_mean=0.1 * rng.normal(size=m),
    )
    if time_varying:
        kw["H"] = H + 0.1 * rng.normal(size=(T, m, n))
    return kw


# One compilation per filter structure/shape; filters and models are traced arguments.
run = eqx.filter_jit(lambda key, flt, model, prior, ctrl, ref, **kw: closed_loop(key, flt, model, prior, ctrl, ref, **kw))


# --- LQR -------------------------------------------------------------------------------------


def test_lqr_gain_matches_scipy(rng):
    K = _lqr004().gain
    np.testing.assert_allclose(K, _np_lqr_gain(A4, B4, Q_LQR, R_LQR), rtol=1e-10, atol=1e-12)
    for _ in range(3):
        n, p = 4, 2
        A = rng.normal(size=(n, n))
        A = 1.2 * A / np.max(np.abs(np.linalg.eigvals(A)))  # unstable: the LQR must stabilize
        B = rng.normal(size=(n, p))
        q = rng.normal(size=(n, n))
        Q = q @ q.T + 0.1 * np.eye(n)
        R = np.diag(rng.uniform(0.5, 2.0, size=p))
        K = LQRController.design(A, B, Q, R).gain
        ref = _np_lqr_gain(A, B, Q, R)
        np.testing.assert_allclose(K, ref, rtol=1e-9, atol=1e-10)
        assert np.max(np.abs(np.linalg.eigvals(A - B @ np.asarray(K)))) < 1.0
    ctrl = LQRController(np.arange(8.0).reshape(2, 4))
    x, r = np.array([1.0, 2.0, 3.0, 4.0]), np.array([0.5, 0.0, -1.0, 2.0])
    np.testing.assert_allclose(ctrl(jnp.asarray(x), jnp.asarray(r)), -np.arange(8.0).reshape(2, 4) @ (x - r))


# --- replay against NumPy --------------------------------------------------------------------


@pytest.mark.parametrize("measure_initial, time_varying", [(True, True), (False, False)])
def test_kalman_filter_replay(rng, getkey, measure_initial, time_varying):
    T = 12
    true_kw = _random_system(rng, time_varying=time_varying, T=T)
    true = jdrkf.LinearModel(**true_kw)
    # Nominal model: mismatched F, Q and noise mean (the filter must use these, the plant the true ones).
    nom_kw = dict(true_kw, F=0.9 * true_kw["F"], Q=2.0 * true_kw["Q"], noise_mean=np.zeros(2))
    nominal = jdrkf.LinearModel(**nom_kw)
    prior = jdrkf.Gaussian(jnp.asarray(rng.normal(size=3)), jnp.asarray(0.5 * np.eye(3)))
    x0_law = jdrkf.Gaussian(jnp.asarray(rng.normal(size=3)), jnp.asarray(np.eye(3)))
    ref = rng.normal(size=(T + 1, 3))
    Qc = np.diag([1.0, 2.0, 0.5])
    Rc = 0.3 * np.eye(2)
    lqr = LQRController.design(true_kw["F"], true_kw["B"], Qc, Rc)
    res = run(getkey(), jdrkf.KalmanFilter(), nominal, prior, lqr, ref,
              true_model=true, initial_state=x0_law, measure_initial=measure_initial)
    assert res.states.shape == (T + 1, 3) and res.controls.shape == (T + 1, 2)
    assert res.observations.shape == (T + 1, 2) and res.process_noise.shape == (T, 2)
    assert res.measurement_noise.shape == (T + 1, 2) and (res.results == jdrkf.RESULTS.successful).shape == (T + 1,)
    K = _np_lqr_gain(true_kw["F"], true_kw["B"], Qc, Rc)
    xs, ests, us, ys = _np_closed_loop(
        np.asarray(res.initial_state), np.asarray(res.process_noise), np.asarray(res.measurement_noise), ref, K,
        nominal, true, prior.mean, prior.cov, measure_initial,
    )
    np.testing.assert_allclose(res.states, xs, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(res.estimates, ests, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(res.controls, us, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(res.observations, ys, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(res.cost(Qc, Rc), _np_cost(xs, us, ref, Qc, Rc), rtol=1e-10)
    np.testing.assert_allclose(res.mse(), np.mean(np.sum((ests - xs) ** 2, axis=1)), rtol=1e-10)
    assert bool(res.result == jdrkf.RESULTS.successful)
    # The draws have the laws' means (loose check that defaults are the true model's laws).
    assert np.all(np.isfinite(np.asarray(res.process_noise)))


def test_steady_state_and_moment_drkf_replay_common_random_numbers(getkey):
    # The identity-model trick for the y_0 update: SteadyStateKalmanFilter keeps its
    # steady gain; DRKF with Moment(θ) sets (worst case θP, θR: the fading-memory KF)
    # robustifies the prior. Oracles: constant-gain and fading-memory NumPy filters.
    # All filters run with the same key and non-Gaussian (U-quadratic) laws: the draws
    # must be identical (common random numbers) and inside the laws' support.
    model, prior, ref = _seed004()
    T = 20
    ref = ref[: T + 1]
    lqr = _lqr004()
    K = _np_lqr_gain(A4, B4, Q_LQR, R_LQR)
    Qn, Rn = 0.01 * np.eye(4), 0.01 * np.eye(2)
    Pss = scipy.linalg.solve_discrete_are(A4.T, C4.T, Qn, Rn)
    Kss = Pss @ C4.T @ np.linalg.inv(C4 @ Pss @ C4.T + Rn)

    def ss_update(mean, P, y, nm, t):
        return mean + Kss @ (y - C4 @ mean), P

    theta = 1.3

    def fading_update(mean, P, y, nm, t):
        S = C4 @ P @ C4.T + Rn
        Kf = P @ C4.T @ np.linalg.inv(S)
        return mean + Kf @ (y - C4 @ mean), theta * (P - Kf @ C4 @ P)

    uq4 = jdrkf.UQuadraticNoise(-0.1 * np.ones(4), 0.1 * np.ones(4))
    uq2 = jdrkf.UQuadraticNoise(-0.1 * np.ones(2), 0.1 * np.ones(2))
    laws = dict(initial_state=uq4, process_noise=uq4, measurement_noise=uq2)
    key = getkey()
    results = []
    for flt, upd in [
        (jdrkf.SteadyStateKalmanFilter(), ss_update),
        (jdrkf.DRKF(state_set=Moment(theta), noise_set=Moment(theta)), fading_update),
    ]:
        res = run(key, flt, model, prior, lqr, ref, **laws)
        xs, ests, us, _ = _np_closed_loop(
            np.asarray(res.initial_state), np.asarray(res.process_noise), np.asarray(res.measurement_noise), ref, K,
            model, model, prior.mean, prior.cov, True, gain_fn=upd,
        )
        np.testing.assert_allclose(res.states, xs, rtol=1e-10, atol=1e-10)
        np.testing.assert_allclose(res.estimates, ests, rtol=1e-10, atol=1e-10)
        np.testing.assert_allclose(res.controls, us, rtol=1e-10, atol=1e-10)
        results.append(res)
    # Moment DRKF: the reported x̂_0 covariance is θ (P₀ − P₀Hᵀ(HP₀Hᵀ + R)⁻¹HP₀).
    P0 = 0.01 * np.eye(4)
    post = P0 - P0 @ C4.T @ np.linalg.solve(C4 @ P0 @ C4.T + Rn, C4 @ P0)
    np.testing.assert_allclose(results[1].covariances[0], theta * post, rtol=1e-10, atol=1e-14)
    a, b = results
    for name in ("initial_state", "process_noise", "measurement_noise"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
        assert np.all(np.abs(np.asarray(getattr(a, name))) <= 0.1)
    assert not np.allclose(a.estimates, b.estimates)  # the filters differ, the draws do not
    c = run(getkey(), jdrkf.SteadyStateKalmanFilter(), model, prior, lqr, ref, **laws)
    assert not np.allclose(a.process_noise, c.process_noise)  # another key, other draws


# --- vmap and grad ---------------------------------------------------------------------------


def _mean_cost(make_filter):
    model, prior, ref = _seed004()
    lqr = _lqr004()

    def loss(theta, keys):
        runs = jax.vmap(lambda k: closed_loop(k, make_filter(theta), model, prior, lqr, ref[:21]))(keys)
        return jnp.mean(runs.cost(Q_LQR, R_LQR))

    return jax.jit(jax.value_and_grad(loss))


@pytest.mark.parametrize(
    "make_filter, theta",
    [
        (lambda th: jdrkf.DRKF(state_set=Moment(th), noise_set=Moment(th)), 1.3),
        pytest.param(lambda th: jdrkf.RiskSensitiveKF(th), 2.0, marks=pytest.mark.slow),  # ~20-40 s to compile
    ],
    ids=["drkf-moment", "risk-sensitive"],
)
def test_vmap_and_grad_matches_finite_differences(make_filter, theta):
    keys = jax.random.split(jax.random.key(4), 16)
    value_and_grad = _mean_cost(make_filter)  # one compilation: values for the differences too
    _, grad = value_and_grad(jnp.asarray(theta), keys)
    h = 1e-5
    fd = (value_and_grad(jnp.asarray(theta + h), keys)[0] - value_and_grad(jnp.asarray(theta - h), keys)[0]) / (2 * h)
    assert abs(float(grad)) > 1e-6  # the hyper-parameter does move the cost
    np.testing.assert_allclose(grad, fd, rtol=1e-5)


# --- failures and bad input ------------------------------------------------------------------


def test_filter_failure_is_reported_or_raised(getkey):
    # Scalar double-free system (cheap to compile): x⁺ = x + u + w, y = x + v.
    model = jdrkf.LinearModel(F=[[1.0]], H=[[1.0]], Q=[[1.0]], R=[[1.0]], B=[[1.0]])
    prior = jdrkf.Gaussian(jnp.zeros(1), jnp.eye(1))
    lqr = LQRController.design(model.F, model.B, np.eye(1), np.eye(1))
    ref = np.zeros((6, 1))
    big = 5.0  # θ > 1/λ_max(P) (P ≥ 1 after the first prediction): the recursion breaks down
    res = run(getkey(), jdrkf.RiskSensitiveKF(big, throw=False), model, prior, lqr, ref)
    assert bool(res.result == jdrkf.RESULTS.risk_sensitive_breakdown)
    codes = np.asarray(res.results == jdrkf.RESULTS.risk_sensitive_breakdown)
    assert codes.shape == (6,) and codes[1:].all()
    with pytest.raises(Exception, match="risk-sensitive"):
        run(getkey(), jdrkf.RiskSensitiveKF(big), model, prior, lqr, ref)
    ok = run(getkey(), jdrkf.RiskSensitiveKF(0.1, throw=False), model, prior, lqr, ref)
    assert bool(ok.result == jdrkf.RESULTS.successful)


def test_bad_input():
    model, prior, ref = _seed004()
    lqr = _lqr004()
    key = jax.random.key(0)
    kf = jdrkf.KalmanFilter()
    no_b = jdrkf.LinearModel(F=A4, H=C4, Q=0.01 * np.eye(4), R=0.01 * np.eye(2))
    with pytest.raises(ValueError, match="model has no control matrix B"):
        closed_loop(key, kf, no_b, prior, lqr, ref)
    with pytest.raises(ValueError, match="true_model has no control matrix B"):
        closed_loop(key, kf, model, prior, lqr, ref, true_model=no_b)
    with pytest.raises(ValueError, match=r"reference has shape \(51, 3\)"):
        closed_loop(key, kf, model, prior, lqr, ref[:, :3])
    with pytest.raises(ValueError, match="reference has shape"):
        closed_loop(key, kf, model, prior, lqr, ref[:1])
    with pytest.raises(ValueError, match="reference must have 2 dimensions"):
        closed_loop(key, kf, model, prior, lqr, ref[0])
    with pytest.raises(ValueError, match="prior has dimension 3"):
        closed_loop(key, kf, model, jdrkf.Gaussian(jnp.zeros(3), jnp.eye(3)), lqr, ref)
    three = jdrkf.LinearModel(F=A4, H=np.eye(3, 4), Q=0.01 * np.eye(4), R=np.eye(3), B=B4)
    with pytest.raises(ValueError, match="true_model has"):
        closed_loop(key, kf, model, prior, lqr, ref, true_model=three)
    with pytest.raises(ValueError, match="initial_state draws vectors of dimension 2"):
        closed_loop(key, kf, model, prior, lqr, ref, initial_state=jdrkf.GaussianNoise(np.eye(2)))
    with pytest.raises(ValueError, match="measurement_noise draws vectors of dimension 4"):
        closed_loop(key, kf, model, prior, lqr, ref, measurement_noise=jdrkf.GaussianNoise(np.eye(4)))
    with pytest.raises(ValueError, match=r"must return a \(2,\) array"):
        closed_loop(key, kf, model, prior, LQRController(np.ones((3, 4))), ref)
    with pytest.raises(ValueError, match="filter must be a jdrkf filter"):
        closed_loop(key, lambda *a: None, model, prior, lqr, ref)
    with pytest.raises(ValueError, match="PRNG key"):
        closed_loop(None, kf, model, prior, lqr, ref)
    tv = jdrkf.LinearModel(F=np.broadcast_to(A4, (10, 4, 4)), H=C4, Q=0.01 * np.eye(4), R=0.01 * np.eye(2), B=B4)
    with pytest.raises(ValueError, match="time-varying with 10 steps but 50"):
        closed_loop(key, kf, tv, prior, lqr, ref)
    with pytest.raises(ValueError, match="B has shape"):
        LQRController.design(A4, B4[:3], Q_LQR, R_LQR)
    with pytest.raises(ValueError, match="R has shape"):
        LQRController.design(A4, B4, Q_LQR, np.eye(3))
    res = run(key, kf, model, prior, lqr, ref)
    with pytest.raises(ValueError, match="Q has shape"):
        res.cost(np.eye(3), R_LQR)
    assert isinstance(res, ClosedLoopResult)

# --- Jang et al. smoke run ---------------------------------------------------------------------


def test_seed004_smoke_and_vmap():
    model, prior, ref = _seed004()
    lqr = _lqr004()
    keys = jax.random.split(jax.random.key(2024), 64)
    runs = jax.vmap(lambda k: closed_loop(k, jdrkf.KalmanFilter(), model, prior, lqr, ref))(keys)
    assert runs.states.shape == (64, 51, 4) and runs.controls.shape == (64, 51, 2)
    cost = np.asarray(runs.cost(Q_LQR, R_LQR))
    assert cost.shape == (64,) and runs.mse().shape == (64,)
    assert np.all(np.isfinite(cost)) and bool(jnp.all(runs.result == jdrkf.RESULTS.successful))
    # The plant starts at 0, the reference at (0, 2.5, 0, 1): the initial velocity
    # error alone costs 2.5² + 1² = 7.25, so the cost is above that but bounded.
    assert 7.25 < cost.mean() < 500.0
    # Tracking: after 10 s the position error is of the order of the noise (σ_v = 0.1).
    pos_err = np.asarray(runs.states - runs.reference)[:, :, [0, 2]]
    assert np.sqrt(np.mean(pos_err[:, -10:] ** 2)) < 0.5
    assert 0.0 < float(runs.mse().mean()) < 1.0
    # vmap = single runs.
    one = run(keys[3], jdrkf.KalmanFilter(), model, prior, lqr, ref)
    np.testing.assert_allclose(runs.states[3], one.states, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(cost[3], one.cost(Q_LQR, R_LQR), rtol=1e-12)
