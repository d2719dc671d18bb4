"""`converged` is set only by a check a wrong answer cannot pass.

Each solver is stopped early (zero or one iteration) and must then report failure, and
the steady-state DR solver must find the feasible root of its optimality system on a
system where an infeasible root exists (checked against the SDP solved by Clarabel).
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jdrkf
from jdrkf.sets import KL, Wasserstein, bcot_worst_case, ci_weights, maxent_kl_solve, theta_max, worst_case
from stationary_oracle import stationary_sdp

# A random 2-state system with a nearly singular process noise (eigenvalues 1e-8 and
# 0.02) on which the optimality system of the steady-state problem has a root with an
# indefinite worst-case prior (trace 3.9573, above the SDP optimum 3.9529).
SPURIOUS_ROOT_SYSTEM = dict(
    F=[[0.9345217140409523, -0.012457641373551303], [-0.012457641373551183, 0.9364809818368653]],
    H=[[-0.7308045420469873, -0.4547072604734497]],
    Q=[[0.00494250341089901, -0.008864311244574749], [-0.008864311244574749, 0.015898061383277224]],
    R=[[0.1418617397593826]],
)


def test_steady_state_finds_the_feasible_root():
    m = {k: np.asarray(v) for k, v in SPURIOUS_ROOT_SYSTEM.items()}
    model = jdrkf.LinearModel(**{k: jnp.asarray(v) for k, v in m.items()})
    sol = jdrkf.SteadyStateDRKF(0.1, 0.1).solve(model)
    ref = stationary_sdp(m["F"], m["H"], m["Q"], m["R"], 0.1, 0.1)
    assert ref["accurate"]
    assert bool(sol.converged)
    for name in ("prior_cov", "noise_cov", "posterior_cov"):
        assert np.linalg.eigvalsh(np.asarray(getattr(sol, name))).min() > 0, name
    np.testing.assert_allclose(float(sol.value), ref["value"], rtol=1e-8)
    np.testing.assert_allclose(np.asarray(sol.posterior_cov), ref["posterior_cov"], atol=1e-6)


@pytest.fixture
def problem():
    rng = np.random.default_rng(3)
    a = rng.normal(size=(3, 3))
    b = rng.normal(size=(2, 2))
    return a @ a.T + np.eye(3), rng.normal(size=(2, 3)), b @ b.T + np.eye(2)


@pytest.mark.parametrize("sets", [(Wasserstein(0.5), Wasserstein(0.3)), pytest.param((KL(0.5), KL(0.3)), marks=pytest.mark.slow)],
                         ids=["wasserstein", "kl"])
def test_worst_case_stopped_early_is_not_converged(problem, sets):
    prior, h, noise = problem
    exact = worst_case(*sets, prior, h, noise)
    assert bool(exact.converged)
    early = worst_case(*sets, prior, h, noise, max_iter=0)
    assert abs(float(early.value) / float(exact.value) - 1) > 0.1  # the nominal, far from the optimum
    assert not bool(early.converged)


# Found by a randomized stress run: ‖H‖ ≈ 0.03, so the noise ball's multiplier is ~1.4e4.
_WEAK_H = {
    "M": [[0.6881824458293557, -0.15733320892445596, 0.09672656218485763], [-0.15733320892445596, 0.25887380884538425, -0.12069883798028061],
          [0.09672656218485763, -0.12069883798028061, 0.351734362687899]],
    "H": [[0.009444301128736104, 0.025057654935306168, 0.02030837615403191], [0.003597731229763481, 0.00011603240737337756, 0.005477070178803299]],
    "R": [[32.60702086898454, -3.9712696039220616], [-3.9712696039220616, 1.51823403322882]],
    "radii": (1.7203085476169293, 1.2952883786158453),
}


@pytest.mark.parametrize("rtol", [None, 1e-8])
def test_large_multiplier_is_solved_to_the_certificate(rtol):
    """A multiplier of ~1e4 made the fallback Newton's stopping test (relative to ‖x‖) stop
    with the noise ball's equation at 2e-10, above the certificate's rtol: a correct value
    (gap 0) reported not converged. The fallback now runs to the certificate's tolerance."""
    from sdp_oracles import decoupled_wasserstein_sdp

    M, H, R = (np.asarray(_WEAK_H[k]) for k in "MHR")
    rx, rv = _WEAK_H["radii"]
    out = worst_case(Wasserstein(rx), Wasserstein(rv), M, H, R, rtol=rtol)
    assert bool(out.converged)
    ref = decoupled_wasserstein_sdp(M, H, R, rx, rv)["value"]  # certified to 1e-14 by a NumPy Frank–Wolfe gap
    assert abs(float(out.value) / ref - 1) < 1e-9


