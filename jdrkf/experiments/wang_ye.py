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
from ..sets import EpsContamination, Moment, Wasserstein, wasserstein_mmse_joint
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


def joint_noise_covariance(form: str = "independent", dtype=None) -> jnp.ndarray:
    """Covariance of the part of `(x_k, y_k)` not explained by `x_{k−1}` that a WKF adds to
    `[F; HF] P [F; HF]ᵀ` to form its nominal joint covariance (Shafieezadeh-Abadeh et al.
    2018, as adapted by Wang & Ye). `form`:

    - `"independent"`: `[[Q, QHᵀ], [HQ, HQHᵀ + R]]`, independent `w` and `v` — the model of
      Sec. VII, what `WassersteinKF` uses, and the authors' current WKF code;
    - `"sqrt-broadcast"`: `B Bᵀ` with `B = [Q^½; H Q^½ + R^½ 1ᵀ]` (`Q^½` the symmetric square
      root), i.e. a scalar `R^½` added to *each* entry of the row `H Q^½` instead of a separate
      noise column: it models `v = R^½ (z₁ + z₂)`, variance `2R`, correlated with `w = Q^½ z`.
      This is the form of the WKF in the authors' earlier code (Wang, Wu & Lim 2021) and in the
      first published version of their t-distribution experiment;
    - `"block-diagonal"`: `blkdiag(Q, HQHᵀ + R)`, the cross term `QHᵀ` dropped (the first
      published version of the WKF of their Tables I–III folder);
    - `"squared"`: the square of the `"independent"` matrix (a covariance passed where a
      square-root factor was expected; a later version of the t-distribution experiment)."""
    m = nominal_model(dtype)
    q, h, r = m.Q, m.H, m.R
    full = jnp.block([[q, q @ h.T], [h @ q, h @ q @ h.T + r]])
    if form == "independent":
        return full
    if form == "sqrt-broadcast":
        w, v = jnp.linalg.eigh(q)
        q_half = (v * jnp.sqrt(w)) @ v.T
        b = jnp.concatenate([q_half, h @ q_half + jnp.sqrt(r[0, 0])], axis=0)
        return b @ b.T
    if form == "block-diagonal":
        return jax.scipy.linalg.block_diag(q, h @ q @ h.T + r)
    if form == "squared":
        return full @ full.T
    raise ValueError(f"unknown form {form!r}")


def wkf_gains(radius: float, num_steps: int, noise: jnp.ndarray, p0=None, *, tol: float = 1e-13) -> np.ndarray:
    """Gains `G_t` (`(T, 2, 1)`) of a WKF whose nominal joint covariance is
    `[F; HF] P [F; HF]ᵀ + noise`, worst case solved exactly by `jdrkf.sets.wasserstein_mmse_joint`,
    `P ← S_xx − G S_yx`. The recursion never sees the data, so the estimate is the linear filter
    `x̂_k = F x̂_{k−1} + G_k (y_k − H F x̂_{k−1})` (`apply_gains`). Once the nominal covariance
    stops changing (max change `< tol`) the last gain is repeated."""
    m = nominal_model(noise.dtype)
    a = jnp.concatenate([m.F, m.H @ m.F], axis=0)
    radius = jnp.asarray(radius, noise.dtype)
    p = jnp.eye(2, dtype=noise.dtype) if p0 is None else p0
    gains, prev = np.zeros((num_steps, 2, 1)), None
    for t in range(num_steps):
        sigma = a @ p @ a.T + noise
        if prev is not None and float(jnp.max(jnp.abs(sigma - prev))) < tol:
            gains[t:] = gains[t - 1]
            break
        g, p = _wkf_step(sigma, radius)
        gains[t], prev = np.asarray(g), sigma
    return gains


@jax.jit
def _wkf_step(sigma, radius):
    s = wasserstein_mmse_joint(sigma, 2, radius).cov
    g = jnp.linalg.solve(s[2:, 2:], s[2:, :2]).T
    return g, s[:2, :2] - g @ s[2:, :2]


