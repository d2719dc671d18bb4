"""Li, Shi, Yu, Shi, "Variational Robust Kalman Filters: A Unified Framework":
`li-torsion` (Example 4 / Sec. IV-C, Table IV) and `li-identity` (Example 1, Table III).

Settings follow the authors' MATLAB code (`lsl-zsj/Variational-Robust-Kalman-Filters`), which differs from
the printed text in places (listed in each report's notes).

**li-torsion.** Two-inertia torsion system (`b_m = 0.015`, `b_t = 0.004`,
`J_m = 5.4538e-4`, `J_t = 2.1841e-4`, `K_s = 1`), ZOH at `dt = 0.01`, state
`[θ_m, θ_t, ω_m, ω_t]`, both angles measured. Filters run on the disturbance-augmented
model `[d; x]`, `A = [[1, 0], [G₂, F]]`, `Q_a = diag(0.01, 0.01, 0.01, 100, 100)`,
`R_a = 0.1 I₂`, `x̂₀ = 0`, `P₀ = 0.01 I₅`, 2000 steps. The authors' truth (their
`measurement_generation_y*.m`) draws the disturbance white, `d_k = w_{d,k}`, entering
the same step: `x_k = F x_{k−1} + G₂ d_k + w_{x,k}`, `x₀ = 0`; we simulate exactly that
(`F_true = blkdiag(0, F)`, `G_true = [[1, 0], [G₂, I₄]]`). Per-state RMSE over the
horizon of `[d, θ_m, θ_t, ω_m, ω_t]` (the paper's `x₁..x₅`).

Noise cases (the code's names; Table IV's Case 1/2/3 are y2/y4/y3):

- y2: process (and disturbance) noise variance ×100 at MATLAB steps 801–1199.
- y4: process noise variance ×900 with probability 0.01 per step (whole vector);
  measurement std × `a(t) = 2 sin²(2π·0.05 t) + 1`, `t = k dt`.
- y3: measurement std × `a(t)`, replaced with probability 0.01 by `N(0, 900 R)`.

**li-identity.** `dt = 0.01`, 5000 steps, `F = [[1, dt], [0, 1]]`, `G = [dt²/2; dt]`,
unit acceleration noise, `H = [1, 0]`, `R = 0.1`, `x₀ = 0`, filters `x̂₀ = 0`,
`P₀ = diag(0.001, 0.001)`. y1 (Table III Case 1): `0.95 N(0, R) + 0.05 N(0, 100R)`;
y2 (Case 2): measurement std × `(2 sin(2π·0.02 t))² + 1` (the authors' code).
"""

from __future__ import annotations

import time
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np
import scipy.linalg

from .. import metrics
from .._gaussian import Gaussian
from .._models import LinearModel
from .._montecarlo import montecarlo
from .._noise import AbstractNoise, GaussianNoise, MixtureNoise, ScaledNoise
from .._simulate import simulate
from ..filters import KalmanFilter
from ..filters._base import DEFAULT_OUTPUTS, with_outputs
from ..filters._reweighted import RBKF, STKF, STKF_AR1, VBKF
from ..sets._weights import Barron, GaussianKernel, PseudoHuber
from ._registry import Experiment, Report, Row, register
from ._tune import TuningProblem

DT = 0.01
NUM_STEPS = 2000  # torsion horizon (20 s)
IDENTITY_STEPS = 5000  # identity-demo horizon (50 s)
# Posterior covariance of the iterative filters: the authors' Joseph form with the nominal
# P⁻ and R (see notes); "reweighted" is the library default.
COVARIANCE = "nominal"

# Torsion constants (system_dynamic_construction.m) and noise levels (robust_adaptive_filters_test_y*.m).
B_M, B_T, J_M, J_T, K_S = 0.015, 0.004, 5.4538e-4, 2.1841e-4, 1.0
V_WD, V_WN, V_VN = 0.01, 0.01, 0.1
STEP_WINDOW = (800, 1199)  # 0-based t (MATLAB steps 801..1199) of the ×100 process-noise window in y2
STEP_SCALE = 100.0
PROC_OUTLIER_P, PROC_OUTLIER_SCALE = 0.01, 900.0
MEAS_OUTLIER_P, MEAS_OUTLIER_SCALE = 0.01, 900.0
SLOW_FREQ = 0.05  # Hz, torsion a(t)

STATE_NAMES = ("d", "theta_m", "theta_t", "omega_m", "omega_t")
TORSION_CASES = ("y2", "y4", "y3")  # Table IV Case 1, 2, 3
PAPER_CASE = {"y2": "Case 1", "y4": "Case 2", "y3": "Case 3", "y1": "Case 1", "y2-identity": "Case 2"}

