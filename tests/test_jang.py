"""Jang, Hakobyan & Yang (2025) experiments (`jang-convergence`, `jang-lqr`): small runs that check the
pieces against the paper's setting and independent NumPy computations."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jdrkf
import jdrkf.experiments
from jdrkf import _progress
from jdrkf.experiments import jang


@pytest.mark.slow
def test_convergence_experiment_small(tmp_path):
    report = jang.run_convergence(3, seed=0)
    rows = {(r.filter, r.metric): r for r in report.rows}
    np.testing.assert_allclose(rows[("2-D benchmark", "theta_max")].mean, 3.356, rtol=5e-3)
    # Fig. 1: the gap at step 20 is of the order of the paper's ≈ 8e-6.
    assert 1e-6 < rows[("2-D benchmark", "relative trace gap at step 20")].mean < 1e-4
    assert rows[("random systems", "fraction within 2%")].mean == 1.0
    curve = report.curves["to the optimum of (14)"]
    assert curve[0] > 0.5 and curve[19] < 1e-4
    # The recursion reaches its own limit to round-off while the gap to (14) levels off.
    assert report.curves["to the recursion's own limit (step 40)"][-2] < 1e-10 < curve[-1]
    from jdrkf.plotting import plot_error_curves

    assert plot_error_curves(report, tmp_path / "conv.png").exists()


def test_random_systems_satisfy_assumptions():
    a, c, w, v, th, _ = jang.random_systems(np.random.default_rng(1), 4)
    for i in range(4):
        ctrb = np.concatenate([np.linalg.cholesky(w[i]), a[i] @ np.linalg.cholesky(w[i])], axis=1)
        obsv = np.concatenate([c[i], c[i] @ a[i]], axis=0)
        assert np.linalg.matrix_rank(ctrb) == 2 and np.linalg.matrix_rank(obsv) == 2
        assert np.isfinite(th[i]) and th[i] > 0


def test_lqr_setting():
    a, b, c = jang.lqr_system()
    np.testing.assert_allclose(a @ np.array([1.0, 2.0, 3.0, 4.0]), [1.4, 2.0, 3.8, 4.0])
    ref = jang.reference_trajectory()
    assert ref.shape == (51, 4)
    np.testing.assert_allclose(ref[-1], [5 * np.sin(5.0), 2.5 * np.cos(5.0), 10.0, 1.0])
    # U-quadratic on [-0.1, 0.1]: variance (3/20)(b − a)² = 0.006.
    *_, qv, rv = jang.noise_laws("uquadratic")
    np.testing.assert_allclose([qv, rv], [0.006, 0.006])
    with pytest.raises(ValueError, match="unknown noise setting"):
        jang.noise_laws("laplace")


@pytest.mark.parametrize("setting", ["gaussian", "uquadratic"])
def test_setting_noise_draws_its_law(setting):
    """The switchable law draws the setting's law: variances 0.01 (Gaussian) or 0.006
    (U-quadratic, bounded by 0.1 and concentrated near the ends of the box)."""
    _, w, v, qv, _ = jang.noise_laws(setting)
    draws = np.asarray(jax.vmap(lambda k: w.sample(k))(jax.random.split(jax.random.key(0), 20000)))
    np.testing.assert_allclose(np.var(draws, axis=0), qv, rtol=0.05)
    np.testing.assert_allclose(np.diag(np.asarray(w.cov)), qv)
    assert v.dim == 2 and w.dim == 4
    if setting == "uquadratic":
        assert np.abs(draws).max() <= 0.1 and np.mean(np.abs(draws) > 0.05) > 0.8  # U-shaped: 1 − 0.5³
    else:
        assert np.abs(draws).max() > 0.3  # Gaussian tails (σ = 0.1) leave the box


def test_choose_theta_skips_failing_theta():
    cost = np.array([[1.0, 1.0], [0.2, 0.2], [0.3, 0.3]])
    assert jang._choose_theta(cost, np.ones_like(cost, bool)) == 1
    ok = np.ones_like(cost, bool)
    ok[1, 0] = False  # one failed training run rules θ index 1 out
    assert jang._choose_theta(cost, ok) == 2


def test_registered_scales():
    exp = jdrkf.experiments.get("jang-lqr")
    assert exp.full == {"runs": 200, "train_runs": 200}
    assert exp.default_runs < exp.full["runs"] and exp.default_runs >= 100
    assert exp.options(full=True)["train_runs"] == 200


@pytest.mark.slow
def test_em_nominals_and_closed_loop_chunks():
    keys = jax.random.split(jax.random.key(0), 3)
    qs, rs, iters = jang._nominal_models(keys, "gaussian")
    assert qs.shape == (3, 4, 4) and rs.shape == (3, 2, 2) and iters.shape == (3,)
    assert np.all(np.linalg.eigvalsh(np.asarray(qs)) >= 1e-4 - 1e-12)
    loop_keys = jax.random.split(jax.random.key(1), 3)
    with _progress.reporter(False).phase("test", 6) as bar:
        # chunk 2: the last call is padded with a repeat of the last run
        one = jang._closed_loop_costs("SS-KF", np.zeros(3), qs, rs, loop_keys, "gaussian", 2, bar)
        whole = jang._closed_loop_costs("SS-KF", np.zeros(3), qs, rs, loop_keys, "gaussian", 3, bar)
    assert all(v.shape == (3,) for v in one) and np.all(one[2]) and np.all(np.isfinite(one[0]))
    np.testing.assert_allclose(one[0], whole[0], rtol=1e-12)
    # With θ = 0 the steady-state DRKF is the steady-state KF: same closed loop (common random numbers).
    with _progress.reporter(False).phase("test", 3) as bar:
        dr0 = jang._closed_loop_costs("SS-DRKF", np.zeros(3), qs, rs, loop_keys, "gaussian", 3, bar)
        dr = jang._closed_loop_costs("SS-DRKF", np.full(3, 0.4), qs, rs, loop_keys, "gaussian", 3, bar)
    np.testing.assert_allclose(dr0[0], one[0], rtol=1e-8)
    assert np.all(dr[2]) and not np.allclose(dr[0], one[0])


@pytest.mark.slow  # ~30 s
def test_lqr_experiment_small(tmp_path):
    report = jang.run_lqr(3, seed=0, train_runs=2, settings=("gaussian",), names=("SS-KF", "SS-DRKF"))
    assert [(r.filter, r.metric) for r in report.rows] == [
        ("Gaussian: SS-KF", "lqr_cost"), ("Gaussian: SS-KF", "mse"), ("Gaussian: SS-DRKF", "lqr_cost"), ("Gaussian: SS-DRKF", "mse")]
    assert all(r.runs == 3 for r in report.rows)
    assert any("SS-DRKF ranks" in n for n in report.notes)
    assert any("θ chosen on 2 separate training runs" in n for n in report.notes)
    assert any("Scale: 3 test runs per setting" in n and "2 separate training runs" in n for n in report.notes)
    em = next(n for n in report.notes if "EM stopped" in n)
    assert "of the 5 runs" in em  # training + test runs
    # The θ sweep is on the training runs: one row per training run, one column per θ.
    sweep = next(iter(report.sweeps.values()))
    assert "training runs" in next(iter(report.sweeps)) and sweep.values["SS-DRKF"].shape == (2, len(jang.THETAS))
    # A failed run is NaN in a sweep; the plot averages the finite runs (the CLI's --plots path).
    sweep.values["SS-DRKF"][0, 0] = np.nan
    from jdrkf.plotting import plot_sweeps

    assert plot_sweeps(report, tmp_path / "sweeps.png").exists()


def test_default_training_runs_are_capped():
    """The default θ-selection uses at most `TRAIN_RUNS` training runs (the cut default)."""
    import inspect

    assert inspect.signature(jang.run_lqr).parameters["train_runs"].default is None
    assert jang.TRAIN_RUNS < jdrkf.experiments.get("jang-lqr").default_runs
