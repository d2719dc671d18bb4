"""Experiment registry and the report format of `jdrkf reproduce`."""

from __future__ import annotations

import dataclasses
import inspect
from typing import Any, Callable, Mapping

import numpy as np

from .. import _progress, metrics

# Paper numbers within this relative distance of each other are a tie: the papers'
# tables are mostly single random episodes, printed to 3–4 digits.
PAPER_TIE_RTOL = 0.01

# Filter labels used across the reproductions, spelled out for the report's legend. A
# label is explained by its longest entry it starts with ("MKF-tuned" by "MKF"), after
# any "setting: " prefix; an experiment's own `legend` takes precedence.
GLOSSARY: dict[str, str] = {
    "KF": "Kalman filter on the nominal model",
    "TMKF": "Kalman filter given the true model and the outlier-free measurements (clairvoyant reference)",
    "HKF": "Huber Kalman filter (Huber M-estimate measurement update)",
    "tau-KF": "τ-robust Kalman filter of Zorzi (least favourable model in a τ-divergence ball)",
    "WKF": "Wasserstein Kalman filter of Shafieezadeh-Abadeh et al. (Wasserstein ball on the joint law)",
    "MKF": "moment-based distributionally robust Kalman filter of Wang & Ye (Algorithm 1)",
    "SS-KF": "steady-state Kalman filter (constant gain)",
    "SS-DRKF": "steady-state Wasserstein distributionally robust Kalman filter of Jang et al.",
    "risk-sensitive": "risk-sensitive Kalman filter",
    "BCOT": "bicausal optimal-transport distributionally robust Kalman filter",
    "CKF": "centralized Kalman filter using all sensors",
    "CI": "covariance intersection fusion of the sensors' local estimates",
    "KL-MDRKF": "marginal distributionally robust Kalman filter, per-sensor KL balls (Chen et al.)",
    "MC-MDRKF": "marginal distributionally robust Kalman filter, per-sensor moment constraints (Chen et al.)",
    "STKF": "Student-t Kalman filter (variational, Li et al.)",
    "RBKF": "reweighted robust Kalman filter with a robust loss (Li et al.)",
    "VBKF": "variational Bayesian Kalman filter with unknown measurement covariance",
    "PF": "bootstrap particle filter",
    "UKF": "unscented Kalman filter",
    "EnKF": "ensemble Kalman filter",
    "RPF": "distributionally robust particle filter of Wang (2022)",
}


def explain(label: str, legend: Mapping[str, str] | None = None) -> str | None:
    """The spelled-out name of a filter label, or `None` if neither `legend` nor the
    glossary knows it."""
    legend = {} if legend is None else legend
    if label in legend:
        return legend[label]
    name = label.rsplit(": ", 1)[-1]
    for table in (legend, GLOSSARY):
        keys = [k for k in table if name == k or name.startswith(k + "-") or name.startswith(k + " ") or (name.startswith(k) and name[len(k):].isdigit())]
        if keys:
            return table[max(keys, key=len)]
    return None


@dataclasses.dataclass(frozen=True)
class Row:
    """One (filter, metric) line: the paper's number and ours over `runs` runs.
    `values` (optional, not compared) keeps the per-run values for paired comparisons."""

    filter: str
    metric: str
    paper: float | None
    mean: float
    ci95: tuple[float, float]
    runs: int
    values: np.ndarray | None = dataclasses.field(default=None, compare=False, repr=False)

    @classmethod
    def from_values(cls, filter: str, metric: str, paper: float | None, values) -> "Row":
        """Mean and 95% interval of per-run `values`; for strictly positive values the
        interval is built on the log scale (`metrics.mean_ci(..., scale="log")`), so it
        stays positive."""
        v = np.asarray(values, dtype=np.float64).ravel()
        mean, ci = metrics.mean_ci(v, scale="log" if v.size > 1 and np.all(v > 0) else "linear")
        return cls(filter, metric, paper, mean, ci, int(v.size), v)

    @property
    def sd(self) -> float | None:
        """Standard deviation of the per-run values (`None` without at least two)."""
        return None if self.values is None or self.values.size < 2 else float(np.std(self.values, ddof=1))

    @property
    def outside_ci(self) -> bool:
        """Whether the paper's number lies outside our 95% interval (False without one)."""
        return self.paper is not None and self.runs > 1 and not (self.ci95[0] <= self.paper <= self.ci95[1])

    @property
    def paper_percentile(self) -> float | None:
        """Percentage of our per-run values at or below the paper's number: where a
        single-episode paper number falls among our runs (`None` without per-run values)."""
        if self.paper is None or self.values is None or self.values.size < 2:
            return None
        return 100.0 * float(np.mean(self.values <= self.paper))


