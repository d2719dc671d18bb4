"""Smoke tests of the Wang (2022) reproductions (`wang-growth`, `wang-methods`, `wang-tracking`)
at tiny sizes: structure, protocols and the paper's numbers attached. The filters
themselves are tested against independent oracles in test_particle, test_dr_particle,
test_unscented."""

import inspect

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jdrkf._gaussian import Gaussian
from jdrkf.experiments import get
from jdrkf.experiments import wang_nonlinear as wn
from jdrkf.sets._maxent import maxent_transport_solve
from jdrkf.sets._particle import _pairwise


def test_growth_models_match_the_paper_equations():
    m = wn.growth_models(jnp.float64)
    x, t = jnp.asarray([1.7]), jnp.asarray(4)  # step k = 5
    f = 1.7 / 2 + 25 * 1.7 / (1 + 1.7**2) + 8 * np.cos(1.2 * 5)
    assert np.allclose(m["true"].f(x, t), f, rtol=1e-14)
    assert np.allclose(m["nominal"].h(x, t), 1.7**2 / 20, rtol=1e-14)
    assert np.allclose(m["true"].h(x, t), 1.7**2 / 20 + 0.5 * np.sin(1.7), rtol=1e-14)


def test_tracking_truth_turns_at_speed_two_and_sensor_moves_up():
    m = wn.tracking_models(jnp.float64)
    x = jnp.asarray([5.0, 0.0, 5.0, 0.0])
    nxt = m["true"].transition(x, jnp.zeros(2), jnp.asarray(99))  # φ = π/2: velocity (0, 2)
    assert np.allclose(nxt, [5.0, 0.0, 6.0, 2.0], atol=1e-12)
    y = m["nominal"].h(x, jnp.asarray(9))  # sensor at (0, 5) after 10 steps of 0.5 s at 1 m/s
    assert np.allclose(y, [5.0, 0.0], atol=1e-12)


def _growth_data(runs, steps=25):
    models = wn.growth_models()
    traj = wn.simulate(jax.random.key(3), models["true"], wn._point_mass(1), steps, runs)
    return models, Gaussian(jnp.zeros(1), jnp.ones((1, 1))), traj.observations, jax.random.split(jax.random.key(4), runs)


