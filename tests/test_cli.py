"""The `jdrkf` command line and the experiment registry."""

import contextlib
import json
import pathlib
import re
import subprocess
import sys
import time

import jax
import numpy as np
import pytest

import jdrkf
import jdrkf.experiments
from jdrkf import _progress, cli


def test_list(capsys):
    assert cli.main(["list"]) == 0
    out = capsys.readouterr().out
    for name in ["wang-ye-table1", "wang-ye-table2", "wang-ye-table3"]:
        assert name in out


def test_reproduce_table_json_and_plot(tmp_path, capsys):
    path = tmp_path / "t3.json"
    code = cli.main(["reproduce", "wang-ye-table3", "--runs", "4", "--seed", "7", "--json", str(path), "--plots", str(tmp_path), "--no-progress"])
    assert code == 0
    out = capsys.readouterr().out
    assert "| TMKF | rmse | 3.23 |" in out and "| KF | rmse | 21.04 |" in out
    assert "realized rate" in out
    data = json.loads(path.read_text())
    assert data["experiment"] == "wang-ye-table3" and data["seed"] == 7
    rows = {r["filter"]: r for r in data["rows"]}
    assert set(rows) == {"TMKF", "KF", "HKF", "tau-KF", "WKF", "MKF", "MKF-tuned"}
    for r in rows.values():
        assert set(r) == {"filter", "metric", "paper", "mean", "ci95", "runs", "sd", "outside_ci", "paper_percentile"}
        assert r["runs"] == 4 and r["metric"] == "rmse"
        assert r["ci95"][0] < r["mean"] < r["ci95"][1]
    # Clairvoyant TMKF (true F, outlier-free data) is far better than the nominal KF.
    assert rows["TMKF"]["mean"] < 0.5 * rows["KF"]["mean"]
    # Table III's headline: the MKF (robust to both model error and outliers) beats the KF.
    assert rows["MKF"]["mean"] < rows["KF"]["mean"]
    assert (tmp_path / "wang-ye-table3.png").stat().st_size > 10_000


def test_table1_tmkf_matches_paper_scale():
    # Independent check of the scenario: with the true model the KF error is the
    # paper's ~3.25 (Table I); 20 runs give a CI of about ±0.1.
    wy = jdrkf.experiments.wang_ye
    traj = wy.scenario(jax.random.key(1), 20, 1.0, False)
    out = jdrkf.montecarlo({"TMKF": wy.filters()["TMKF"]}, wy.nominal_model(), wy.prior(), traj,
                           metrics={"rmse": lambda tr, res: jdrkf.metrics.rmse(tr.states, res.filtered_means)})
    assert abs(np.mean(out["TMKF"]["rmse"]) - 3.25) < 0.25


def test_report_ranking_and_errors(capsys):
    row = jdrkf.experiments.Row
    rep = jdrkf.experiments.Report("x", 0, [row("A", "rmse", 1.0, 2.0, (1.5, 2.5), 3), row("B", "rmse", 2.0, 1.0, (0.5, 1.5), 3)])
    assert rep.ranking_agrees("rmse") is False
    # Unpaired (no per-run values): A − B = 1 ± hypot(0.5, 0.5), above 0: the paper's order is reversed.
    (pair,) = rep.ranking_pairs("rmse")
    assert pair["verdict"] == "reversed" and not pair["paired"]
    np.testing.assert_allclose(pair["ci95"], (1 - np.hypot(0.5, 0.5), 1 + np.hypot(0.5, 0.5)))
    assert "0 reversed" not in rep.table() and "1 reversed" in rep.table()
    assert cli.main(["reproduce", "no-such-experiment"]) == 2
    assert "unknown experiment 'no-such-experiment'" in capsys.readouterr().err


def _report(values: dict, paper: dict):
    return jdrkf.experiments.Report("x", 0, [jdrkf.experiments.Row.from_values(f, "rmse", paper[f], v) for f, v in values.items()])


