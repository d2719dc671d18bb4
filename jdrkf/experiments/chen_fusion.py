"""Chen, Li, Liu, He, "A Marginal Distributionally Robust Kalman Filter for Sensor
Fusion" (IEEE SPL 2025): `chen-fusion` (Table I, Fig. 1).

Three scalar sensors measure position, velocity and acceleration (`H = I₃`) of a
constant-acceleration target, eq. (34): `x_{t+1} = F x_t + G w_t`, `w ~ N(0, 1)`,
`y_t^i = x_t^i + β_i w_{t−1} + η_t^i`, `β = (0.5, 0.8, 0.4)`, `η^i ~ N(0, (5, 8, 10))`.
The sensor noises are correlated with each other and with the state through the
previous process noise; every filter's nominal model has `v_t^i = η_t^i` (independent
sensors). 600 steps, `x_0 = 0`, `x̂_0 = 0`. Filters: covariance intersection over
local posteriors from a common fused prior (`CI`, determinant criterion as MATLAB's
`fusecovint`), the KF on sensor 1 (`KF`), the marginal KL and moment DR filters
(`KL-MDRKF`, `MC-MDRKF`), and the centralized KF (`CKF`, computed but not shown in
the paper).

Two scenario variants (the authors' MATLAB code `lylechan42/MDRKF` differs from the text):

- `paper`: the text's settings — `T_s = 0.1`, nominal `Q = 1` (the true one), `V_0 = 100 I`.
- `authors-code`: what `dynamic_estimation_MC.m` runs — `dt = 0.01`, nominal
  `Q = 0.01` (100× below the simulated process noise), `P_0 = I`.

Radii: the authors' grids (`γ = g ∈ linspace(0, 1, 10)` with `γ₁ = 1 − g`,
`γ₂ = 1 + g`; `c ∈ 0.3·linspace(0, 1, 10)` in their `2·KL` units, i.e. our KL radius
`c/2`; end points moved 1e-3 inside, see `GAMMA_GRID`), one value shared by the three
sensors, selected on *separate training runs* (the authors picked post hoc on the
evaluation runs); then refined by gradient (optax Adam through the filters and the
solver's implicit derivatives, `-grad` rows; γ₁ and γ₂ tuned separately).
"""

from __future__ import annotations

import time

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .. import _progress
from .._gaussian import Gaussian
from .._multisensor import MultiSensorModel
from .._simulate import simulate
from ..filters import KalmanFilter
from ..filters._fusion import CKF, CovarianceIntersection, MarginalDRKF
from ..sets._marginal import MarginalKL, MarginalMoment
from ..tuning import fit, grid_search
from ._registry import Experiment, Report, Row, register
from ._tune import TuningProblem

NUM_STEPS = 600
BETA = (0.5, 0.8, 0.4)
ETA_VAR = (5.0, 8.0, 10.0)
Q_TRUE = 1.0
VARIANTS = {
    "paper": {"dt": 0.1, "q_nominal": 1.0, "p0": 100.0},
    "authors-code": {"dt": 0.01, "q_nominal": 0.01, "p0": 1.0},
}
# The authors' grids, with the two degenerate end points moved inside: g = 0 (γ₁ = γ₂ = 1) and
# c = 0 leave the constraint set without an interior (the solver then falls back to slow
# projected gradient), and g = 1 gives γ₁ = 0, outside the set's definition.
GAMMA_GRID = np.clip(np.linspace(0.0, 1.0, 10), 1e-3, 1.0 - 1e-3)
KL_GRID = np.maximum(0.5 * 0.3 * np.linspace(0.0, 1.0, 10), 1e-4)  # the authors' c (= 2·KL) halved
COMPONENTS = ("x", "v", "a")
# Table I: time-averaged MSE of position, velocity, acceleration (1000 runs).
PAPER = {
    "CI": (7.9864, 23.0917, 16.7782),
    "KF": (10.5345, 30.2828, 20.3734),
    "KL-MDRKF": (1.7764, 8.5224, 13.5665),
    "MC-MDRKF": (1.4468, 1.8426, 2.6792),
}
FILTER_ORDER = ("CI", "KF", "KL-MDRKF", "MC-MDRKF", "CKF")