def test_stacked_and_sequential_runs_match_bootstrap_pf_and_separate_runs():
    # The growth table runs the PF as DRParticleFilter(θ = 1, ε = 0) stacked with the RPF.
    models, prior, ys, keys = _growth_data(runs=3)
    stacked = wn._run_stack(wn._stack([wn._rpf(40, 1.0, 0.0), wn._rpf(40)]), models["nominal"], prior, ys, keys)
    pf = wn._run_batch(wn._pf(40), models["nominal"], prior, ys, keys)
    rpf = wn._run_batch(wn._rpf(40), models["nominal"], prior, ys, keys)
    np.testing.assert_allclose(stacked[0], pf, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(stacked[1], rpf, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(wn._run_one_by_one(wn._rpf(40), models["nominal"], prior, ys, keys), rpf, rtol=1e-12, atol=1e-12)
    assert not np.allclose(stacked[0], stacked[1])


def test_method5_solves_stop_early_at_the_noise_floor():
    # Growth-model likelihood particles (x + v)²/20 around 200 particles: under vmap every
    # solve iterates as long as the slowest; Newton used to alternate between two points
    # ~14 ulps apart at the noise floor of the residual until max_iter = 100.
    kx, kv = jax.random.split(jax.random.key(0))
    x = 15 * jax.random.normal(kx, (200, 1))
    ys = (x[:, None, :] + jax.random.normal(kv, (200, 50, 1))) ** 2 / 20
    y, radius, q = jnp.asarray([8.3**2 / 20]), 0.05, jnp.full((50,), 1 / 50)
    cost = jax.vmap(lambda yr: _pairwise(yr, jnp.concatenate([y[None], yr])))(ys)
    res = jax.jit(jax.vmap(lambda c: maxent_transport_solve(q, c, radius)))(cost)
    assert int(np.max(res.iterations)) <= 20 and bool(np.all(res.converged))
    # The dual solves C(v₀) = θ (transport cost of the row softmax), checked in NumPy.
    c, v0 = np.asarray(cost), np.asarray(res.dual)[:, None, None]
    p = np.exp(-v0 * (c - c.min(axis=2, keepdims=True)))
    p /= p.sum(axis=2, keepdims=True)
    active = np.asarray(res.dual) > 0  # else the budget exceeds the cost of uniform rows
    assert active.mean() > 0.5
    np.testing.assert_allclose(np.sum(p * c, axis=(1, 2))[active] / 50, radius, rtol=1e-9)


def test_growth_notes_are_computed_from_the_runs():
    rng = np.random.default_rng(0)
    exact = rng.normal(4.6, 0.5, 40)
    low = wn._gap_note(exact + 0.1 + 0.01 * rng.normal(size=40), exact, 500)
    high = wn._gap_note(exact + 1.5, exact, 500)
    assert "0% of 40 trajectories" in low and "unusual trajectory" in low
    assert "100% of 40 trajectories" in high and "not unusual" in high
    assert f"{exact.mean() - wn.PAPER_GROWTH['exact']['PF'][-1]:+.2f}" in low
    vals = {"PF": exact, "RPF": exact + 0.1, "UKF": exact + 6.0}
    note = wn._level_note("exact", 500, 40, vals, {k: wn.PAPER_GROWTH["exact"][k][-1] for k in vals})
    assert f"PF {exact.mean():.2f} (paper 3.61" in note and f"UKF {exact.mean() + 6:.2f} (paper 9.29" in note
    assert f"{100 * np.mean(exact <= 3.61):.0f}% of our trajectories give a PF at or below" in note


def test_methods_full_mode_is_the_larger_scale():
    exp = get("wang-methods")
    params = inspect.signature(exp.run).parameters
    assert set(exp.full) - {"runs"} <= set(params) and set(exp.quick) - {"runs"} <= set(params)
    default = exp.options()
    assert default["runs"] <= exp.full["runs"]
    assert params["particles"].default < exp.full["particles"]
    assert params["likelihood_particles"].default < exp.full["likelihood_particles"]
    assert get("wang-growth").full is None  # its default is the paper's scale


@pytest.mark.slow  # ~25 s of compiles; the filters are unit-tested elsewhere
def test_growth_report_protocols():
    rep = wn.run_growth(runs=3, seed=0, particles=(50,), thetas=(2.5, 5.0))
    metrics = {r.metric for r in rep.rows}
    assert metrics == {f"RTAMSE [{c}, {p}, N=50]" for c in ("mismatch", "exact") for p in ("honest", "authors")}
    for r in rep.rows:
        assert np.isfinite(r.mean) and r.runs == 3
        assert r.paper == wn.PAPER_GROWTH[r.metric.split("[")[1].split(",")[0]][r.filter][0]
        if r.filter.startswith("UKF") and "authors" in r.metric:
            assert r.ci95[0] == pytest.approx(r.ci95[1])  # one trajectory, deterministic filter
        if r.filter.startswith("PF") and "honest" in r.metric:
            assert r.ci95[1] > r.ci95[0]
    assert "growth-theta" in rep.sweeps
    # Notes quote this run's numbers, so another seed changes them.
    pf = next(r for r in rep.rows if r.filter == "PF" and r.metric == "RTAMSE [exact, honest, N=50]")
    assert any(f"PF {pf.mean:.2f} (paper 4.22" in n for n in rep.notes)
    assert any("Tables I–II share one trajectory" in n for n in rep.notes)
    other = wn.run_growth(runs=3, seed=1, particles=(50,), thetas=(2.5, 5.0))
    assert other.notes[:-1] != rep.notes[:-1]


@pytest.mark.slow
def test_methods_and_tracking_reports_run():
    rep = wn.run_methods(runs=2, seed=0, particles=50, likelihood_particles=10, radii=(0.1,))
    assert len(rep.rows) == 6 and all(np.isfinite(r.mean) for r in rep.rows)
    assert sum("paired RTAMSE difference" in n for n in rep.notes) == 2
    rep = wn.run_tracking(runs=2, seed=0, particles=100, episodes=2)
    assert {r.filter for r in rep.rows} == {"PF", "UKF", "EnKF", "RPF"}
    assert all(np.isfinite(r.mean) for r in rep.rows)
