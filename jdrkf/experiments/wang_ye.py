"""Wang & Ye (2022), "Distributionally Robust State Estimation for Linear Systems
Subject to Uncertainty and Outlier", IEEE TSP — Section VII, Tables I–III.

System (Sec. VII): `F_k^real = F + [[0, α Δ_k], [0, 0]]`, `Δ_k ~ U[−1, 1]` i.i.d.,
`G = I`, `H = [1, −1]`, `Q = [[1.9608, 0.0195], [0.0195, 1.9605]]`, `R = 1`,
`x_0 ~ N(0, I)`, filters start at `x̂_0 = 0`, `P_0 = I`, `T = 1000`; outliers
`±100` added to each channel with probability 5% (Sec. VII and the authors' MATLAB code `Spratm-Asleaf/DRSE-Outlier`).
"""

from __future__ import annotations

import functools

import jax
import jax.numpy as jnp
import numpy as np
import optax

from .. import _progress, metrics, tuning
from .._gaussian import Gaussian
from .._models import LinearModel
from .._montecarlo import Clairvoyant, montecarlo
from .._noise import OutlierNoise, UniformPerturbation
from .._simulate import simulate
from ..filters import DRKF, HuberKF, KalmanFilter, TauKF, WassersteinKF
from ..sets import EpsContamination, Moment, Wasserstein
from ._registry import Experiment, Report, Row, register
from ._tune import TuningProblem

NUM_STEPS = 1000
OUTLIER_PROB = 0.05
OUTLIER_MAGNITUDE = 100.0
# Paper parameters (Sec. VII-B): HKF k = 1.4 (ε = 0.05); τ-KF τ = 0, c = 1.5e-4; WKF ρ = 0.1;
# MKF θ₂ₓ = θ₂ᵥ = 1.02, k = 1.4, ε = 0.05.
EPS, HUBER_K, TAU_C, WKF_RHO, MKF_THETA2 = 0.05, 1.4, 1.5e-4, 0.1, 1.02
# Tuned MKF: θ₂ fitted by Adam on TRAIN_RUNS runs simulated with a key independent of the
# evaluation runs, starting from TUNE_START.
TRAIN_RUNS, TUNE_STEPS, TUNE_START = 16, 40, 1.05

# `jdrkf tune`: horizon of the training and held-out runs (full, quick).
TUNING_STEPS = (200, 100)

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


def scenario(
    key,
    num_runs: int,
    alpha: float,
    outliers: bool,
    num_steps: int = NUM_STEPS,
    *,
    prob: float = OUTLIER_PROB,
    magnitude: float = OUTLIER_MAGNITUDE,
):
    """Simulate the Sec. VII truth: `F_k = F + [[0, α Δ_k], [0, 0]]` and, if `outliers`,
    `±magnitude` added to each channel with probability `prob`.

    The perturbation and the outlier law are always in place (`α = 0` gives `F_k = F`
    exactly; `outliers=False` is `prob = 0`), so trajectories of every setting have the same
    structure (one compilation) and the nominal draws do not depend on `α` or `prob`."""
    model = nominal_model()
    noise = OutlierNoise(model.R, prob if outliers else 0.0, magnitude)
    perturb = UniformPerturbation(jnp.array([[0.0, 1.0], [0.0, 0.0]]), alpha)
    return simulate(key, model, prior(), num_steps, num_runs, measurement_noise=noise, transition_perturbation=perturb)


def mkf(theta2: float = MKF_THETA2) -> DRKF:
    """The paper's MKF: moment sets with `θ₂ₓ = θ₂ᵥ = theta2` and ε-contamination outliers."""
    return DRKF(state_set=Moment(theta2), noise_set=Moment(theta2), outliers=EpsContamination(EPS, k=HUBER_K), throw=False)


def filters():
    """The six filters of Tables I–III with the paper's parameters, labelled as in the paper."""
    return {
        "TMKF": Clairvoyant(KalmanFilter(throw=False)),
        "KF": KalmanFilter(throw=False),
        "HKF": HuberKF(EPS, HUBER_K, throw=False),
        "tau-KF": TauKF(0.0, TAU_C, throw=False),
        "WKF": WassersteinKF(WKF_RHO, throw=False),
        "MKF": mkf(),
    }


def tune_mkf(key, alpha: float, outliers: bool, runs: int = TRAIN_RUNS, steps: int = TUNE_STEPS, num_steps: int = NUM_STEPS) -> tuning.FitResult:
    """Fit the MKF's `θ₂` (tied for state and noise) by gradient descent on the mean
    RMSE of `runs` training runs of the scenario simulated with `key`."""
    train = scenario(key, runs, alpha, outliers, num_steps)
    objective = tuning.rmse_objective(nominal_model(), prior(), train)
    return tuning.fit(
        mkf(TUNE_START), objective, where=lambda f: (f.state_set.theta2, f.noise_set.theta2),
        bounds=(1.0, None), shared=True, optimizer=optax.adam(0.05), steps=steps,
    )


