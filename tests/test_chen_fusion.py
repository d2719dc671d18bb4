"""Tests of the Chen et al. (2025) reproduction (`chen-fusion`): the scenario matches the
paper's eq. (34) and the authors' settings, one grid point's shared filter run equals
separate runs, the tuning keeps its best iterate and reports its grid, the notes are
computed from the run, and the `code-dt0.1` variant lands on Table I's levels. The filters
and the solver are tested against independent oracles in test_fusion and test_marginal."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jdrkf import KalmanFilter, MarginalDRKF
from jdrkf.experiments import chen_fusion as cf
from jdrkf.sets import MarginalKL, MarginalMoment

# Table I (Chen et al. 2025): time-averaged MSE of x, v, a over 1000 runs.
TABLE_KF = (10.5345, 30.2828, 20.3734)
TABLE_KL = (1.7764, 8.5224, 13.5665)
TABLE_MC = (1.4468, 1.8426, 2.6792)


def _runs(variant, runs, steps, key=0):
    _, true, _ = cf.scenario(variant, jnp.float64)
    return cf._simulate(jax.random.key(key), true, runs, steps)


def _component_mse(flt, model, prior, traj, sensor1=False):
    """Per-component MSE over runs and steps, the filter run directly through the public API."""
    ys = traj.observations[..., :1] if sensor1 else traj.observations
    mdl = model.sensor(0) if sensor1 else model
    means = jax.vmap(lambda y: flt(mdl, prior, y).filtered_means)(ys)
    return np.mean((np.asarray(traj.states) - np.asarray(means)) ** 2, axis=(0, 1))


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


def test_variants_are_the_text_the_code_and_the_code_with_the_texts_sampling_period():
    assert cf.VARIANTS["paper"] == {"dt": 0.1, "q_nominal": 1.0, "p0": 100.0}
    assert cf.VARIANTS["authors-code"] == {"dt": 0.01, "q_nominal": 0.01, "p0": 1.0}
    assert cf.VARIANTS["code-dt0.1"] == {**cf.VARIANTS["authors-code"], "dt": 0.1}


def test_grids_stay_inside_the_sets():
    assert np.all(1.0 - cf.GAMMA_GRID > 0) and np.all(cf.GAMMA_GRID > 0)
    assert np.all(cf.KL_GRID > 0) and np.isclose(cf.KL_GRID[-1], 0.15)
    mc, kl = cf.TUNED["MC-MDRKF"][1], cf.TUNED["KL-MDRKF"][1]
    assert np.allclose(mc[:, 0] + mc[:, 1], 2.0) and np.allclose(mc[[0, -1], 0], [0.999, 0.001])
    assert np.allclose(kl[:, 0], cf.KL_GRID) and np.isclose(kl[1, 0], 0.15 / 9)


def test_grid_profile_flags_a_minimum_at_the_grid_end():
    grid = np.array([0.1, 0.2, 0.3])
    low = cf.grid_profile("[paper] X", "g", grid, np.array([1.0, 1.5, 2.0]))
    assert "lower end" in low and "100.0% above" in low and "0.1: 1" in low
    assert "upper end" in cf.grid_profile("X", "g", grid, np.array([3.0, 2.0, 1.0]))
    assert "inside the grid" in cf.grid_profile("X", "g", grid, np.array([3.0, 1.0, 2.0]))


def test_grid_notes_show_the_training_choice_the_post_hoc_choices_and_the_profile():
    grid = np.array([[0.9, 1.1], [0.8, 1.2], [0.7, 1.3]])  # g = 0.1, 0.2, 0.3
    losses = np.array([5.0, 6.0, 7.0])  # training optimum at the lower end
    test = np.array([[1.0, 2.0, 9.0], [3.0, 1.5, 4.0], [2.0, 3.0, 3.5]])  # sums 12, 8.5, 8.5 -> first minimum g = 0.2
    choice, profile = cf._grid_notes("[v] MC-MDRKF", "MC-MDRKF", grid, losses, test)
    assert "training grid choice g = 0.1 (γ₁ = 0.9, γ₂ = 1.1), training MSE 5, test MSE 12." in choice
    assert "the grid's best is g = 0.2, test MSE 8.5" in choice
    assert "x 1 (g = 0.1), v 1.5 (g = 0.2), a 3.5 (g = 0.3)" in choice
    assert profile.startswith("[v] MC-MDRKF grid profile (g: training MSE) 0.1: 5, 0.2: 6, 0.3: 7; minimum at the grid's lower end")
    kl_choice, kl_profile = cf._grid_notes("[v] KL-MDRKF", "KL-MDRKF", np.array([[0.01], [0.02]]), np.array([2.0, 1.0]), test[:2])
    assert "c = 0.02 (the authors' 2·KL units: 0.04)" in kl_choice and "(c: training MSE) 0.01: 2, 0.02: 1; minimum at the grid's upper end" in kl_profile


def test_single_sensor_kf_lands_on_table_one_only_with_the_texts_sampling_period():
    """The KF on sensor 1 has no radius to tune: its Table I row identifies the setting.
    With the authors' code and T_s = 0.1 it is within 5% on x, v, a; the text's and the
    code's own settings are off by at least 1.8× on some component."""
    worst = {}
    for variant in cf.VARIANTS:
        model, _, prior = cf.scenario(variant, jnp.float64)
        mse = _component_mse(KalmanFilter(), model, prior, _runs(variant, 1000, cf.NUM_STEPS), sensor1=True)
        worst[variant] = np.max(np.abs(np.log(mse / np.asarray(TABLE_KF))))
    assert worst["code-dt0.1"] < np.log(1.05)
    assert worst["paper"] > np.log(1.8) and worst["authors-code"] > np.log(1.8)


