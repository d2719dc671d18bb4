"""Jang, Hakobyan & Yang (2025) experiments (`jang-convergence`, `jang-lqr`): small runs that check the
pieces against the paper's setting and independent NumPy computations."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jdrkf
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
    x0, w, v, _, _ = jang.noise_laws("uquadratic")
    draws = jax.vmap(lambda k: w.sample(k))(jax.random.split(jax.random.key(0), 20000))
    np.testing.assert_allclose(np.var(np.asarray(draws), axis=0), 0.006, rtol=0.05)


@pytest.mark.slow
def test_em_nominals_and_closed_loop_batch():
    qs, rs = jang._nominal_models(jax.random.key(0), "gaussian", 3)
    assert qs.shape == (3, 4, 4) and rs.shape == (3, 2, 2)
    assert np.all(np.linalg.eigvalsh(np.asarray(qs)) >= 1e-4 - 1e-12)
    a, b, _ = jang.lqr_system()
    controller = jdrkf.LQRController.design(a, b, jang.LQR_Q, jang.LQR_R)
    laws = jang._laws("gaussian")
    keys = jax.random.split(jax.random.key(1), 3)
    ref = jnp.asarray(jang.reference_trajectory())
    out = {}
    for name in ("SS-KF", "SS-DRKF"):
        flt = jang.filters(0.4)[name]
        cost, mse, ok, _ = jang._run_batch(flt, qs, rs, keys, laws, jang._true_model("gaussian"), controller, ref)
        assert np.all(np.asarray(ok)) and np.all(np.isfinite(np.asarray(cost)))
        out[name] = np.asarray(cost)
    # With θ = 0 the steady-state DRKF is the steady-state KF: same closed loop (common random numbers).
    cost0, *_ = jang._run_batch(jdrkf.SteadyStateDRKF(0.0, 0.0, throw=False), qs, rs, keys, laws, jang._true_model("gaussian"), controller, ref)
    np.testing.assert_allclose(np.asarray(cost0), out["SS-KF"], rtol=1e-8)


@pytest.mark.slow  # ~30 s
def test_lqr_experiment_small(tmp_path):
    # Same shapes as above, so the two filters are not compiled again.
    report = jang.run_lqr(3, seed=0, train_runs=3, settings=("gaussian",), names=("SS-KF", "SS-DRKF"))
    assert [(r.filter, r.metric) for r in report.rows] == [
        ("Gaussian: SS-KF", "lqr_cost"), ("Gaussian: SS-KF", "mse"), ("Gaussian: SS-DRKF", "lqr_cost"), ("Gaussian: SS-DRKF", "mse")]
    assert any("SS-DRKF ranks" in n for n in report.notes)
    assert any("θ chosen on 3 separate training runs" in n for n in report.notes)
    # A failed run is NaN in a sweep; the plot averages the finite runs (the CLI's --plots path).
    sweep = next(iter(report.sweeps.values()))
    sweep.values["SS-DRKF"][0, 0] = np.nan
    from jdrkf.plotting import plot_sweeps

    assert plot_sweeps(report, tmp_path / "sweeps.png").exists()
