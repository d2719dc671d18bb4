"""Monte Carlo engine: common random numbers, chunking, clairvoyant filters, sharding."""

import os
import pathlib
import subprocess
import sys
import textwrap

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jdrkf
from oracles import numpy_kalman_filter


def _setup(alpha=1.0, runs=6, T=40, outliers=True):
    model = jdrkf.LinearModel([[0.9802, 0.0196], [0.0, 0.9802]], [[1.0, -1.0]], [[1.9608, 0.0195], [0.0195, 1.9605]], [[1.0]])
    prior = jdrkf.Gaussian(np.zeros(2), np.eye(2))
    noise = jdrkf.OutlierNoise(model.R, 0.2, 50.0) if outliers else None
    traj = jdrkf.simulate(
        jax.random.key(3), model, prior, T, runs, measurement_noise=noise,
        transition_perturbation=jdrkf.UniformPerturbation([[0.0, 1.0], [0.0, 0.0]], alpha),
    )
    return model, prior, traj


def test_metrics_match_direct_numpy_filtering():
    model, prior, traj = _setup()
    out = jdrkf.montecarlo({"KF": jdrkf.KalmanFilter(), "TMKF": jdrkf.Clairvoyant(jdrkf.KalmanFilter())}, model, prior, traj)
    assert set(out) == {"KF", "TMKF"} and out["KF"]["rmse"].shape == (traj.num_runs,)
    for r in range(traj.num_runs):
        x = np.asarray(traj.states[r])
        kf = numpy_kalman_filter(np.zeros(2), np.eye(2), np.asarray(traj.observations[r]), model.F, model.H, model.Q, model.R)
        tm = numpy_kalman_filter(
            np.zeros(2), np.eye(2), np.asarray(traj.clean_observations[r]),
            np.asarray(traj.transition_matrices[r]), model.H, model.Q, model.R,
        )
        np.testing.assert_allclose(out["KF"]["rmse"][r], np.sqrt(np.mean(np.sum((x - kf["filtered_means"]) ** 2, -1))), rtol=1e-10)
        np.testing.assert_allclose(out["TMKF"]["rmse"][r], np.sqrt(np.mean(np.sum((x - tm["filtered_means"]) ** 2, -1))), rtol=1e-10)
    assert out["KF"]["success"].all()
    # The clairvoyant filter is far better under outliers and model error.
    assert out["TMKF"]["rmse"].mean() < out["KF"]["rmse"].mean()


def test_chunking_does_not_change_results():
    model, prior, traj = _setup(runs=7)
    flts = {"KF": jdrkf.KalmanFilter()}
    a = jdrkf.montecarlo(flts, model, prior, traj, chunk_size=3)
    b = jdrkf.montecarlo(flts, model, prior, traj, chunk_size=100)
    np.testing.assert_array_equal(a["KF"]["rmse"], b["KF"]["rmse"])


def test_custom_metrics_and_true_model():
    model, prior, _ = _setup()
    true_model = jdrkf.LinearModel(0.5 * model.F, model.H, model.Q, model.R)
    traj = jdrkf.simulate(jax.random.key(1), true_model, prior, 30, 4)
    mets = {"mean_sq": lambda tr, res: jnp.mean(jdrkf.metrics.squared_error(tr.states, res.filtered_means))}
    out = jdrkf.montecarlo({"TM": jdrkf.Clairvoyant(jdrkf.KalmanFilter())}, model, prior, traj, true_model=true_model, metrics=mets)
    for r in range(4):
        ref = numpy_kalman_filter(np.zeros(2), np.eye(2), np.asarray(traj.observations[r]), true_model.F, model.H, model.Q, model.R)
        np.testing.assert_allclose(out["TM"]["mean_sq"][r], np.mean(np.sum((np.asarray(traj.states[r]) - ref["filtered_means"]) ** 2, -1)), rtol=1e-10)


def test_montecarlo_validation():
    model, prior, traj = _setup(runs=2, T=5)
    with pytest.raises(ValueError, match="filters is empty"):
        jdrkf.montecarlo({}, model, prior, traj)
    with pytest.raises(ValueError, match=r"filters\['x'\] must be a jdrkf filter"):
        jdrkf.montecarlo({"x": object()}, model, prior, traj)
    with pytest.raises(ValueError, match="chunk_size must be >= 1"):
        jdrkf.montecarlo({"KF": jdrkf.KalmanFilter()}, model, prior, traj, chunk_size=0)
    with pytest.raises(ValueError, match="chunk_size must be an integer"):
        jdrkf.montecarlo({"KF": jdrkf.KalmanFilter()}, model, prior, traj, chunk_size=2.5)


def test_sharded_over_two_host_devices_matches_single_device(tmp_path):
    model, prior, traj = _setup(runs=5)
    single = jdrkf.montecarlo({"KF": jdrkf.KalmanFilter()}, model, prior, traj)["KF"]["rmse"]
    np.save(tmp_path / "single.npy", single)
    script = textwrap.dedent(
        f"""
        import jax, numpy as np
        jax.config.update("jax_enable_x64", True)
        assert len(jax.local_devices()) == 2, jax.local_devices()
        import sys; sys.path.insert(0, {str(pathlib.Path(__file__).parent)!r})
        from test_montecarlo import _setup
        import jdrkf
        model, prior, traj = _setup(runs=5)
        out = jdrkf.montecarlo({{"KF": jdrkf.KalmanFilter()}}, model, prior, traj, chunk_size=3)
        np.testing.assert_allclose(out["KF"]["rmse"], np.load({str(tmp_path / "single.npy")!r}), rtol=1e-12)
        print("OK", len(jax.local_devices()))
        """
    )
    env = dict(os.environ, XLA_FLAGS="--xla_force_host_platform_device_count=2", JAX_PLATFORMS="cpu")
    proc = subprocess.run([sys.executable, "-c", script], env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "OK 2" in proc.stdout


def test_progress_bars_show_compiling_then_runs(capsys):
    model, prior, traj = _setup(runs=5, T=5)
    jdrkf.montecarlo({"KF": jdrkf.KalmanFilter()}, model, prior, traj, chunk_size=2, progress=True)
    err = capsys.readouterr().err.replace("\r", "\n")
    assert "compiling Monte Carlo (1 filter, 2 runs per call)" in err
    assert "Monte Carlo: 100%" in err and "5/5" in err and ("run/s" in err or "s/run" in err)  # rate; per-chunk updates: test_cli


def test_keeps_the_callers_order_of_filters_and_metrics():
    # JAX flattens dicts in sorted key order; the result must follow the caller's order instead.
    model, prior, traj = _setup(runs=2, T=5)
    flts = {"zeta": jdrkf.KalmanFilter(), "alpha": jdrkf.Clairvoyant(jdrkf.KalmanFilter()), "Mid": jdrkf.KalmanFilter()}
    mets = {"z_rmse": lambda tr, res: jdrkf.metrics.rmse(tr.states, res.filtered_means),
            "a_mse": lambda tr, res: jnp.mean(jdrkf.metrics.squared_error(tr.states, res.filtered_means))}
    out = jdrkf.montecarlo(flts, model, prior, traj, metrics=mets, chunk_size=1)
    assert list(out) == ["zeta", "alpha", "Mid"]
    assert all(list(v) == ["z_rmse", "a_mse", "success"] for v in out.values())
    np.testing.assert_allclose(out["zeta"]["z_rmse"] ** 2, out["zeta"]["a_mse"], rtol=1e-12)