def kinematics(dt: float) -> tuple[np.ndarray, np.ndarray]:
    """Constant-acceleration `F` and `G = [dt²/2, dt, 1]ᵀ` of eq. (34)."""
    f = np.array([[1.0, dt, dt**2 / 2], [0.0, 1.0, dt], [0.0, 0.0, 1.0]])
    g = np.array([[dt**2 / 2], [dt], [1.0]])
    return f, g


def scenario(variant: str, dtype=None) -> tuple[MultiSensorModel, MultiSensorModel, Gaussian]:
    """`(nominal, true, prior)` of a variant: the nominal model has independent sensors
    (`β = 0`) and the variant's `Q`; the true one simulates eq. (34)."""
    cfg = VARIANTS[variant]
    f, g = kinematics(cfg["dt"])
    hs = [np.eye(3)[i : i + 1] for i in range(3)]
    rs = [np.array([[r]]) for r in ETA_VAR]

    def make(q, beta):
        return MultiSensorModel(
            F=jnp.asarray(f, dtype), G=jnp.asarray(g, dtype), Q=jnp.asarray([[q]], dtype),
            H=[jnp.asarray(h, dtype) for h in hs], R=[jnp.asarray(r, dtype) for r in rs],
            beta=None if beta is None else [jnp.asarray([[b]], dtype) for b in beta],
        )

    prior = Gaussian(jnp.zeros(3, dtype), cfg["p0"] * jnp.eye(3, dtype=dtype))
    return make(cfg["q_nominal"], None), make(Q_TRUE, BETA), prior


def _simulate(key, true_model, num_runs, dtype=None):
    # x_0 = 0 exactly (the authors' getCorrData): a point-mass prior.
    x0 = Gaussian(jnp.zeros(3, dtype), jnp.zeros((3, 3), dtype))
    return simulate(key, true_model, x0, NUM_STEPS, num_runs)


def _filters(set_mc=None, set_kl=None):
    return {
        "CI": CovarianceIntersection("det", throw=False),
        "KF": None,  # sensor 1 only: run on model.sensor(0)
        "KL-MDRKF": MarginalDRKF(set_kl if set_kl is not None else MarginalKL(0.0), throw=False),
        "MC-MDRKF": MarginalDRKF(set_mc if set_mc is not None else MarginalMoment(1.0, 1.0), throw=False),
        "CKF": CKF(throw=False),
    }


def _means(name, flt, model, prior, ys):
    if name == "KF":
        sensor = model.sensor(0)
        return jax.vmap(lambda y: KalmanFilter(throw=False)(sensor, prior, y[:, :1]).filtered_means)(ys)
    return jax.vmap(lambda y: flt(model, prior, y).filtered_means)(ys)


def _mse_objective(model, prior, traj):
    """Mean over runs and steps of ‖x_t − x̂_t‖² (the authors' selection criterion)."""

    def objective(flt):
        means = _means("MDRKF", flt, model, prior, traj.observations)
        return jnp.mean(jnp.sum((traj.states - means) ** 2, axis=-1))

    return objective


def grid_profile(label: str, name: str, grid: np.ndarray, losses: np.ndarray) -> str:
    """The training MSE along a 1-D radius grid, and whether its minimum sits at an end of
    the grid (then the grid cannot tell how much robustness the data want beyond it)."""
    losses = np.asarray(losses)
    best = int(np.nanargmin(losses))
    spread = (np.nanmax(losses) - losses[best]) / losses[best]
    profile = ", ".join(f"{x:.3g}: {v:.4g}" for x, v in zip(grid, losses, strict=True))
    where = ("at the grid's lower end (least robustness tried): the training runs favour the nominal filter"
             if best == 0 else "at the grid's upper end: a larger radius might do better"
             if best == len(grid) - 1 else "inside the grid")
    return (f"{label} grid profile ({name}: training MSE) {profile}; minimum {where}; "
            f"the worst grid point is {100 * spread:.1f}% above the best.")