def test_grid_point_is_one_filter_run_over_training_and_test_runs():
    model, _, prior = cf.scenario("code-dt0.1", jnp.float64)
    train, test = _runs("code-dt0.1", 3, 40, key=1), _runs("code-dt0.1", 4, 40, key=2)
    loss, per_run, curve = cf._grid_point(cf._kl, jnp.asarray([0.05]), model, prior,
                                          (train.states, train.observations), (test.states, test.observations))
    flt = MarginalDRKF(MarginalKL(0.05))
    assert np.isclose(loss, _component_mse(flt, model, prior, train).sum(), rtol=1e-10)
    means = np.asarray(jax.vmap(lambda y: flt(model, prior, y).filtered_means)(test.observations))
    err2 = (np.asarray(test.states) - means) ** 2
    assert np.asarray(per_run).shape == (4, 3) and np.asarray(curve).shape == (40,)
    assert np.allclose(per_run, err2.mean(axis=1), rtol=1e-10) and np.allclose(curve, err2[..., 0].mean(axis=0), rtol=1e-10)


@pytest.mark.slow  # ~25 s: compiles the filter's gradient
def test_refinement_keeps_the_start_when_every_step_is_worse():
    """Adam with a learning rate of 2 from c = 0.05 overshoots to c ≈ 0.3 … 2.8 (all worse on
    these runs): the refinement must return the start, with its own training MSE."""
    model, _, prior = cf.scenario("code-dt0.1", jnp.float64)
    train = _runs("code-dt0.1", 3, 40, key=1)
    params, loss, start_loss, step = cf._refine(cf._kl, np.array([0.05]), cf._mse_objective(model, prior, train), (0.0, None), 2.0, 4)
    direct = _component_mse(MarginalDRKF(MarginalKL(0.05)), model, prior, train).sum()
    assert step == 0 and np.isclose(params[0], 0.05, rtol=1e-12)
    assert np.isclose(loss, direct, rtol=1e-10) and np.isclose(start_loss, direct, rtol=1e-10)
    worse = _component_mse(MarginalDRKF(MarginalKL(0.3)), model, prior, train).sum()
    assert worse > direct  # the overshoot is indeed worse: the test can tell the start from a later iterate


@pytest.mark.slow  # ~40 s
def test_tiny_run_reports_grids_refinement_and_notes_from_its_own_numbers():
    rep = cf.run(runs=4, seed=3, variants=("paper",), train_runs=3, fit_steps=1, num_steps=30)
    names = {r.filter for r in rep.rows}
    assert {"CI", "KF", "KL-MDRKF", "MC-MDRKF", "CKF", "MC-MDRKF-grad", "KL-MDRKF-grad"} <= names
    assert all(np.isfinite(r.mean) for r in rep.rows)
    assert {r.metric for r in rep.rows} == {f"MSE {c} [paper]" for c in cf.COMPONENTS}
    notes = "\n".join(rep.notes)
    for name, axis in (("MC-MDRKF", "g"), ("KL-MDRKF", "c")):
        assert f"[paper] {name} grid profile ({axis}: training MSE)" in notes
        assert f"[paper] {name}: training grid choice" in notes
        grad = next(n for n in rep.notes if n.startswith(f"[paper] {name}-grad:"))
        trained, start = (float(x) for x in grad.split("training MSE ")[1].rstrip(").").split(" (grid choice "))
        assert trained <= start
    kf = [next(r.mean for r in rep.rows if r.filter == "KF" and r.metric == f"MSE {c} [paper]") for c in cf.COMPONENTS]
    ratios = ", ".join(f"{m / p:.2f}" for m, p in zip(kf, TABLE_KF))
    assert f"paper: {ratios}; closest: `paper`" in notes
    assert "(seed 3, 4 runs)" in notes and "4 evaluation runs and 3 training runs" in notes
    assert rep.settings == {"training runs": 3, "steps": 30, "gradient steps": 1}


@pytest.mark.slow  # ~30 s: three 600-step worst-case paths
def test_code_with_the_texts_sampling_period_reproduces_the_dr_rows():
    """`code-dt0.1`: KL-MDRKF at the authors' c = 0.0333 (our 0.0167, the training grid's
    choice) is within 5% of Table I's KL row; Table I's MC-MDRKF row is within 5% of the
    per-component best of the moment grid (x, v at g = 2/9; a at g = 7/9)."""
    model, _, prior = cf.scenario("code-dt0.1", jnp.float64)
    test = _runs("code-dt0.1", 1000, cf.NUM_STEPS, key=7)
    kl = _component_mse(MarginalDRKF(MarginalKL(0.15 / 9)), model, prior, test)  # our c = the authors' c / 2
    assert np.allclose(kl, TABLE_KL, rtol=0.05)
    g = {2: _component_mse(MarginalDRKF(MarginalMoment(1 - 2 / 9, 1 + 2 / 9)), model, prior, test),
         7: _component_mse(MarginalDRKF(MarginalMoment(1 - 7 / 9, 1 + 7 / 9)), model, prior, test)}
    assert np.allclose(g[2][:2], TABLE_MC[:2], rtol=0.05) and np.isclose(g[7][2], TABLE_MC[2], rtol=0.05)
    assert g[2][2] > 1.5 * TABLE_MC[2] and g[7][1] > 1.5 * TABLE_MC[1]  # no single radius gives the whole row
