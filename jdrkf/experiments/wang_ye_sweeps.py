"""Wang & Ye (2022), Section VII-D "Sensitivity Analysis": Fig. 1(a), 1(b) and Fig. 2.

Same system as Tables I–III (`wang_ye`), over `T = 10⁴` steps (as in the authors' code `Spratm-Asleaf/DRSE-Outlier`):

- `wang-ye-sensitivity`, Fig. 1(a): `α = 0`, outliers `±25` with probability `ε_real`
  swept over 0…0.5; the DR estimator without ambiguity (`θ₂ = 1`) under the
  ε-contamination model (`ε = 0.01`, `K = 2`) and the ε-normal model (`ε = 0.03`).
  Fig. 1(b): `α = 1`, `ε_real = 0.05`, outliers `±50`; the MKF (`k = 1.4`, `ε = 0.05`)
  with `θ₂ₓ = θ₂ᵥ = θ₂` swept over 1.00…1.10.
- `wang-ye-breakdown`, Fig. 2: the six filters of Tables I–III with the paper's
  parameters, outliers `±50` with probability `ε_real` swept over 0…0.5, `α ∈ {0, 1}`.

Every `ε_real` of a sweep is simulated with the same key, so the runs share their
states, nominal noise and `Δ_k` across the sweep and only the outliers differ (nested
outlier sets: an outlier at `ε_real = 0.1` is one at 0.3 too); within one `ε_real`
all filters see the same runs (`montecarlo`'s common random numbers).
"""

from __future__ import annotations

import itertools

import jax
import jax.numpy as jnp
import numpy as np

from .. import metrics
from .._montecarlo import Clairvoyant, montecarlo
from .._simulate import Trajectories
from ..filters import DRKF, KalmanFilter
from ..sets import EpsContamination, EpsNormal
from . import wang_ye
from ._registry import Experiment, Report, Row, Sweep, register

# Horizon of the registered experiments (the paper's); read at call time, so tests may
# shrink it (or pass `num_steps=`).
NUM_STEPS = 10_000
DEFAULT_RUNS = 20
EPS_REAL = (0.0, 0.1, 0.2, 0.3, 0.4, 0.5)  # paper: 0:0.01:0.5
THETA2 = tuple(round(1.0 + 0.01 * i, 2) for i in range(11))  # paper: 1 + (0:0.01:0.1)
SENSITIVITY_MAGNITUDE, THETA_MAGNITUDE, BREAKDOWN_MAGNITUDE = 25.0, 50.0, 50.0
THETA_EPS_REAL = 0.05
# Fig. 1(a) filters: ε-contamination with ε = 0.01 and K = 2 (the paper's rounding of
# K(0.01) = 1.945); ε-normal with ε = 0.03.
CONTAMINATION_EPS, CONTAMINATION_K, NORMAL_EPS = 0.01, 2.0, 0.03
BOOTSTRAP = 2000

# The authors' stored breakdown numbers (one 10⁴-step episode each, `Spratm-Asleaf/DRSE-Outlier`,
# ONLY_OUTLIER.mat and ALSO_UNCERTAINTY.mat): PAPER_BREAKDOWN[α][ε_real][filter].
_FILTERS = ("TMKF", "KF", "HKF", "tau-KF", "WKF", "MKF")
PAPER_BREAKDOWN = {
    0.0: {
        0.0: dict(zip(_FILTERS, (9.45, 9.45, 9.45, 10.12, 9.78, 10.24), strict=True)),
        0.1: dict(zip(_FILTERS, (8.48, 13.08, 8.58, 16.06, 13.89, 9.82), strict=True)),
        0.3: dict(zip(_FILTERS, (8.92, 19.71, 9.31, 24.78, 20.69, 10.18), strict=True)),
        0.5: dict(zip(_FILTERS, (9.04, 24.45, 10.08, 31.12, 25.82, 11.38), strict=True)),
    },
    1.0: {
        0.0: dict(zip(_FILTERS, (8.78, 11.78, 12.28, 9.71, 8.82, 9.72), strict=True)),
        0.1: dict(zip(_FILTERS, (8.86, 15.25, 12.18, 16.43, 13.94, 10.17), strict=True)),
        0.3: dict(zip(_FILTERS, (9.39, 23.16, 16.21, 25.64, 21.61, 12.38), strict=True)),
        0.5: dict(zip(_FILTERS, (9.48, 26.47, 16.38, 31.35, 25.85, 13.78), strict=True)),
    },
}

