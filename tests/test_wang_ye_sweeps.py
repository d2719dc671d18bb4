"""Wang & Ye (2022) Sec. VII-D reproductions: `wang-ye-sensitivity` (Fig. 1) and
`wang-ye-breakdown` (Fig. 2), run small (few runs, short horizon)."""

import math

import jax
import numpy as np
import pytest

import jdrkf.experiments
from jdrkf import cli
from jdrkf.experiments import wang_ye_sweeps as sw

RUNS, STEPS = 3, 200


@pytest.fixture(scope="module")
def sensitivity():
    return sw.run_sensitivity(runs=RUNS, seed=3, num_steps=STEPS)


@pytest.fixture(scope="module")
def breakdown():
    return sw.run_breakdown(runs=RUNS, seed=5, num_steps=STEPS)


def test_registered(capsys):
    assert cli.main(["list"]) == 0
    out = capsys.readouterr().out
    assert "wang-ye-sensitivity" in out and "wang-ye-breakdown" in out
    for name in ("wang-ye-sensitivity", "wang-ye-breakdown"):
        exp = jdrkf.experiments.get(name)
        assert exp.run in (sw.run_sensitivity, sw.run_breakdown) and exp.default_runs >= 2
    assert sw.NUM_STEPS == 10_000  # the paper's horizon in the registered experiments


def test_eps_sweep_scenario_common_random_numbers():
    traj = sw.eps_sweep_scenario(jax.random.key(0), 4, 1.0, 50.0, (0.0, 0.2, 0.5), num_steps=300)
    assert traj.states.shape == (12, 300, 2) and traj.transition_matrices.shape == (12, 300, 2, 2)
    states, clean, out, fs = (np.asarray(a).reshape(3, 4, *a.shape[1:]) for a in (traj.states, traj.clean_observations, traj.outliers, traj.transition_matrices))
    # Same states, nominal noise and Δ_k at every ε_real; outlier sets nested.
    for j in (1, 2):
        np.testing.assert_array_equal(states[j], states[0])
        np.testing.assert_array_equal(clean[j], clean[0])
        np.testing.assert_array_equal(fs[j], fs[0])
    assert not out[0].any() and np.all(out[1] <= out[2])
    assert 0.1 < out[1].mean() < 0.3 and 0.4 < out[2].mean() < 0.6
    y = np.asarray(traj.observations).reshape(3, 4, 300, 1)
    np.testing.assert_allclose(np.abs(y[2] - clean[2])[out[2]], 50.0)


def test_sensitivity_structure(sensitivity):
    rep = sensitivity
    assert rep.experiment == "wang-ye-sensitivity" and rep.seed == 3
    fig_a, fig_b = rep.sweeps.values()
    np.testing.assert_allclose(fig_a.x, sw.EPS_REAL)
    assert set(fig_a.values) == {"HKF-contamination", "HKF-normal", "KF", "TMKF"}
    for v in fig_a.values.values():
        assert v.shape == (RUNS, len(sw.EPS_REAL)) and np.all(np.isfinite(v))
    np.testing.assert_allclose(fig_b.x, sw.THETA2)
    assert fig_b.x[0] == 1.0 and math.isclose(fig_b.x[-1], 1.1)
    assert set(fig_b.values) == {"MKF"} and fig_b.values["MKF"].shape == (RUNS, 11)
    rows = {(r.filter, r.metric): r for r in rep.rows}
    assert len(rows) == 4 * 6 + 11
    row = rows[("HKF-contamination", "rmse@eps_real=0.3")]
    assert row.runs == RUNS and row.paper is None
    assert math.isclose(row.mean, fig_a.values["HKF-contamination"][:, 3].mean())
    assert math.isclose(rows[("MKF", "rmse@theta2=1.03")].mean, fig_b.values["MKF"][:, 3].mean())
    notes = " ".join(rep.notes)
    assert "Paper's claim (Fig. 1(a))" in notes and "Paper's claim (Fig. 1(b))" in notes
    assert "relative spread" in notes and "bootstrap 95% interval of the argmin" in notes
    assert f"{RUNS} seeded Monte Carlo runs (seed 3) of T = {STEPS} steps" in notes
    # Without outliers (ε_real = 0) and α = 0, TMKF is the KF on the same data.
    np.testing.assert_allclose(fig_a.values["TMKF"][:, 0], fig_a.values["KF"][:, 0])


