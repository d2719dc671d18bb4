"""Wang & Ye (2022), "Distributionally Robust State Estimation for Linear Systems
Subject to Uncertainty and Outlier", IEEE TSP — Section VII, Tables I–III.

System (Sec. VII): `F_k^real = F + [[0, α Δ_k], [0, 0]]`, `Δ_k ~ U[−1, 1]` i.i.d.,
`G = I`, `H = [1, −1]`, `Q = [[1.9608, 0.0195], [0.0195, 1.9605]]`, `R = 1`,
`x_0 ~ N(0, I)`, filters start at `x̂_0 = 0`, `P_0 = I`, `T = 1000`; outliers
`±100` added to each channel with probability 5% (reference-settings.md §1).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from .. import metrics
from .._gaussian import Gaussian
from .._models import LinearModel
from .._montecarlo import Clairvoyant, montecarlo
from .._noise import GaussianNoise, OutlierNoise, UniformPerturbation
from .._simulate import simulate
from ..filters import KalmanFilter
from ._registry import Experiment, Report, Row, register


NUM_STEPS = 1000
OUTLIER_PROB = 0.05
OUTLIER_MAGNITUDE = 100.0

# Paper numbers (RMSE, one episode each): Table I (α=1, no outliers), II (α=0, outliers), III (both).
PAPER = {
    "wang-ye-table1": {"TMKF": 3.25, "KF": 14.52, "HKF": 14.74, "tau-KF": 9.90, "WKF": 9.95, "MKF": 9.91},
    "wang-ye-table2": {"TMKF": 7.64, "KF": 16.14, "HKF": 7.70, "tau-KF": 19.41, "WKF": 16.56, "MKF": 8.19},
    "wang-ye-table3": {"TMKF": 3.23, "KF": 21.04, "HKF": 16.14, "tau-KF": 22.15, "WKF": 16.94, "MKF": 11.72},
}


def nominal_model(dtype=None) -> LinearModel:
    """The nominal model of Sec. VII (`α` enters only the simulated truth)."""
    f = jnp.array([[0.9802, 0.0196], [0.0, 0.9802]], dtype)
    h = jnp.array([[1.0, -1.0]], dtype)
    q = jnp.array([[1.9608, 0.0195], [0.0195, 1.9605]], dtype)
    r = jnp.array([[1.0]], dtype)
    return LinearModel(F=f, H=h, Q=q, R=r)


def prior(dtype=None) -> Gaussian:
    return Gaussian(jnp.zeros(2, dtype), jnp.eye(2, dtype=dtype))


def scenario(key, num_runs: int, alpha: float, outliers: bool, num_steps: int = NUM_STEPS):
    """Simulate the Sec. VII truth: perturbed `F` (if `alpha > 0`) and optional outliers."""
    model = nominal_model()
    noise = OutlierNoise(model.R, OUTLIER_PROB, OUTLIER_MAGNITUDE) if outliers else GaussianNoise(model.R)
    perturb = UniformPerturbation(jnp.array([[0.0, 1.0], [0.0, 0.0]]), alpha) if alpha > 0 else None
    return simulate(key, model, prior(), num_steps, num_runs, measurement_noise=noise, transition_perturbation=perturb)


def filters():
    """The filters registered so far, labelled as in the paper."""
    return {"TMKF": Clairvoyant(KalmanFilter()), "KF": KalmanFilter()}


def _run(name: str, alpha: float, outliers: bool, runs: int, seed: int, progress: bool = False, curves: bool = False) -> Report:
    traj = scenario(jax.random.key(seed), runs, alpha, outliers)
    mets = {"rmse": lambda tr, res: metrics.rmse(tr.states, res.filtered_means)}
    if curves:
        mets["squared_error"] = lambda tr, res: metrics.squared_error(tr.states, res.filtered_means)
    flts = filters()
    out = montecarlo(flts, nominal_model(), prior(), traj, metrics=mets, chunk_size=500, progress=progress)
    paper = PAPER[name]
    rows = [Row.from_values(f, "rmse", paper.get(f), out[f]["rmse"]) for f in flts]
    notes = [
        "Paper numbers are single random episodes of T=1000 steps (no seed, no Monte Carlo average); "
        f"ours are means over {runs} seeded runs with 95% Student-t intervals, so a paper number "
        "outside our interval is expected where episodes vary widely; the percentile notes below "
        "show where each paper number falls among our runs.",
        "TMKF is clairvoyant: it knows the true per-step F_k and filters the outlier-free measurements.",
    ]
    if alpha == 0:
        notes.append(
            "With α = 0 the pair (F, H) is barely observable (det of the observability matrix 0.0196), so "
            "the error varies strongly between episodes: the authors' own code gave TMKF 9.45 on one "
            "10⁴-step run at α = 0 (reference-settings.md §1, breakdown test), close to our mean."
        )
    if outliers:
        realized = float(np.mean(np.asarray(traj.outliers)))
        notes.append(f"Outliers: ±{OUTLIER_MAGNITUDE:g} per channel with probability {OUTLIER_PROB}; realized rate {realized:.2%}.")
    for f in flts:
        if paper.get(f) is not None:
            pct = 100.0 * float(np.mean(np.asarray(out[f]["rmse"]) <= paper[f]))
            notes.append(f"{f}: the paper's single-episode {paper[f]:g} is at or above {pct:.0f}% of our per-run RMSEs.")
    notes.append("Filters HKF, tau-KF, WKF and MKF of the paper's table are not implemented yet in jdrkf; their paper numbers are omitted.")
    report = Report(experiment=name, seed=seed, rows=rows, notes=notes)
    if curves:
        report.curves = {f: np.mean(out[f]["squared_error"], axis=0) for f in flts}
    return report


def _make(name, alpha, outliers, description):
    def run(runs: int, seed: int, progress: bool = False, curves: bool = False) -> Report:
        return _run(name, alpha, outliers, runs, seed, progress, curves)

    return register(Experiment(name=name, description=description, default_runs=100, run=run))


_make("wang-ye-table1", 1.0, False, "Wang & Ye 2022, Table I: model uncertainty (α=1), no outliers; RMSE, T=1000.")
_make("wang-ye-table2", 0.0, True, "Wang & Ye 2022, Table II: no model uncertainty (α=0), 5% outliers of ±100; RMSE, T=1000.")
_make("wang-ye-table3", 1.0, True, "Wang & Ye 2022, Table III: model uncertainty (α=1) and 5% outliers of ±100; RMSE, T=1000.")