_RMSE = {"rmse": lambda tr, res: metrics.rmse(tr.states, res.filtered_means)}


def eps_sweep_scenario(key, num_runs: int, alpha: float, magnitude: float, eps_real=EPS_REAL, num_steps: int | None = None) -> Trajectories:
    """`wang_ye.scenario` at every `ε_real` with the same key, concatenated along the run axis
    (`ε_real`-major: runs `j·num_runs … (j+1)·num_runs − 1` have `eps_real[j]`)."""
    num_steps = NUM_STEPS if num_steps is None else num_steps
    trajs = [wang_ye.scenario(key, num_runs, alpha, True, num_steps, prob=p, magnitude=magnitude) for p in eps_real]
    return jax.tree.map(lambda *a: jnp.concatenate(a, axis=0), *trajs)


def _by_x(values, num_x: int) -> np.ndarray:
    """`(num_x · runs,)` `x`-major per-run values → `(runs, num_x)`."""
    return np.asarray(values).reshape(num_x, -1).T


def _shift_transitions(traj: Trajectories) -> Trajectories:
    """The authors' TMKF off-by-one: at step `t` it used `F_{t+1}` (the last step keeps `F_T`)."""
    fs = traj.transition_matrices
    shifted = jnp.concatenate([fs[:, 1:], fs[:, -1:]], axis=1)
    return Trajectories(traj.initial_states, traj.states, traj.observations, traj.clean_observations, traj.outliers, shifted)


def _failures(out) -> dict[str, int]:
    return {f: int(np.sum(~np.asarray(o["success"]))) for f, o in out.items() if not np.all(o["success"])}


def _paired(a, b) -> str:
    """`mean(a − b)` over runs with its 95% CI, as text."""
    mean, (lo, hi) = metrics.mean_ci(np.asarray(a) - np.asarray(b))
    return f"{mean:+.3g} [{lo:+.3g}, {hi:+.3g}]"


def _mean_ci(a) -> str:
    mean, (lo, hi) = metrics.mean_ci(a)
    return f"{mean:.3g} [{lo:.3g}, {hi:.3g}]"


def _paired_sign(a, b) -> int:
    """+1 if `a − b` is significantly positive (95% CI above 0), −1 if below, 0 otherwise."""
    _, (lo, hi) = metrics.mean_ci(np.asarray(a) - np.asarray(b))
    return 1 if lo > 0 else -1 if hi < 0 else 0


def _relative_spread(values: np.ndarray) -> float:
    """`(max − min) / min` of the run-mean curve of `values` `(runs, len(x))`."""
    mean = values.mean(axis=0)
    return float((mean.max() - mean.min()) / mean.min())


def _bootstrap_argmin(values: np.ndarray, x, seed: int, num: int = BOOTSTRAP) -> tuple[float, float]:
    """2.5% and 97.5% percentiles of the argmin `x` of the run-mean curve over `num`
    bootstrap resamples of the runs."""
    rng = np.random.default_rng(seed)
    idx = rng.integers(0, values.shape[0], (num, values.shape[0]))
    arg = np.asarray(x)[np.argmin(values[idx].mean(axis=1), axis=1)]
    return float(np.percentile(arg, 2.5)), float(np.percentile(arg, 97.5))


def _common_notes(runs: int, seed: int, num_steps: int) -> list[str]:
    return [
        f"Ours: {runs} seeded Monte Carlo runs (seed {seed}) of T = {num_steps} steps per grid point, means with 95% "
        "Student-t intervals; the paper's curves are one random episode of T = 10⁴ steps per grid point (no seed, "
        "no averaging) on the finer grid 0:0.01 — ours is coarser to keep the run short.",
        "Common random numbers: all filters see the same runs, and every grid point reuses the same states, "
        "nominal noise and Δ_k (only the outliers change, nested in ε_real), so differences along a curve and "
        "between filters are paired and much tighter than the per-point intervals suggest.",
    ]


# ----------------------------------------------------------------- Fig. 1: sensitivity


def sensitivity_filters():
    """Fig. 1(a): the DR estimator without ambiguity under both outlier models, plus
    the nominal KF and the clairvoyant TMKF as references."""
    return {
        "HKF-contamination": DRKF(outliers=EpsContamination(CONTAMINATION_EPS, k=CONTAMINATION_K), throw=False),
        "HKF-normal": DRKF(outliers=EpsNormal(NORMAL_EPS), throw=False),
        "KF": KalmanFilter(throw=False),
        "TMKF": Clairvoyant(KalmanFilter(throw=False)),
    }