# Table IV: RMSE of x1..x5 = [d, θ_m, θ_t, ω_m, ω_t], one unseeded run each.
PAPER_TORSION = {
    "y2": {
        "VBKF": (0.710, 2.609, 2.717, 71.101, 111.818),
        "STKF-AR1": (0.507, 0.237, 0.249, 58.162, 64.819),
        "KF": (0.604, 0.589, 0.477, 55.350, 71.400),
        "RBKF1": (0.557, 0.258, 0.265, 55.888, 62.650),
        "RBKF2": (0.535, 0.254, 0.259, 55.664, 60.958),
        "RBKF3": (0.555, 0.273, 0.271, 55.093, 60.377),
    },
    "y4": {
        "VBKF": (0.408, 0.625, 0.863, 32.089, 58.726),
        "STKF-AR1": (0.375, 0.423, 0.503, 28.231, 47.228),
        "KF": (0.468, 0.416, 0.515, 28.315, 49.509),
        "RBKF1": (0.392, 2.151, 2.263, 35.268, 62.601),
        "RBKF2": (0.380, 0.743, 0.978, 32.881, 59.835),
        "RBKF3": (0.386, 0.502, 0.754, 30.510, 56.959),
    },
    "y3": {
        "VBKF": (0.200, 0.359, 0.406, 15.085, 23.448),
        "STKF-AR2": (0.203, 0.322, 0.389, 15.165, 22.948),
        "KF": (0.359, 0.600, 0.524, 21.320, 34.781),
        "RBKF1": (0.229, 0.428, 0.508, 16.257, 24.640),
        "RBKF2": (0.210, 0.363, 0.425, 15.576, 23.530),
        "RBKF3": (0.215, 0.341, 0.411, 15.554, 23.630),
    },
}

# Table III: RMSE of [position, velocity], one run each.
PAPER_IDENTITY = {
    "y1": {"VBKF-fixed": (0.053, 0.081), "STKF": (0.053, 0.081), "KF": (0.111, 0.129)},
    "y2": {"VBKF": (0.092, 0.086), "STKF-AR1": (0.092, 0.086), "KF": (0.130, 0.143)},
}
# Table III, last column: average number of (fixed-point / VB) iterations per step.
PAPER_IDENTITY_ITERATIONS = {
    "y1": {"VBKF-fixed": 4.0, "STKF": 1.096, "KF": 1.0},
    "y2": {"VBKF": 4.0, "STKF-AR1": 2.190, "KF": 1.0},
}


# ----------------------------------------------------------------------------- torsion model


def torsion_discrete() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """ZOH discretization (`dt = 0.01`) of the two-inertia system: `(F, G₁, G₂)` (MATLAB `c2d`)."""
    a = np.array([
        [0.0, 0.0, 1.0, 0.0],
        [0.0, 0.0, 0.0, 1.0],
        [-K_S / J_M, K_S / J_M, -B_M / J_M, 0.0],
        [K_S / J_T, -K_S / J_T, 0.0, -B_T / J_T],
    ])
    b = np.array([[0.0, 0.0], [0.0, 0.0], [1.0 / J_M, 0.0], [0.0, 1.0 / J_T]])
    m = np.zeros((6, 6))
    m[:4, :4], m[:4, 4:] = a * DT, b * DT
    e = scipy.linalg.expm(m)
    return e[:4, :4], e[:4, 4], e[:4, 5]


def torsion_model(dtype=None) -> LinearModel:
    """The filters' augmented model `[d; x]` with a random-walk disturbance (KF-DOB)."""
    f, _, g2 = torsion_discrete()
    fa = np.zeros((5, 5))
    fa[0, 0], fa[1:, 0], fa[1:, 1:] = 1.0, g2, f
    ha = np.zeros((2, 5))
    ha[0, 1] = ha[1, 2] = 1.0
    qa = np.diag([V_WD, V_WN, V_WN, V_WN / DT**2, V_WN / DT**2])
    return LinearModel(F=jnp.asarray(fa, dtype), H=jnp.asarray(ha, dtype), Q=jnp.asarray(qa, dtype), R=V_VN * jnp.eye(2, dtype=dtype))


def torsion_truth(dtype=None) -> LinearModel:
    """The authors' simulated truth: white disturbance `d_k` entering the same step."""
    f, _, g2 = torsion_discrete()
    nominal = torsion_model(dtype)
    ft = np.zeros((5, 5))
    ft[1:, 1:] = f
    gt = np.eye(5)
    gt[1:, 0] = g2
    return LinearModel(F=jnp.asarray(ft, dtype), H=nominal.H, Q=nominal.Q, R=nominal.R, G=jnp.asarray(gt, dtype))


def torsion_prior(dtype=None) -> Gaussian:
    return Gaussian(jnp.zeros(5, dtype), 0.01 * jnp.eye(5, dtype=dtype))


def _float(t):
    return jnp.asarray(t).astype(jnp.result_type(float))


def _slow_amp(t, freq: float = SLOW_FREQ):
    """The authors' torsion std multiplier at 0-based index `t` (MATLAB `t = i dt`, `i = t + 1`)."""
    s = jnp.sin(2.0 * jnp.pi * freq * DT * (_float(t) + 1.0))
    return 2.0 * s**2 + 1.0