def apply_gains(gains: np.ndarray, observations) -> np.ndarray:
    """Filtered means `(runs, T, 2)` of the linear filter with gains `(T, 2, 1)`, `x̂_0 = 0`."""
    f = np.asarray(nominal_model().F, np.float64)
    h = np.asarray(nominal_model().H, np.float64)[0]
    y = np.asarray(observations, np.float64)[..., 0]
    xh, out = np.zeros((y.shape[0], 2)), np.zeros((*y.shape, 2))
    for t in range(y.shape[1]):
        xp = xh @ f.T
        xh = xp + (y[:, t] - xp @ h)[:, None] * gains[t][:, 0][None, :]
        out[:, t] = xh
    return out


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
            "KF, tau-KF and WKF have no outlier model, so every ±100 outlier enters their update in full."
        )
        notes.append(_wkf_note(name, traj, np.asarray(out["KF"]["rmse"]), np.asarray(out["WKF"]["rmse"]), num_steps))
        realized = float(np.mean(np.asarray(traj.outliers)))
        notes.append(f"Outliers: ±{OUTLIER_MAGNITUDE:g} per channel with probability {OUTLIER_PROB}; realized rate {realized:.2%}.")
    notes += _swap_notes(paper, {f: np.asarray(out[f]["rmse"]) for f in flts})
    for f in flts:
        if paper.get(f) is not None:
            pct = 100.0 * float(np.mean(np.asarray(out[f]["rmse"]) <= paper[f]))
            notes.append(f"{f}: the paper's single-episode {paper[f]:g} is at or above {pct:.0f}% of our per-run RMSEs.")
    if not outliers:
        mean = {r.filter: r.mean for r in rows}
        mk, wk, nc = (np.asarray(out[f]["rmse"]) for f in ("MKF", "WKF", "MKF-no-clip"))
        order = paper["MKF"] / paper["WKF"]
        notes.append(
            "Without outliers, Huber clipping only discards information: the MKF (clipping at k = 1.4 as in "
            f"the paper) has RMSE {mean['MKF']:.3g} here, the same filter without an outlier model "
            f"(MKF-no-clip) {mean['MKF-no-clip']:.3g}; HKF vs KF shows the same cost (ours {mean['HKF']:.3g} vs "
            f"{mean['KF']:.3g}; paper 14.74 vs 14.52). The authors' MKF code clips too (threshold k·√θ₂ on the "
            "innovation normalized by the nominal S) and gives our numbers on identical data "
            "(benchmarks/wang_ye_gaps.py); their own stored 5000-step run at α = 1 without outliers (k = 2, "
            "ε = 0) has MKF 11.45 vs WKF 10.39, the order we find. The paper's single episode lies within our "
            f"spread: its MKF {paper['MKF']:g} is at or above {100 * np.mean(mk <= paper['MKF']):.0f}% of our "
            f"per-run MKF RMSEs; its order, MKF/WKF ≤ {order:.3f}, holds in {100 * np.mean(mk / wk <= order):.0f}% "
            f"of our runs (paired; mean MKF/WKF {np.mean(mk / wk):.3f}), and in {100 * np.mean(nc / wk <= order):.0f}% "
            "for MKF-no-clip — one episode cannot tell whether the paper's run clipped."
        )
    theta2 = float(fitted.params[int(np.argmin(fitted.losses)), 0])
    notes += [
        f"MKF-tuned: θ₂ₓ = θ₂ᵥ fitted by Adam ({TUNE_STEPS} steps from {TUNE_START}) on the mean RMSE of {TRAIN_RUNS} "
        f"training runs simulated with a key independent of the evaluation runs: θ₂ = {theta2:.4f} "
        f"(paper: {MKF_THETA2}, chosen post hoc on the test episode by the authors' FindBestGamma).",
        "tau-KF is Zorzi's filter as published (filtered estimate x̂_{k|k}, noise covariances as given). The "
        "authors' code fed it one-step-delayed measurements (so it output x̂_{k|k-1} against everyone's x̂_{k|k}) "
        "and passed covariances where square-root factors were expected (process covariance ≈ 3.84 I instead "
        "of 1.96 I). Both handicap their tau-KF: re-run on our breakdown episodes (benchmarks/wang_ye_gaps.py, "
        "section 4, 200 episodes per grid point), their variant puts all 8 of the paper's Fig. 2 tau-KF numbers "
        "inside the central 95% of its per-episode RMSEs, ours 4 of 8; the squared covariance does most of it.",
        "WKF: the authors' Frank–Wolfe stops at a 1e-4 relative gap with 2/(k+2) steps; ours solves each step "
        "to round-off (backtracking Frank–Wolfe + Newton polish).",
    ]
    report = Report(experiment=name, seed=seed, rows=rows, notes=notes)
    if curves:
        report.curves = {f: np.asarray(out[f]["squared_error"]) for f in flts}  # per run: the figure draws 95% bands
    return report


def _wkf_note(name: str, traj, kf_rmse: np.ndarray, wkf_rmse: np.ndarray, num_steps: int) -> str:
    """The WKF gap, computed on this run: our WKF/KF ratio against that of a WKF with the nominal
    joint covariance the authors' published runs used (`joint_noise_covariance("sqrt-broadcast")`)."""
    gains = wkf_gains(WKF_RHO, num_steps, joint_noise_covariance("sqrt-broadcast"))
    est = apply_gains(gains, traj.observations)
    auth = np.sqrt(np.mean(np.sum((np.asarray(traj.states, np.float64) - est) ** 2, -1), -1))
    ours_m, (ours_lo, ours_hi) = metrics.mean_ci(wkf_rmse / kf_rmse)
    auth_m, (auth_lo, auth_hi) = metrics.mean_ci(auth / kf_rmse)
    target = PAPER[name]["WKF"] / PAPER[name]["KF"]
    pct = 100.0 * float(np.mean(auth / kf_rmse <= target))
    return (
        f"WKF vs the paper: ours is the WKF of Shafieezadeh-Abadeh et al. on the model of Sec. VII (independent "
        f"process and measurement noise), WKF/KF = {ours_m:.3f} [{ours_lo:.3f}, {ours_hi:.3f}] on these runs "
        f"(paper {target:.3f}). The authors' published WKF numbers (these tables, their stored breakdown "
        "runs) fit a WKF whose nominal joint covariance adds B Bᵀ with B = [Q^½; H Q^½ + R^½ 1ᵀ] — R^½ added to "
        "each entry of the row H Q^½, i.e. measurement noise of variance 2R correlated with the process noise "
        "(the WKF of their earlier code) — not the model's [[Q, QHᵀ], [HQ, HQHᵀ + R]]; the Results.mat stored "
        "with their code (WKF 15.86 < KF 17.30) fits yet another version, blkdiag(Q, HQHᵀ + R). That WKF, run on the "
        f"same runs (exact solver, ρ = {WKF_RHO}), gives WKF/KF = {auth_m:.3f} [{auth_lo:.3f}, {auth_hi:.3f}]; "
        f"the paper's ratio is at or above {pct:.0f}% of its per-run ratios. Evidence: benchmarks/wang_ye_gaps.py."
    )


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