def test_ranking_is_paired_and_respects_ties():
    rng = np.random.default_rng(0)
    base = rng.uniform(5.0, 15.0, 30)  # a large run-to-run spread, shared by all filters (common random numbers)
    values = {"A": base, "B": base + 0.05 + 0.01 * rng.standard_normal(30), "C": base + 0.05 + 0.01 * rng.standard_normal(30)}
    # Paper: A < B clearly, B and C within 1% (a tie).
    pairs = _report(values, {"A": 10.0, "B": 12.0, "C": 12.05}).ranking_pairs("rmse")
    assert [(p["a"], p["b"], p["verdict"]) for p in pairs] == [("A", "B", "agrees"), ("B", "C", "tie")]
    # Paired interval from NumPy/SciPy: mean difference ± t_{0.975, 29} s / √30.
    from scipy import stats
    d = values["A"] - values["B"]
    half = stats.t.ppf(0.975, 29) * d.std(ddof=1) / np.sqrt(30)
    np.testing.assert_allclose(pairs[0]["ci95"], (d.mean() - half, d.mean() + half), rtol=1e-9)
    assert pairs[0]["paired"] and pairs[0]["ci95"][1] < 0  # resolved only because it is paired
    # Unpaired, the same means would not be resolved (the spread of `base` dominates).
    lo_a, hi_a = _report(values, {"A": 10.0, "B": 12.0, "C": 12.05}).rows[0].ci95
    assert hi_a - lo_a > 1.0
    # The paper's order reversed in ours: B < A in the paper.
    rev = _report({"A": values["A"], "B": values["B"]}, {"A": 12.0, "B": 10.0}).ranking_pairs("rmse")
    assert rev[0]["a"] == "B" and rev[0]["verdict"] == "reversed"


def test_row_places_the_paper_number_among_our_runs():
    row = jdrkf.experiments.Row
    v = np.arange(1.0, 11.0)  # 1, ..., 10: mean 5.5, interval about [3.3, 7.7]
    inside, above, single = row.from_values("A", "rmse", 6.0, v), row.from_values("A", "rmse", 9.5, v), row.from_values("A", "rmse", 9.5, [2.0])
    assert not inside.outside_ci and above.outside_ci and not single.outside_ci  # one run: no interval to leave
    assert inside.paper_percentile == 60.0 and above.paper_percentile == 90.0 and single.paper_percentile is None
    assert row("A", "rmse", 9.5, 5.5, (3.3, 7.7), 10).paper_percentile is None  # no per-run values kept
    (j,) = jdrkf.experiments.Report("x", 0, [above]).to_json()["rows"]
    assert j["outside_ci"] is True and j["paper_percentile"] == 90.0 and j["sd"] == pytest.approx(np.sqrt(110 / 12))


def test_report_header_legend_single_run_and_positive_ci():
    row = jdrkf.experiments.Row
    rng = np.random.default_rng(1)
    skewed = np.exp(rng.normal(0.0, 2.0, 5))  # positive, heavy right tail: a linear t-interval goes below 0
    lin_lo = skewed.mean() - 2.7764451051977987 * skewed.std(ddof=1) / np.sqrt(5)  # t_{0.975, 4}
    assert lin_lo < 0
    rows = [row.from_values("MKF-tuned", "rmse", 11.7, skewed), row.from_values("HKF", "rmse", None, [3.0])]
    rep = jdrkf.experiments.Report("x", 3, rows, settings={"runs": 5})
    lo, hi = rows[0].ci95
    # Log-scale delta-method interval: m · exp(±t · se / m).
    m, se = skewed.mean(), skewed.std(ddof=1) / np.sqrt(5)
    np.testing.assert_allclose((lo, hi), (m * np.exp(-2.7764451051977987 * se / m), m * np.exp(2.7764451051977987 * se / m)), rtol=1e-9)
    assert 0 < lo < m < hi
    text = rep.table()
    assert "nan" not in text and "— (1 run)" in text
    assert "Run settings: seed 3, runs 5" in text
    assert "- MKF-tuned: moment-based distributionally robust Kalman filter" in text
    assert "- HKF: Huber Kalman filter" in text


class _Computed(Exception):
    pass


@pytest.fixture
def no_compute(monkeypatch):
    """Fail if the CLI reaches the experiment (or imports the experiments for `reproduce`)."""
    def boom(*args, **kwargs):
        raise _Computed("the CLI computed before rejecting its arguments")

    monkeypatch.setattr(jdrkf.experiments.Experiment, "reproduce", boom)
    monkeypatch.setattr(jdrkf.experiments, "get", boom)


def _one_line_error(capsys, code, *needles):
    err = capsys.readouterr().err
    assert code == 2
    assert err.endswith("\n") and err.count("\n") == 1, err
    assert err.startswith("jdrkf: error: ")
    for n in needles:
        assert n in err, err


@pytest.mark.parametrize(
    "args, needle",
    [
        (["--runs", "1"], "argument --runs: must be at least 2, got 1"),
        (["--runs", "2.5"], "argument --runs: expected an integer, got '2.5'"),
        (["--seed", "-1"], "argument --seed: must be in [0, 4294967296), got -1"),
        (["--seed", str(2**32)], "argument --seed: must be in [0, 4294967296)"),
        (["--precision", "float16"], "argument --precision: invalid choice"),
    ],
)
def test_bad_ranges_fail_at_once(args, needle, capsys, no_compute):
    t0 = time.perf_counter()
    with pytest.raises(SystemExit) as e:
        cli.main(["reproduce", "wang-ye-table3", *args])
    assert time.perf_counter() - t0 < 1.0
    _one_line_error(capsys, e.value.code, needle)