def run_sensitivity(runs: int, seed: int, progress: bool = False, curves: bool = False, num_steps: int | None = None) -> Report:
    del curves  # no per-step curves: the figure is the sweep
    num_steps = NUM_STEPS if num_steps is None else num_steps
    key = jax.random.key(seed)
    model, prior = wang_ye.nominal_model(), wang_ye.prior()
    eps_real = np.asarray(EPS_REAL)

    # Fig. 1(a): one Monte Carlo call over all ε_real (runs concatenated).
    traj_a = eps_sweep_scenario(jax.random.fold_in(key, 0), runs, 0.0, SENSITIVITY_MAGNITUDE, EPS_REAL, num_steps)
    flts_a = sensitivity_filters()
    out_a = montecarlo(flts_a, model, prior, traj_a, metrics=_RMSE, chunk_size=500, progress=progress)
    vals_a = {f: _by_x(out_a[f]["rmse"], len(eps_real)) for f in flts_a}

    # Fig. 1(b): the same runs for every θ₂ (one compilation: θ₂ is an array leaf).
    traj_b = wang_ye.scenario(jax.random.fold_in(key, 1), runs, 1.0, True, num_steps, prob=THETA_EPS_REAL, magnitude=THETA_MAGNITUDE)
    out_b = [montecarlo({"MKF": wang_ye.mkf(t)}, model, prior, traj_b, metrics=_RMSE, chunk_size=500, progress=progress)["MKF"] for t in THETA2]
    vals_b = np.stack([np.asarray(o["rmse"]) for o in out_b], axis=1)
    kf_b = montecarlo({"KF": KalmanFilter(throw=False)}, model, prior, traj_b, metrics=_RMSE, chunk_size=500)["KF"]["rmse"]
    failed_b = sum(int(np.sum(~np.asarray(o["success"]))) for o in out_b)

    rows = [Row.from_values(f, f"rmse@eps_real={e:g}", None, vals_a[f][:, j]) for f in flts_a for j, e in enumerate(EPS_REAL)]
    rows += [Row.from_values("MKF", f"rmse@theta2={t:.2f}", None, vals_b[:, j]) for j, t in enumerate(THETA2)]

    notes = _common_notes(runs, seed, num_steps)
    realized = np.asarray(traj_a.outliers).reshape(len(eps_real), -1).mean(axis=1)
    notes.append(
        f"Fig. 1(a): α = 0, outliers ±{SENSITIVITY_MAGNITUDE:g} with probability ε_real (realized "
        + ", ".join(f"{r:.3f}" for r in realized)
        + f"). HKF-contamination is the DR estimator with θ₂ = 1 and the ε-contamination model (ε = {CONTAMINATION_EPS}, "
        f"K = {CONTAMINATION_K:g}); HKF-normal uses the ε-normal model with ε = {NORMAL_EPS} (our roots (a, b, c) = "
        "(1.3462, 1.3534, 1.2324); the authors' code used Huber's table entry a = b = 1.3496, c = 1.2316, which is "
        "ε ≈ 0.0303). KF (nominal) and TMKF (clairvoyant: outlier-free data) are references, not in the paper's figure."
    )
    # Claim 1(a): insensitive to ε_real.
    kf_spread = _relative_spread(vals_a["KF"])
    flat = []
    for f in ("HKF-contamination", "HKF-normal"):
        spread = _relative_spread(vals_a[f])
        flat.append(spread < 0.25 * kf_spread)
        notes.append(
            f"{f}: mean RMSE {vals_a[f][:, 0].mean():.3g} at ε_real = 0 and {vals_a[f][:, -1].mean():.3g} at 0.5 "
            f"(paired change {_paired(vals_a[f][:, -1], vals_a[f][:, 0])}); relative spread (max − min)/min of the "
            f"curve {spread:.1%}, vs {kf_spread:.1%} for the KF."
        )
    notes.append(
        "Paper's claim (Fig. 1(a)): the estimator is not sensitive to ε_real, so the recommended ε, K, a, b, c can be "
        "kept whatever the true outlier rate. Ours "
        + ("agree" if all(flat) else "DISAGREE")
        + " (criterion: each HKF curve's relative spread under a quarter of the KF's); the curves are flat "
        "relative to the KF, though not constant: the error still grows with ε_real (paired change above)."
    )
    # Claim 1(b): strong dependence on θ₂ with an interior minimum.
    mean_b = vals_b.mean(axis=0)
    j_min = int(np.argmin(mean_b))
    lo, hi = _bootstrap_argmin(vals_b, THETA2, seed)
    interior = 0 < j_min < len(THETA2) - 1 and _paired_sign(vals_b[:, 0], vals_b[:, j_min]) > 0 and _paired_sign(vals_b[:, -1], vals_b[:, j_min]) > 0
    notes.append(
        f"Fig. 1(b): α = 1, ε_real = {THETA_EPS_REAL}, outliers ±{THETA_MAGNITUDE:g} (realized "
        f"{float(np.mean(np.asarray(traj_b.outliers))):.3f}); MKF with k = {wang_ye.HUBER_K}, ε = {wang_ye.EPS} and "
        f"θ₂ₓ = θ₂ᵥ = θ₂. Mean RMSE is smallest at θ₂ = {THETA2[j_min]:.2f} ({mean_b[j_min]:.3g}; bootstrap 95% "
        f"interval of the argmin over runs [{lo:.2f}, {hi:.2f}]); at θ₂ = 1.00 it is {mean_b[0]:.3g} (paired excess "
        f"{_paired(vals_b[:, 0], vals_b[:, j_min])}) and at 1.10 {mean_b[-1]:.3g} (paired excess "
        f"{_paired(vals_b[:, -1], vals_b[:, j_min])}); relative range of the curve {_relative_spread(vals_b):.1%}. "
        f"The nominal KF has {_mean_ci(kf_b)} on the same runs; MKF is worse than it for θ₂ ≥ "
        f"{next((f'{t:.2f}' for t, m in zip(THETA2, mean_b, strict=True) if t > THETA2[j_min] and m > kf_b.mean()), 'none of the grid')}. "
        f"Tables I–III use θ₂ = {wang_ye.MKF_THETA2}."
    )
    notes.append(
        "Paper's claim (Fig. 1(b)): the RMSE depends heavily on θ₂ — too small is not robust enough, too large too "
        "conservative — so θ₂ must be tuned. Ours "
        + ("agree" if interior else "DISAGREE")
        + " (criterion: the minimum of the mean curve is interior and both endpoints are significantly worse, paired 95% CI)."
    )
    failed = _failures(out_a)
    if failed or failed_b:
        notes.append(f"Runs flagged unsuccessful (result code): {failed | ({'MKF (Fig. 1b)': failed_b} if failed_b else {})}.")

    report = Report(experiment="wang-ye-sensitivity", seed=seed, rows=rows, notes=notes)
    report.sweeps = {
        f"Fig. 1(a): α=0, ±{SENSITIVITY_MAGNITUDE:g} outliers": Sweep("ε_real", eps_real, vals_a),
        f"Fig. 1(b): α=1, ε_real={THETA_EPS_REAL}, ±{THETA_MAGNITUDE:g}": Sweep("θ₂", np.asarray(THETA2), {"MKF": vals_b}),
    }
    return report