def test_drkf_stopped_early_reports_solver_not_converged(problem, rng):
    model = jdrkf.LinearModel(F=0.9 * jnp.eye(2), H=jnp.array([[1.0, 0.5]]), Q=0.1 * jnp.eye(2), R=jnp.eye(1))
    prior = jdrkf.Gaussian(jnp.zeros(2), jnp.eye(2))
    ys = jnp.asarray(rng.normal(size=(5, 1)))
    flt = jdrkf.DRKF(state_set=Wasserstein(0.5), noise_set=Wasserstein(0.5), max_iter=0, throw=False)
    assert flt(model, prior, ys).result == jdrkf.RESULTS.solver_not_converged
    with pytest.raises(Exception, match="did not reach its tolerance"):
        jdrkf.DRKF(state_set=Wasserstein(0.5), noise_set=Wasserstein(0.5), max_iter=0)(model, prior, ys)


@pytest.mark.parametrize("max_iter", [0, 1])
def test_steady_state_dr_stopped_early_is_not_converged(max_iter):
    model = jdrkf.LinearModel(F=jnp.array([[0.9, 0.1], [0.0, 0.9]]), H=jnp.array([[1.0, 0.0]]), Q=0.1 * jnp.eye(2), R=jnp.eye(1))
    assert bool(jdrkf.SteadyStateDRKF(0.5, 0.5).solve(model).converged)
    assert not bool(jdrkf.SteadyStateDRKF(0.5, 0.5, max_iter=max_iter).solve(model).converged)


def test_other_solvers_stopped_early_are_not_converged():
    f, c, w, v = np.array([[0.9, 0.1], [0.0, 0.9]]), np.array([[1.0, 0.0]]), 0.1 * np.eye(2), np.eye(1)
    assert bool(bcot_worst_case(np.eye(2), w, v, f, c, 0.3).converged)
    assert not bool(bcot_worst_case(np.eye(2), w, v, f, c, 0.3, max_iter=1).converged)
    infos = jnp.stack([2 * jnp.eye(2), jnp.array([[1.0, 0.3], [0.3, 0.5]]), jnp.array([[0.2, 0.0], [0.0, 3.0]])])
    assert bool(ci_weights(infos).converged)
    assert not bool(ci_weights(infos, max_iter=0).converged)
    assert bool(theta_max(f, c, w, v).valid)
    assert not bool(theta_max(f, c, w, v, max_iter=1).valid)
    q = jnp.array([0.1, 0.2, 0.3, 0.4])
    assert bool(maxent_kl_solve(q, 0.1).converged)
    for k in (0, 1):
        assert not bool(maxent_kl_solve(q, 0.1, max_iter=k).converged)


def test_em_with_zero_iterations_is_not_converged(rng):
    model = jdrkf.LinearModel(F=0.9 * jnp.eye(2), H=jnp.eye(2), Q=0.1 * jnp.eye(2), R=0.5 * jnp.eye(2))
    prior = jdrkf.Gaussian(jnp.zeros(2), jnp.eye(2))
    traj = jdrkf.simulate(jax.random.key(0), model, prior, num_steps=50, num_runs=1)
    res = jdrkf.em_noise_covariances(model.F, model.H, traj.observations[0], jnp.zeros(2), jnp.eye(2), max_iter=0)
    assert int(res.iterations) == 0
    assert not bool(res.converged)


