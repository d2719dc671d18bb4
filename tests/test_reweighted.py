"""Iteratively reweighted robust KFs of Li, Shi, Yu, Shi (STKF, RBKF, STKF-AR1/AR2, VBKF):
weight functions (eq. 17, Table I), Algorithm 1 against a NumPy oracle, and the
identities Proposition 1, Theorem 4, Proposition 2 and (by simulation) Theorem 5."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from oracles import numpy_kalman_filter

import jdrkf
from jdrkf.filters._reweighted import RBKF, STKF, STKF_AR1, STKF_AR2, VBKF
from jdrkf.sets._weights import Barron, GaussianKernel, Huber, PseudoHuber, StudentT

run = eqx.filter_jit(lambda flt, model, prior, ys, observed=None: flt(model, prior, ys, observed=observed))
N, M = 3, 2


def _model(seed=0, n=N, m=M):
    rng = np.random.default_rng(seed)
    a = rng.normal(size=(n, n))
    f = 0.95 * a / max(1.0, np.max(np.abs(np.linalg.eigvals(a))))
    b = rng.normal(size=(n, n))
    c = rng.normal(size=(m, m))
    q = b @ b.T / n + 0.1 * np.eye(n)
    r = c @ c.T / m + 0.2 * np.eye(m)
    return jdrkf.LinearModel(F=f, H=rng.normal(size=(m, n)), Q=q, R=r)


def _data(model, seed=1, steps=25, outliers=True):
    rng = np.random.default_rng(seed)
    f, h, q, r = (np.asarray(a) for a in (model.F, model.H, model.Q, model.R))
    x = np.zeros(f.shape[0])
    ys = []
    for _ in range(steps):
        x = f @ x + rng.multivariate_normal(np.zeros(len(x)), q)
        v = rng.multivariate_normal(np.zeros(h.shape[0]), r)
        if outliers and rng.uniform() < 0.2:
            v = 10.0 * v
        ys.append(h @ x + v)
    return np.array(ys)


PRIOR = jdrkf.Gaussian(jnp.zeros(N), jnp.eye(N))


def _kf_ref(model, ys):
    return numpy_kalman_filter(np.zeros(N), np.eye(N), ys, model.F, model.H, model.Q, model.R)


def _close(a, b, tol=1e-8):
    np.testing.assert_allclose(a.filtered_means, b.filtered_means, rtol=tol, atol=tol)
    np.testing.assert_allclose(a.filtered_covariances, b.filtered_covariances, rtol=tol, atol=tol)


# ----------------------------------------------------------------------------- oracle


def numpy_irls_filter(ys, model, wx, wy, max_iter, tol, covariance):
    """Algorithm 1 with NumPy, loop by loop (weights as NumPy callables or None)."""
    f, h, q, r = (np.asarray(a) for a in (model.F, model.H, model.Q, model.R))
    n = f.shape[0]
    x, p = np.zeros(n), np.eye(n)
    means, covs, iters = [], [], []
    for y in ys:
        xp, pp = f @ x, f @ p @ f.T + q
        lp, lr = np.linalg.cholesky(pp), np.linalg.cholesky(r)
        xj = xp
        for j in range(1, max_iter + 1):
            ex = np.linalg.solve(lp, xp - xj)
            ey = np.linalg.solve(lr, y - h @ xj)
            pt = pp if wx is None else lp @ np.diag(1 / wx(ex)) @ lp.T
            rt = r if wy is None else lr @ np.diag(1 / wy(ey)) @ lr.T
            k = pt @ h.T @ np.linalg.inv(h @ pt @ h.T + rt)
            xn = xp + k @ (y - h @ xp)
            done = np.linalg.norm(xn - xj) <= tol * np.linalg.norm(xn)
            xj = xn
            if done:
                break
        a = np.eye(n) - k @ h
        p = a @ pt @ a.T + k @ rt @ k.T if covariance == "reweighted" else a @ pp @ a.T + k @ r @ k.T
        x = xj
        means.append(x), covs.append(p), iters.append(j)
    return np.array(means), np.array(covs), np.array(iters)


# ----------------------------------------------------------------------------- weights


E = jnp.array([-30.0, -2.0, -0.3, 0.0, 0.5, 3.0])


@pytest.mark.parametrize(
    "w, ref",
    [
        (StudentT(3.0, 2.0), lambda e: 3.0 / (3.0 * 2.0 + e**2)),
        (GaussianKernel(1.5, 2.0, floor=0.0), lambda e: np.exp(-(e**2) / (2 * 1.5**2 * 2.0)) / 2.0),
        (Barron(0.5, 2.0), lambda e: ((e**2 / 2.0) / 1.5 + 1) ** (0.25 - 1) / 2.0),
        (PseudoHuber(1.5, 2.0), lambda e: 1 / (2.0 * np.sqrt(1 + e**2 / (1.5 * 2.0)))),
        (Huber(1.345), lambda e: np.minimum(1.0, 1.345 / np.maximum(np.abs(e), 1e-300))),
    ],
)
def test_weights_match_table_one(w, ref):
    np.testing.assert_allclose(w(E), ref(np.asarray(E)), rtol=1e-14)


@pytest.mark.parametrize(
    "w", [StudentT(jnp.inf), GaussianKernel(jnp.inf), Barron(2.0), PseudoHuber(jnp.inf), Huber(jnp.inf)]
)
def test_disabled_weight_is_one_with_finite_gradients(w):
    np.testing.assert_array_equal(w(E), np.ones(E.shape))
    g = jax.grad(lambda w, e: jnp.sum(w(e)))(w, E)
    assert all(bool(jnp.all(jnp.isfinite(leaf))) for leaf in jax.tree_util.tree_leaves(g))
    ge = jax.grad(lambda e: jnp.sum(w(e)))(E)
    np.testing.assert_array_equal(ge, np.zeros(E.shape))


def test_weights_per_channel_and_floor():
    w = StudentT(jnp.array([jnp.inf, 1.0]), jnp.array([1.0, 0.5]))
    np.testing.assert_allclose(w(jnp.array([7.0, 2.0])), [1.0, 1.0 / (0.5 + 4.0)], rtol=1e-14)
    assert float(GaussianKernel(1.0, floor=1e-4)(jnp.array([100.0]))[0]) == 1e-4
    # Large-but-finite parameters approach the Gaussian weight (Proposition 1, eq. 34).
    for w in (StudentT(1e12), GaussianKernel(1e8), Barron(2.0 - 1e-12), PseudoHuber(1e12), Huber(1e12)):
        np.testing.assert_allclose(w(E), np.ones(E.shape), rtol=1e-9)


# ----------------------------------------------------------------------------- Algorithm 1


@pytest.mark.parametrize("covariance", ["reweighted", "nominal"])
def test_stkf_matches_numpy_algorithm_1(covariance):
    model = _model()
    ys = _data(model)
    nu_x, nu_y = np.array([3.0, 5.0, 2.0]), np.array([4.0, 1.5])
    t2x, t2y = 1.2, np.array([0.8, 1.1])
    flt = STKF(nu_x, t2x, nu_y, t2y, max_iter=6, tol=1e-4, covariance=covariance, outputs="all")
    res = run(flt, model, PRIOR, ys)
    means, covs, iters = numpy_irls_filter(
        ys, model, lambda e: nu_x / (nu_x * t2x + e**2), lambda e: nu_y / (nu_y * t2y + e**2), 6, 1e-4, covariance
    )
    np.testing.assert_allclose(res.filtered_means, means, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(res.filtered_covariances, covs, rtol=1e-10, atol=1e-10)
    np.testing.assert_array_equal(res.info["iterations"], iters)
    assert res.result == jdrkf.RESULTS.successful


def test_rbkf_matches_numpy_algorithm_1():
    model = _model()
    ys = _data(model)
    flt = RBKF(GaussianKernel(2.0, floor=1e-4), PseudoHuber(1.0), max_iter=3, tol=1e-5)
    res = run(flt, model, PRIOR, ys)
    means, covs, _ = numpy_irls_filter(
        ys, model, lambda e: np.maximum(np.exp(-(e**2) / 8.0), 1e-4), lambda e: 1 / np.sqrt(1 + e**2), 3, 1e-5, "reweighted"
    )
    np.testing.assert_allclose(res.filtered_means, means, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(res.filtered_covariances, covs, rtol=1e-10, atol=1e-10)


# ----------------------------------------------------------------------------- Proposition 1


INF = jnp.inf


@pytest.mark.parametrize(
    "flt",
    [
        STKF(INF, 1.0, 1e12, 1.0, outputs="all"),
        RBKF(GaussianKernel(INF), GaussianKernel(1e8), outputs="all"),
        RBKF(Barron(2.0), Barron(2.0 - 1e-12), outputs="all"),
        RBKF(PseudoHuber(INF), PseudoHuber(1e12), outputs="all"),
        RBKF(Huber(INF), Huber(1e12), outputs="all"),
        RBKF(None, None, outputs="all"),
        STKF_AR1(INF, 1.0, 1.0, INF, 1.0, 1.0, outputs="all"),
        VBKF(1e13, 1e13, 1.0, fixed_prior=True, shape_increment=0.0, outputs="all"),
    ],
)
def test_proposition_1_infinite_dof_is_kalman_filter(flt):
    model = _model()
    ys = _data(model)
    res = run(flt, model, PRIOR, ys)
    ref = _kf_ref(model, ys)
    np.testing.assert_allclose(res.filtered_means, ref["filtered_means"], rtol=1e-8, atol=1e-8)
    np.testing.assert_allclose(res.filtered_covariances, ref["filtered_covariances"], rtol=1e-8, atol=1e-8)
    np.testing.assert_allclose(res.loglik_increments, ref["loglik_increments"], rtol=1e-8, atol=1e-8)


# ----------------------------------------------------------------------------- Theorem 4


@pytest.mark.parametrize("nu, tau2, iters", [(4.0, 1.0, 4), (jnp.array([1.5, 6.0]), jnp.array([0.7, 1.3]), 7)])
def test_theorem_4_stkf_equals_vbkf_with_fixed_priors(nu, tau2, iters):
    model = _model()
    ys = _data(model)
    stkf = run(STKF(None, 1.0, nu, tau2, max_iter=iters, tol=0.0), model, PRIOR, ys)
    vb_flt = VBKF.student_t_equivalent(nu, tau2, iters)
    vbkf = run(vb_flt, model, PRIOR, ys)
    _close(stkf, vbkf, 1e-8)
    # Through inverse-gamma parameters (α, β⁻) = (ν/2, ντ²/2): λ = β/α = τ² + e²/ν (eq. 18).
    np.testing.assert_allclose(vb_flt.alpha0, 0.5 * np.asarray(nu))
    np.testing.assert_allclose(vb_flt.beta0, 0.5 * np.asarray(nu) * np.asarray(tau2))


def test_theorem_4_authors_vbkf_fixed_is_not_equal():
    # The authors' VBKF_fixed: α = β = 2, λ = 1 + e²/4 + prr/4, first pass at λ = 1.
    model = _model()
    ys = _data(model)
    stkf = run(STKF(None, 1.0, 4.0, 1.0, max_iter=4, tol=0.0), model, PRIOR, ys)
    authors = run(VBKF(2.0, 2.0, 1.0, 4, fixed_prior=True, shape_increment=0.0), model, PRIOR, ys)
    assert np.max(np.abs(stkf.filtered_means - authors.filtered_means)) > 1e-6


# ----------------------------------------------------------------------------- Proposition 2


def test_proposition_2_rho_one_is_stkf():
    model = _model()
    ys = _data(model)
    kw = {"max_iter": 5, "tol": 1e-6}
    ar = run(STKF_AR1(3.0, 1.2, 1.0, jnp.array([4.0, 2.0]), 0.9, 1.0, **kw, outputs="all"), model, PRIOR, ys)
    st_ = run(STKF(3.0, 1.2, jnp.array([4.0, 2.0]), 0.9, **kw), model, PRIOR, ys)
    _close(ar, st_, 1e-12)
    np.testing.assert_array_equal(ar.info["tau2"][-1], [1.2] * N + [0.9] * M)


@pytest.mark.parametrize("rho_c, tau2, iters", [(0.99, 1.0, 4), (0.9, 0.6, 4)])
def test_proposition_2_adaptive_measurement_channels_are_vbkf(rho_c, tau2, iters):
    model = _model()
    ys = _data(model)
    nu = 1.0 / (1.0 - rho_c)  # fixed point of eq. 43
    ar = run(STKF_AR1(INF, 1.0, 1.0, nu, tau2, rho_c, max_iter=iters, tol=0.0, outputs="all"), model, PRIOR, ys)
    vb = VBKF(nu / 2, nu * tau2 / 2, rho_c, iters, start="predicted", covariance_in_iterations=False, outputs="all")
    vb = run(vb, model, PRIOR, ys)
    _close(ar, vb, 1e-8)
    np.testing.assert_allclose(ar.info["tau2"][:, N:], vb.info["lam"], rtol=1e-8)
    np.testing.assert_allclose(ar.info["nu"][:, N:], 2 * vb.info["alpha"], rtol=1e-12)
    assert np.ptp(np.asarray(ar.info["tau2"][:, N:])) > 0.01  # the scale does adapt


def test_theorem_5_steady_state_of_lambda():
    # Scalar random walk with negligible posterior variance (w P wᵀ ≈ 1e-3, Remark 5):
    # E λ → Σ̄ = Σᵍ + 2wPwᵀ ≈ 1, Var λ → 2(1 − ρ)Σ²/(1 + ρ), ν at its fixed point 1/(1 − ρ).
    # (With large w P wᵀ the simulated mean stays near Σᵍ, not Σᵍ + 2wPwᵀ: the posterior
    # residual is not independent of the estimation error, as the proof assumes.)
    rng = np.random.default_rng(1)
    steps, rho, q = 20_000, 0.95, 1e-6
    x = np.cumsum(rng.normal(size=steps) * np.sqrt(q))
    ys = (x + rng.normal(size=steps))[:, None]
    model = jdrkf.LinearModel(F=np.eye(1), H=np.eye(1), Q=q * np.eye(1), R=np.eye(1))
    prior = jdrkf.Gaussian(jnp.zeros(1), jnp.eye(1))
    res = run(STKF_AR1(INF, 1.0, 1.0, 1 / (1 - rho), 1.0, rho, max_iter=10, tol=1e-10, outputs="all"), model, prior, ys)
    lam = np.asarray(res.info["tau2"][steps // 4 :, 1])
    wpw = float(np.mean(res.filtered_covariances[steps // 4 :, 0, 0]))
    assert wpw < 2e-3
    np.testing.assert_allclose(lam.mean(), 1 + 2 * wpw, rtol=0.03)
    np.testing.assert_allclose(lam.var(), 2 * (1 - rho) * (1 + wpw) ** 2 / (1 + rho), rtol=0.1)


def test_stkf_ar2_switch():
    model = _model()
    ys = _data(model, outliers=False)
    ys[10] = ys[10] + 200.0
    base = {"nu_x": INF, "nu_y": 20.0, "rho_y": 0.95}
    ar1 = run(STKF_AR1(**base, outputs="all"), model, PRIOR, ys)
    never = run(STKF_AR2(**base, xi=INF), model, PRIOR, ys)
    _close(ar1, never, 0.0)
    ar2 = run(STKF_AR2(**base, eta=1.0, outputs="all"), model, PRIOR, ys)
    tau2 = np.asarray(ar2.info["tau2"][:, N:])
    np.testing.assert_array_equal(tau2[10], tau2[9])  # the outlier's update is reverted
    assert np.all(np.asarray(ar1.info["tau2"][10, N:]) > 3 * tau2[10])
    # The authors' gate on ‖e_y‖² (student_forward_adap_y2) also skips the outlier's update.
    gated = run(STKF_AR1(**base, gate=40.0, outputs="all"), model, PRIOR, ys)
    tau2 = np.asarray(gated.info["tau2"][:, N:])
    np.testing.assert_array_equal(tau2[10], tau2[9])
    np.testing.assert_array_equal(gated.info["tau2"][:10], ar1.info["tau2"][:10])
    # Default ξ = η sqrt(2ν²/(ν+1)³) τ²: η = 0 reverts every update.
    frozen = run(STKF_AR2(**base, eta=1e-300, outputs="all"), model, PRIOR, ys)
    np.testing.assert_allclose(frozen.info["tau2"][:, N:], 1.0)


# ----------------------------------------------------------------------------- robustness


@pytest.mark.parametrize(
    "flt",
    [
        STKF(),
        RBKF(None, GaussianKernel(2.0)),
        RBKF(None, Barron(0.5)),
        RBKF(None, Huber(1.345), max_iter=10),
        STKF_AR2(nu_y=4.0, rho_y=0.98),
    ],
)
def test_outlier_moves_robust_filters_less(flt):
    model = _model()
    ys = _data(model, outliers=False)
    sigma = float(np.sqrt(model.R[0, 0]))

    def shift(f, size):
        bad = ys.copy()
        bad[12, 0] += size * sigma
        return np.linalg.norm(run(f, model, PRIOR, bad).filtered_means[12] - run(f, model, PRIOR, ys).filtered_means[12])

    kf = jdrkf.KalmanFilter()
    # Redescending losses reject a 100σ outlier; the monotone Huber loss bounds its
    # influence: its shift hardly grows from 100σ to 1000σ.
    assert shift(flt, 100.0) < 0.25 * shift(kf, 100.0)
    assert shift(flt, 1000.0) < 0.03 * shift(kf, 1000.0)


def test_jit_vmap_agree_and_missing_data():
    model = _model()
    ys = np.stack([_data(model, seed=s, steps=15) for s in range(3)])
    ys[1, 4, 0] = np.nan
    flt = STKF(3.0, 1.0, 4.0, 1.0, max_iter=5, tol=1e-8, throw=False, outputs="all")
    batch = eqx.filter_jit(jax.vmap(lambda y: flt(model, PRIOR, y, observed=~jnp.isnan(y))))(ys)
    for i in range(3):
        one = run(flt, model, PRIOR, ys[i], ~np.isnan(ys[i]))
        np.testing.assert_allclose(batch.filtered_means[i], one.filtered_means, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(batch.filtered_covariances[i], one.filtered_covariances, rtol=1e-12, atol=1e-12)
    assert bool(jnp.all(batch.result == jdrkf.RESULTS.successful))
    # All channels missing: the update is the prediction.
    ys2 = ys[0].copy()
    ys2[5] = np.nan
    res = run(flt, model, PRIOR, ys2, ~np.isnan(ys2))
    np.testing.assert_allclose(res.filtered_means[5], res.predicted_means[5], rtol=1e-12)
    for f in (STKF_AR1(), VBKF()):
        assert np.all(np.isfinite(run(f, model, PRIOR, ys2, ~np.isnan(ys2)).filtered_means))


@settings(max_examples=10, deadline=None)
@given(
    nu=st.floats(0.3, 50.0),
    tau2=st.floats(0.2, 5.0),
    rho=st.floats(0.8, 1.0),
    seed=st.integers(0, 10_000),
)
def test_covariances_symmetric_psd(nu, tau2, rho, seed):
    model = _model()
    ys = _data(model, seed=seed, steps=15)
    for flt in (
        STKF(nu, tau2, nu, tau2, throw=False),
        STKF_AR1(nu, tau2, rho, nu, tau2, rho, throw=False),
        VBKF(nu, nu * tau2, rho, throw=False),
    ):
        res = run(flt, model, PRIOR, ys)
        c = np.asarray(res.filtered_covariances)
        np.testing.assert_array_equal(c, np.swapaxes(c, -1, -2))
        assert np.min(np.linalg.eigvalsh(c)) > 0
        assert res.result == jdrkf.RESULTS.successful


# ----------------------------------------------------------------------------- gradients


def _fd(f, x, h):
    return (f(x + h) - f(x - h)) / (2 * h)


@pytest.mark.parametrize(
    "flt, fields",
    [
        # Early-stopped (bounded while loop) and fixed-iteration modes; STKF-AR1 runs the
        # STKF update (Algorithm 1) with recursive ν, τ².
        (STKF(jnp.array([3.0, 1.5]), 1.0, 2.5, 1.3, max_iter=30, tol=1e-6), ("nu_x", "tau2_x", "nu_y", "tau2_y")),
        (
            STKF_AR1(jnp.array([3.0, 1.5]), 1.1, 1.0, 2.5, 0.8, 0.9, max_iter=3, fixed_iterations=True),
            ("nu_x", "tau2_x", "nu_y", "tau2_y", "rho_y"),
        ),
        (VBKF(3.0, 2.0, 0.95, 3), ("alpha0", "beta0", "rho")),
        (VBKF(3.0, 2.0, 0.95, 3, covariance="nominal"), ("alpha0", "beta0", "rho")),
    ],
)
def test_gradients_match_finite_differences(flt, fields):
    model = _model(n=2, m=1)  # small: reverse-mode compilation dominates the cost
    ys = _data(model, steps=10)
    prior = jdrkf.Gaussian(jnp.zeros(2), jnp.eye(2))

    def loss(f):
        res = f(model, prior, ys)
        return jnp.sum(res.filtered_means**2) + jnp.sum(res.filtered_covariances)

    grads = eqx.filter_jit(eqx.filter_grad(loss))(flt)
    loss_j = eqx.filter_jit(loss)
    for field in fields:
        v = getattr(flt, field)
        h = 1e-6 * v  # directional central difference along h
        def at(x, field=field):
            return eqx.tree_at(lambda f: getattr(f, field), flt, x)

        fd = (loss_j(at(v + h)) - loss_j(at(v - h))) / 2
        np.testing.assert_allclose(jnp.sum(getattr(grads, field) * h), fd, rtol=1e-5, err_msg=field)


def test_forward_mode_derivative_of_early_stopped_loop():
    model = _model()
    ys = _data(model, steps=10)
    flt = STKF(None, 1.0, 2.5, 1.3, max_iter=50, tol=1e-13)

    def f(nu):
        return jnp.sum(eqx.tree_at(lambda f: f.nu_y, flt, nu)(model, PRIOR, ys).filtered_means ** 2)

    nu = jnp.asarray(2.5)
    _, jvp = jax.jit(lambda nu: jax.jvp(f, (nu,), (jnp.ones(()),)))(nu)
    fj = jax.jit(f)
    np.testing.assert_allclose(jvp, (fj(nu + 1e-5) - fj(nu - 1e-5)) / 2e-5, rtol=1e-5)


# ----------------------------------------------------------------------------- validation


@pytest.mark.parametrize(
    "make, match",
    [
        (lambda: StudentT(-1.0), "nu"),
        (lambda: StudentT(4.0, 0.0), "tau2"),
        (lambda: GaussianKernel(jnp.nan), "sigma"),
        (lambda: Barron(2.5), "sigma"),
        (lambda: Huber(0.0), "k"),
        (lambda: STKF(nu_y=-2.0), "nu_y"),
        (lambda: STKF(tau2_x=jnp.ones((2, 2))), "tau2_x"),
        (lambda: STKF(max_iter=0), "max_iter"),
        (lambda: STKF(tol=-1.0), "tol"),
        (lambda: STKF(covariance="joseph"), "covariance"),
        (lambda: RBKF(process_weight="huber"), "process_weight"),
        (lambda: STKF_AR1(rho_y=1.5), "rho_y"),
        (lambda: STKF_AR1(rho_x=0.0), "rho_x"),
        (lambda: STKF_AR2(eta=1.0, xi=1.0), "eta or xi"),
        (lambda: STKF_AR1(gate=-1.0), "gate"),
        (lambda: VBKF(alpha0=0.0), "alpha0"),
        (lambda: VBKF(num_iter=0), "num_iter"),
        (lambda: VBKF(start="x"), "start"),
    ],
)
def test_bad_arguments_raise(make, match):
    with pytest.raises(ValueError, match=match):
        make()


@pytest.mark.parametrize(
    "flt, match",
    [
        (STKF(nu_y=jnp.ones(3)), "nu_y"),
        (RBKF(StudentT(jnp.ones(2))), "process_weight.nu"),
        (STKF_AR1(rho_y=jnp.full(3, 0.9)), "rho_y"),
        (VBKF(beta0=jnp.ones(5)), "beta0"),
    ],
)
def test_channel_count_mismatch_raises(flt, match):
    model = _model()
    with pytest.raises(ValueError, match=match):
        flt(model, PRIOR, _data(model, steps=3))