def _tune(model, prior, train, steps: int, notes: list[str], variant: str):
    """Grid on the training runs, then Adam from the grid optimum. Returns the tuned sets."""
    objective = _mse_objective(model, prior, train)
    out = {}
    mc = MarginalDRKF(MarginalMoment(jnp.asarray(1.0), jnp.asarray(1.0)), throw=False)
    g = grid_search(mc, objective, where=lambda f: (f.set.gamma1, f.set.gamma2), grid=np.stack([1.0 - GAMMA_GRID, 1.0 + GAMMA_GRID], 1))
    kl = MarginalDRKF(MarginalKL(jnp.asarray(0.0)), throw=False)
    k = grid_search(kl, objective, where=lambda f: f.set.radius, grid=KL_GRID)
    out["MC-MDRKF"], out["KL-MDRKF"] = g.filter.set, k.filter.set
    notes.append(
        f"[{variant}] grid choice on {train.num_runs} training runs: MC-MDRKF g = {1.0 - float(g.filter.set.gamma1):.3f} "
        f"(γ₁ = {float(g.filter.set.gamma1):.3f}, γ₂ = {float(g.filter.set.gamma2):.3f}), training MSE {g.loss:.4g}; "
        f"KL-MDRKF c = {float(k.filter.set.radius):.4f} (authors' units 2c = {2 * float(k.filter.set.radius):.4f}), training MSE {k.loss:.4g}."
    )
    notes += [grid_profile(f"[{variant}] MC-MDRKF", "g", GAMMA_GRID, g.losses), grid_profile(f"[{variant}] KL-MDRKF", "c", KL_GRID, k.losses)]
    if steps > 0:
        import optax

        fg = fit(g.filter, objective, where=lambda f: (f.set.gamma1, f.set.gamma2), bounds=[(0.0, 1.0), (1.0, None)], optimizer=optax.adam(0.02), steps=steps)
        fk = fit(k.filter, objective, where=lambda f: f.set.radius, bounds=(0.0, None), optimizer=optax.adam(0.01), steps=steps)
        out["MC-MDRKF-grad"], out["KL-MDRKF-grad"] = fg.filter.set, fk.filter.set
        notes.append(
            f"[{variant}] gradient refinement ({steps} Adam steps from the grid optimum, same training runs): "
            f"MC-MDRKF γ₁ = {float(fg.filter.set.gamma1):.3f}, γ₂ = {float(fg.filter.set.gamma2):.3f} (training MSE {fg.loss:.4g}, "
            f"best iterate: step {fg.best_step}; grid optimum {g.loss:.4g}); "
            f"KL-MDRKF c = {float(fk.filter.set.radius):.4f} (training MSE {fk.loss:.4g}, best iterate: step {fk.best_step}; grid optimum {k.loss:.4g}). "
            "The best training iterate is kept, so a refinement never reports a worse point than the grid's."
        )
    return out


def tuning_problems(quick: bool = False) -> dict[str, TuningProblem]:
    """`KL-MDRKF` with one KL radius per sensor (`c₁, c₂, c₃`, tuned jointly) on the `paper`
    variant, objective: mean over runs and steps of ‖x_t − x̂_t‖² (30 steps quick, 100 full)."""
    model, true_model, prior = scenario("paper")
    x0 = Gaussian(jnp.zeros(3), jnp.zeros((3, 3)))
    num_steps = 30 if quick else 100

    def data(key, runs):
        return simulate(key, true_model, x0, num_steps, runs)

    def make(values):
        return MarginalDRKF(MarginalKL(jnp.stack(values)), throw=False)

    def errors(values, tr):
        means = _means("KL-MDRKF", make(values), model, prior, tr.observations)
        return jnp.mean(jnp.sum((tr.states - means) ** 2, axis=-1), axis=-1)

    return {"KL-MDRKF": TuningProblem(
        "KL-MDRKF", "MarginalDRKF(MarginalKL((c₁, c₂, c₃))), one KL radius per sensor", ("c₁", "c₂", "c₃"),
        (0.05, 0.05, 0.05), ((0.0, None),) * 3, ((1e-3, 0.5, True),) * 3, data, errors,
        f"mean squared error over {num_steps}-step runs", make)}


def run_variant(variant: str, runs: int, seed: int, *, train_runs: int = 200, fit_steps: int = 10, notes: list[str]):
    """Per-run time-averaged component MSEs `{filter: (runs, 3)}` and per-step position MSE curves."""
    model, true_model, prior = scenario(variant)
    key = jax.random.key(seed)
    test = _simulate(jax.random.fold_in(key, 0), true_model, runs)
    train = _simulate(jax.random.fold_in(key, 1), true_model, train_runs)
    tuned = _tune(model, prior, train, fit_steps, notes, variant)
    filters = _filters(tuned["MC-MDRKF"], tuned["KL-MDRKF"])
    for name in ("MC-MDRKF-grad", "KL-MDRKF-grad"):
        if name in tuned:
            filters[name] = MarginalDRKF(tuned[name], throw=False)
    per_run, curves = {}, {}
    with _progress.phase(f"[{variant}] evaluation ({runs} runs per filter)", len(filters), "filter") as bar:
        for name, flt in filters.items():
            means = np.asarray(eqx.filter_jit(_means)(name, flt, model, prior, test.observations))
            err2 = (np.asarray(test.states) - means) ** 2  # (runs, T, 3)
            per_run[name] = err2.mean(axis=1)
            curves[f"{variant}/{name}"] = err2[..., 0].mean(axis=0)
            bar.update(1)
    return per_run, curves