# ------------------------------------------------------------------- Fig. 2: breakdown


def run_breakdown(runs: int, seed: int, progress: bool = False, curves: bool = False, num_steps: int | None = None) -> Report:
    del curves
    num_steps = NUM_STEPS if num_steps is None else num_steps
    key = jax.random.key(seed)
    model, prior = wang_ye.nominal_model(), wang_ye.prior()
    eps_real, n = np.asarray(EPS_REAL), len(EPS_REAL)
    flts = wang_ye.filters()
    rows, sweeps, vals, failed, realized = [], {}, {}, {}, {}
    for alpha in (0.0, 1.0):
        traj = eps_sweep_scenario(jax.random.fold_in(key, int(alpha)), runs, alpha, BREAKDOWN_MAGNITUDE, EPS_REAL, num_steps)
        out = montecarlo(flts, model, prior, traj, metrics=_RMSE, chunk_size=500, progress=progress)
        v = {f: _by_x(out[f]["rmse"], n) for f in flts}
        failed |= {f"{f} (α={alpha:g})": c for f, c in _failures(out).items()}
        if alpha > 0:  # diagnostic: the authors' TMKF, one step ahead in F
            shifted = montecarlo({"TMKF": flts["TMKF"]}, model, prior, _shift_transitions(traj), metrics=_RMSE, chunk_size=500)
            v["TMKF-off-by-one"] = _by_x(shifted["TMKF"]["rmse"], n)
        vals[alpha] = v
        realized[alpha] = np.asarray(traj.outliers).reshape(n, -1).mean(axis=1)
        paper = PAPER_BREAKDOWN[alpha]
        for j, e in enumerate(EPS_REAL):
            rows += [Row.from_values(f, f"rmse@alpha={alpha:g},eps_real={e:g}", paper.get(e, {}).get(f), v[f][:, j]) for f in v]
        paper_x = {f: np.array([paper.get(e, {}).get(f, np.nan) for e in EPS_REAL]) for f in _FILTERS}
        panel = "(a)" if alpha == 0 else "(b)"
        sweeps[f"Fig. 2{panel}: α={alpha:g}, ±{BREAKDOWN_MAGNITUDE:g} outliers"] = Sweep("ε_real", eps_real, v, paper_x)

    notes = _common_notes(runs, seed, num_steps)
    notes.append(
        f"Outliers ±{BREAKDOWN_MAGNITUDE:g} with probability ε_real (realized at α = 0: "
        + ", ".join(f"{r:.3f}" for r in realized[0.0])
        + "). Filters and parameters of Tables I–III (HKF and MKF keep ε = 0.05, k = 1.4; MKF θ₂ = 1.02), "
        "as in the authors' Breakdown-Test."
    )
    # The paper's claim: HKF < MKF at α = 0, MKF < HKF at α = 1.
    verdict = []
    for alpha, want, text in ((0.0, -1, "HKF beats MKF without model uncertainty"), (1.0, 1, "MKF beats HKF with it")):
        v = vals[alpha]
        signs = [_paired_sign(v["HKF"][:, j], v["MKF"][:, j]) for j in range(n)]
        ok = sum(s == want for s in signs)
        verdict.append(ok == n)
        notes.append(
            f"α = {alpha:g}, RMSE(HKF) − RMSE(MKF) per ε_real (paired 95% CI): "
            + "; ".join(f"{e:g}: {_paired(v['HKF'][:, j], v['MKF'][:, j])}" for j, e in enumerate(EPS_REAL))
            + f". '{text}' holds significantly at {ok} of {n} grid points."
        )
    notes.append(
        "Paper's claim (Fig. 2): the HKF is better than the MKF without model uncertainty (α = 0) and worse with it "
        "(α = 1) — the price of robustness. Ours " + ("agree" if all(verdict) else "DISAGREE at some grid points (see above)") + "."
    )
    inside, outside = 0, {}
    for alpha, paper in PAPER_BREAKDOWN.items():
        for e, nums in paper.items():
            j = EPS_REAL.index(e)
            for f, p in nums.items():
                col = vals[alpha][f][:, j]
                if col.min() <= p <= col.max():
                    inside += 1
                else:
                    side = "below" if p < col.min() else "above"
                    outside.setdefault(f, []).append(f"α={alpha:g} ε_real={e:g} ({side})")
    total = sum(len(nums) for paper in PAPER_BREAKDOWN.values() for nums in paper.values())
    notes.append(
        f"{inside} of {total} paper numbers lie within the range of our {runs} per-run RMSEs at their grid point; "
        "outside it: " + ("; ".join(f"{f}: " + ", ".join(w) for f, w in outside.items()) if outside else "none")
        + ". Each paper number is one 10⁴-step episode, and with α = 0 the pair (F, H) is barely observable, so "
        "single episodes vary widely."
    )
    tmkf0 = [PAPER_BREAKDOWN[0.0][e]["TMKF"] for e in PAPER_BREAKDOWN[0.0]]
    notes.append(
        f"The paper's own noise floor: its TMKF sees outlier-free data, so with α = 0 it should not depend on ε_real, "
        f"yet its four episodes give {min(tmkf0):.2f}–{max(tmkf0):.2f}; ours is identical across ε_real by construction "
        f"(common random numbers), {vals[0.0]['TMKF'].mean():.3g} on average, per-run range "
        f"{vals[0.0]['TMKF'][:, 0].min():.3g}–{vals[0.0]['TMKF'][:, 0].max():.3g}."
    )
    t1 = vals[1.0]
    notes.append(
        "TMKF at α = 1: the authors' GenerateData stored F_t after redrawing Δ, so their TMKF filtered with "
        f"F_{{t+1}}. Ours uses the true F_t: RMSE {_mean_ci(t1['TMKF'][:, 0])} (the same at "
        "every ε_real: outlier-free data, common random numbers); TMKF-off-by-one, the same clairvoyant KF given "
        f"F_{{t+1}}, has {_mean_ci(t1['TMKF-off-by-one'][:, 0])}, the paper's 8.78–9.48: the authors' TMKF is not the "
        "clairvoyant bound it is meant to be, which is why our TMKF is about a third of theirs."
    )
    worse = [(a, e) for a, paper in PAPER_BREAKDOWN.items() for e, nums in paper.items() if nums["tau-KF"] > vals[a]["tau-KF"][:, EPS_REAL.index(e)].mean()]
    notes.append(
        "tau-KF is Zorzi's filter as published (filtered estimate x̂_{k|k}); the authors' code fed it one-step-delayed "
        "measurements (it output x̂_{k|k-1}) and passed covariances where square-root factors were expected "
        f"(process covariance ≈ 3.84 I instead of 1.96 I); the paper's tau-KF is above our mean at {len(worse)} of 8 grid "
        "points. Their variant, re-run on this protocol (benchmarks/wang_ye_gaps.py, section 4: 200 episodes per grid "
        "point), puts all 8 paper numbers inside the central 95% of its per-episode RMSEs; the squared covariance does most of it."
    )
    gap = {a: [(PAPER_BREAKDOWN[a][e]["WKF"] - PAPER_BREAKDOWN[a][e]["KF"], float(np.mean(vals[a]["WKF"][:, EPS_REAL.index(e)] - vals[a]["KF"][:, EPS_REAL.index(e)]))) for e in (0.3, 0.5)] for a in PAPER_BREAKDOWN}
    notes.append(
        "WKF: the authors' Frank–Wolfe (2/(k+2) steps) stops at a 1e-4 relative gap; ours solves each step to round-off "
        "(a separate check with WassersteinKF(0.1, rtol=1e-4) and rtol=1e-2 gave the same RMSEs to 3 decimals at ε_real = 0.5, so our solver cannot mimic this). With many outliers our WKF is further above the KF than the paper's: "
        "WKF − KF at ε_real = 0.3, 0.5 is "
        + "; ".join(f"α = {a:g}: paper {g[0][0]:+.2f}, {g[1][0]:+.2f}, ours {g[0][1]:+.2f}, {g[1][1]:+.2f}" for a, g in gap.items())
        + ". An early-stopped Frank–Wolfe started at the nominal covariance would sit between the KF and the exact "
        "WKF, which fits this pattern; we have not verified that it is the cause."
    )
    swaps = []
    for alpha, paper in PAPER_BREAKDOWN.items():
        for e, nums in paper.items():
            j = EPS_REAL.index(e)
            for f, g in itertools.combinations(_FILTERS, 2):
                a, b = vals[alpha][f][:, j], vals[alpha][g][:, j]
                if nums[f] != nums[g] and np.sign(nums[f] - nums[g]) != np.sign(a.mean() - b.mean()):
                    swaps.append(f"α={alpha:g}, ε_real={e:g}: {f} − {g} paper {nums[f] - nums[g]:+.2f}, ours {_paired(a, b)}")
    notes.append(
        "Ranking lines above compare the order of all six filters at one grid point (the paper's ties, e.g. TMKF = KF "
        "= HKF = 9.45 at α = 0, ε_real = 0, are broken by row order, so such a line says little). Pairs ordered "
        "differently from the paper (paired 95% CI of ours): " + ("; ".join(swaps) if swaps else "none") + "."
    )
    if failed:
        notes.append(f"Runs flagged unsuccessful (result code): {failed}.")
    report = Report(experiment="wang-ye-breakdown", seed=seed, rows=rows, notes=notes)
    report.sweeps = sweeps
    return report


register(Experiment(
    name="wang-ye-sensitivity",
    description="Wang & Ye 2022, Fig. 1: RMSE vs ε_real (α=0, ±25) for both HKFs; vs θ₂ for the MKF (α=1); T=10⁴.",
    default_runs=DEFAULT_RUNS,
    run=run_sensitivity,
    quick={"runs": 4, "num_steps": 1000},
))
register(Experiment(
    name="wang-ye-breakdown",
    description="Wang & Ye 2022, Fig. 2: RMSE of the six filters vs ε_real (±50 outliers), α ∈ {0, 1}; T=10⁴.",
    default_runs=DEFAULT_RUNS,
    run=run_breakdown,
    quick={"runs": 4, "num_steps": 1000},
))