@pytest.fixture
def fresh_compilation():
    """Compiled solvers are cached per shape: drop them before and after a test that
    patches a solver's constants."""
    jax.clear_caches()
    yield
    jax.clear_caches()


@pytest.mark.parametrize("kind", ["moment", pytest.param("kl", marks=pytest.mark.slow)])
def test_marginal_barrier_cut_short_is_not_converged(monkeypatch, fresh_compilation, kind):
    from jdrkf.sets import _marginal

    rng = np.random.default_rng(5)
    a = rng.normal(size=(4, 4))
    cov = a @ a.T + np.eye(4)
    st = _marginal.MarginalMoment(0.7, 1.5) if kind == "moment" else _marginal.MarginalKL(0.3)
    exact = _marginal.marginal_mmse(cov, 2, (1, 1), st)
    assert bool(exact.converged) and bool(exact.polished)
    # One Newton step per barrier stage and none at the final weight: the path stops far
    # from the optimum, which the duality-gap certificate must notice.
    monkeypatch.setattr(_marginal, "_NEWTON_PER_STAGE", 1)
    monkeypatch.setattr(_marginal, "_NEWTON_FINAL", 0)
    jax.clear_caches()
    early = _marginal.marginal_mmse(cov, 2, (1, 1), st)
    assert not bool(early.converged) and not bool(early.polished)


def test_maxent_transport_infeasible_budget_is_not_converged():
    q = jnp.array([0.2, 0.3, 0.5])
    cost = jnp.array([[0.5, 1.0], [0.2, 0.4], [1.0, 0.3]])
    c_min = float(q @ jnp.min(cost, axis=1))
    solve = jax.jit(lambda theta: jdrkf.sets.maxent_transport_solve(q, cost, theta))
    ok = solve(c_min + 0.1)
    assert bool(ok.converged) and bool(ok.feasible)
    bad = solve(0.5 * c_min)  # traced: no eager ValueError
    assert not bool(bad.feasible)
    assert not bool(bad.converged)


def test_wasserstein_worst_case_where_frank_wolfe_stalls():
    """An ill-conditioned instance (two nearly parallel rows of H on two of four states,
    R = diag(1e-2, 1e-4)): Frank–Wolfe's line search stalls after 3 iterations at a
    relative gap of 2.5e-6 and the chord steps cannot contract from there (once reported
    `converged=False`); damped Newton now finishes. Oracle: the NumPy Frank–Wolfe of the
    test oracles run to a relative gap of 1e-12 (Clarabel reports this SDP inaccurate)."""
    from sdp_oracles import decoupled_gradient, frank_wolfe, posterior_trace, set_lmo

    r = np.random.default_rng(349)
    a = r.normal(size=(4, 4))
    P = a @ a.T / 4 + np.diag(10 ** r.uniform(-4, 0, 4))
    H = np.zeros((2, 4))
    H[:, :2] = r.normal(size=(2, 2))
    R = np.diag([1e-2, 1e-4])
    wc = worst_case(Wasserstein(0.05), Wasserstein(0.01), P, H, R)
    (sx, sv), gap, _ = frank_wolfe(
        lambda a, b: posterior_trace(a, H, b), lambda a, b: decoupled_gradient(a, H, b),
        [lambda g: set_lmo(("wasserstein", 0.05), g, P), lambda g: set_lmo(("wasserstein", 0.01), g, R)], [P, R], rtol=1e-12,
    )
    assert bool(wc.converged) and float(wc.gap) <= 1e-10 * float(wc.value)
    np.testing.assert_allclose(float(wc.value), posterior_trace(sx, H, sv), rtol=1e-10)
    np.testing.assert_allclose(wc.state_cov, sx, atol=1e-4)
    np.testing.assert_allclose(wc.noise_cov, sv, atol=1e-4)
