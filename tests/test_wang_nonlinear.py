"""Smoke tests of the Wang (2022) reproductions (`wang-growth`, `wang-methods`, `wang-tracking`)
at tiny sizes: structure, protocols and the paper's numbers attached. The filters
themselves are tested against independent oracles in test_particle, test_dr_particle,
test_unscented."""

import jax.numpy as jnp
import numpy as np
import pytest

from jdrkf.experiments import wang_nonlinear as wn


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


@pytest.mark.slow  # ~15 s of compiles; the filters are unit-tested elsewhere
def test_growth_report_protocols():
    rep = wn.run_growth(runs=3, seed=0, particles=(50,), thetas=(5.0,))
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


@pytest.mark.slow
def test_methods_and_tracking_reports_run():
    rep = wn.run_methods(runs=2, seed=0, particles=50, radii=(0.1,))
    assert len(rep.rows) == 6 and all(np.isfinite(r.mean) for r in rep.rows)
    rep = wn.run_tracking(runs=2, seed=0, particles=100, episodes=2)
    assert {r.filter for r in rep.rows} == {"PF", "UKF", "EnKF", "RPF"}
    assert all(np.isfinite(r.mean) for r in rep.rows)