class ReplacementOutlierNoise(AbstractNoise):
    """`base` draw, replaced (whole vector) with probability `p` by `N(0, outlier_cov)`:
    the authors' y3 measurement noise (`rand > 0.99`). The outlier part is the
    replacement minus the nominal draw, so `nominal + outlier` is the replacement."""

    base: AbstractNoise
    outlier_cov: jax.Array
    p: float

    def __init__(self, base: AbstractNoise, p: float, outlier_cov):
        self.base, self.p = base, float(p)
        self.outlier_cov = jnp.asarray(outlier_cov, base.cov.dtype)

    @property
    def dim(self):
        return self.base.dim

    @property
    def mean(self):
        return self.base.mean

    @property
    def cov(self):
        return (1.0 - self.p) * self.base.cov + self.p * self.outlier_cov

    def check_horizon(self, num_steps):
        self.base.check_horizon(num_steps)

    def sample_parts(self, key, t=0):
        k1, k2, k3 = jax.random.split(key, 3)
        nominal, extra = self.base.sample_parts(k1, t)
        nominal = nominal + extra
        root = jnp.linalg.cholesky(self.outlier_cov)
        replacement = root @ jax.random.normal(k2, (self.dim,), nominal.dtype)
        hit = jax.random.bernoulli(k3, self.p)
        return nominal, jnp.where(hit, replacement - nominal, 0.0)


def torsion_noise(case: str, dtype=None) -> tuple[AbstractNoise, AbstractNoise]:
    """True `(process, measurement)` laws of a torsion noise case."""
    model = torsion_model(dtype)
    q, r = GaussianNoise(model.Q), GaussianNoise(model.R)
    slow = ScaledNoise(r, lambda t: _slow_amp(t) ** 2)
    if case == "y2":
        lo, hi = STEP_WINDOW
        return ScaledNoise(q, lambda t: jnp.where((t >= lo) & (t < hi), STEP_SCALE, 1.0)), r
    if case == "y4":
        return MixtureNoise(model.Q, PROC_OUTLIER_P, PROC_OUTLIER_SCALE), slow
    if case == "y3":
        return q, ReplacementOutlierNoise(slow, MEAS_OUTLIER_P, MEAS_OUTLIER_SCALE * model.R)
    raise ValueError(f"unknown torsion case {case!r}; expected one of {TORSION_CASES}")


def torsion_scenario(key, case: str, num_runs: int, num_steps: int | None = None):
    """Simulate `num_runs` runs of a torsion noise case from the authors' truth (`x₀ = 0`)."""
    truth = torsion_truth()
    proc, meas = torsion_noise(case)
    x0 = Gaussian(jnp.zeros(5), jnp.zeros((5, 5)))
    steps = NUM_STEPS if num_steps is None else num_steps
    return simulate(key, truth, x0, steps, num_runs, process_noise=proc, measurement_noise=meas)


def torsion_filters(case: str, covariance: str = COVARIANCE, outputs: str | Sequence[str] = DEFAULT_OUTPUTS) -> dict:
    """The filters of Table IV for a case, with the authors' hyper-parameters (their code);
    `covariance` is the posterior covariance of the iterative filters (see `COVARIANCE`);
    `outputs` is given to every filter (`"all"` to read their `info`)."""
    return {name: with_outputs(flt, outputs) for name, flt in _torsion_filters(case, covariance).items()}


def _torsion_filters(case: str, covariance: str) -> dict:
    cov = covariance
    vbkf = VBKF(alpha0=20.0, beta0=2.03 / V_VN, rho=0.98, covariance=cov, throw=False)  # α₀ = 20, β₀ = 2.03 (absolute variance)
    kf = KalmanFilter(throw=False)
    big = 1e8
    if case == "y2":
        return {
            "VBKF": vbkf,
            "STKF-AR1": STKF_AR1(100.0, 1.0, 0.98, big, 1.0, 1.0, tol=1e-6, covariance=cov, throw=False),
            "KF": kf,
            "RBKF1": RBKF(GaussianKernel(2.0, floor=1e-4), GaussianKernel(big, floor=4e-4), covariance=cov, throw=False),
            "RBKF2": RBKF(Barron(0.5, floor=1e-4), Barron(1.999, floor=1e-4), covariance=cov, throw=False),
            "RBKF3": RBKF(PseudoHuber(1.0), PseudoHuber(big), covariance=cov, throw=False),
        }
    if case == "y4":
        return {
            "VBKF": vbkf,
            "STKF-AR1": STKF_AR1(3.0, 1.0, 1.0, 100.0, 1.0, 0.98, gate=40.0, covariance=cov, throw=False),
            "KF": kf,
            "RBKF1": RBKF(GaussianKernel(2.0, floor=1e-4), GaussianKernel(2.0, floor=4e-4), covariance=cov, throw=False),
            "RBKF2": RBKF(Barron(0.5, floor=1e-4), Barron(0.5, floor=1e-4), covariance=cov, throw=False),
            "RBKF3": RBKF(PseudoHuber(1.0), PseudoHuber(1.0), covariance=cov, throw=False),
        }
    if case == "y3":
        return {
            "VBKF": vbkf,
            # The authors' "STKF-AR2" is student_forward_adap_y2: STKF-AR1 with the ‖e_y‖² > 40 gate.
            "STKF-AR2": STKF_AR1(big, 1.0, 1.0, 100.0, 1.0, 0.98, gate=40.0, covariance=cov, throw=False),
            "KF": kf,
            "RBKF1": RBKF(GaussianKernel(big, floor=1e-4), GaussianKernel(2.0, floor=4e-4), covariance=cov, throw=False),
            "RBKF2": RBKF(Barron(1.999, floor=1e-4), Barron(0.5, floor=1e-4), covariance=cov, throw=False),
            "RBKF3": RBKF(PseudoHuber(big), PseudoHuber(1.0), covariance=cov, throw=False),
        }
    raise ValueError(f"unknown torsion case {case!r}; expected one of {TORSION_CASES}")


