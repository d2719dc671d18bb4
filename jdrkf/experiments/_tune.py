"""Tuning the filters of a registered experiment (`jdrkf tune NAME`): what is tuned, on which
data, and three ways to tune it (gradient, grid, random search), scored on held-out runs.

An experiment that supports tuning registers `tuning(quick) -> {filter label: TuningProblem}`.
A `TuningProblem` is the filter's hyper-parameters as a function of `k` scalars: their start,
bounds and grid box, the training data `data(key, runs)` and the per-run errors
`errors(values, data)`; the objective is their mean over the runs, which is a deterministic,
differentiable function of the values (common random numbers). All three methods tune on runs
simulated with one key and are scored on runs simulated with another.

Cost is counted in forward-filter-equivalents: one evaluation of the training objective;
a value-and-gradient counts as its measured time over the forward time.
"""

from __future__ import annotations

import dataclasses
import json
import pathlib
import time
from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
from jaxtyping import Array, Float, PRNGKeyArray, PyTree

from .. import _progress, tuning
from ..filters._base import AbstractFilter
from ._registry import EXPERIMENTS, Row, get

METHODS = ("grad", "grid", "random")


@dataclasses.dataclass(frozen=True)
class TuningProblem:
    """One filter of an experiment as a function of `k` scalar hyper-parameters.

    - `names`, `start` (the filter's default values), `bounds` (`(lower, upper)` per
      parameter, `upper=None` for none; as in `jdrkf.tuning.fit`) and `box`
      (`(low, high, log_spaced)` per parameter: the region of grid and random search).
    - `data(key, runs)`: simulated runs (any pytree); `errors(values, data)`: the per-run
      errors `(runs,)` of the filter with parameters `values` (a tuple of scalars).
    - `make(values)`: the filter itself, when it does not depend on anything but `values`
      (`jdrkf reproduce --params` adds it to the experiment's filters); `None` otherwise.
    """

    filter: str
    description: str
    names: tuple[str, ...]
    start: tuple[float, ...]
    bounds: tuple[tuple[float, float | None], ...]
    box: tuple[tuple[float, float, bool], ...]
    data: Callable[[PRNGKeyArray, int], PyTree]
    errors: Callable[[tuple, PyTree], Float[Array, " runs"]]
    metric: str
    make: Callable[[tuple], AbstractFilter] | None = None

    def loss(self, values: tuple, data: PyTree) -> Float[Array, ""]:
        """The training objective: the mean of `errors(values, data)` over the runs."""
        return jnp.mean(self.errors(values, data))


class _Params(eqx.Module):
    values: tuple


def _as_values(row) -> tuple:
    return tuple(jnp.asarray(float(x)) for x in row)


