"""Input checks of issue 18 (items 3 and 4): positive-semidefinite covariances, no silent
clipping in `simulate`, integer counts, the failure signal of the steady-state Kalman
gain and the argument checks of `jdrkf.tuning.fit`. Oracles: NumPy eigenvalues, the
tolerance formula stated in `check_covariance`, sample moments with their standard
errors, SciPy's DARE solver and a PBH detectability test."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg

import jdrkf
from jdrkf import tuning
from jdrkf.sets import EpsContamination, Moment


def _with_spectrum(rng, lam):
    """Symmetric matrix with eigenvalues `lam` and a random orthogonal eigenbasis."""
    v, _ = np.linalg.qr(rng.normal(size=(len(lam), len(lam))))
    return (v * np.asarray(lam)) @ v.T


def test_indefinite_covariances_are_rejected_and_round_off_accepted(rng):
    n = 3
    bad = np.array([[1.0, 2.0, 0.0], [2.0, 1.0, 0.0], [0.0, 0.0, 1.0]])  # nonnegative diagonal, λ_min = −1
    lam_min = np.linalg.eigvalsh(bad)[0]
    F, H = np.eye(n), np.ones((1, n))
    with pytest.raises(ValueError, match=rf"Q must be positive semidefinite: Q has smallest eigenvalue {lam_min:.6g}"):
        jdrkf.LinearModel(F, H, bad, np.eye(1))
    with pytest.raises(ValueError, match="R must be positive semidefinite"):
        jdrkf.LinearModel(np.eye(2), np.eye(2), np.eye(2), bad[:2, :2])
    with pytest.raises(ValueError, match="cov must be positive semidefinite"):
        jdrkf.Gaussian(np.zeros(n), bad)
    with pytest.raises(ValueError, match="cov must be positive semidefinite"):
        jdrkf.GaussianNoise(bad)
    # time-varying: the offending step is named
    qs = np.stack([np.eye(n)] * 5)
    qs[3] = bad
    with pytest.raises(ValueError, match=r"Q\[3\] has smallest eigenvalue"):
        jdrkf.LinearModel(F, H, qs, np.eye(1))
    # Tolerance stated in the docstring: λ_min ≥ −100 · n · eps(dtype) · |λ|_max.
    for dtype in (np.float64, np.float32):
        tol = 100 * n * np.finfo(dtype).eps
        inside = _with_spectrum(rng, [1.0, 0.5, -0.1 * tol]).astype(dtype)
        outside = _with_spectrum(rng, [1.0, 0.5, -10 * tol]).astype(dtype)
        jdrkf.GaussianNoise(jnp.asarray(inside))
        with pytest.raises(ValueError, match="positive semidefinite"):
            jdrkf.GaussianNoise(jnp.asarray(outside))
        # rank-deficient PSD (G Gᵀ, G tall) formed in this precision is accepted
        G = rng.normal(size=(6, 2)).astype(dtype)
        Q = jnp.asarray(G) @ jnp.asarray(G).T
        assert np.linalg.eigvalsh(np.asarray(Q, np.float64))[:4].max() < 1e-3 * float(jnp.max(Q))
        jdrkf.LinearModel(jnp.eye(6, dtype=dtype), jnp.ones((1, 6), dtype), Q, jnp.eye(1, dtype=dtype))


def test_simulate_samples_singular_covariance_exactly_and_never_clips(rng):
    n, runs, steps = 3, 4000, 5
    G = np.array([[1.0], [2.0], [-1.0]])
    Q = G @ G.T  # rank one
    prior = jdrkf.Gaussian(np.zeros(n), np.eye(n))
    # F = 0: x_k = w_k, so the states are draws of N(0, Q)
    model = jdrkf.LinearModel(np.zeros((n, n)), np.ones((1, n)), Q, np.eye(1))
    xs = np.asarray(jdrkf.simulate(jax.random.key(0), model, prior, steps, runs).states).reshape(-1, n)
    N = xs.shape[0]
    cov = xs.T @ xs / N
    se = np.sqrt((np.outer(np.diag(Q), np.diag(Q)) + Q**2) / N)  # std. error of each entry
    assert np.all(np.abs(cov - Q) < 5 * se)
    # the null space of Q gets no variance (to round-off: an eigenvalue ~eps of Q^½ Q^½)
    null = scipy.linalg.null_space(G.T)
    assert np.max(np.abs(null.T @ cov @ null)) < 1e-13 * np.max(Q)

    bad = np.array([[1.0, 2.0, 0.0], [2.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    # a concrete indefinite Q that bypassed the model's checks (eqx.tree_at) is still an error
    edited = eqx.tree_at(lambda m: m.Q, model, jnp.asarray(bad))
    with pytest.raises(ValueError, match="model.Q must be positive semidefinite"):
        jdrkf.simulate(jax.random.key(0), edited, prior, steps, 2)
    # a traced indefinite Q gives NaN draws, not draws from a clipped Q
    sim = jax.jit(lambda q: jdrkf.simulate(jax.random.key(0), jdrkf.LinearModel(np.zeros((n, n)), np.ones((1, n)), q, np.eye(1)), prior, steps, 2).states)
    assert np.all(np.isnan(sim(jnp.asarray(bad))))
    np.testing.assert_allclose(sim(jnp.asarray(Q)), np.asarray(jdrkf.simulate(jax.random.key(0), model, prior, steps, 2).states), atol=1e-12)


def test_counts_must_be_positive_integers():
    model = jdrkf.LinearModel(np.eye(2), np.ones((1, 2)), np.eye(2), np.eye(1))
    prior = jdrkf.Gaussian(np.zeros(2), np.eye(2))
    key = jax.random.key(0)
    for bad in (2.7, 2.0, True, "3", None):
        with pytest.raises(ValueError, match="num_steps"):
            jdrkf.simulate(key, model, prior, bad, 2)
        with pytest.raises(ValueError, match="num_runs"):
            jdrkf.simulate(key, model, prior, 3, bad)
    tr = jdrkf.simulate(key, model, prior, np.int64(3), np.array(2))
    assert tr.states.shape == (2, 3, 2)


def _pbh_detectable(F, H):
    """(F, H) detectable iff [λI − F; H] has full column rank for every |λ| ≥ 1 eigenvalue."""
    n = F.shape[0]
    return all(
        np.linalg.matrix_rank(np.vstack([lam * np.eye(n) - F, H])) == n for lam in np.linalg.eigvals(F) if abs(lam) >= 1
    )


def _dare_residual(P, F, H, Q, R):
    return F @ P @ F.T - F @ P @ H.T @ np.linalg.solve(H @ P @ H.T + R, H @ P @ F.T) + Q - P


def test_steady_state_gain_failure_signal(rng):
    n = 2
    prior = jdrkf.Gaussian(np.zeros(n), np.eye(n))
    ys = rng.normal(size=(8, 1))
    healthy = (np.array([[0.9, 0.2], [0.0, 0.5]]), np.array([[1.0, 0.0]]), np.eye(n), np.eye(1))
    cases = {
        # unstable mode 1.5 not seen by H: no stabilizing solution (the DARE solver gives NaN)
        "undetectable": (np.diag([0.9, 1.5]), np.array([[1.0, 0.0]]), np.eye(n), np.eye(1)),
        # unobserved unstable mode without noise: a finite PSD DARE solution, but F(I − KH) unstable
        "undetectable, finite P": (np.diag([0.5, 2.0]), np.array([[1.0, 0.0]]), np.diag([1.0, 0.0]), np.eye(1)),
        # detectable, but no noise excites the unstable mode: P = 0 solves the DARE; the
        # stabilizing solution is diag(3, 0) (scalar DARE p = 4p − 4p²/(p + 1) on mode 2)
        "wrong solution": (np.diag([2.0, 0.5]), np.array([[1.0, 0.0]]), np.zeros((n, n)), np.eye(1)),
    }
    F, H, Q, R = healthy
    ss = jdrkf.SteadyStateKalmanFilter.solve(jdrkf.LinearModel(*healthy))
    assert bool(ss.converged)
    np.testing.assert_allclose(ss.predicted_cov, scipy.linalg.solve_discrete_are(F.T, H.T, Q, R), atol=1e-10)
    assert not _pbh_detectable(*cases["undetectable"][:2]) and not _pbh_detectable(*cases["undetectable, finite P"][:2])
    assert _pbh_detectable(*cases["wrong solution"][:2])
    for name, (F, H, Q, R) in cases.items():
        model = jdrkf.LinearModel(F, H, Q, R)
        ss = jdrkf.SteadyStateKalmanFilter.solve(model)
        assert not bool(ss.converged), name
        if name == "wrong solution":
            p_star = np.diag([3.0, 0.0])
            np.testing.assert_allclose(_dare_residual(p_star, F, H, Q, R), 0.0, atol=1e-12)
            assert np.max(np.abs(np.asarray(ss.predicted_cov) - p_star)) > 1.0  # the returned P is not the steady state
        with pytest.raises(ValueError, match="model: no stabilizing steady-state Kalman gain"):
            jdrkf.SteadyStateKalmanFilter(throw=False)(model, prior, ys)
        res = jax.jit(lambda m: jdrkf.SteadyStateKalmanFilter(throw=False)(m, prior, ys))(model)
        assert res.result == jdrkf.RESULTS.solver_not_converged, name
    # under vmap the flag is per model, and healthy models keep their results
    stacked = jax.tree.map(lambda *x: jnp.stack(x), jdrkf.LinearModel(*healthy), jdrkf.LinearModel(*cases["undetectable"]))
    flags = jax.vmap(lambda m: jdrkf.SteadyStateKalmanFilter.solve(m).converged)(stacked)
    np.testing.assert_array_equal(flags, [True, False])
    res = jax.vmap(lambda m: jdrkf.SteadyStateKalmanFilter(throw=False)(m, prior, ys))(stacked)
    np.testing.assert_array_equal(res.result._value, [jdrkf.RESULTS.successful._value, jdrkf.RESULTS.solver_not_converged._value])


def test_fit_rejects_bad_steps_and_start_values_and_keeps_the_start():
    flt = jdrkf.DRKF(state_set=Moment(1.02), noise_set=Moment(1.03), outliers=EpsContamination(0.05))

    def objective(f):
        return (f.outliers.eps - 0.3) ** 2

    where = lambda f: f.outliers.eps
    for bad in (-1, 0, 2.7, True):
        with pytest.raises(ValueError, match="steps"):
            tuning.fit(flt, objective, where=where, bounds=(0.0, 0.5), steps=bad)
    with pytest.raises(ValueError, match=r"start value of filter\.outliers\.eps is 0\.05, outside its bounds \[0\.1, 0\.5\]"):
        tuning.fit(flt, objective, where=where, bounds=(0.1, 0.5), steps=1)
    with pytest.raises(ValueError, match=r"filter\.state_set\.theta2 is 1\.02, outside"):
        tuning.fit(flt, objective, where=lambda f: f.state_set.theta2, bounds=(1.05, None), steps=1)
    with pytest.raises(ValueError, match="shared=True.*start values differ"):
        tuning.fit(flt, objective, where=lambda f: (f.state_set.theta2, f.noise_set.theta2), shared=True, bounds=(1.0, None), steps=1)
    # a start inside the bounds but close to one is kept (not moved 1e-3 inside)
    near = jdrkf.DRKF(state_set=Moment(1.02), noise_set=Moment(1.03), outliers=EpsContamination(2e-4))
    res = tuning.fit(near, objective, where=where, bounds=(0.0, 0.5), steps=1)
    np.testing.assert_allclose(res.params[0, 0], 2e-4, rtol=1e-9)
    res = tuning.fit(near, objective, where=where, bounds=(0.0, np.inf), steps=1)
    np.testing.assert_allclose(res.params[0, 0], 2e-4, rtol=1e-9)