def tuning_problems(alpha: float, outliers: bool, quick: bool = False) -> dict[str, TuningProblem]:
    """Three parameters tuned jointly per filter, on the mean RMSE of runs of the scenario
    (`TUNING_STEPS` steps): `W-DRKF`, `DRKF(Wasserstein(θx), Wasserstein(θv),
    EpsContamination(ε))`, and `MKF`, moment sets with separate `θ₂ₓ`, `θ₂ᵥ` and Huber's
    `ε` (its clipping point `k` follows from `ε`)."""
    model, p0 = nominal_model(), prior()
    num_steps = TUNING_STEPS[quick]

    def data(key, runs):
        return scenario(key, runs, alpha, outliers, num_steps)

    def rmse_of(make):
        def errors(values, tr):
            flt = make(values)
            return metrics.rmse(tr.states, jax.vmap(lambda y: flt(model, p0, y).filtered_means)(tr.observations))

        return errors

    def wdrkf(v):
        return DRKF(state_set=Wasserstein(v[0]), noise_set=Wasserstein(v[1]), outliers=EpsContamination(v[2]), throw=False)

    def moment(v):
        return DRKF(state_set=Moment(v[0]), noise_set=Moment(v[1]), outliers=EpsContamination(v[2]), throw=False)

    metric = f"mean RMSE over {num_steps}-step runs"
    return {
        "W-DRKF": TuningProblem("W-DRKF", "DRKF(Wasserstein(θx), Wasserstein(θv), EpsContamination(ε))", ("θx", "θv", "ε"),
                                (0.1, 0.1, EPS), ((0.0, None), (0.0, None), (0.0, 0.5)),
                                ((0.005, 2.0, True), (0.005, 2.0, True), (0.005, 0.3, True)), data, rmse_of(wdrkf), metric, wdrkf),
        "MKF": TuningProblem("MKF", "DRKF(Moment(θ₂ₓ), Moment(θ₂ᵥ), EpsContamination(ε))", ("θ₂ₓ", "θ₂ᵥ", "ε"),
                             (MKF_THETA2, MKF_THETA2, EPS), ((1.0, None), (1.0, None), (0.0, 0.5)),
                             ((1.001, 1.3, True), (1.001, 1.3, True), (0.005, 0.3, True)), data, rmse_of(moment), metric, moment),
    }


def _run(name: str, alpha: float, outliers: bool, runs: int, seed: int, progress: bool = False, curves: bool = False,
         num_steps: int = NUM_STEPS, params=None) -> Report:
    key = jax.random.key(seed)
    traj = scenario(key, runs, alpha, outliers, num_steps)
    mets = {"rmse": lambda tr, res: metrics.rmse(tr.states, res.filtered_means)}
    if curves:
        mets["squared_error"] = lambda tr, res: metrics.squared_error(tr.states, res.filtered_means)
    with _progress.phase(f"tuning the MKF's θ₂ ({TUNE_STEPS} Adam steps on {TRAIN_RUNS} runs)"):
        fitted = tune_mkf(jax.random.fold_in(key, 2**31 - 1), alpha, outliers, num_steps=num_steps)
    flts = filters() | {"MKF-tuned": fitted.filter}
    problems = tuning_problems(alpha, outliers)
    flts |= {f"{label}-params": problems[label].make(values) for label, values in (params or {}).items()}
    if not outliers:  # diagnostic: the MKF without its outlier model (no Huber clipping)
        flts["MKF-no-clip"] = DRKF(state_set=Moment(MKF_THETA2), noise_set=Moment(MKF_THETA2), throw=False)
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
            "10⁴-step run at α = 0 (their breakdown test), close to our mean."
        )
    if outliers:
        notes.append(
            "KF, tau-KF and WKF have no outlier model, so every ±100 outlier enters their update in full; "
            "in our runs the WKF stays close to the KF. The paper's single-episode WKF number lies low in "
            "our per-run distribution (percentile line below); we have not identified why."
        )
        realized = float(np.mean(np.asarray(traj.outliers)))
        notes.append(f"Outliers: ±{OUTLIER_MAGNITUDE:g} per channel with probability {OUTLIER_PROB}; realized rate {realized:.2%}.")
    notes += _swap_notes(paper, {f: np.asarray(out[f]["rmse"]) for f in flts})
    for f in flts:
        if paper.get(f) is not None:
            pct = 100.0 * float(np.mean(np.asarray(out[f]["rmse"]) <= paper[f]))
            notes.append(f"{f}: the paper's single-episode {paper[f]:g} is at or above {pct:.0f}% of our per-run RMSEs.")
    if not outliers:
        mean = {r.filter: r.mean for r in rows}
        notes.append(
            "Without outliers, Huber clipping only discards information: the MKF (clipping at k = 1.4 as in "
            f"the paper) has RMSE {mean['MKF']:.3g} here, the same filter without an outlier model "
            f"(MKF-no-clip) {mean['MKF-no-clip']:.3g}; HKF vs KF shows the same cost (ours {mean['HKF']:.3g} vs "
            f"{mean['KF']:.3g}; paper 14.74 vs 14.52). The paper's tau-KF, MKF and WKF (9.90, 9.91, 9.95) tie "
            "within 0.5% on one episode, with the MKF's θ₂ picked post hoc on that episode, so a different "
            "order among these three is within the paper's own noise."
        )
    theta2 = float(fitted.params[int(np.argmin(fitted.losses)), 0])
    notes += [
        f"MKF-tuned: θ₂ₓ = θ₂ᵥ fitted by Adam ({TUNE_STEPS} steps from {TUNE_START}) on the mean RMSE of {TRAIN_RUNS} "
        f"training runs simulated with a key independent of the evaluation runs: θ₂ = {theta2:.4f} "
        f"(paper: {MKF_THETA2}, chosen post hoc on the test episode by the authors' FindBestGamma).",
        "tau-KF is Zorzi's filter as published (filtered estimate x̂_{k|k}, noise covariances as given). The "
        "authors' code fed it one-step-delayed measurements (so it output x̂_{k|k-1} against everyone's x̂_{k|k}) "
        "and passed covariances where square-root factors were expected (process covariance ≈ 3.84 I instead "
        "of 1.96 I). Both handicap their tau-KF; we have not rerun their variant to measure each effect "
        "(the percentile line shows where their number falls among our runs).",
        "WKF: the authors' Frank–Wolfe stops at a 1e-4 relative gap with 2/(k+2) steps; ours solves each step "
        "to round-off (backtracking Frank–Wolfe + Newton polish).",
    ]
    report = Report(experiment=name, seed=seed, rows=rows, notes=notes)
    if curves:
        report.curves = {f: np.asarray(out[f]["squared_error"]) for f in flts}  # per run: the figure draws 95% bands
    return report