@dataclasses.dataclass
class Sweep:
    """Per-run values of several filters over a swept parameter: `values[name]` has
    shape `(runs, len(x))`; `paper[name]` optionally gives the paper's numbers at `x`
    (NaN where the paper has none)."""

    x_label: str
    x: np.ndarray
    values: dict[str, np.ndarray]
    paper: dict[str, np.ndarray] = dataclasses.field(default_factory=dict)
    y_label: str = "RMSE"


def _fmt(x: float) -> str:
    return f"{x:.4g}"


@dataclasses.dataclass
class Report:
    """Result of an experiment: rows, free-text notes (how and why we differ from the
    paper), the seed, and optional per-step curves and parameter sweeps for plotting.

    `title`, `scenario`, `metric`, `legend` and `settings` make up the header of
    `table()`; `Experiment.reproduce` fills them from the registry."""

    experiment: str
    seed: int
    rows: list[Row]
    notes: list[str] = dataclasses.field(default_factory=list)
    curves: dict[str, np.ndarray] = dataclasses.field(default_factory=dict)
    sweeps: dict[str, Sweep] = dataclasses.field(default_factory=dict)
    curves_ylabel: str | None = None  # None: curves are per-step MSEs (plotted in dB, smoothed)
    title: str = ""
    scenario: str = ""
    metric: str = ""
    legend: dict[str, str] = dataclasses.field(default_factory=dict)
    settings: dict[str, Any] = dataclasses.field(default_factory=dict)

    def to_json(self) -> dict:
        return {
            "experiment": self.experiment,
            "seed": self.seed,
            "title": self.title,
            "scenario": self.scenario,
            "metric": self.metric,
            "settings": self.settings,
            "rows": [
                {"filter": r.filter, "metric": r.metric, "paper": r.paper, "mean": r.mean, "ci95": list(r.ci95), "runs": r.runs,
                 "sd": r.sd, "outside_ci": r.outside_ci, "paper_percentile": r.paper_percentile}
                for r in self.rows
            ],
            "notes": self.notes,
            "sweeps": {
                name: {
                    "x_label": sw.x_label,
                    "x": np.asarray(sw.x).tolist(),
                    "values": {f: np.asarray(v).tolist() for f, v in sw.values.items()},
                    "paper": {f: [None if np.isnan(p) else float(p) for p in np.asarray(v, float)] for f, v in sw.paper.items()},
                }
                for name, sw in self.sweeps.items()
            },
        }

    def ranking_agrees(self, metric: str) -> bool | None:
        """Whether ordering the filters by our mean gives the paper's order (`None` if
        the paper gives fewer than two numbers for `metric`). Strict: ties count as
        disagreements here; `ranking_pairs` weighs them."""
        rows = [r for r in self.rows if r.metric == metric and r.paper is not None]
        if len(rows) < 2:
            return None
        return [r.filter for r in sorted(rows, key=lambda r: r.paper)] == [r.filter for r in sorted(rows, key=lambda r: r.mean)]

    def ranking_pairs(self, metric: str) -> list[dict]:
        """Compare the paper's order of the filters for `metric` with ours, one pair of
        neighbours in the paper's order at a time (lower first).

        Each pair gets the 95% interval of our difference `a − b`: paired over runs when
        both rows carry per-run values of the same length (every reproduction runs its
        filters on the same simulated runs), otherwise from the two rows' own intervals
        (half-widths combined in quadrature). The verdict is

        - `"agrees"`: the paper has `a < b` and our interval lies below 0;
        - `"tie"`: our interval contains 0 (not resolved with these runs), or the paper's
          numbers are within `PAPER_TIE_RTOL` of each other and ours are too;
        - `"reversed"`: our interval lies on the other side of 0;
        - `"separated"`: the paper ties `a` and `b`, ours separate them.
        """
        rows = sorted((r for r in self.rows if r.metric == metric and r.paper is not None), key=lambda r: r.paper)
        out = []
        for a, b in zip(rows[:-1], rows[1:]):
            paired = a.values is not None and b.values is not None and a.values.size == b.values.size and a.values.size > 1
            if paired:
                diff, (lo, hi) = metrics.mean_ci(a.values - b.values)
            else:
                diff = a.mean - b.mean
                ha = (a.ci95[1] - a.ci95[0]) / 2 if a.runs > 1 else np.nan
                hb = (b.ci95[1] - b.ci95[0]) / 2 if b.runs > 1 else np.nan
                half = float(np.hypot(ha, hb))
                lo, hi = diff - half, diff + half
            paper_tie = abs(a.paper - b.paper) <= PAPER_TIE_RTOL * max(abs(a.paper), abs(b.paper))
            if not (lo <= hi):  # no interval (single runs): compare the means
                lo = hi = diff
            contains0 = lo <= 0 <= hi
            if paper_tie:
                verdict = "tie" if contains0 else "separated"
            else:
                verdict = "tie" if contains0 else ("agrees" if hi < 0 else "reversed")
            out.append({"a": a.filter, "b": b.filter, "paper": (a.paper, b.paper), "diff": float(diff),
                        "ci95": (float(lo), float(hi)), "paired": paired, "paper_tie": paper_tie, "verdict": verdict})
        return out

    def header(self) -> list[str]:
        """The report's header lines: title, scenario, metric, run settings, legend."""
        title = f"## {self.experiment}" + (f" — {self.title}" if self.title else "")
        lines = [title, ""]
        if self.scenario:
            lines.append(f"Scenario: {self.scenario}")
        if self.metric:
            lines.append(f"Metric: {self.metric}")
        settings = {"seed": self.seed, **self.settings}
        lines.append("Run settings: " + ", ".join(f"{k} {v}" for k, v in settings.items()))
        names = dict.fromkeys(r.filter for r in self.rows)
        legend = [(n, explain(n, self.legend)) for n in names]
        legend = [(n, e) for n, e in legend if e is not None]
        if legend:
            lines += ["", "Filters:"] + [f"- {n}: {e}" for n, e in legend]
        return lines

    def table(self) -> str:
        """Markdown report: header, then per filter and metric the paper's number and our
        mean with its 95% interval over the runs, then the ranking check against the
        paper (paired intervals first, ties as ties) and the notes."""
        lines = self.header() + [
            "",
            "| filter | metric | paper | ours (mean) | 95% CI | runs |",
            "|---|---|---|---|---|---|",
        ]
        for r in self.rows:
            paper = "—" if r.paper is None else _fmt(r.paper)
            if r.runs < 2 or not np.all(np.isfinite(r.ci95)):
                ci = "— (1 run)" if r.runs < 2 else "—"
            else:
                ci = f"[{_fmt(r.ci95[0])}, {_fmt(r.ci95[1])}]"
            lines.append(f"| {r.filter} | {r.metric} | {paper} | {_fmt(r.mean)} | {ci} | {r.runs} |")
        for metric in dict.fromkeys(r.metric for r in self.rows):
            pairs = self.ranking_pairs(metric)
            if not pairs:
                continue
            count = {v: sum(p["verdict"] == v for p in pairs) for v in ("agrees", "tie", "reversed", "separated")}
            lines += ["", f"Ranking by {metric} against the paper's order, neighbour by neighbour (our difference, 95% CI):"]
            for p in pairs:
                rel = "≈" if p["paper_tie"] else "<"
                kind = "paired over runs" if p["paired"] else "unpaired"
                verdict = {
                    "agrees": "agrees",
                    "tie": "tie (the interval contains 0)" if not p["paper_tie"] else "tie, as in the paper",
                    "reversed": "reversed",
                    "separated": "the paper's tie is separated in ours",
                }[p["verdict"]]
                lines.append(
                    f"- paper {p['a']} {rel} {p['b']} ({_fmt(p['paper'][0])} vs {_fmt(p['paper'][1])}): ours "
                    f"{p['a']} − {p['b']} = {p['diff']:.3g} [{p['ci95'][0]:.3g}, {p['ci95'][1]:.3g}] ({kind}): {verdict}"
                )
            lines.append(
                f"Ranking by {metric} agrees with the paper for {count['agrees']} of {len(pairs)} neighbouring pairs; "
                f"{count['tie']} tie(s), {count['separated']} paper tie(s) separated, {count['reversed']} reversed."
            )
        if self.notes:
            lines += ["", "Notes:"] + [f"- {n}" for n in self.notes]
        return "\n".join(lines)


