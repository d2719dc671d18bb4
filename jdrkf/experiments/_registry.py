"""Experiment registry and the report format of `jdrkf reproduce`."""

from __future__ import annotations

import dataclasses
from typing import Callable

import numpy as np

from .. import metrics


@dataclasses.dataclass(frozen=True)
class Row:
    """One (filter, metric) line: the paper's number and ours over `runs` runs."""

    filter: str
    metric: str
    paper: float | None
    mean: float
    ci95: tuple[float, float]
    runs: int

    @classmethod
    def from_values(cls, filter: str, metric: str, paper: float | None, values) -> "Row":
        mean, ci = metrics.mean_ci(values)
        return cls(filter, metric, paper, mean, ci, int(np.size(values)))


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


@dataclasses.dataclass
class Report:
    """Result of an experiment: rows, free-text notes (how and why we differ from the
    paper), the seed, and optional per-step curves and parameter sweeps for plotting."""

    experiment: str
    seed: int
    rows: list[Row]
    notes: list[str] = dataclasses.field(default_factory=list)
    curves: dict[str, np.ndarray] = dataclasses.field(default_factory=dict)
    sweeps: dict[str, Sweep] = dataclasses.field(default_factory=dict)
    curves_ylabel: str | None = None  # None: curves are per-step MSEs (plotted in dB, smoothed)

    def to_json(self) -> dict:
        return {
            "experiment": self.experiment,
            "seed": self.seed,
            "rows": [
                {"filter": r.filter, "metric": r.metric, "paper": r.paper, "mean": r.mean, "ci95": list(r.ci95), "runs": r.runs}
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
        the paper gives fewer than two numbers for `metric`)."""
        rows = [r for r in self.rows if r.metric == metric and r.paper is not None]
        if len(rows) < 2:
            return None
        return [r.filter for r in sorted(rows, key=lambda r: r.paper)] == [r.filter for r in sorted(rows, key=lambda r: r.mean)]

    def table(self) -> str:
        """Markdown table: filter, metric, paper, ours (mean and 95% CI), runs."""
        lines = [
            f"## {self.experiment} (seed {self.seed})",
            "",
            "| filter | metric | paper | ours (mean) | 95% CI | runs |",
            "|---|---|---|---|---|---|",
        ]
        for r in self.rows:
            paper = "—" if r.paper is None else f"{r.paper:.4g}"
            lines.append(f"| {r.filter} | {r.metric} | {paper} | {r.mean:.4g} | [{r.ci95[0]:.4g}, {r.ci95[1]:.4g}] | {r.runs} |")
        lines.append("")
        for metric in dict.fromkeys(r.metric for r in self.rows):
            agrees = self.ranking_agrees(metric)
            if agrees is not None:
                lines.append(f"Ranking by {metric} agrees with the paper: {'yes' if agrees else 'NO'}")
        if self.notes:
            lines += ["", "Notes:"] + [f"- {n}" for n in self.notes]
        return "\n".join(lines)


@dataclasses.dataclass(frozen=True)
class Experiment:
    """A registered reproduction: `run(runs, seed, progress, curves) -> Report`."""

    name: str
    description: str
    default_runs: int
    run: Callable[..., Report]


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