def test_sensitivity_hkf_flatter_than_kf(sensitivity):
    # Fig. 1(a)'s point, robustly even on short runs: the Huber-type estimators barely
    # move as ε_real goes 0 → 0.5, while the KF's error grows by tens of percent.
    vals = next(iter(sensitivity.sweeps.values())).values
    kf_growth = vals["KF"][:, -1] / vals["KF"][:, 0]
    for name in ("HKF-contamination", "HKF-normal"):
        assert np.all(vals[name][:, -1] / vals[name][:, 0] < 1.0 + 0.5 * (kf_growth - 1.0))
    assert np.all(kf_growth > 1.2)


def test_breakdown_structure_and_paper_numbers(breakdown):
    rep = breakdown
    assert list(rep.sweeps) == ["Fig. 2(a): α=0, ±50 outliers", "Fig. 2(b): α=1, ±50 outliers"]
    six = {"TMKF", "KF", "HKF", "tau-KF", "WKF", "MKF"}
    sw0, sw1 = rep.sweeps.values()
    assert set(sw0.values) == six and set(sw1.values) == six | {"TMKF-off-by-one"}
    for s in (sw0, sw1):
        np.testing.assert_allclose(s.x, sw.EPS_REAL)
        assert all(v.shape == (RUNS, 6) for v in s.values.values())
        assert set(s.paper) == six
    # The authors' numbers at ε_real = 0, 0.1, 0.3, 0.5 only (NaN at 0.2, 0.4).
    np.testing.assert_array_equal(sw0.paper["KF"], [9.45, 13.08, np.nan, 19.71, np.nan, 24.45])
    np.testing.assert_array_equal(sw1.paper["MKF"], [9.72, 10.17, np.nan, 12.38, np.nan, 13.78])
    rows = {(r.filter, r.metric): r for r in rep.rows}
    assert len(rows) == 6 * 6 + 7 * 6
    assert rows[("MKF", "rmse@alpha=1,eps_real=0.3")].paper == 12.38
    assert rows[("tau-KF", "rmse@alpha=0,eps_real=0.5")].paper == 31.12
    assert rows[("HKF", "rmse@alpha=0,eps_real=0.2")].paper is None
    assert rows[("TMKF-off-by-one", "rmse@alpha=1,eps_real=0")].paper is None
    assert math.isclose(rows[("WKF", "rmse@alpha=1,eps_real=0.4")].mean, sw1.values["WKF"][:, 4].mean())
    notes = " ".join(rep.notes)
    assert "Paper's claim (Fig. 2)" in notes and "holds significantly at" in notes
    assert "off-by-one" in notes and "Pairs ordered differently from the paper" in notes
    table = rep.table()
    assert "Ranking by rmse@alpha=1,eps_real=0.3 agrees with the paper" in table
    assert "Ranking by rmse@alpha=0,eps_real=0.2" not in table  # no paper numbers there


def test_breakdown_substance(breakdown):
    sw0, sw1 = breakdown.sweeps.values()
    j = sw.EPS_REAL.index(0.3)
    # α = 0, 30% outliers of ±50: Huber clipping removes most of the KF's error, per run.
    assert np.all(sw0.values["HKF"][:, j] < 0.7 * sw0.values["KF"][:, j])
    # The clairvoyant KF given F_{t+1} instead of F_t (the authors' TMKF) is far worse.
    assert np.all(sw1.values["TMKF-off-by-one"] > 1.5 * sw1.values["TMKF"])


def test_cli_end_to_end(tmp_path, capsys, monkeypatch):
    monkeypatch.setattr(sw, "NUM_STEPS", STEPS)
    path = tmp_path / "s.json"
    code = cli.main(["reproduce", "wang-ye-sensitivity", "--runs", str(RUNS), "--seed", "3", "--json", str(path), "--plots", str(tmp_path), "--no-progress"])
    assert code == 0
    out = capsys.readouterr().out
    assert "| HKF-normal | rmse@eps_real=0.3 | — |" in out and "| MKF | rmse@theta2=1.10 | — |" in out
    assert (tmp_path / "wang-ye-sensitivity-sweeps.png").stat().st_size > 10_000
    assert path.exists()