def _swap_notes(paper: dict, values: dict) -> list[str]:
    """One note per pair of filters whose order differs from the paper's, with the paired
    95% interval of the per-run difference (same runs for both filters)."""
    names = [f for f in paper if f in values]
    notes = []
    for i, a in enumerate(names):
        for b in names[i + 1:]:
            if (paper[a] - paper[b]) * (values[a].mean() - values[b].mean()) < 0:
                mean, (lo, hi) = metrics.mean_ci(values[a] - values[b])
                verdict = "a statistical tie (the interval contains 0)" if lo <= 0 <= hi else "a significant difference"
                notes.append(
                    f"Order differs from the paper for {a} vs {b} (paper {paper[a]:g} vs {paper[b]:g}): ours "
                    f"{a} − {b} = {mean:.3g}, paired 95% CI [{lo:.3g}, {hi:.3g}], {verdict}."
                )
    return notes


def _make(name, alpha, outliers, description):
    def run(runs: int, seed: int, progress: bool = False, curves: bool = False, num_steps: int = NUM_STEPS, params=None) -> Report:
        return _run(name, alpha, outliers, runs, seed, progress, curves, num_steps, params)

    return register(Experiment(
        name=name, description=description, default_runs=100, run=run, quick={"runs": 8, "num_steps": 300},
        scenario="2-D linear system x_k = F_k x_{k-1} + w_k, y_k = [1, −1] x_k + v_k (Sec. VII), true "
        f"F_k = F + [[0, α Δ_k], [0, 0]] with Δ_k ~ U[−1, 1] and α = {alpha:g}; "
        + (f"±{OUTLIER_MAGNITUDE:g} outliers in y with probability {OUTLIER_PROB:g}; " if outliers else "no outliers; ")
        + f"the filters know only the nominal F; T = {NUM_STEPS} steps, x_0 ~ N(0, I).",
        metric=f"RMSE of the filtered state over the {NUM_STEPS} steps of a run, sqrt(mean_k ‖x_k − x̂_k‖²) "
        "(units of the state; lower is better); mean over runs.",
        legend={"MKF-tuned": "the MKF with θ₂ fitted by gradient on separate training runs",
                "MKF-no-clip": "the MKF without its outlier model (diagnostic)",
                "W-DRKF-params": "DRKF with Wasserstein sets and ε-contamination, parameters from `jdrkf tune`",
                "MKF-params": "the MKF with θ₂ₓ, θ₂ᵥ, ε from `jdrkf tune`"},
        tuning=functools.partial(tuning_problems, alpha, outliers),
    ))


_make("wang-ye-table1", 1.0, False, "Wang & Ye 2022, Table I: model uncertainty (α=1), no outliers; RMSE, T=1000.")
_make("wang-ye-table2", 0.0, True, "Wang & Ye 2022, Table II: no model uncertainty (α=0), 5% outliers of ±100; RMSE, T=1000.")
_make("wang-ye-table3", 1.0, True, "Wang & Ye 2022, Table III: model uncertainty (α=1) and 5% outliers of ±100; RMSE, T=1000.")