def _per_state_rmse(tr, res):
    return jnp.sqrt(jnp.mean((tr.states - res.filtered_means) ** 2, axis=-2))


def _case_rows(case: str, out: dict, paper: dict, names) -> list[Row]:
    rows = []
    for i in range(len(names)):
        for f in out:
            p = paper.get(f)
            rows.append(Row.from_values(f, f"rmse_x{i + 1}@{case}", None if p is None else p[i], out[f]["rmse"][:, i]))
    return rows


def _agreement_notes(report: Report, cases, num_states: int) -> list[str]:
    notes = []
    for case in cases:
        agree = [i + 1 for i in range(num_states) if report.ranking_agrees(f"rmse_x{i + 1}@{case}")]
        notes.append(f"{case}: our ranking equals the paper's for states x{agree} of x1..x{num_states}." if agree else f"{case}: our ranking differs from the paper's for every state.")
    return notes


def _paired_notes(out_by_case: dict, names) -> list[str]:
    """Paired 95% intervals (same runs) of the proposed filter's RMSE minus the KF's, per state."""
    notes = []
    for case, out in out_by_case.items():
        prop = next(f for f in out if f.startswith("STKF"))
        parts = []
        for i, sname in enumerate(names):
            mean, (lo, hi) = metrics.mean_ci(out[prop]["rmse"][:, i] - out["KF"]["rmse"][:, i])
            parts.append(f"x{i + 1} ({sname}) {mean:.3g} [{lo:.3g}, {hi:.3g}]")
        notes.append(f"{case}: {prop} − KF RMSE, paired mean and 95% CI: " + "; ".join(parts) + ".")
    return notes


def _spread_notes(out_by_case: dict, paper: dict) -> list[str]:
    """Where each single-run paper number falls among our per-run RMSEs."""
    notes = []
    for case, out in out_by_case.items():
        outside, total = [], 0
        for f, vals in paper[case].items():
            if f not in out:
                continue
            for i, p in enumerate(vals):
                total += 1
                pct = 100.0 * float(np.mean(out[f]["rmse"][:, i] <= p))
                if pct < 2.5 or pct > 97.5:
                    outside.append(f"{f} x{i + 1} ({pct:.0f}%)")
        notes.append(
            f"{case}: {total - len(outside)} of {total} paper numbers lie within the central 95% of our per-run RMSEs"
            + (f"; outside (percentile of the paper number among our runs): {', '.join(outside)}." if outside else ".")
        )
    return notes


def _best_notes(out_by_case: dict, paper: dict, names) -> list[str]:
    notes = []
    for case, out in out_by_case.items():
        for i, sname in enumerate(names):
            ours = min((f for f in out if f in paper[case]), key=lambda f: float(np.mean(out[f]["rmse"][:, i])))
            theirs = min(paper[case], key=lambda f: paper[case][f][i])
            if ours != theirs:
                notes.append(f"{case}, x{i + 1} ({sname}): best filter is {ours} in ours, {theirs} in the paper.")
    return notes


# A whitened process draw ‖Q^{-1/2} w‖² above this is a y4 outlier: a nominal χ²₅ draw exceeds it
# with probability ~1e-40, a ×900 draw falls below it with probability ~6e-4.
OUTLIER_THRESHOLD = 200.0


def process_outliers(tr) -> tuple[np.ndarray, np.ndarray]:
    """Per run: the number of process-noise outliers and their energy `Σ ‖Q^{-1/2} w_k‖²`
    over the outlier steps, with `w_k = G⁻¹(x_k − F x_{k−1})` recovered from the states of
    `torsion_truth` (y4's ×900 draws; the simulation does not record process outliers)."""
    truth = torsion_truth()
    x = np.asarray(tr.states)
    prev = np.concatenate([np.asarray(tr.initial_states)[:, None], x[:, :-1]], axis=1)
    w = np.linalg.solve(np.asarray(truth.G), np.swapaxes(x - prev @ np.asarray(truth.F).T, 1, 2))
    z2 = np.sum(np.swapaxes(w, 1, 2) ** 2 / np.diag(np.asarray(truth.Q)), axis=-1)
    hit = z2 > OUTLIER_THRESHOLD
    return hit.sum(axis=1), np.where(hit, z2, 0.0).sum(axis=1)