@dataclasses.dataclass(frozen=True)
class Timing:
    """Measured time in seconds of a whole `jdrkf reproduce NAME --no-progress` process
    (import, compiling, tuning, Monte Carlo) at the default run count and with `--quick`.

    It is the process's CPU time (user + system): the machine was shared with other
    jobs, under which wall-clock times were 3–6 times longer and not reproducible; on an
    idle machine of the same kind the wall time is about this or less (XLA keeps at least
    one core busy). `estimated`: the default time is scaled linearly in the run count
    from a run with a tenth of the runs (fixed costs scaled too: an upper estimate)."""

    default_s: float | None  # None: not measured
    quick_s: float
    estimated: bool = False
    full_s: float | None = None  # `--full` (paper scale), if the experiment has one
    full_estimated: bool = False  # `full_s` scaled up as `default_s` is when `estimated`


# Machine the default TIMINGS were measured on, one experiment at a time (float64, jax 0.10;
# benchmarks/results/reproduce_times_cpu.md). Quick times of experiments unchanged since were
# measured earlier on a 2-core Xeon; full times are estimates scaled from smaller runs.
MEASURED_ON = "2-core AMD EPYC"
TIMINGS: dict[str, Timing] = {
    "chen-fusion": Timing(258.4, 44.1, full_s=630.0, full_estimated=True),
    "jang-convergence": Timing(26.9, 24.2),
    "jang-lqr": Timing(173.9, 62.0, full_s=540.0, full_estimated=True),
    "li-convergence": Timing(13.9, 12.4),
    "li-identity": Timing(21.8, 16.2),
    "li-torsion": Timing(68.0, 42.0),
    "wang-growth": Timing(122.4, 17.5),
    "wang-methods": Timing(156.4, 17.4, full_s=1640.0, full_estimated=True),
    "wang-tracking": Timing(52.1, 35.7),
    "wang-ye-breakdown": Timing(25.9, 16.4),
    "wang-ye-sensitivity": Timing(16.0, 11.1),
    "wang-ye-table1": Timing(22.4, 20.8),
    "wang-ye-table2": Timing(24.7, 19.7),
    "wang-ye-table3": Timing(24.4, 20.1),
}


