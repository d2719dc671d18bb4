"""Figures for experiment reports (needs the optional dependency matplotlib)."""

from __future__ import annotations

import pathlib

import numpy as np

from .experiments import Report


def _pyplot():
    try:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt
    except ImportError as e:  # pragma: no cover - depends on the environment
        raise ImportError("plotting needs matplotlib: pip install 'jdrkf[notebooks]'") from e
    return plt


def moving_average(x: np.ndarray, window: int) -> np.ndarray:
    """Trailing moving average with a window that grows over the first `window` steps."""
    c = np.cumsum(np.insert(np.asarray(x, dtype=np.float64), 0, 0.0))
    idx = np.arange(1, len(x) + 1)
    lo = np.maximum(idx - window, 0)
    return (c[idx] - c[lo]) / (idx - lo)


def plot_error_curves(report: Report, path: str | pathlib.Path, window: int = 50) -> pathlib.Path:
    """Per-step mean squared error `10 log10(e_k)` smoothed over `window` steps, one
    line per filter (the style of Wang & Ye 2022, Figs. 1–2). Returns the file path."""
    if not report.curves:
        raise ValueError("the report has no per-step curves; run the experiment with curves=True")
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(7, 4))
    for name, curve in report.curves.items():
        ax.plot(np.arange(1, len(curve) + 1), 10 * np.log10(moving_average(curve, window)), label=name)
    ax.set_xlabel("time step k")
    ax.set_ylabel(f"10 log10 MSE ({window}-step moving average, dB)")
    ax.set_title(report.experiment)
    ax.legend()
    ax.grid(alpha=0.3)
    path = pathlib.Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path