def test_unwritable_json_fails_before_computing(tmp_path, capsys, no_compute):
    blocker = tmp_path / "file"
    blocker.write_text("x")  # a file where a directory is needed: unwritable even for root
    t0 = time.perf_counter()
    code = cli.main(["reproduce", "wang-ye-table3", "--json", str(blocker / "out.json")])
    assert time.perf_counter() - t0 < 1.0
    _one_line_error(capsys, code, "cannot write --json", "out.json")
    _one_line_error(capsys, cli.main(["reproduce", "wang-ye-table3", "--json", str(tmp_path)]), "it is a directory")
    # a writable path is left as it was (nothing created before the run)
    ok = tmp_path / "new" / "t.json"
    assert cli._check_file(ok) is None and not ok.exists()


def test_unwritable_plot_dir_fails_before_computing(tmp_path, capsys, no_compute):
    blocker = tmp_path / "file"
    blocker.write_text("x")
    _one_line_error(capsys, cli.main(["reproduce", "wang-ye-table3", "--plots", str(blocker)]), "cannot write --plots")


def test_missing_matplotlib_fails_before_computing(tmp_path, capsys, monkeypatch, no_compute):
    # `None` in sys.modules makes `import matplotlib...` raise ImportError, as if not installed.
    for name in [m for m in sys.modules if m == "matplotlib" or m.startswith("matplotlib.")]:
        monkeypatch.delitem(sys.modules, name)
    monkeypatch.setitem(sys.modules, "matplotlib", None)
    t0 = time.perf_counter()
    code = cli.main(["reproduce", "wang-ye-table3", "--plots", str(tmp_path / "figs")])
    assert time.perf_counter() - t0 < 1.0
    _one_line_error(capsys, code, "--plots needs matplotlib", "pip install 'jdrkf[cli]'")


def test_missing_tqdm_with_progress_fails_before_computing(capsys, monkeypatch, no_compute):
    monkeypatch.setitem(sys.modules, "tqdm", None)
    _one_line_error(capsys, cli.main(["reproduce", "wang-ye-table3", "--progress"]), "--progress needs tqdm")


def test_cli_extra_installs_what_the_cli_imports():
    import tomllib

    pyproject = pathlib.Path(__file__).resolve().parent.parent / "pyproject.toml"
    cli_extra = tomllib.loads(pyproject.read_text())["project"]["optional-dependencies"]["cli"]
    names = {re.split(r"[<>=\[ ]", d)[0] for d in cli_extra}
    assert {"matplotlib", "tqdm"} <= names


def test_quick_mode_and_list(capsys, monkeypatch):
    seen = {}

    def fake_run(runs, seed, progress=False, curves=False, **options):
        seen.update(runs=runs, seed=seed, progress=progress, **options)
        return jdrkf.experiments.Report("fake", seed, [jdrkf.experiments.Row.from_values("KF", "rmse", 1.0, [1.0, 2.0])])

    exp = jdrkf.experiments.Experiment("fake", "a fake experiment", 100, fake_run, metric="RMSE (m)",
                                       quick={"runs": 3, "num_steps": 10})
    monkeypatch.setitem(jdrkf.experiments.EXPERIMENTS, "fake", exp)
    assert cli.main(["reproduce", "fake", "--quick", "--seed", "5", "--no-progress"]) == 0
    assert seen == {"runs": 3, "seed": 5, "progress": False, "num_steps": 10}
    out = capsys.readouterr().out
    assert "## fake — a fake experiment" in out and "Metric: RMSE (m)" in out
    assert "runs 3, mode quick (runs=3, num_steps=10)" in out and "precision float64" in out
    seen.clear()
    assert cli.main(["reproduce", "fake", "--quick", "--runs", "7", "--no-progress"]) == 0
    assert seen["runs"] == 7 and seen["num_steps"] == 10
    assert cli.main(["list"]) == 0
    line = next(ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("fake "))
    assert line.split()[1:5] == ["100", "—", "3", "—"]  # runs, time (not measured), quick runs, quick time
    for e in jdrkf.experiments.EXPERIMENTS.values():  # every experiment has a quick mode smaller than its default
        assert 2 <= e.quick["runs"] <= e.default_runs


