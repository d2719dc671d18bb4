"""Figures for experiment reports (needs the optional dependency matplotlib)."""

from __future__ import annotations

import pathlib

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


def _style(i: int) -> dict:
    """Line style of the `i`-th series: colours cycle with dashes, so that neighbours in
    the legend differ in both."""
    return {"color": f"C{i % 10}", "linestyle": _STYLES[i % len(_STYLES)]}


def _legend_outside(ax):
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8, frameon=False)


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

    fig = _figure(figsize=(7.5 * len(report.sweeps), 4))
    axes = fig.subplots(1, len(report.sweeps), squeeze=False)
    for ax, (title, sw) in zip(axes[0], report.sweeps.items(), strict=True):
        for i, (name, vals) in enumerate(sw.values.items()):
            # Failed runs are NaN in a sweep: each point averages the finite runs.
            cols = [vals[:, j][np.isfinite(vals[:, j])] for j in range(len(sw.x))]
            stats = [metrics.mean_ci(c) if c.size > 1 else (float(np.mean(c)) if c.size else np.nan, (np.nan, np.nan)) for c in cols]
            mean = np.array([m for m, _ in stats])
            (line,) = ax.plot(sw.x, mean, label=name, **_style(i))
            ax.fill_between(sw.x, [c[0] for _, c in stats], [c[1] for _, c in stats], color=line.get_color(), alpha=0.2)
            if name in sw.paper:
                ax.plot(sw.x, sw.paper[name], "x", color=line.get_color(), label=f"{name} (paper)")
        ax.set_xlabel(sw.x_label)
        ax.set_ylabel(sw.y_label)
        ax.set_title(f"{title}: mean and 95% band" + (", x = paper" if sw.paper else ""), fontsize=10)
        ax.grid(alpha=0.3)
        _legend_outside(ax)
    return _save(fig, path)


def plot_error_curves(report: Report, path: str | pathlib.Path, window: int = 50) -> pathlib.Path:
    """Per-step mean squared error `10 log10(e_k)` smoothed over `window` steps, one
    line per filter (the style of Wang & Ye 2022, Figs. 1–2). A report with
    `curves_ylabel` set has other per-step quantities: they are drawn unsmoothed on a
    log scale with that label. Returns the file path."""
    if not report.curves:
        raise ValueError("the report has no per-step curves; run the experiment with curves=True")
    fig = _figure(figsize=(8.5, 4))
    ax = fig.subplots()
    for i, (name, curve) in enumerate(report.curves.items()):
        k = np.arange(1, len(curve) + 1)
        if report.curves_ylabel is None:
            ax.plot(k, 10 * np.log10(moving_average(curve, window)), label=name, **_style(i))
        else:
            ax.semilogy(k, curve, label=name, **_style(i))
    ax.set_xlabel("time step k")
    ax.set_ylabel(f"10 log10 MSE ({window}-step moving average, dB)" if report.curves_ylabel is None else report.curves_ylabel)
    what = "per-step MSE, mean over runs" if report.curves_ylabel is None else report.curves_ylabel
    runs = report.settings.get("runs")
    ax.set_title(f"{report.experiment}: {what}" + (f" ({runs} runs)" if runs else ""), fontsize=10)
    _legend_outside(ax)
    ax.grid(alpha=0.3)
    return _save(fig, path)