def _duration(seconds: float) -> str:
    return f"{seconds:.0f} s" if seconds < 100 else f"{seconds / 60:.0f} min" if seconds < 6000 else f"{seconds / 3600:.1f} h"


@dataclasses.dataclass(frozen=True)
class Experiment:
    """A registered reproduction: `run(runs, seed, progress, curves, **quick_options) -> Report`.

    `scenario`, `metric` (with units) and `legend` (filter label → name, beyond the shared
    `GLOSSARY`) head the report. `quick` holds the `--quick` setting: `"runs"` and any
    keyword options of `run` that shrink the problem. `full`, for experiments whose default
    is cut to fit minutes, holds the paper's scale in the same form (`--full`); `None`: the
    default is the paper's scale. `timing` is the measured time
    (`TIMINGS`, machine `MEASURED_ON`), `None` if not measured. `tuning(quick)`, if given,
    returns the experiment's tuning problems `{filter label: TuningProblem}` (`jdrkf tune`);
    a `run` with a `params` argument (`{filter label: tuned values}`) also evaluates those."""

    name: str
    description: str
    default_runs: int
    run: Callable[..., Report]
    scenario: str = ""
    metric: str = ""
    legend: Mapping[str, str] = dataclasses.field(default_factory=dict)
    quick: Mapping[str, Any] = dataclasses.field(default_factory=lambda: {"runs": 4})
    full: Mapping[str, Any] | None = None
    tuning: Callable[[bool], Mapping[str, Any]] | None = None

    @property
    def takes_params(self) -> bool:
        """Whether `reproduce(params=...)` can add filters with tuned parameters."""
        return self.tuning is not None and "params" in inspect.signature(self.run).parameters

    def check_takes_params(self) -> None:
        """`ValueError` naming the experiments that do, unless this one `takes_params`."""
        if not self.takes_params:
            raise ValueError(f"experiment {self.name!r} takes no tuned parameters; experiments that do: "
                             f"{', '.join(sorted(n for n, e in EXPERIMENTS.items() if e.takes_params))}")

    @property
    def timing(self) -> Timing | None:
        return TIMINGS.get(self.name)

    def time_estimate(self, quick: bool = False, full: bool = False) -> str:
        """The measured time as text: "45 s", "est. 2.1 h", or "—" if not measured."""
        t = self.timing
        seconds = None if t is None else t.quick_s if quick else t.full_s if full else t.default_s
        if seconds is None:
            return "—"
        estimated = t.full_estimated if full else t.estimated and not quick
        return ("est. " if estimated else "") + _duration(seconds)

    def options(self, quick: bool = False, full: bool = False) -> dict[str, Any]:
        """Keyword options of `run` for the mode: `quick`, `full` (paper scale) or neither
        (the default); `"runs"` included."""
        if quick and full:
            raise ValueError("quick and full exclude each other")
        if full and self.full is None:
            raise ValueError(f"experiment {self.name!r} has no separate paper-scale setting: its default is the paper's scale")
        return {"runs": self.default_runs, **(self.quick if quick else self.full if full else {})}

    def reproduce(self, runs: int | None = None, seed: int = 0, *, quick: bool = False, full: bool = False,
                  progress: bool = False, curves: bool = False, settings: Mapping[str, Any] | None = None,
                  params: Mapping[str, tuple[float, ...]] | None = None) -> Report:
        """Run the experiment (`runs=None`: the run count of the mode — default, `quick`
        or `full`) and fill the report's header; `settings` adds entries to its run
        settings. `progress`:
        report the phases as bars on stderr (needs `tqdm`), unless a reporter is
        installed (`jdrkf._progress.reporting`), which then gets them. `params`: tuned
        values per filter label (from `jdrkf tune`), added as filters `<label>-params`."""
        options = self.options(quick, full)
        if params:
            self.check_takes_params()
            options["params"] = dict(params)
        mode_runs = options.pop("runs")
        runs = mode_runs if runs is None else runs
        mode = "quick" if quick else "full" if full else None
        with _progress.reporting(_progress.reporter(progress)) as reporter, \
                reporter.phase(f"{self.name} ({runs} runs{', ' + mode if mode else ''}), total"):
            report = self.run(runs=runs, seed=seed, progress=progress, curves=curves, **options)
        report.title = report.title or self.description
        report.scenario = report.scenario or self.scenario
        report.metric = report.metric or self.metric
        report.legend = {**self.legend, **report.legend}
        report.settings = {"runs": runs, **({"mode": f"{mode} (" + ", ".join(f"{k}={v}" for k, v in (self.quick if quick else self.full).items()) + ")"} if mode else {}),
                           **report.settings, **(settings or {})}
        return report


EXPERIMENTS: dict[str, Experiment] = {}


def register(experiment: Experiment) -> Experiment:
    if experiment.name in EXPERIMENTS:
        raise ValueError(f"experiment {experiment.name!r} is already registered")
    EXPERIMENTS[experiment.name] = experiment
    return experiment


def get(name: str) -> Experiment:
    try:
        return EXPERIMENTS[name]
    except KeyError:
        raise ValueError(f"unknown experiment {name!r}; available: {', '.join(sorted(EXPERIMENTS))}") from None