def test_full_mode_restores_the_paper_scale(capsys, monkeypatch):
    seen = {}

    def fake_run(runs, seed, progress=False, curves=False, **options):
        seen.update(runs=runs, **options)
        return jdrkf.experiments.Report("fake", seed, [jdrkf.experiments.Row.from_values("KF", "rmse", 1.0, [1.0, 2.0])])

    exp = jdrkf.experiments.Experiment("fake", "a fake experiment", 20, fake_run, quick={"runs": 3, "particles": 10},
                                       full={"runs": 500, "particles": 1000})
    monkeypatch.setitem(jdrkf.experiments.EXPERIMENTS, "fake", exp)
    assert cli.main(["reproduce", "fake", "--no-progress"]) == 0
    assert seen == {"runs": 20}
    assert ", mode " not in capsys.readouterr().out
    seen.clear()
    assert cli.main(["reproduce", "fake", "--full", "--no-progress"]) == 0
    assert seen == {"runs": 500, "particles": 1000}
    assert "runs 500, mode full (runs=500, particles=1000)" in capsys.readouterr().out
    seen.clear()
    assert cli.main(["reproduce", "fake", "--full", "--runs", "30", "--no-progress"]) == 0
    assert seen == {"runs": 30, "particles": 1000}
    with pytest.raises(SystemExit):  # --quick and --full exclude each other
        cli.main(["reproduce", "fake", "--full", "--quick"])
    assert "not allowed with argument" in capsys.readouterr().err
    monkeypatch.setitem(jdrkf.experiments.TIMINGS, "fake", jdrkf.experiments.Timing(60.0, 5.0, full_s=7200.0, full_estimated=True))
    assert cli.main(["list"]) == 0
    line = next(ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("fake "))
    assert line.split()[1:9] == ["20", "60", "s", "3", "5", "s", "500", "est."] and "2.0 h" in line
    _fake_experiment(monkeypatch, "plain")  # no paper-scale setting: --full is an error naming the experiment
    assert cli.main(["reproduce", "plain", "--full", "--no-progress"]) == 2
    assert "'plain' has no separate paper-scale setting" in capsys.readouterr().err
    with pytest.raises(ValueError, match="exclude each other"):
        exp.options(quick=True, full=True)
    import inspect

    for e in jdrkf.experiments.EXPERIMENTS.values():  # a paper scale is at least the default, in options of the run
        if e.full is not None:
            assert e.full["runs"] >= e.default_runs, e.name
            params = inspect.signature(e.run).parameters
            if not any(q.kind is q.VAR_KEYWORD for q in params.values()):  # the fake run takes **options
                assert set(e.full) - {"runs"} <= set(params), e.name


