"""Figures of experiment reports: per-step bands, styles, paper marks."""

import itertools

import numpy as np
import pytest

pytest.importorskip("matplotlib")

from jdrkf import metrics, plotting
from jdrkf.experiments import Report, Row


def test_mean_band_matches_mean_ci_per_step():
    rng = np.random.default_rng(0)
    positive = np.exp(rng.normal(0.0, 1.0, (7, 5)))
    signed = rng.normal(0.0, 1.0, (7, 5))
    for values, scale in ((positive, "log"), (signed, "linear")):
        mean, lo, hi = plotting.mean_band(values)
        for k in range(values.shape[1]):
            m, (a, b) = metrics.mean_ci(values[:, k], scale=scale)
            np.testing.assert_allclose((mean[k], lo[k], hi[k]), (m, a, b), rtol=1e-12)
    # one run: no interval, the band collapses onto the mean
    mean, lo, hi = plotting.mean_band(positive[:1])
    np.testing.assert_array_equal(lo, mean)
    np.testing.assert_array_equal(hi, mean)


def test_neighbouring_series_differ_in_colour_dash_and_marker():
    styles = [plotting._style(i, 1000) for i in range(8)]
    for a, b in itertools.pairwise(styles):
        assert a["color"] != b["color"] and a["linestyle"] != b["linestyle"] and a["marker"] != b["marker"]
    assert len({s["markevery"] for s in styles}) > 1  # markers staggered between series


def test_error_curve_figure_from_per_run_curves(tmp_path):
    rng = np.random.default_rng(1)
    rows = [Row.from_values("KF", "rmse", 3.0, [3.0, 3.2]), Row.from_values("HKF", "rmse", None, [2.0, 2.1])]
    report = Report("fake", 0, rows, curves={"KF": rng.uniform(1, 2, (6, 200)), "HKF": rng.uniform(1, 2, 200)},
                    title="a fake experiment", settings={"runs": 6, "mode": "quick (runs=6)"})
    path = plotting.plot_error_curves(report, tmp_path / "f.png")
    assert path.stat().st_size > 10_000
    with pytest.raises(ValueError, match="no per-step curves"):
        plotting.plot_error_curves(Report("fake", 0, rows), tmp_path / "g.png")


def test_moving_average_against_numpy_convolution():
    x = np.random.default_rng(2).normal(size=30)
    w = 4
    full = np.convolve(x, np.ones(w) / w, mode="valid")  # windows ending at index w-1, ..., 29
    np.testing.assert_allclose(plotting.moving_average(x, w)[w - 1:], full, rtol=1e-12)
    np.testing.assert_allclose(plotting.moving_average(x, w)[:w - 1], np.cumsum(x[:w - 1]) / np.arange(1, w))
