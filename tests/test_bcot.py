"""BCOT DR Kalman filter (Han 2023; docs/math/steady_state.md) against independent oracles:
a cvxpy + Clarabel SDP of the per-step problem (`bcot_oracle.py`), SciPy Bures
distances, the NumPy Kalman filter (`oracles.py`) and finite differences."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jdrkf
from jdrkf.filters._bcot import BCOTKF
from jdrkf.sets import bcot_worst_case

from bcot_oracle import bcot_sdp, budget, posterior_trace
from oracles import numpy_kalman_filter

# One compilation per filter structure / data shape (the radius is a traced field). The
# NaN entries of the test data are missing observations.
run = eqx.filter_jit(lambda flt, model, prior, ys, inputs: flt(model, prior, ys, inputs=inputs, observed=~jnp.isnan(ys)))


def _spd(rng, d, floor):
    a = rng.normal(size=(d, d))
    return a @ a.T / d + floor * np.eye(d)


def _instance(rng, n, m):
    a = rng.normal(size=(n, n))
    a = 0.95 * a / max(1.0, np.max(np.abs(np.linalg.eigvals(a))))
    return _spd(rng, n, 0.5), _spd(rng, n, 0.2), _spd(rng, m, 0.3), a, rng.normal(size=(m, n))


def _model(rng, n=3, m=2, p=1):
    f = rng.normal(size=(n, n))
    f = 0.9 * f / max(1.0, np.max(np.abs(np.linalg.eigvals(f))))
    return jdrkf.LinearModel(
        F=f,
        H=rng.normal(size=(m, n)),
        Q=_spd(rng, n, 0.2),
        R=_spd(rng, m, 0.3),
        G=rng.normal(size=(n, n)),  # G Q Gᵀ must be positive definite for BCOT
        B=rng.normal(size=(n, p)),
        process_mean=rng.normal(size=n),
        noise_mean=rng.normal(size=m),
    )


SHAPES = [(2, 1), (4, 2)]  # few shapes: each one compiles the solver once


@pytest.mark.parametrize("n, m", SHAPES)
def test_step_matches_sdp(n, m):
    # 10 random instances in total (5 per shape). The SDP value is the oracle; our
    # worst case is also checked to be feasible, budget-active and to attain the value,
    # with SciPy's sqrtm-based Bures distance.
    rng = np.random.default_rng(100 + 10 * n + m)
    for radius in (0.02, 0.3, 1.0, 4.0, 10.0):
        sp, qp, rp, a, c = _instance(rng, n, m)
        sol = bcot_worst_case(sp, qp, rp, a, c, radius)
        ref = bcot_sdp(sp, qp, rp, a, c, radius)
        assert bool(sol.converged) and int(sol.iterations) <= 30
        assert float(sol.residual) < 1e-10 and abs(float(sol.gap)) < 1e-10 * ref["value"]
        np.testing.assert_allclose(float(sol.value), ref["value"], rtol=1e-6)
        sig, q, r = (np.asarray(x) for x in (sol.prior_cov, sol.process_cov, sol.noise_cov))
        assert budget(sig, q, r, sp, qp, rp, a, c) == pytest.approx(radius, rel=1e-8)
        assert posterior_trace(sig, q, r, a, c) == pytest.approx(ref["value"], rel=1e-6)
        # The SDP's own maximizer agrees to its (lower) primal accuracy.
        for ours, theirs in ((sig, ref["Sigma"]), (q, ref["Q"]), (r, ref["R"])):
            np.testing.assert_allclose(ours, theirs, atol=2e-3 * np.max(np.abs(theirs)))
        # Worst-case gain is the Kalman gain of the worst case.
        p = a @ sig @ a.T + q
        np.testing.assert_allclose(sol.gain, p @ c.T @ np.linalg.inv(c @ p @ c.T + r), atol=1e-9)


def test_value_monotone_in_radius():
    rng = np.random.default_rng(7)
    sp, qp, rp, a, c = _instance(rng, 4, 2)
    radii = [0.0, 1e-8, 1e-4, 0.01, 0.1, 0.5, 1.0, 3.0, 10.0, 100.0]
    sols = [bcot_worst_case(sp, qp, rp, a, c, r) for r in radii]
    assert all(bool(sol.converged) for sol in sols)
    kf = posterior_trace(sp, qp, rp, a, c)  # the radius-0 value is the Kalman filter's
    values = np.array([float(sol.value) for sol in sols])
    assert values[0] == pytest.approx(kf, rel=1e-13)
    np.testing.assert_array_equal(np.asarray(sols[0].prior_cov), sp)  # nominal, exactly
    np.testing.assert_array_equal(np.asarray(sols[0].noise_cov), rp)
    assert np.all(values[1:] >= kf) and np.all(np.diff(values) > 0)
    # Large budgets: the multiplier γ* = df*/dr decreases towards 1 (f* ≈ r for r → ∞).
    mult = np.array([float(sol.multiplier) for sol in sols[1:]])
    assert np.all(np.diff(mult) < 0) and 1.0 < mult[-1] < 1.2
    # An iteration cap that is too small is reported (same compiled solver: max_iter is traced).
    assert not bool(bcot_worst_case(sp, qp, rp, a, c, 3.0, max_iter=1).converged)


def test_derivatives_by_implicit_function_theorem():
    rng = np.random.default_rng(3)
    sp, qp, rp, a, c = _instance(rng, 4, 2)

    def outputs(r):
        sol = bcot_worst_case(sp, qp, rp, a, c, r)
        return jnp.stack([sol.value, sol.prior_cov[0, 1], sol.process_cov[1, 2], sol.noise_cov[0, 1]])

    jac = jax.jit(jax.jacfwd(outputs))
    for r in (1e-3, 0.2, 2.0):
        h = 1e-5 * r
        fd = (outputs(r + h) - outputs(r - h)) / (2 * h)
        g = jac(jnp.asarray(r))
        np.testing.assert_allclose(g[0], fd[0], rtol=1e-6)
        np.testing.assert_allclose(g[1:], fd[1:], rtol=1e-5, atol=1e-9 * np.max(np.abs(fd)))
        # Envelope theorem: df*/dr = γ* (the budget multiplier).
        np.testing.assert_allclose(g[0], bcot_worst_case(sp, qp, rp, a, c, r).multiplier, rtol=1e-10)
    # At radius 0 the value grows like √radius: the derivative is not silently zero.
    assert np.all(np.isnan(jac(jnp.asarray(0.0))))


@pytest.mark.slow
def test_missing_component_equals_reduced_problem():
    # A NaN measurement decouples its row (H row 0, unit nominal variance): same worst
    # case as the problem without that row.
    rng = np.random.default_rng(11)
    sp, qp, rp, a, c = _instance(rng, 3, 2)
    c_masked = c.copy()
    c_masked[1] = 0.0
    r_masked = np.diag([rp[0, 0], 1.0])
    full = bcot_worst_case(sp, qp, r_masked, a, c_masked, 0.5)
    reduced = bcot_worst_case(sp, qp, rp[:1, :1], a, c[:1], 0.5)
    np.testing.assert_allclose(full.value, reduced.value, rtol=1e-10)
    np.testing.assert_allclose(full.prior_cov, reduced.prior_cov, atol=1e-10)
    np.testing.assert_allclose(full.noise_cov[:1, :1], reduced.noise_cov, atol=1e-10)
    np.testing.assert_allclose(full.noise_cov[1, 1], 1.0, atol=1e-10)


def _data(rng, model, steps=12):
    ys = rng.normal(size=(steps, model.obs_dim))
    ys[3, 1] = np.nan
    ys[7, :] = np.nan
    inputs = rng.normal(size=(steps, model.B.shape[1]))
    prior = jdrkf.Gaussian(rng.normal(size=model.state_dim), _spd(rng, model.state_dim, 0.5))
    return prior, ys, inputs


def test_zero_radius_is_kalman_filter():
    rng = np.random.default_rng(0)
    model = _model(rng)
    prior, ys, inputs = _data(rng, model)
    res = run(BCOTKF(0.0, outputs="all"), model, prior, ys, inputs)
    ref = numpy_kalman_filter(prior.mean, prior.cov, ys, model.F, model.H, model.Q, model.R, G=model.G,
                              B=model.B, inputs=inputs, process_mean=model.process_mean, noise_mean=model.noise_mean)
    for key in ("filtered_means", "filtered_covariances", "predicted_means", "predicted_covariances", "loglik_increments"):
        np.testing.assert_allclose(getattr(res, key), ref[key], rtol=1e-10, atol=1e-10)


def test_filter_step_uses_worst_case_and_predicts_once():
    rng = np.random.default_rng(1)
    model = _model(rng)
    prior, ys, inputs = _data(rng, model)
    radius = 0.3
    res = run(BCOTKF(radius, outputs="all"), model, prior, ys, inputs)
    assert res.result == jdrkf.RESULTS.successful
    # Step 1 from the prior: the SDP of (Σ_p, G Q Gᵀ, R) gives the posterior trace.
    f, g, h = (np.asarray(x) for x in (model.F, model.G, model.H))
    qp = g @ np.asarray(model.Q) @ g.T
    ref = bcot_sdp(np.asarray(prior.cov), qp, np.asarray(model.R), f, h, radius)
    np.testing.assert_allclose(np.trace(res.filtered_covariances[0]), ref["value"], rtol=1e-6)
    # The mean is predicted once: x⁻ = F x̂ + B u + G μ_w at every step.
    means = np.vstack([prior.mean, np.asarray(res.filtered_means[:-1])])
    x_pred = means @ f.T + inputs @ np.asarray(model.B).T + g @ np.asarray(model.process_mean)
    np.testing.assert_allclose(res.predicted_means, x_pred, rtol=1e-12, atol=1e-12)
    # Update with the reported worst case, recomputed in NumPy (step 2: all observed).
    k = 1
    sig, q, r = (np.asarray(res.info[key][k]) for key in ("prior_cov", "process_cov", "noise_cov"))
    p = f @ sig @ f.T + q
    gain = p @ h.T @ np.linalg.inv(h @ p @ h.T + r)
    innov = ys[k] - np.asarray(model.noise_mean) - h @ x_pred[k]
    np.testing.assert_allclose(res.filtered_means[k], x_pred[k] + gain @ innov, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(res.filtered_covariances[k], (np.eye(3) - gain @ h) @ p, rtol=1e-9, atol=1e-10)
    np.testing.assert_allclose(res.predicted_covariances[k], p, rtol=1e-12, atol=1e-12)
    # The worst case lies on the budget around the previous posterior.
    hr_budget = budget(sig, q, r, np.asarray(res.filtered_covariances[k - 1]), qp, np.asarray(model.R), f, h)
    assert hr_budget == pytest.approx(radius, rel=1e-8)
    np.testing.assert_allclose(res.info["value"], np.trace(res.filtered_covariances, axis1=1, axis2=2), rtol=1e-10)
    # Step 4 has y[1] missing: its posterior trace is the SDP value of the problem
    # without that row (around the previous posterior).
    ref = bcot_sdp(np.asarray(res.filtered_covariances[2]), qp, np.asarray(model.R)[:1, :1], f, h[:1], radius)
    np.testing.assert_allclose(np.trace(res.filtered_covariances[3]), ref["value"], rtol=1e-6)
    # Posterior trace at the first step grows with the radius; radius 0 = KF.
    traces = [np.trace(run(BCOTKF(rad), model, prior, ys, inputs).filtered_covariances[0]) for rad in (0.0, 0.1, 0.3, 1.0)]
    assert np.all(np.diff(traces) > 0)


def test_filter_vmap_over_runs_and_jit():
    rng = np.random.default_rng(2)
    model = _model(rng)
    prior, ys, inputs = _data(rng, model)
    ys_runs = np.stack([ys, ys + rng.normal(size=ys.shape), ys - 1.0])
    flt = BCOTKF(0.5, outputs="all")
    batched = eqx.filter_jit(jax.vmap(lambda y: flt(model, prior, y, inputs=inputs, observed=~jnp.isnan(y))))(ys_runs)
    assert batched.filtered_means.shape == (3, 12, 3)
    for i in range(3):
        one = run(flt, model, prior, ys_runs[i], inputs)
        np.testing.assert_allclose(batched.filtered_means[i], one.filtered_means, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(batched.filtered_covariances[i], one.filtered_covariances, rtol=1e-12, atol=1e-12)
    assert np.all(batched.result == jdrkf.RESULTS.successful)
    assert np.all(np.asarray(batched.info["iterations"]) <= 30)


@pytest.mark.slow
def test_not_converged_is_reported():
    rng = np.random.default_rng(4)
    model = _model(rng)
    prior, ys, inputs = _data(rng, model)
    res = run(BCOTKF(2.0, max_iter=1, throw=False), model, prior, ys, inputs)
    assert res.result == jdrkf.RESULTS.solver_not_converged


def test_bad_input():
    with pytest.raises(ValueError, match="radius"):
        BCOTKF(-0.1)
    with pytest.raises(ValueError, match="radius"):
        BCOTKF(float("nan"))
    with pytest.raises(ValueError, match="radius"):
        BCOTKF(np.ones(2))
    with pytest.raises(ValueError, match="max_iter"):
        BCOTKF(0.1, max_iter=0)
    eye2, eye1 = np.eye(2), np.eye(1)
    with pytest.raises(ValueError, match="C has shape"):
        bcot_worst_case(eye2, eye2, eye1, eye2, np.ones((1, 3)), 0.1)
    with pytest.raises(ValueError, match="A has shape"):
        bcot_worst_case(eye2, eye2, eye1, np.eye(3), np.ones((1, 2)), 0.1)
    with pytest.raises(ValueError, match="process_cov has shape"):
        bcot_worst_case(eye2, np.eye(3), eye1, eye2, np.ones((1, 2)), 0.1)
    with pytest.raises(ValueError, match="radius"):
        bcot_worst_case(eye2, eye2, eye1, eye2, np.ones((1, 2)), -1.0)


@pytest.mark.slow
def test_filter_gradients():
    # Through the whole filter: d loss / d radius vs central differences (r > 0), and at
    # radius 0 the derivative in Q equals the Kalman filter's.
    rng = np.random.default_rng(0)
    model = _model(rng)
    prior, ys, inputs = _data(rng, model)

    def loss(flt, mdl):
        res = flt(mdl, prior, ys, inputs=inputs, observed=~np.isnan(ys))
        return jnp.sum(res.filtered_means**2) + jnp.sum(jnp.trace(res.filtered_covariances, axis1=1, axis2=2))

    with_q = eqx.filter_jit(jax.grad(lambda q, flt: loss(flt, eqx.tree_at(lambda m: m.Q, model, q))))
    np.testing.assert_allclose(with_q(model.Q, BCOTKF(0.0)), with_q(model.Q, jdrkf.KalmanFilter()), atol=1e-10)
    value = eqx.filter_jit(lambda r: loss(BCOTKF(r), model))
    grad = eqx.filter_jit(jax.grad(lambda r: loss(BCOTKF(r), model)))
    for r in (0.05, 0.3):
        fd = (value(jnp.asarray(r + 1e-6)) - value(jnp.asarray(r - 1e-6))) / 2e-6
        np.testing.assert_allclose(grad(jnp.asarray(r)), fd, rtol=1e-6)


def test_bcot_set_object_matches_the_function_and_checks_its_radius():
    """`jdrkf.sets.BCOT(radius).worst_case` is `bcot_worst_case` without the eager checks;
    the filter holds the set (`BCOTKF(r).set.radius == r`, `.radius` reads it)."""
    sp, qp, rp, a, c = _instance(np.random.default_rng(7), 2, 1)
    ref = bcot_worst_case(sp, qp, rp, a, c, 0.4)
    sol = jdrkf.sets.BCOT(0.4).worst_case(*(jnp.asarray(x) for x in (sp, qp, rp, a, c)), 100)
    for field in ("prior_cov", "process_cov", "noise_cov", "value"):
        np.testing.assert_allclose(getattr(sol, field), getattr(ref, field), rtol=1e-12, atol=1e-14)
    assert bool(sol.converged)
    flt = BCOTKF(0.4)
    assert isinstance(flt.set, jdrkf.sets.BCOT) and float(flt.radius) == 0.4
    assert bool(jdrkf.sets.BCOT(0.0).valid())
    assert not bool(jax.jit(lambda r: eqx.tree_at(lambda s: s.radius, jdrkf.sets.BCOT(0.1), r).valid())(-0.1))
    with pytest.raises(ValueError, match="radius"):
        jdrkf.sets.BCOT(-1.0)