def test_console_script_entry_point():
    proc = subprocess.run([sys.executable, "-m", "jdrkf.cli", "list"], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0 and "wang-ye-table2" in proc.stdout


class _Recorder:
    """A progress reporter that records phases and their updates."""

    def __init__(self):
        self.phases = []

    @contextlib.contextmanager
    def phase(self, name, total=None, unit="it"):
        rec = {"name": name, "total": total, "unit": unit, "updates": []}
        self.phases.append(rec)

        class P:
            def update(self, n=1):
                rec["updates"].append(n)

        yield P()


def _fake_experiment(monkeypatch, name="fake"):
    """A registered experiment that reports a 'tuning' phase of 3 steps, like the real ones."""
    def fake_run(runs, seed, progress=False, curves=False):
        with _progress.phase("tuning", total=3, unit="step") as p:
            for _ in range(3):
                p.update()
        rep = jdrkf.experiments.Report(name, seed, [jdrkf.experiments.Row.from_values("KF", "rmse", 2.0, np.arange(1.0, runs + 1))])
        if curves:
            rep.curves = {"KF": np.ones((runs, 20)), "HKF": np.full(20, 2.0)}
        return rep

    exp = jdrkf.experiments.Experiment(name, "a fake experiment", 5, fake_run)
    monkeypatch.setitem(jdrkf.experiments.EXPERIMENTS, name, exp)
    return exp


def test_progress_reports_every_phase_on_stderr(tmp_path, capsys, monkeypatch):
    _fake_experiment(monkeypatch)
    assert cli.main(["reproduce", "fake", "--progress", "--plots", str(tmp_path)]) == 0
    captured = capsys.readouterr()
    err = captured.err.replace("\r", "\n")
    assert "fake (5 runs), total" in err  # the whole run, with its elapsed time
    assert "tuning: 100%" in err and "3/3" in err and ("step/s" in err or "s/step" in err)  # rate
    assert "plotting: 100%" in err and "1/1" in err
    assert "tuning" not in captured.out and "| KF | rmse |" in captured.out  # bars on stderr, report on stdout
    assert "expect about" not in err  # no measured time: no estimate
    # quiet: --no-progress, and by default when stderr is not a terminal (pytest captures it)
    for flags in (["--no-progress"], []):
        assert cli.main(["reproduce", "fake", *flags]) == 0
        assert capsys.readouterr().err == ""
    # a measured time is announced before the run (not when --runs changes the run count)
    monkeypatch.setitem(jdrkf.experiments.TIMINGS, "fake", jdrkf.experiments.Timing(default_s=95.0, quick_s=4.0))
    assert cli.main(["reproduce", "fake", "--progress"]) == 0
    err = capsys.readouterr().err
    assert err.startswith(f"fake: expect about 95 s (CPU time measured on a {jdrkf.experiments.MEASURED_ON})")
    assert cli.main(["reproduce", "fake", "--progress", "--runs", "3"]) == 0
    assert "expect about" not in capsys.readouterr().err


def test_library_is_quiet_unless_a_reporter_is_installed(capsys, monkeypatch):
    exp = _fake_experiment(monkeypatch)
    exp.reproduce()
    assert capsys.readouterr().err == ""
    rec = _Recorder()
    with _progress.reporting(rec):
        exp.reproduce(runs=2)
    assert [p["name"] for p in rec.phases] == ["fake (2 runs), total", "tuning"]
    assert rec.phases[1]["updates"] == [1, 1, 1] and rec.phases[1]["total"] == 3
    assert _progress.current().__class__ is _progress.Quiet  # restored after the block


def test_tqdm_reporter_shows_rate_and_eta():
    import io

    buf = io.StringIO()
    with _progress.TqdmReporter(file=buf).phase("Monte Carlo", total=4, unit="run") as bar:
        bar.update(2)
        bar.update(2)
    last = buf.getvalue().replace("\r", "\n").strip().splitlines()[-1]
    assert re.match(r"Monte Carlo: 100%.*4/4 \[\d\d:\d\d<\d\d:\d\d, .*(run/s|s/run)\]", last), last


def test_montecarlo_reports_compiling_then_runs_in_chunks():
    model = jdrkf.LinearModel(F=np.eye(1), H=np.eye(1), Q=np.eye(1), R=np.eye(1))
    prior = jdrkf.Gaussian(np.zeros(1), np.eye(1))
    traj = jdrkf.simulate(jax.random.key(0), model, prior, 3, 250)
    rec = _Recorder()
    with _progress.reporting(rec):
        out = jdrkf.montecarlo({"KF": jdrkf.KalmanFilter()}, model, prior, traj)
    names = [p["name"] for p in rec.phases]
    assert names[0].startswith("compiling Monte Carlo (1 filter, 100 runs per call)") and names[1] == "Monte Carlo"
    mc = rec.phases[1]
    # 250 runs: at least 100 runs per call, at most 10 calls -> 100 + 100 + 50 runs
    assert mc["total"] == 250 and mc["unit"] == "run" and mc["updates"] == [100, 100, 50]
    # chunking does not change the results: one call over all runs gives the same per-run RMSE
    whole = jdrkf.montecarlo({"KF": jdrkf.KalmanFilter()}, model, prior, jax.tree.map(lambda a: a[:100], traj))
    np.testing.assert_array_equal(out["KF"]["rmse"][:100], whole["KF"]["rmse"])


def test_list_shows_measured_times(capsys, monkeypatch):
    _fake_experiment(monkeypatch)
    monkeypatch.setitem(jdrkf.experiments.TIMINGS, "fake", jdrkf.experiments.Timing(default_s=7200.0, quick_s=42.0, estimated=True))
    assert cli.main(["list"]) == 0
    out = capsys.readouterr().out
    line = next(ln for ln in out.splitlines() if ln.startswith("fake "))
    assert line.split()[1:6] == ["5", "est.", "2.0", "h", "4"] and "42 s" in line
    assert f"CPU time of the whole command on a {jdrkf.experiments.MEASURED_ON}" in out
    assert set(jdrkf.experiments.TIMINGS) - {"fake"} <= set(jdrkf.experiments.EXPERIMENTS)  # no stale entries


def test_quick_options_are_options_of_the_run_and_shrink_the_horizon():
    import inspect

    for e in jdrkf.experiments.EXPERIMENTS.values():
        params = inspect.signature(e.run).parameters
        for option in set(e.quick) - {"runs"}:
            assert option in params, (e.name, option)
        if "num_steps" in params:  # an experiment with a horizon shrinks it in quick mode
            default = params["num_steps"].default
            assert "num_steps" in e.quick, e.name
            assert default is None or e.quick["num_steps"] < default, e.name


# --------------------------------------------------------------------------- `jdrkf tune`

_TRUE_F = 0.9


def _numpy_kf_rmse(values, states, observations):
    """Per-run RMSE of a scalar Kalman filter in NumPy (the oracle): `x_k = 0.9 x_{k−1} + w`,
    `y_k = x_k + v`, nominal `Q, R, P₀ = values`, `x̂₀ = 0`."""
    q, r, p0 = values
    out = []
    for xs, ys in zip(states, observations):
        m, p, err2 = 0.0, p0, []
        for x, y in zip(xs[:, 0], ys[:, 0]):
            m, p = _TRUE_F * m, _TRUE_F**2 * p + q
            gain = p / (p + r)
            m, p = m + gain * (y - m), (1 - gain) * p
            err2.append((x - m) ** 2)
        out.append(np.sqrt(np.mean(err2)))
    return np.asarray(out)


def _fake_tuning_experiment(monkeypatch, name="fake-tune"):
    """A registered experiment with a cheap tuning problem: the Kalman filter of a scalar model
    whose nominal Q, R and P₀ are tuned (the truth: Q = R = P₀ = 1); its run records `params`."""
    from jdrkf.experiments._tune import TuningProblem

    true = jdrkf.LinearModel(F=np.array([[_TRUE_F]]), H=np.eye(1), Q=np.eye(1), R=np.eye(1))
    seen = {}

    def data(key, runs):
        return jdrkf.simulate(key, true, jdrkf.Gaussian(np.zeros(1), np.eye(1)), 25, runs)

    def make(values):
        return jdrkf.KalmanFilter(throw=False)

    def errors(values, tr):
        model = jdrkf.LinearModel(F=np.array([[_TRUE_F]]), H=np.eye(1), Q=values[0] * np.eye(1), R=values[1] * np.eye(1))
        prior = jdrkf.Gaussian(np.zeros(1), values[2] * np.eye(1))
        return jdrkf.metrics.rmse(tr.states, jax.vmap(lambda y: jdrkf.KalmanFilter()(model, prior, y).filtered_means)(tr.observations))

    problem = TuningProblem("KF", "Kalman filter with nominal Q, R, P0", ("q", "r", "p0"), (0.2, 5.0, 1.0),
                            ((0.0, None), (0.0, 20.0), (0.0, None)), ((0.05, 5.0, True), (0.05, 10.0, True), (0.1, 10.0, True)),
                            data, errors, "mean RMSE", make)

    def run(runs, seed, progress=False, curves=False, params=None):
        seen["params"] = params
        return jdrkf.experiments.Report(name, seed, [jdrkf.experiments.Row.from_values("KF", "rmse", None, [1.0, 2.0])])

    exp = jdrkf.experiments.Experiment(name, "a fake experiment with a tuning problem", 5, run,
                                       tuning=lambda quick: {"KF": problem})
    monkeypatch.setitem(jdrkf.experiments.EXPERIMENTS, name, exp)
    return problem, seen


def _check_tune_json(path, problem, method, runs, seed):
    data = json.loads(path.read_text())
    assert data["experiment"] == "fake-tune" and data["method"] == method and data["runs"] == runs
    (f,) = data["filters"]
    assert {"filter", "parameters", "start", "bounds", "tuned", "train", "start_train", "heldout", "start_heldout",
            "cost", "evaluations", "curve"} <= set(f)
    tuned = np.asarray(f["tuned"])
    for x, (lo, hi) in zip(tuned, problem.bounds):
        assert lo < x and (hi is None or x < hi)
    assert not np.allclose(tuned, problem.start)  # the method moved away from the start
    # Oracle: the reported training and held-out errors from a NumPy Kalman filter on the same runs.
    key = jax.random.key(seed)
    train, test = (problem.data(jax.random.fold_in(key, i), runs) for i in (0, 1))
    np.testing.assert_allclose(f["train"], _numpy_kf_rmse(tuned, train.states, train.observations).mean(), rtol=1e-8)
    held = _numpy_kf_rmse(tuned, test.states, test.observations)
    np.testing.assert_allclose(f["heldout"]["mean"], held.mean(), rtol=1e-8)
    lo, hi = f["heldout"]["ci95"]
    assert np.isfinite([lo, hi]).all() and lo < held.mean() < hi
    np.testing.assert_allclose(f["start_heldout"]["mean"], _numpy_kf_rmse(problem.start, test.states, test.observations).mean(), rtol=1e-8)
    assert f["train"] < f["start_train"]  # the start (Q 5× too small, R 5× too large) is far from the truth
    assert all(np.isfinite(c).all() for c in f["curve"])
    return f


def test_tune_gradient_end_to_end_json_plot_and_reproduce_params(tmp_path, capsys, monkeypatch):
    problem, seen = _fake_tuning_experiment(monkeypatch)
    code = cli.main(["tune", "fake-tune", "--method", "grad", "--budget", "30", "--runs", "4", "--seed", "3",
                     "--out", str(tmp_path), "--no-progress"])
    assert code == 0
    out = capsys.readouterr().out
    assert "| KF (start) | q, r, p0 | 0.2, 5, 1 |" in out and "| KF (grad) | q, r, p0 |" in out
    f = _check_tune_json(tmp_path / "tune-fake-tune-grad.json", problem, "grad", 4, 3)
    # the budget, unless one step (a value-and-gradient and a forward) costs more
    assert f["cost"] <= max(30, 1 + f["vg_over_forward"]) + 1e-9 and f["evaluations"] >= 2
    assert f["ad_mode"] in ("reverse", "forward")  # the cheaper at the start, timed
    assert (tmp_path / "tune-fake-tune-grad.png").stat().st_size > 5_000
    # reproduce --params hands the tuned values to the experiment's run
    assert cli.main(["reproduce", "fake-tune", "--params", str(tmp_path / "tune-fake-tune-grad.json"), "--no-progress"]) == 0
    np.testing.assert_array_equal(seen["params"]["KF"], f["tuned"])


def test_tune_grid_and_random(tmp_path, capsys, monkeypatch):
    problem, _ = _fake_tuning_experiment(monkeypatch)
    assert cli.main(["tune", "fake-tune", "--method", "grid", "--budget", "8", "--runs", "3", "--out", str(tmp_path)]) == 0
    f = _check_tune_json(tmp_path / "tune-fake-tune-grid.json", problem, "grid", 3, 0)
    # k = 2 points per axis: the best of the 8 corners of the box, by the NumPy oracle.
    assert f["k"] == 2 and f["evaluations"] == 8
    key = jax.random.key(0)
    train = problem.data(jax.random.fold_in(key, 0), 3)
    corners = [np.asarray(c) for c in np.array(np.meshgrid(*[[lo, hi] for lo, hi, _ in problem.box], indexing="ij")).reshape(3, -1).T]
    losses = [_numpy_kf_rmse(c, train.states, train.observations).mean() for c in corners]
    np.testing.assert_allclose(f["tuned"], corners[int(np.argmin(losses))], rtol=1e-12)
    assert cli.main(["tune", "fake-tune", "--method", "random", "--budget", "5", "--runs", "3", "--out", str(tmp_path)]) == 0
    f = _check_tune_json(tmp_path / "tune-fake-tune-random.json", problem, "random", 3, 0)
    assert f["evaluations"] == 5 and f["cost"] == 5
    for x, (lo, hi, _) in zip(f["tuned"], problem.box):
        assert lo <= x <= hi
    capsys.readouterr()


@pytest.mark.parametrize(
    "args, needle",
    [
        (["--budget", "0.5"], "argument --budget: must be a finite number at least 1, got 0.5"),
        (["--budget", "inf"], "argument --budget: must be a finite number at least 1"),
        (["--budget", "x"], "argument --budget: expected a number, got 'x'"),
        (["--method", "adam"], "argument --method: invalid choice"),
        (["--runs", "1"], "argument --runs: must be at least 2, got 1"),
    ],
)
def test_tune_bad_arguments_fail_at_once(args, needle, capsys):
    with pytest.raises(SystemExit) as e:
        cli.main(["tune", "wang-ye-table3", *args])
    _one_line_error(capsys, e.value.code, needle)


def test_tune_and_params_errors(tmp_path, capsys, monkeypatch):
    _fake_tuning_experiment(monkeypatch)
    # an experiment without a tuning problem: the error lists those with one
    _one_line_error(capsys, cli.main(["tune", "wang-ye-breakdown"]), "'wang-ye-breakdown' has no tuning problem",
                    "chen-fusion", "wang-ye-table3", "li-torsion", "jang-lqr", "wang-growth")
    _one_line_error(capsys, cli.main(["tune", "no-such-experiment"]), "unknown experiment 'no-such-experiment'")
    blocker = tmp_path / "file"
    blocker.write_text("x")
    _one_line_error(capsys, cli.main(["tune", "fake-tune", "--out", str(blocker)]), "cannot write --out")
    # --params: not a tune result, another experiment's, an experiment whose run takes none, an unknown filter
    _one_line_error(capsys, cli.main(["reproduce", "fake-tune", "--params", str(blocker)]), "not a result of `jdrkf tune`")
    other = tmp_path / "other.json"
    other.write_text(json.dumps({"experiment": "wang-ye-table1", "filters": [{"filter": "MKF", "tuned": [1.0, 1.0, 0.1]}]}))
    _one_line_error(capsys, cli.main(["reproduce", "fake-tune", "--params", str(other)]), "tuned for 'wang-ye-table1', not 'fake-tune'")
    _one_line_error(capsys, cli.main(["reproduce", "chen-fusion", "--params", str(other)]), "tuned for 'wang-ye-table1'")
    other.write_text(json.dumps({"experiment": "chen-fusion", "filters": [{"filter": "KL-MDRKF", "tuned": [0.1, 0.1, 0.1]}]}))
    _one_line_error(capsys, cli.main(["reproduce", "chen-fusion", "--params", str(other)]), "'chen-fusion' takes no tuned parameters", "wang-ye-table3")
    other.write_text(json.dumps({"experiment": "fake-tune", "filters": [{"filter": "UKF", "tuned": [1.0, 1.0, 1.0]}]}))
    _one_line_error(capsys, cli.main(["reproduce", "fake-tune", "--params", str(other)]), "cannot use tuned parameters of 'UKF'")


@pytest.mark.slow  # about a minute: compiles the DR filters' solvers and their derivatives
def test_tune_wang_ye_quick_then_reproduce_with_tuned_radii(tmp_path, capsys):
    assert cli.main(["tune", "wang-ye-table3", "--quick", "--method", "grad", "--budget", "15", "--runs", "3",
                     "--out", str(tmp_path), "--no-progress"]) == 0
    data = json.loads((tmp_path / "tune-wang-ye-table3-grad.json").read_text())
    problems = jdrkf.experiments.wang_ye.tuning_problems(1.0, True, quick=True)
    assert [f["filter"] for f in data["filters"]] == ["W-DRKF", "MKF"]
    for f in data["filters"]:
        p = problems[f["filter"]]
        assert np.isfinite(f["heldout"]["mean"]) and np.isfinite(f["train"])
        for x, (lo, hi) in zip(f["tuned"], p.bounds):
            assert lo < x and (hi is None or x < hi)
        assert not np.allclose(f["tuned"], p.start)
        assert f["train"] <= f["start_train"]
    capsys.readouterr()
    assert cli.main(["reproduce", "wang-ye-table3", "--runs", "2", "--quick", "--no-progress",
                     "--params", str(tmp_path / "tune-wang-ye-table3-grad.json")]) == 0
    out = capsys.readouterr().out
    assert "| W-DRKF-params | rmse |" in out and "| MKF-params | rmse |" in out


@pytest.mark.parametrize(
    "args, needle",
    [
        (["--distributed", "--coordinator", "127.0.0.1:1234"],
         "--num-processes and --process-id must be given with --coordinator (a manual launch)"),
        (["--distributed", "--coordinator", "h:1", "--num-processes", "2", "--process-id", "2"],
         "--process-id must be below --num-processes (2), got 2"),
        (["--coordinator", "h:1", "--num-processes", "2", "--process-id", "0"],
         "--coordinator, --num-processes, --process-id only apply with --distributed"),
    ],
)
def test_distributed_options_are_checked_before_starting(args, needle, capsys, no_compute, monkeypatch):
    def boom(**kwargs):
        raise _Computed("the CLI started the distributed runtime before rejecting its arguments")

    monkeypatch.setattr(jax.distributed, "initialize", boom)
    with pytest.raises(SystemExit) as e:
        cli.main(["reproduce", "wang-ye-table3", *args])
    _one_line_error(capsys, e.value.code, needle)


def test_distributed_start_failure_is_one_line(capsys, no_compute, monkeypatch):
    def fail(**kwargs):
        assert kwargs == {}  # no --coordinator: JAX's cluster detection
        raise ValueError("coordinator_address should be defined.")

    monkeypatch.setattr(jax.distributed, "initialize", fail)
    _one_line_error(capsys, cli.main(["reproduce", "wang-ye-table3", "--distributed"]),
                    "--distributed: jax.distributed.initialize() failed: coordinator_address should be defined;",
                    "pass --coordinator HOST:PORT --num-processes N --process-id I")


def test_tune_help_names_exactly_the_experiments_with_a_tuning_problem(capsys):
    """`jdrkf tune --help` lists the tunable experiments without importing them (startup stays
    light), so the list is written out: it must match the registry."""
    import jdrkf.experiments as ex

    with pytest.raises(SystemExit):
        cli.main(["tune", "--help"])
    text = " ".join(capsys.readouterr().out.split()).replace("- ", "-")  # argparse wraps after hyphens
    listed = re.search(r"with a tuning problem: ([^)]*?)(?: options:|$)", text).group(1)
    names = set()
    for item in listed.split(", "):
        stem, *alts = item.strip().split("/")
        names.add(stem)
        names.update(stem[: -len(a)] + a for a in alts)
    tunable = {name for name, exp in ex.EXPERIMENTS.items() if exp.tuning is not None}
    assert names == tunable
