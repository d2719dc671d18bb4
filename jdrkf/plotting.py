"""Figures for experiment reports (needs the optional dependency matplotlib)."""

from __future__ import annotations

import pathlib
import textwrap

import numpy as np

from .experiments import Report


def _figure(**kwargs):
    """A matplotlib `Figure` that is not registered with pyplot: no backend is chosen
    and no global state changes, so saving works headless and notebooks keep inline plots."""
    try:
        from matplotlib.figure import Figure
    except ImportError as e:  # pragma: no cover - depends on the environment
        raise ImportError("plotting needs matplotlib: pip install 'jdrkf[cli]'") from e
    return Figure(**kwargs)


def moving_average(x: np.ndarray, window: int) -> np.ndarray:
    """Trailing moving average with a window that grows over the first `window` steps."""
    c = np.cumsum(np.insert(np.asarray(x, dtype=np.float64), 0, 0.0))
    idx = np.arange(1, len(x) + 1)
    lo = np.maximum(idx - window, 0)
    return (c[idx] - c[lo]) / (idx - lo)


_STYLES = ("-", "--", "-.", ":")
_MARKERS = ("o", "s", "^", "v", "D", "P", "X", "*", "<", ">")


def _style(i: int, points: int) -> dict:
    """Line style of the `i`-th series: colour, dash pattern and marker all change from
    one series to the next, so near-identical curves stay distinguishable; about ten
    markers per line over its `points` points, staggered between series so that they do
    not hide each other."""
    every = max(1, points // 10)
    return {"color": f"C{i % 10}", "linestyle": _STYLES[i % len(_STYLES)], "marker": _MARKERS[i % len(_MARKERS)],
            "markevery": ((i * every) // 7 % every, every), "markersize": 4, "linewidth": 1.2}


def mean_band(values: np.ndarray, level: float = 0.95) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per column of `values` `(runs, T)`: the mean `m` over runs and the `level` Student-t
    interval for it, built on the log scale, `m exp(±t se/m)`, where every value is
    positive (as `metrics.mean_ci(..., scale="log")` does) and `m ± t se` elsewhere.
    With one run the interval is the mean itself."""
    from .metrics import t_quantile

    v = np.asarray(values, dtype=np.float64)
    mean = v.mean(axis=0)
    if v.shape[0] < 2:
        return mean, mean, mean
    half = t_quantile(0.5 + level / 2.0, v.shape[0] - 1) * v.std(axis=0, ddof=1) / np.sqrt(v.shape[0])
    positive = np.all(v > 0, axis=0)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.exp(half / mean)
    lo = np.where(positive, mean / ratio, mean - half)
    hi = np.where(positive, mean * ratio, mean + half)
    return mean, lo, hi


def _legend_outside(ax, gap: float = 0.01):
    ax.legend(loc="upper left", bbox_to_anchor=(1.0 + gap, 1.0), fontsize=8, frameon=False)


def _title(report: Report, width: int = 110) -> str:
    """Title lines: the experiment, what it reproduces, and the run mode if not default."""
    text = f"{report.experiment}: {report.title}" if report.title else report.experiment
    if "mode" in report.settings:
        text += f" [{report.settings['mode']}]"
    return textwrap.fill(text, width)


def _save(fig, path):
    path = pathlib.Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    return path


def plot_sweeps(report: Report, path: str | pathlib.Path) -> pathlib.Path:
    """One panel per parameter sweep of the report: mean over runs with a 95% band per
    filter, and the paper's numbers as markers where given. Returns the file path."""
    if not report.sweeps:
        raise ValueError("the report has no parameter sweeps")
    from . import metrics

    fig = _figure(figsize=(7.5 * len(report.sweeps), 4.3))
    axes = fig.subplots(1, len(report.sweeps), squeeze=False)
    for ax, (title, sw) in zip(axes[0], report.sweeps.items(), strict=True):
        for i, (name, vals) in enumerate(sw.values.items()):
            # Failed runs are NaN in a sweep: each point averages the finite runs.
            cols = [vals[:, j][np.isfinite(vals[:, j])] for j in range(len(sw.x))]
            stats = [metrics.mean_ci(c) if c.size > 1 else (float(np.mean(c)) if c.size else np.nan, (np.nan, np.nan)) for c in cols]
            mean = np.array([m for m, _ in stats])
            (line,) = ax.plot(sw.x, mean, label=name, **_style(i, 10))
            ax.fill_between(sw.x, [c[0] for _, c in stats], [c[1] for _, c in stats], color=line.get_color(), alpha=0.12, linewidth=0)
            if name in sw.paper:
                ax.plot(sw.x, sw.paper[name], "x", color=line.get_color(), markersize=8, label=f"{name} (paper)")
        ax.set_xlabel(sw.x_label)
        ax.set_ylabel(sw.y_label)
        runs = next(iter(sw.values.values())).shape[0]
        ax.set_title(f"{title}\n{sw.y_label}: mean and 95% CI over {runs} runs" + ("; x = paper" if sw.paper else ""), fontsize=9)
        ax.grid(alpha=0.3)
        _legend_outside(ax)
    fig.suptitle(_title(report, width=int(55 * len(report.sweeps))), fontsize=10)
    return _save(fig, path)


def plot_error_curves(report: Report, path: str | pathlib.Path, window: int = 50) -> pathlib.Path:
    """Per-step curves, one line per filter with a distinct colour, dash and marker.

    Without `curves_ylabel` the curves are per-step squared errors `e_k`, drawn as
    `10 log10` of their `window`-step moving average (the style of Wang & Ye 2022,
    Figs. 1–2); the paper's RMSE of a filter, where the report has one, is marked at the
    right edge at its level `20 log10 RMSE` (the time average of `e_k` in dB). With
    `curves_ylabel` set they are other per-step quantities, drawn unsmoothed on a log
    scale. A curve of shape `(runs, T)` is drawn as its mean over runs with a 95%
    band (`mean_band`). Returns the file path."""
    if not report.curves:
        raise ValueError("the report has no per-step curves; run the experiment with curves=True")
    fig = _figure(figsize=(10, 4.5))
    ax = fig.subplots()
    mse = report.curves_ylabel is None
    paper = {r.filter: r.paper for r in report.rows if r.metric == "rmse" and r.paper is not None} if mse else {}
    runs, marks = set(), 0
    for i, (name, curve) in enumerate(report.curves.items()):
        curve = np.asarray(curve, dtype=np.float64)
        per_run = curve if curve.ndim == 2 else curve[None]
        runs.add(per_run.shape[0])
        if mse:
            per_run = np.stack([moving_average(c, window) for c in per_run])
        mean, lo, hi = mean_band(per_run)
        k = np.arange(1, mean.size + 1)
        to_y = (lambda x: 10 * np.log10(x)) if mse else (lambda x: x)
        (line,) = ax.plot(k, to_y(mean), label=name, **_style(i, mean.size))
        if per_run.shape[0] > 1:
            ax.fill_between(k, to_y(lo), to_y(hi), color=line.get_color(), alpha=0.12, linewidth=0)
        if name in paper:  # staggered to the right of the axes, so that close values stay visible
            ax.plot([mean.size * (1.012 + 0.012 * (marks % 3))], [20 * np.log10(paper[name])], marker="<", markersize=8,
                    color=line.get_color(), markeredgecolor="black", linestyle="none", clip_on=False)
            marks += 1
    if not mse:
        ax.set_yscale("log")
    if paper:
        ax.plot([], [], marker="<", markersize=9, color="white", markeredgecolor="black", linestyle="none",
                label="paper's RMSE, as 20 log10 RMSE\n(right edge, filter's colour)")
    ax.set_xlim(0, max(np.asarray(c).shape[-1] for c in report.curves.values()))
    ax.set_xlabel("time step k")
    ax.set_ylabel(f"MSE, {window}-step moving average (dB)" if mse else report.curves_ylabel)
    what = f"per-step MSE 10 log10(mean_runs ‖x_k − x̂_k‖²), {window}-step moving average" if mse else report.curves_ylabel
    n = max(runs)
    band = f"mean and 95% CI over {n} runs" if n > 1 else f"mean over {report.settings.get('runs', 'the')} runs (no band: the report keeps the mean only)"
    ax.set_title(f"{_title(report)}\n{what}; {band}", fontsize=9)
    _legend_outside(ax, gap=0.06 if paper else 0.01)  # clear of the paper's marks
    ax.grid(alpha=0.3)
    return _save(fig, path)