def run(runs: int = 1000, seed: int = 0, progress: bool = False, curves: bool = True, *, variants=tuple(VARIANTS), train_runs: int = 200, fit_steps: int = 10) -> Report:
    notes: list[str] = []
    rows, all_curves = [], {}
    t0 = time.perf_counter()
    for variant in variants:
        per_run, cv = run_variant(variant, runs, seed, train_runs=train_runs, fit_steps=fit_steps, notes=notes)
        all_curves.update(cv)
        for name, vals in per_run.items():
            for j, comp in enumerate(COMPONENTS):
                paper = PAPER.get(name, (None,) * 3)[j]
                rows.append(Row.from_values(name, f"MSE {comp} [{variant}]", paper, vals[:, j]))
    notes += _explain(rows, variants)
    notes += WHY
    notes.append(
        f"{runs} evaluation runs and {train_runs} training runs per variant (keys fold_in(seed, 0) and fold_in(seed, 1)); "
        f"MSE = per-run mean over the {NUM_STEPS} steps of the squared error of each component, then mean over runs with a 95% t-interval. "
        f"The paper's numbers are shown against both variants (they come from the authors' code, whose settings differ from the text). "
        f"Wall time {time.perf_counter() - t0:.0f} s."
    )
    return Report("chen-fusion", seed, rows, notes, all_curves if curves else {}, curves_ylabel=None)


WHY = [
    "Why the paper's ordering holds only in part (seed 0, 1000 runs): in the `paper` variant the nominal Q is the true "
    "one and the only error is the β-correlation, which is small (it adds 0.25/0.64/0.16 to noise variances of 5/8/10). "
    "The training grid then picks the smallest radii (no robustness), and the centralized KF, which the paper does not "
    "show, is best on every component; the DR filters still beat CI and the single-sensor KF on position and velocity, "
    "as in Table I, but CI is better on acceleration.",
    "In the `authors-code` variant the nominal Q is 100× below the simulated one. There the DR filters' inflation pays "
    "off on acceleration (MC-MDRKF < KL-MDRKF < CI < KF, the paper's order), while CI and the centralized KF are better "
    "on position and velocity: a marginal ball that also has to cover the missing process noise makes the filters "
    "conservative where the data are informative.",
    "Our MSE levels differ from Table I's by large factors in both variants (e.g. the single-sensor KF's position MSE "
    "is 10.5 in the paper, 1.5 and 2.0 here). The authors' released script cannot produce its own plots (it references "
    "undefined variables), so the run behind Table I and its averaging are not known.",
]


def _explain(rows, variants) -> list[str]:
    """Say where the paper's ordering MC-MDRKF < KL-MDRKF < CI/KF holds and where not."""
    out = []
    for variant in variants:
        for comp in COMPONENTS:
            vals = {r.filter: r.mean for r in rows if r.metric == f"MSE {comp} [{variant}]"}
            order = " < ".join(sorted((k for k in ("CI", "KF", "KL-MDRKF", "MC-MDRKF") if k in vals), key=vals.get))
            holds = vals["MC-MDRKF"] <= vals["KL-MDRKF"] <= min(vals["CI"], vals["KF"])
            out.append(f"[{variant}] {comp}: {order} — the paper's MC-MDRKF < KL-MDRKF < CI/KF {'holds' if holds else 'does NOT hold'}.")
    return out


register(
    Experiment(
        name="chen-fusion",
        description="Chen et al. 2025 Table I / Fig. 1: marginal DR fusion of three correlated sensors (paper and authors-code variants)",
        default_runs=1000,
        run=run,
        quick={"runs": 10, "train_runs": 10, "fit_steps": 0, "variants": ("paper",)},
        tuning=tuning_problems,
    )
)
