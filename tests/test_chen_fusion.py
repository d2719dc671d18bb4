"""Smoke tests of the Chen et al. (2025) reproduction (`chen-fusion`): the scenario matches the
paper's eq. (34) and the authors' settings, and a tiny run produces Table I's rows. The
filters and the solver are tested against independent oracles in test_fusion and
test_marginal."""

import jax.numpy as jnp
import numpy as np
import pytest

from jdrkf.experiments import chen_fusion as cf


@pytest.mark.parametrize("variant", list(cf.VARIANTS))
def test_scenario(variant):
    nominal, true, prior = cf.scenario(variant, jnp.float64)
    dt = cf.VARIANTS[variant]["dt"]
    assert np.allclose(nominal.F, [[1, dt, dt**2 / 2], [0, 1, dt], [0, 0, 1]])
    assert np.allclose(nominal.G[:, 0], [dt**2 / 2, dt, 1.0])
    assert nominal.dims == (1, 1, 1)
    assert np.allclose(nominal.Q, cf.VARIANTS[variant]["q_nominal"]) and np.allclose(true.Q, 1.0)
    # eq. (34) with q = 1: Cov(v) = ββᵀ + diag(5, 8, 10) (the authors' commented-out marginal)
    beta = np.asarray(cf.BETA)
    assert np.allclose(true.true_noise_cov(), np.outer(beta, beta) + np.diag(cf.ETA_VAR))
    assert np.allclose(nominal.true_noise_cov(), np.diag(cf.ETA_VAR))
    assert np.allclose(prior.cov, cf.VARIANTS[variant]["p0"] * np.eye(3))


def test_grids_stay_inside_the_sets():
    assert np.all(1.0 - cf.GAMMA_GRID > 0) and np.all(cf.GAMMA_GRID > 0)
    assert np.all(cf.KL_GRID > 0) and np.isclose(cf.KL_GRID[-1], 0.15)


@pytest.mark.slow
def test_tiny_run_has_table_rows():
    rep = cf.run(runs=4, seed=0, variants=("paper",), train_runs=3, fit_steps=1)
    names = {r.filter for r in rep.rows}
    assert {"CI", "KF", "KL-MDRKF", "MC-MDRKF", "CKF", "MC-MDRKF-grad", "KL-MDRKF-grad"} <= names
    assert all(np.isfinite(r.mean) for r in rep.rows)
    assert {r.metric for r in rep.rows} == {f"MSE {c} [paper]" for c in cf.COMPONENTS}


def test_grid_profile_flags_a_minimum_at_the_grid_end():
    grid = np.array([0.1, 0.2, 0.3])
    low = cf.grid_profile("[paper] X", "g", grid, np.array([1.0, 1.5, 2.0]))
    assert "lower end" in low and "100.0% above" in low and "0.1: 1" in low
    assert "upper end" in cf.grid_profile("X", "g", grid, np.array([3.0, 2.0, 1.0]))
    assert "inside the grid" in cf.grid_profile("X", "g", grid, np.array([3.0, 1.0, 2.0]))