def _log_ratio_to_paper(out: dict, paper: dict, idx) -> np.ndarray:
    """`log(our mean over runs idx / paper)` for every (filter, state) of the paper."""
    return np.array([np.log(np.mean(out[f]["rmse"][idx], axis=0) / np.asarray(p)) for f, p in paper.items() if f in out])


def _y4_draw_note(tr, out: dict, steps: int) -> str:
    """How y4's levels depend on the process-outlier draw, from this run's data."""
    paper = PAPER_TORSION["y4"]
    count, energy = process_outliers(tr)
    kf = out["KF"]["rmse"][:, 3]
    low = np.argsort(energy, kind="stable")[: max(1, len(energy) // 20)]
    lr_all, lr_low = _log_ratio_to_paper(out, paper, slice(None)), _log_ratio_to_paper(out, paper, low)
    r = np.corrcoef(energy, kf)[0, 1] if len(kf) > 2 else float("nan")
    return (
        f"y4 (Table IV Case 2): {count.mean():.1f} process-noise outliers (variance ×900) per {steps}-step run "
        f"(range {count.min()}–{count.max()}; expected {PROC_OUTLIER_P * steps:.0f}); the KF's ω_m (x4) RMSE rises with "
        f"their energy Σ‖Q^(-1/2)w‖² (correlation {r:.2f}). The paper's single run (the authors' rng(44); their "
        f"MATLAB stream is not reproduced) has KF x4 = {paper['KF'][3]}, at percentile "
        f"{100 * np.mean(kf <= paper['KF'][3]):.1f} of our runs. Over all runs our means exceed the paper's "
        f"{lr_all.size} y4 numbers by a median factor {np.exp(np.median(lr_all)):.2f} (median |log ratio| "
        f"{np.median(np.abs(lr_all)):.2f}); over the {len(low)} runs (5%) with the least outlier energy by "
        f"{np.exp(np.median(lr_low)):.2f} (median |log ratio| {np.median(np.abs(lr_low)):.2f}): the level gap is "
        "the paper's mild outlier draw, and the paired differences below are what a single run cannot resolve."
    )


def run_torsion(runs: int, seed: int, progress: bool = False, curves: bool = False, num_steps: int | None = None, cases=TORSION_CASES) -> Report:
    steps = NUM_STEPS if num_steps is None else num_steps
    key = jax.random.key(seed)
    model, prior = torsion_model(), torsion_prior()
    rows, out_by_case, traj_by_case, realized = [], {}, {}, {}
    start = time.perf_counter()
    for j, case in enumerate(cases):
        traj = traj_by_case[case] = torsion_scenario(jax.random.fold_in(key, j), case, runs, steps)
        flts = torsion_filters(case)
        prop = next(f for f in flts if f.startswith("STKF"))
        flts[f"{prop} (reweighted cov)"] = torsion_filters(case, "reweighted")[prop]
        out = montecarlo(flts, model, prior, traj, metrics={"rmse": _per_state_rmse}, chunk_size=500, progress=progress)
        out_by_case[case] = out
        rows += _case_rows(case, out, PAPER_TORSION[case], STATE_NAMES)
        realized[case] = {f: float(np.mean(out[f]["success"])) for f in out}
    elapsed = time.perf_counter() - start
    report = Report(experiment="li-torsion", seed=seed, rows=rows)
    failed = {c: {f: s for f, s in r.items() if s < 1.0} for c, r in realized.items()}
    failed = {c: v for c, v in failed.items() if v}
    report.notes = [
        "Table IV's Case 1/2/3 are the authors' torsion scripts y2/y4/y3 (step-like process noise; process "
        "outliers + slow-varying measurement noise; measurement outliers + slow-varying measurement noise); "
        "metrics are named after the scripts, e.g. rmse_x4@y2. States x1..x5 = [d, θ_m, θ_t, ω_m, ω_t] (the "
        "augmented state, as the authors' rms(statef − [d; state], 2)); the paper reports all five.",
        f"Paper numbers are single runs ({NUM_STEPS} steps; y2, y3 unseeded, y4 the authors' rng(44)); ours are means over {runs} seeded runs of "
        f"{steps} steps with 95% Student-t intervals, so paper numbers outside our intervals and rank swaps "
        "between close filters are expected.",
        "Settings follow the authors' code, not the printed text: R = 0.1 I₂ (paper eq. 57: 0.5 I₂); "
        "Q_a = diag(0.01, 0.01, 0.01, 100, 100) (velocity variance V_wn/dt²; eq. 57 prints 0.01 I₅); the ×100 "
        "window is MATLAB steps 801–1199 (eq. 56 prints the window reversed); a(t) = 2 sin²(2π·0.05 t) + 1 "
        "multiplies the noise *std* (eq. 57 prints R_t = [2 sin²(0.04π t) + 1] R, a variance); measurement "
        "outliers replace the draw with N(0, 900 R) with probability 0.01 (whole vector); the truth's "
        "disturbance is white and enters the same step (x_k = F x_{k−1} + G₂ d_k + w_k), while the filters "
        "assume a random walk entering with one step delay (A = [[1, 0], [G₂, F]]).",
        "KF is the plain KF on the augmented model (the authors' KF-DOB), run in every case as in Table IV.",
        "Hyper-parameters as in the authors' scripts: VBKF α₀ = 20, β₀ = 2.03 absolute (= 20.3 in units of "
        "R), ρ = 0.98, 4 VB iterations; STKF-AR1 (y2) ν_p = 100, ρ_p = 0.98, ν_r = 1e8, ρ_r = 1, tol 1e-6; "
        "STKF-AR1 (y4) ν_p = 3 fixed, ν_r = 100, ρ_r = 0.98; STKF-AR2 (y3) ν_p = 1e8, ν_r = 100, ρ_r = 0.98. "
        "The authors' STKF-AR1/AR2 in y3/y4 is student_forward_adap_y2, i.e. STKF-AR1 whose measurement "
        "scale update is skipped when ‖e_y‖² > 40 (our STKF_AR1(gate=40)); it is not the paper's Algorithm 3 "
        "(our STKF_AR2 with η), which we do not run. RBKF σ = 1e8 (disabled channel) and σ = 1.999 (≈ L2) "
        "are used literally; RBKF1 floors 1e-4/4e-4, RBKF2 floor 1e-4 (RBKF3's 1e-4 floor never binds here).",
        f"Posterior covariance of the iterative filters (VBKF, STKF-AR, RBKF): covariance={COVARIANCE!r}, the "
        "authors' Joseph form with the nominal P⁻ and R (their code, which produced Table IV: akf_forward_vb.m "
        "too, whose gain uses the adapted R_t) rather than the library default 'reweighted'; this is a "
        "reproduction of their numbers, so we keep their quirk. The row '… (reweighted cov)' (no paper number, "
        "not ranked) is the proposed filter with the library default (I − K̃H)P̃(I − K̃H)ᵀ + K̃R̃K̃ᵀ, for comparison.",
        f"Runtime of the Monte Carlo (all cases, {runs} runs × {steps} steps): {elapsed:.0f} s.",
    ]
    if failed:
        report.notes.append(f"Runs whose filter reported a failure (fraction of successful runs): {failed}.")
    if "y4" in out_by_case:
        report.notes.append(_y4_draw_note(traj_by_case["y4"], out_by_case["y4"], steps))
    report.notes += _agreement_notes(report, cases, 5)
    report.notes += _spread_notes(out_by_case, {c: PAPER_TORSION[c] for c in cases})
    report.notes += _paired_notes(out_by_case, STATE_NAMES)
    report.notes += _best_notes(out_by_case, {c: PAPER_TORSION[c] for c in cases}, STATE_NAMES)
    return report


# ----------------------------------------------------------------------------- identity demo


def identity_model(dtype=None) -> LinearModel:
    f = jnp.array([[1.0, DT], [0.0, 1.0]], dtype)
    g = jnp.array([[0.5 * DT**2], [DT]], dtype)
    return LinearModel(F=f, H=jnp.array([[1.0, 0.0]], dtype), Q=jnp.eye(1, dtype=dtype), R=jnp.array([[0.1]], dtype), G=g)


def identity_prior(dtype=None) -> Gaussian:
    return Gaussian(jnp.zeros(2, dtype), 0.001 * jnp.eye(2, dtype=dtype))


def _identity_amp(t):
    """The authors' identity std multiplier (their `t = 0:dt:…`, so `t = index · dt`)."""
    s = jnp.sin(2.0 * jnp.pi * 0.02 * DT * _float(t))
    return (2.0 * s) ** 2 + 1.0


def _printed_variance_factor(t):
    """The paper's printed y2 law (eq. 57 form): variance × `2 sin²(0.04π t) + 1`, `t = index · dt`."""
    return 2.0 * jnp.sin(0.04 * jnp.pi * DT * _float(t)) ** 2 + 1.0


def identity_scenario(key, case: str, num_runs: int, num_steps: int | None = None):
    """Simulate an identity case: y1, y2 (the authors' code) or "y2-printed" (the paper's printed law)."""
    model = identity_model()
    r = GaussianNoise(model.R)
    if case == "y1":
        meas = MixtureNoise(model.R, 0.05, 100.0)
    elif case == "y2":
        meas = ScaledNoise(r, lambda t: _identity_amp(t) ** 2)
    elif case == "y2-printed":
        meas = ScaledNoise(r, _printed_variance_factor)
    else:
        raise ValueError(f"unknown identity case {case!r}; expected 'y1', 'y2' or 'y2-printed'")
    x0 = Gaussian(jnp.zeros(2), jnp.zeros((2, 2)))
    steps = IDENTITY_STEPS if num_steps is None else num_steps
    return simulate(key, model, x0, steps, num_runs, measurement_noise=meas)


def identity_filters(case: str, covariance: str = COVARIANCE, outputs: str | Sequence[str] = DEFAULT_OUTPUTS) -> dict:
    """The filters of Table III for a case, with the authors' hyper-parameters (their code);
    `outputs` is given to every filter (`"all"` to read their `info`)."""
    return {name: with_outputs(flt, outputs) for name, flt in _identity_filters(case, covariance).items()}


def _identity_filters(case: str, covariance: str) -> dict:
    cov = covariance
    if case == "y1":
        return {
            "VBKF-fixed": VBKF(2.0, 2.0, 1.0, 4, fixed_prior=True, shape_increment=0.0, covariance=cov, throw=False),
            "STKF": STKF(None, 1.0, 4.0, 1.0, max_iter=2, tol=0.01, covariance=cov, throw=False),
            "KF": KalmanFilter(throw=False),
        }
    return {
        "VBKF": VBKF(50.0, 50.0, 0.99, covariance=cov, throw=False),
        "STKF-AR1": STKF_AR1(1e8, 1.0, 1.0, 100.0, 1.0, 0.99, covariance=cov, throw=False),
        "KF": KalmanFilter(throw=False),
    }


def _mean_iterations(tr, res):
    """Average iterations per step of the fixed-point filters (`info["iterations"]`);
    NaN for filters that do not report a count (KF, VBKF: see `_iteration_values`)."""
    info = res.info
    if isinstance(info, dict) and "iterations" in info:
        return jnp.mean(info["iterations"].astype(res.filtered_means.dtype))
    return jnp.full((), jnp.nan, res.filtered_means.dtype)


def _iteration_values(flt, values: np.ndarray) -> np.ndarray:
    """Per-run iterations per step: the reported count, `num_iter` for the VBKF (a
    fixed-length loop) and 1 for the KF (one update)."""
    if isinstance(flt, VBKF):
        return np.full(values.shape, float(flt.num_iter))
    if isinstance(flt, KalmanFilter):
        return np.ones(values.shape)
    return values


def _identity_y2_note(out: dict, printed_kf: np.ndarray, runs: int) -> str:
    """Where Table III's y2 position numbers fall among our runs, and the KF under the printed law."""
    paper = PAPER_IDENTITY["y2"]
    pct = ", ".join(f"{f} {paper[f][0]} at percentile {100 * np.mean(out[f]['rmse'][:, 0] <= paper[f][0]):.1f}" for f in paper)
    mean, (lo, hi) = metrics.mean_ci(printed_kf)
    side = "below" if hi < paper["KF"][0] else "above" if lo > paper["KF"][0] else "around"
    return (
        f"y2 position RMSE (x1), the paper's single run among our {runs} runs: {pct}. We keep the authors' code law "
        "(std × a(t), a up to 5). Side check with the printed law (variance × (2 sin²(0.04π t) + 1)) on the same "
        f"number of runs: KF position RMSE {mean:.3f} [{lo:.3f}, {hi:.3f}], {side} the paper's {paper['KF'][0]}."
    )


def run_identity(runs: int, seed: int, progress: bool = False, curves: bool = False, num_steps: int | None = None) -> Report:
    steps = IDENTITY_STEPS if num_steps is None else num_steps
    key = jax.random.key(seed)
    model, prior = identity_model(), identity_prior()
    rows, iter_rows, out_by_case = [], [], {}
    start = time.perf_counter()
    for j, case in enumerate(("y1", "y2")):
        traj = identity_scenario(jax.random.fold_in(key, j), case, runs, steps)
        flts = identity_filters(case)
        prop = next(f for f in flts if f.startswith("STKF"))
        flts[f"{prop} (reweighted cov)"] = identity_filters(case, "reweighted")[prop]
        out = montecarlo(
            flts, model, prior, traj, metrics={"rmse": _per_state_rmse, "iterations": _mean_iterations}, chunk_size=500, progress=progress,
        )
        out_by_case[case] = out
        rows += _case_rows(case, out, PAPER_IDENTITY[case], ("position", "velocity"))
        for f, flt in flts.items():
            iters = _iteration_values(flt, out[f]["iterations"])
            iter_rows.append(Row.from_values(f, f"iterations@{case}", PAPER_IDENTITY_ITERATIONS[case].get(f), iters))
    printed = montecarlo({"KF": KalmanFilter(throw=False)}, model, prior, identity_scenario(jax.random.fold_in(key, 2), "y2-printed", runs, steps),
                         metrics={"rmse": _per_state_rmse}, chunk_size=500, progress=progress)["KF"]["rmse"][:, 0]
    elapsed = time.perf_counter() - start
    rows += iter_rows
    report = Report(experiment="li-identity", seed=seed, rows=rows)
    report.notes = [
        "Table III Case 1/2 are the authors' identity scripts y1/y2; x1 = position, x2 = velocity (the "
        "paper reports both). Paper numbers are single unseeded runs of 5000 steps; ours are means over "
        f"{runs} seeded runs of {steps} steps with 95% intervals.",
        "y1: 0.95 N(0, R) + 0.05 N(0, 100 R). y2: noise std × (2 sin(2π·0.02 t))² + 1 as in the authors' "
        "code (the paper prints the variance factor 2 sin²(0.04π t) + 1). The truth starts at x₀ = 0 and "
        "our x₁ already carries process noise (the authors' x₁ = F x₀ is noise-free; negligible over 5000 steps).",
        "STKF: ν = 4, τ² = 1 on the measurement, process channels Gaussian, at most 2 iterations, tol 0.01 "
        "(the authors' STKF.m; the paper text says m_iter = 4). VBKF-fixed: α = 2 fixed, β⁻ = 2, 4 "
        "iterations (λ = 1 + e²/4 + prr/4). VBKF: α₀ = β₀ = 50, ρ = 0.99. STKF-AR1: ν_p = 1e8, ρ_p = 1, "
        "ν_r = 100, ρ_r = 0.99, 4 iterations, tol 1e-5.",
        f"Iterative filters use covariance={COVARIANCE!r} (the authors' nominal-covariance Joseph form, as in "
        "their STKF.m / student_forward_adap.m / akf_forward_vb.m). With it in every filter, STKF-AR1 equals the "
        "VBKF (to ~1e-5) and the STKF the VBKF-fixed (to ~1e-3): Table III's ties. The rows '… (reweighted cov)' "
        "(no paper number, not ranked) use the library default; Proposition 2 (STKF-AR1 = VBKF) holds there "
        "too when both filters use it.",
        "The paper's Table III ties the robust pair (0.053/0.053, 0.081/0.081, 0.092/0.092, 0.086/0.086), so "
        "the 'Ranking … agrees' lines compare against an arbitrary order of the tied pair; the substantive "
        "claim, both robust/adaptive filters beat the KF, is checked by the paired intervals below.",
        _identity_y2_note(out_by_case["y2"], printed, runs),
        "iterations@y1/y2 (Table III's last column): average number of iterations per step, per run. STKF and "
        "STKF-AR1 report the fixed-point passes actually run (info['iterations'], at least 1; the count the "
        "authors' STKF.m / student_forward_adap.m store as iter = cnt − num, stopping when ‖x_j − x_{j−1}‖ ≤ "
        "tol‖x_j‖ (they divide by ‖x_{j−1}‖ + 1e-5): STKF tol 0.01 and at most 2 passes, STKF-AR1 tol 1e-5 and at most 4). The VBKFs run a fixed "
        "number of VB iterations (4, the row is that constant) and the KF one update (1). The relative stopping "
        "rule depends on ‖x_j‖, which grows over a run (the velocity is a random walk), so the counts depend on "
        "the horizon and the state's drift, not only on the noise.",
        f"Runtime of the Monte Carlo: {elapsed:.0f} s.",
    ]
    report.notes += _agreement_notes(report, ("y1", "y2"), 2)
    report.notes += _spread_notes(out_by_case, PAPER_IDENTITY)
    report.notes += _paired_notes(out_by_case, ("position", "velocity"))
    report.notes += _best_notes(out_by_case, PAPER_IDENTITY, ("position", "velocity"))
    return report


def tuning_problems(quick: bool = False) -> dict[str, TuningProblem]:
    """`STKF-AR1` (Algorithm 2) on torsion case y3: the measurement channels' initial `ν`,
    `τ²` and forgetting `ρ`, tuned jointly on the mean RMSE (100 steps quick, 400 full)."""
    model, prior = torsion_model(), torsion_prior()
    num_steps = 100 if quick else 400

    def data(key, runs):
        return torsion_scenario(key, "y3", runs, num_steps)

    def make(values):
        return STKF_AR1(nu_y=values[0], tau2_y=values[1], rho_y=values[2], throw=False)

    def errors(values, tr):
        flt = make(values)
        return metrics.rmse(tr.states, jax.vmap(lambda y: flt(model, prior, y).filtered_means)(tr.observations))

    return {"STKF-AR1": TuningProblem(
        "STKF-AR1", "STKF_AR1 measurement channels: initial ν, τ², forgetting ρ; torsion case y3", ("ν_y", "τ²_y", "ρ_y"),
        (100.0, 1.0, 0.99), ((0.0, None), (0.0, None), (0.0, 1.0)), ((1.0, 300.0, True), (0.1, 10.0, True), (0.9, 0.999, False)),
        data, errors, f"mean RMSE over {num_steps}-step runs", make)}


register(Experiment(
    name="li-torsion",
    description="Li et al. (Variational Robust KFs), Example 4 / Table IV: 1-DOF torsion, 3 complex noise cases; per-state RMSE, T=2000.",
    default_runs=200,
    run=run_torsion,
    quick={"runs": 4, "num_steps": 1300},
    tuning=tuning_problems,
))
register(Experiment(
    name="li-identity",
    description="Li et al. (Variational Robust KFs), Example 1 / Table III: constant-acceleration model, outliers / slow-varying R; RMSE, T=5000.",
    default_runs=200,
    run=run_identity,
    quick={"runs": 4, "num_steps": 1000},
))