@dataclasses.dataclass
class Trace:
    """One tuning method's run: `params` and training `loss` of its best point, `cost` in
    forward-equivalents, `evaluations` of the objective (a value-and-gradient counts one),
    `wall_s`, and `history`: `(cumulative cost, params, training loss)` per evaluation, in
    order (for the convergence curve)."""

    method: str
    params: list[float]
    loss: float
    cost: float
    evaluations: int
    wall_s: float
    history: list[tuple[float, list[float], float]]
    extra: dict[str, Any] = dataclasses.field(default_factory=dict)

    def improvements(self, marks: int = 10) -> list[int]:
        """Indices into `history` where the best training loss so far drops (at most
        `marks` of them, evenly spread, always the last)."""
        losses = np.asarray([h[2] for h in self.history], dtype=np.float64)
        best = np.minimum.accumulate(np.where(np.isnan(losses), np.inf, losses))
        change = [i for i in range(len(best)) if i == 0 or best[i] < best[i - 1]]
        return sorted(set(change[:: max(1, len(change) // marks)]) | {change[-1]})


class Evaluator:
    """The objective of `problem` on fixed `data`, jitted once: the per-run `errors(values)`
    (on other data of the same shape too), their mean `loss(values)`, `value_and_grad(values)`
    in automatic-differentiation `mode`, and the median times of a forward and of a
    value-and-gradient call in each mode (`timing()`, which also sets `mode` to the cheaper)."""

    def __init__(self, problem: TuningProblem, data: PyTree):
        self.problem, self.data = problem, data
        self.mode, self.vg_times = "reverse", {}
        self._errors = eqx.filter_jit(problem.errors)
        self._vg = {m: eqx.filter_jit(tuning.value_and_grad(problem.loss, mode=m)) for m in tuning.MODES}

    def loss(self, values) -> float:
        return float(np.mean(self.errors(values)))

    def errors(self, values, data: PyTree | None = None) -> np.ndarray:
        return np.asarray(self._errors(_as_values(values), self.data if data is None else data))

    def value_and_grad(self, values) -> tuple[float, np.ndarray]:
        value, grad = self._vg[self.mode](_as_values(values), self.data)
        return float(value), np.asarray([float(g) for g in grad])

    def timing(self, repeats: int = 3) -> tuple[float, float]:
        """Median seconds of a forward call and of a value-and-gradient call at the start,
        in the cheaper mode, which becomes `mode` (both modes' times: `vg_times`)."""
        start = _as_values(self.problem.start)

        def median_time(fn):
            jax.block_until_ready(fn(start, self.data))
            times = []
            for _ in range(repeats):
                t = time.perf_counter()
                jax.block_until_ready(fn(start, self.data))
                times.append(time.perf_counter() - t)
            return float(np.median(times))

        forward = median_time(self._errors)
        self.vg_times = {m: median_time(fn) for m, fn in self._vg.items()}
        self.mode = min(self.vg_times, key=self.vg_times.get)
        return forward, self.vg_times[self.mode]


def tune_gradient(ev: Evaluator, *, ratio: float, steps: int, tol: float | None = 1e-4, restarts: int = 0,
                  key: PRNGKeyArray | None = None, learning_rate: float = 0.1) -> Trace:
    """Adam (`jdrkf.tuning.fit`, `patience=3`, restarts jittered by 0.5 in the unconstrained
    space, derivatives in `ev.mode`) from the problem's start. Each recorded iterate costs `ratio` forward-equivalents
    (a value-and-gradient), except the last one of a start that ran out of steps (a forward)."""
    p = ev.problem
    t = time.perf_counter()
    res = tuning.fit(_Params(_as_values(p.start)), lambda q: p.loss(q.values, ev.data), where=lambda q: q.values,
                     bounds=list(p.bounds), optimizer=optax.adam(learning_rate), steps=steps, tol=tol, patience=3,
                     restarts=restarts, jitter=0.5, key=key, mode=ev.mode)
    wall = time.perf_counter() - t
    history, cum = [], 0.0
    for run in res.runs:
        for i in range(len(run.losses)):
            cum += 1.0 if (not run.converged and i == len(run.losses) - 1) else ratio
            history.append((cum, [float(x) for x in run.params[i]], float(run.losses[i])))
    return Trace("grad", [float(x) for x in res.params[res.best_step]], res.loss, cum, len(history), wall, history,
                 {"steps": [len(r.losses) - 1 for r in res.runs], "converged": [r.converged for r in res.runs],
                  "start_losses": [float(r.losses[r.best_step]) for r in res.runs], "best_start": res.start,
                  "best_step": res.best_step})


def _axis(low: float, high: float, log: bool, k: int) -> np.ndarray:
    return np.geomspace(low, high, k) if log else np.linspace(low, high, k)


def _evaluate_rows(ev: Evaluator, method: str, rows: np.ndarray, extra: dict) -> Trace:
    """Every row by `jdrkf.tuning.grid_search` (compiled `lax.map` over chunks of rows)."""
    t = time.perf_counter()
    res = tuning.grid_search(_Params(_as_values(ev.problem.start)), lambda q: ev.problem.loss(q.values, ev.data),
                             where=lambda q: q.values, grid=rows)
    wall = time.perf_counter() - t
    best = int(np.nanargmin(res.losses))
    history = [(float(i + 1), [float(x) for x in row], float(loss)) for i, (row, loss) in enumerate(zip(rows, res.losses, strict=True))]
    return Trace(method, history[best][1], history[best][2], float(len(rows)), len(rows), wall, history,
                 {**extra, "losses": np.asarray(res.losses)})


def grid_points(problem: TuningProblem, k: int) -> np.ndarray:
    """The full grid with `k` points per axis of `problem.box`, `(k^d, d)`."""
    axes = [_axis(lo, hi, log, k) for lo, hi, log in problem.box]
    return np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, len(axes))


def tune_grid(ev: Evaluator, k: int) -> Trace:
    """Every point of the `k`-per-axis grid over the box."""
    return _evaluate_rows(ev, "grid", grid_points(ev.problem, k), {"k": k})


def tune_random(ev: Evaluator, count: int, rng: np.random.Generator) -> Trace:
    """`count` points drawn uniformly in the box (log-uniformly on log-spaced axes)."""
    rows = np.stack([np.exp(rng.uniform(np.log(lo), np.log(hi), count)) if log else rng.uniform(lo, hi, count)
                     for lo, hi, log in ev.problem.box], -1)
    return _evaluate_rows(ev, "random", rows, {})


def heldout_curve(trace: Trace, heldout: Callable[[list[float]], float], marks: int = 10) -> list[tuple[float, float]]:
    """`(cost, held-out error of the best point so far)` where the training loss improves,
    and at the final cost."""
    curve = [(trace.history[i][0], heldout(trace.history[i][1])) for i in trace.improvements(marks)]
    return curve + [(trace.cost, curve[-1][1])]


# --------------------------------------------------------------------------- `jdrkf tune`


def supporting() -> list[str]:
    """Names of the registered experiments with a tuning problem."""
    return sorted(name for name, exp in EXPERIMENTS.items() if exp.tuning is not None)


def problems(name: str, quick: bool = False) -> dict[str, TuningProblem]:
    """The tuning problems `{filter label: TuningProblem}` of experiment `name`; `ValueError`
    for an unknown experiment or one without a tuning problem."""
    exp = get(name)
    if exp.tuning is None:
        raise ValueError(f"experiment {name!r} has no tuning problem; experiments with one: {', '.join(supporting())}")
    return dict(exp.tuning(quick))


def _summary(values: np.ndarray) -> dict:
    """Mean and 95% interval of per-run errors (`Row.from_values`); NaN with the count of failed runs."""
    failed = int(np.sum(~np.isfinite(values)))
    if failed:
        return {"mean": float("nan"), "ci95": [float("nan")] * 2, "runs": int(values.size), "failed": failed}
    row = Row.from_values("", "", None, values)
    return {"mean": row.mean, "ci95": list(row.ci95), "runs": row.runs, "failed": 0}


def tune(name: str, *, method: str = "grad", budget: float | None = None, runs: int | None = None, seed: int = 0,
         quick: bool = False) -> dict:
    """Tune every filter of experiment `name` with `method` within `budget`
    forward-equivalents (default 100, 20 with `quick`) on `runs` training runs (default 16,
    4 with `quick`); score the start and the tuned parameters on as many held-out runs
    simulated with another key. Returns the JSON-ready result (see `table`).

    `grad`: Adam with `⌊(budget − 1)/r⌋` steps, `r` the measured value-and-gradient over
    forward time ratio (at least one step); `grid`: `k = max(2, ⌊budget^{1/d}⌋)` points per
    axis of the box; `random`: `budget` points."""
    if method not in METHODS:
        raise ValueError(f"method must be one of {', '.join(METHODS)}, got {method!r}")
    budget = (20.0 if quick else 100.0) if budget is None else float(budget)
    if not (np.isfinite(budget) and budget >= 1):
        raise ValueError(f"budget must be at least 1 forward-equivalent, got {budget}")
    runs = (4 if quick else 16) if runs is None else runs
    probs = problems(name, quick)
    key = jax.random.key(seed)
    out = {"experiment": name, "method": method, "budget": budget, "seed": seed, "quick": quick, "runs": runs,
           "heldout_runs": runs, "filters": []}
    for j, (label, p) in enumerate(probs.items()):
        t0 = time.perf_counter()
        with _progress.phase(f"{label}: simulating, compiling, timing"):
            train = p.data(jax.random.fold_in(key, 0), runs)
            test = p.data(jax.random.fold_in(key, 1), runs)
            ev = Evaluator(p, train)
            t_fwd, t_vg = ev.timing()
        ratio = t_vg / t_fwd
        if method == "grad":
            trace = tune_gradient(ev, ratio=ratio, steps=max(1, int((budget - 1) // ratio)),
                                  key=jax.random.fold_in(key, 2 + j))
        elif method == "grid":
            trace = tune_grid(ev, max(2, int(np.floor(budget ** (1 / len(p.names)) + 1e-9))))
        else:
            trace = tune_random(ev, max(1, int(budget)), np.random.default_rng([seed, j]))
        with _progress.phase(f"{label}: held-out evaluation"):
            curve = heldout_curve(trace, lambda values, ev=ev, test=test: float(np.mean(ev.errors(values, test))))
            start_err, tuned_err = ev.errors(p.start, test), ev.errors(trace.params, test)
        out["filters"].append({
            "filter": label, "description": p.description, "metric": p.metric, "parameters": list(p.names),
            "start": list(p.start), "bounds": [list(b) for b in p.bounds], "box": [list(b) for b in p.box],
            "tuned": trace.params, "start_train": ev.loss(p.start), "train": trace.loss,
            "start_heldout": _summary(start_err), "heldout": _summary(tuned_err),
            "cost": trace.cost, "evaluations": trace.evaluations, "forward_s": t_fwd, "vg_over_forward": ratio,
            "ad_mode": ev.mode, "tuning_wall_s": trace.wall_s, "wall_s": time.perf_counter() - t0, "curve": [list(c) for c in curve],
            **({"steps": trace.extra["steps"], "converged": trace.extra["converged"]} if method == "grad" else {}),
            **({"k": trace.extra["k"]} if method == "grid" else {}),
        })
    return out


def _ci(s: dict) -> str:
    return "—" if not np.all(np.isfinite(s["ci95"])) else f"[{s['ci95'][0]:.4g}, {s['ci95'][1]:.4g}]"


def table(result: dict) -> str:
    """Markdown: per filter, the start and the tuned parameters with their training loss,
    held-out error (mean and 95% interval over the held-out runs) and cost."""
    r = result
    lines = [
        f"## jdrkf tune {r['experiment']} — method {r['method']}, budget {r['budget']:g} forward-equivalents",
        "",
        f"Run settings: seed {r['seed']}, {r['runs']} training runs, {r['heldout_runs']} held-out runs (another key)"
        + (", quick" if r["quick"] else ""),
        "",
        "| filter | parameters | values | training | held-out (mean) | 95% CI | cost (fwd-eq) | wall s |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for f in r["filters"]:
        fmt = lambda v: ", ".join(f"{x:.4g}" for x in v)
        names = ", ".join(f["parameters"])
        lines.append(f"| {f['filter']} (start) | {names} | {fmt(f['start'])} | {f['start_train']:.5g} | "
                     f"{f['start_heldout']['mean']:.5g} | {_ci(f['start_heldout'])} | — | — |")
        lines.append(f"| {f['filter']} ({r['method']}) | {names} | {fmt(f['tuned'])} | {f['train']:.5g} | "
                     f"{f['heldout']['mean']:.5g} | {_ci(f['heldout'])} | {f['cost']:.1f} | {f['tuning_wall_s']:.1f} |")
    lines.append("")
    for f in r["filters"]:
        extra = (f"; Adam steps {f['steps']}, converged {f['converged']}" if "steps" in f else
                 f"; k = {f['k']} points per axis" if "k" in f else "")
        failed = [f"{s['failed']} failed {which} runs" for which, s in (("start", f["start_heldout"]), ("tuned", f["heldout"])) if s["failed"]]
        lines.append(f"- {f['filter']}: {f['description']}; metric: {f['metric']}; a value-and-gradient costs "
                     f"{f['vg_over_forward']:.2f} forward-equivalents ({1e3 * f['forward_s']:.1f} ms per forward){extra}"
                     + ("; " + ", ".join(failed) if failed else "") + ".")
    return "\n".join(lines)


def plot(result: dict, path: pathlib.Path) -> pathlib.Path:
    """Held-out error of the best point so far vs cost, one panel per filter."""
    from matplotlib.figure import Figure

    filters = result["filters"]
    fig = Figure(figsize=(5 * len(filters), 3.8), layout="constrained")
    for ax, f in zip(fig.subplots(1, len(filters), squeeze=False)[0], filters, strict=True):
        x, y = zip(*f["curve"])
        ax.step(x, y, where="post", color="C0", label=f"{result['method']}")
        ax.axhline(f["start_heldout"]["mean"], color="0.5", lw=0.8, ls=":", label="start (defaults)")
        ax.set_xscale("log")
        ax.set_xlabel("cost (forward-filter-equivalents)")
        ax.set_ylabel(f"held-out {f['metric']}")
        ax.set_title(f"{result['experiment']}: {f['filter']} ({', '.join(f['parameters'])})", fontsize=9)
        ax.legend(fontsize=8)
    fig.savefig(path, dpi=110)
    return path


def write(result: dict, out: pathlib.Path) -> tuple[pathlib.Path, pathlib.Path]:
    """`tune-<name>-<method>.json` and `.png` in directory `out`."""
    stem = out / f"tune-{result['experiment']}-{result['method']}"
    path = stem.with_suffix(".json")
    path.write_text(json.dumps(result, indent=1))
    return path, plot(result, stem.with_suffix(".png"))


def command(name: str, *, method: str, budget: float | None, runs: int | None, seed: int, quick: bool,
            out: pathlib.Path | None) -> dict:
    """`jdrkf tune`: `tune`, print the `table`, and with `out` write the JSON and the plot."""
    result = tune(name, method=method, budget=budget, runs=runs, seed=seed, quick=quick)
    print(table(result), flush=True)
    if out is not None:
        with _progress.phase("plotting", total=1, unit="figure") as bar:
            paths = write(result, out)
            bar.update()
        print(f"\nresult: {paths[0]}\nfigure: {paths[1]}")
    return result


def load_params(path: pathlib.Path, name: str) -> dict[str, tuple[float, ...]]:
    """`{filter label: tuned values}` from a JSON file written by `jdrkf tune name`;
    `ValueError` if it is not one, is for another experiment, or names filters or
    parameters the experiment's tuning problems do not have."""
    try:
        data = json.loads(pathlib.Path(path).read_text())
        filters = data["filters"]
        experiment = data["experiment"]
        values = {f["filter"]: tuple(float(x) for x in f["tuned"]) for f in filters}
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise ValueError(f"--params {path}: not a result of `jdrkf tune` ({type(e).__name__}: {e})") from None
    if experiment != name:
        raise ValueError(f"--params {path} holds parameters tuned for {experiment!r}, not {name!r}")
    get(name).check_takes_params()
    probs = problems(name)
    for label, vals in values.items():
        if label not in probs or probs[label].make is None:
            usable = [k for k, p in probs.items() if p.make is not None]
            raise ValueError(f"--params {path}: {name!r} cannot use tuned parameters of {label!r} (it can: {', '.join(usable)})")
        if len(vals) != len(probs[label].names):
            raise ValueError(f"--params {path}: {label!r} needs {len(probs[label].names)} values, got {len(vals)}")
    return values

