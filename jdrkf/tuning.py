"""Tuning filter hyper-parameters (ambiguity radii, ε, …) by gradient or by grid search
on simulated training runs.

Every filter in jdrkf is an `eqx.Module` whose hyper-parameters are array leaves, and
every solver inside is differentiable (implicit derivatives), so a Monte Carlo RMSE is
a differentiable function of the radii:

```python
train = jdrkf.simulate(jax.random.key(1), model, prior, 1000, 64, measurement_noise=noise)
objective = jdrkf.tuning.rmse_objective(model, prior, train)
mkf = jdrkf.DRKF(state_set=Moment(1.05), noise_set=Moment(1.05), outliers=EpsContamination(0.05, k=1.4))
fit = jdrkf.tuning.fit(mkf, objective, where=lambda f: (f.state_set.theta2, f.noise_set.theta2),
                       bounds=(1.0, None), shared=True, steps=50)
fit.filter  # the tuned filter (the best iterate: fit.best_step; history: fit.params, fit.losses)
```

`fit` also takes a convergence test (`tol`, `patience`), jittered `restarts` (every start's
history in `fit.runs`), `scan=True` (the loop as one compiled `lax.scan`), `progress`, and
`mode="forward"`: derivatives by forward mode, often cheaper for a few parameters through
long filter loops (`value_and_grad(f, mode=...)` is the same choice for any objective).

Evaluate the tuned filter on runs simulated with a different key (separate training
and test data).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
from jaxtyping import Array, ArrayLike, Float, PRNGKeyArray, PyTree

from . import _progress, metrics
from ._gaussian import Gaussian
from ._models import LinearModel
from ._simulate import Trajectories
from ._validation import check_count
from .filters._base import AbstractFilter

__all__ = ["FitResult", "FitRun", "GridResult", "fit", "grid_search", "rmse_objective", "value_and_grad"]

MODES = ("reverse", "forward")


def _check_mode(mode: str) -> None:
    if mode not in MODES:
        raise ValueError(f"mode must be one of {MODES}, got {mode!r}")


def value_and_grad(fn: Callable[..., Float[Array, ""]], *, mode: str = "reverse") -> Callable[..., tuple[Array, PyTree]]:
    """`fn ↦ (x, *args) ↦ (fn(x, *args), ∇ₓ fn)` for a scalar `fn` of the pytree `x`.

    `mode="reverse"` is `jax.value_and_grad`: one backward pass, whatever the number of
    parameters, but through a filter's time loop it stores every step and pays for the
    reverse of each loop inside a step (a bounded `while_loop` is replayed in reverse in
    full). `mode="forward"` is `jax.jacfwd`: one tangent per parameter carried alongside
    the forward pass, nothing stored, so for a handful of parameters it can cost less
    (measured on Li et al.'s STKF-AR1 with 3 parameters: 3.4 forward passes against 9–15).
    Both give the same derivative."""
    _check_mode(mode)
    if mode == "reverse":
        return jax.value_and_grad(fn)

    def forward(x, *args):
        def with_value(x):
            value = fn(x, *args)
            return value, value

        grad, value = jax.jacfwd(with_value, has_aux=True)(x)
        return value, grad

    return forward


def rmse_objective(
    model: LinearModel, prior: Gaussian, trajectories: Trajectories, *, clean: bool = False
) -> Callable[[AbstractFilter], Float[Array, ""]]:
    """`objective(filter)` = the mean over runs of the RMSE (`jdrkf.metrics.rmse`) of
    the filtered means on `trajectories` (from `jdrkf.simulate`), filtered with the
    nominal `model`. The data are fixed (common random numbers), so the objective is
    a deterministic, differentiable function of the filter's array leaves.

    `clean=True` filters the outlier-free observations instead. Build the filter
    with `throw=False` when a failing run should give a NaN loss rather than an error.
    """
    ys = trajectories.clean_observations if clean else trajectories.observations
    states = trajectories.states

    def objective(flt: AbstractFilter) -> Float[Array, ""]:
        means = jax.vmap(lambda y: flt(model, prior, y).filtered_means)(ys)
        return jnp.mean(metrics.rmse(states, means))

    return objective


class _Bounds(eqx.Module):
    lower: float
    upper: float | None

    def to(self, u):
        """`lower + softplus(u)` or `lower + (upper − lower) sigmoid(u)`, clipped to the
        representable values of `u`'s dtype strictly inside the bounds (in float32,
        `sigmoid(u)` rounds to 1 from `u ≈ 17` and `softplus(u)` vanishes next to `lower`)."""
        x = self.lower + jax.nn.softplus(u) if self.upper is None else self.lower + (self.upper - self.lower) * jax.nn.sigmoid(u)
        lo, hi = self.inside(u.dtype)
        return jnp.clip(x, lo, hi)

    def inside(self, dtype) -> tuple[float, float | None]:
        """The values of `dtype` nearest to the bounds strictly inside `(lower, upper)`,
        skipping subnormals (XLA on CPU flushes them to zero, e.g. `0 < 1e-45` in float32)."""
        info = np.finfo(dtype)

        def inner(bound, direction):
            x = np.asarray(bound, info.dtype)
            x = x if (float(x) - bound) * direction > 0 else np.nextafter(x, np.asarray(direction * np.inf, info.dtype))
            return float(x) if abs(float(x)) >= info.tiny else direction * float(info.tiny)

        return inner(self.lower, 1), None if self.upper is None else inner(self.upper, -1)

    def inverse(self, x: float, name: str, dtype) -> float:
        """`u` with `to(u) = x`; a start `x` on a bound (compared in the leaf's `dtype`) is
        first moved `1e-3` inside (`1e-3` of the width for two bounds), one outside raises."""
        lower = float(np.asarray(self.lower, dtype))
        upper = None if self.upper is None else float(np.asarray(self.upper, dtype))
        if not (np.isfinite(x) and x >= lower and (upper is None or x <= upper)):
            shown = f"[{self.lower}, {'inf' if self.upper is None else self.upper}]"
            raise ValueError(f"the start value of {name} is {x:.6g}, outside its bounds {shown}")
        if self.upper is None:
            z = x - self.lower if x > lower else 1e-3
            return z + np.log(-np.expm1(-z))  # softplus⁻¹
        p = 1e-3 if x == lower else 1 - 1e-3 if x == upper else (x - self.lower) / (self.upper - self.lower)
        return np.log(p) - np.log1p(-p)


def _parse_bounds(bounds, count):
    if bounds is None:
        bounds = (0.0, None)
    if len(bounds) == 2 and not isinstance(bounds[0], Sequence):
        bounds = [bounds] * count
    if len(bounds) != count:
        raise ValueError(f"bounds must be one (lower, upper) pair or one per tuned leaf ({count}), got {len(bounds)}")
    out = []
    for pair in bounds:
        if not (isinstance(pair, Sequence) and len(pair) == 2):
            raise ValueError(f"bounds must be (lower, upper) pairs, got {pair!r}")
        lo, hi = pair
        hi = None if hi is not None and float(hi) == np.inf else hi
        if lo is None or not np.isfinite(float(lo)) or (hi is not None and not np.isfinite(float(hi))):
            raise ValueError(f"bounds must have a finite lower and a finite (or None) upper, got ({lo}, {hi})")
        if hi is not None and not hi > lo:
            raise ValueError(f"bounds must have upper > lower, got ({lo}, {hi})")
        out.append(_Bounds(float(lo), None if hi is None else float(hi)))
    return out


def _select(where, flt):
    leaves = where(flt)
    return tuple(leaves) if isinstance(leaves, (tuple, list)) else (leaves,)


def _leaf_names(flt, leaves):
    """`filter.path.to.leaf` for each selected leaf (its position in `where` if not found)."""
    paths = {id(leaf): jax.tree_util.keystr(path) for path, leaf in jax.tree_util.tree_flatten_with_path(flt)[0]}
    return [f"filter{paths[id(leaf)]}" if id(leaf) in paths else f"where(filter)[{i}]" for i, leaf in enumerate(leaves)]


def _leaves(where, flt):
    leaves = _select(where, flt)
    if not leaves:
        raise ValueError("where must select at least one scalar float array leaf of the filter")
    for leaf in leaves:
        if not (eqx.is_array(leaf) and jnp.issubdtype(leaf.dtype, jnp.inexact) and leaf.ndim == 0):
            raise ValueError("where must select scalar float array leaves of the filter (e.g. lambda f: f.state_set.radius)")
    return leaves


class FitRun(eqx.Module):
    """The history of one start of `fit`: `params` `(n + 1, k)` and `losses` `(n + 1,)`
    of the iterates `0, …, n` (`n = steps` unless the convergence test stopped the run
    earlier), the index `best_step` of the smallest loss, and `converged`."""

    params: np.ndarray
    losses: np.ndarray
    best_step: int
    converged: bool


class FitResult(eqx.Module):
    """Result of `fit`: the filter with the best parameters seen over all steps and
    starts (`filter`; never a worse later iterate), its objective `loss`, which `start`
    and `best_step` it comes from and whether that start `converged`; `params`
    `(n + 1, k)` and `losses` `(n + 1,)` are the history of that start, and `runs` holds
    every start's `FitRun` (start 0 = the filter's own values)."""

    filter: PyTree
    loss: float
    params: np.ndarray
    losses: np.ndarray
    best_step: int
    converged: bool
    start: int
    runs: tuple[FitRun, ...]


def _check_progress(progress, scan: bool):
    """`(show, callback)` for `fit`'s `progress` argument."""
    if progress is None or isinstance(progress, bool):
        show, callback = bool(progress), None
    elif callable(progress):
        show, callback = False, progress
    else:
        raise ValueError(f"progress must be a bool or a callable(start, step, loss, params), got {progress!r}")
    if scan and (show or callback is not None):
        raise ValueError("progress is not available with scan=True (the loop is one compiled program)")
    return show, callback


def fit(
    flt: AbstractFilter,
    objective: Callable[[AbstractFilter], Float[Array, ""]],
    *,
    where: Callable[[AbstractFilter], Array | tuple[Array, ...]],
    bounds: tuple | Sequence[tuple] | None = None,
    shared: bool = False,
    optimizer: optax.GradientTransformation | None = None,
    steps: int = 100,
    tol: float | None = None,
    patience: int = 3,
    restarts: int = 0,
    jitter: float = 1.0,
    key: PRNGKeyArray | None = None,
    scan: bool = False,
    progress: bool | Callable[[int, int, float, np.ndarray], None] = False,
    mode: str = "reverse",
) -> FitResult:
    """Minimize `objective(filter)` over the leaves `where(filter)` with optax.

    Each tuned leaf is `lower + softplus(u)` (or `lower + (upper − lower) sigmoid(u)`
    when `upper` is given) of an unconstrained `u`, clipped to the values of the leaf's
    dtype strictly inside the bounds, so constraints such as `θ > 0`, `θ₂ > 1`
    (`bounds=(1.0, None)`) or `0 < ε < 0.5` (`bounds=(0.0, 0.5)`) hold even where the
    map saturates in float32. `bounds` is one `(lower, upper)` pair for all leaves or
    one per leaf (`lower` finite; `upper` finite, or `None` / `inf` for no upper bound);
    `shared=True` ties all selected leaves to one parameter (e.g. `θ₂ₓ = θ₂ᵥ`). The
    initial values are the filter's current ones (moved `1e-3` inside a bound they sit
    on, where the softplus gradient would vanish); a value outside its bounds raises
    `ValueError`, and so do unequal values of leaves tied by `shared`.

    - `steps`: the most optimizer steps per start (a positive integer). Default
      optimizer: `optax.adam(0.05)`. Each step (filter runs, solver derivatives) is jitted.
    - `tol`, `patience`: convergence test. A start stops, with `converged=True`, after
      `patience` consecutive steps with `|L_i − L_{i−1}| ≤ tol |L_{i−1}|` and
      `|p_i − p_{i−1}| ≤ tol |p_{i−1}|` for every parameter `p`; `tol=None` (default)
      runs all `steps`. Running out of steps gives `converged=False`.
    - `restarts`: further starts `u₀ + jitter · N(0, I)` in the unconstrained space
      (drawn with `key`, default `jax.random.key(0)`); the result is the best iterate
      by `objective` over all starts, and `runs` keeps every start's history.
    - `scan=True` runs each start's loop inside one compiled `lax.scan` (steps after
      convergence are skipped by `lax.cond`); no progress is reported then.
    - `progress`: `True` shows a tqdm bar (a reporter installed by the caller, e.g.
      the command line, gets the steps whatever this flag); a callable is called as
      `progress(start, step, loss, params)` after every step.
    - `mode`: `"reverse"` (default) or `"forward"` automatic differentiation of the
      objective (`value_and_grad`); same iterates, different cost.
    """
    steps = check_count("steps", steps)
    patience = check_count("patience", patience)
    restarts = check_count("restarts", restarts, minimum=0)
    if tol is not None and not (np.isfinite(tol) and tol > 0):
        raise ValueError(f"tol must be a positive number or None, got {tol!r}")
    if not (np.isfinite(jitter) and jitter >= 0):
        raise ValueError(f"jitter must be a finite number >= 0, got {jitter!r}")
    show, callback = _check_progress(progress, scan)
    _check_mode(mode)
    leaves = _leaves(where, flt)
    names = _leaf_names(flt, leaves)
    starts = [float(leaf) for leaf in leaves]
    if shared and len(set(starts)) > 1:
        shown = ", ".join(f"{x:.6g}" for x in starts)
        raise ValueError(f"shared=True ties {', '.join(names)} to one parameter, but their start values differ ({shown})")
    count = 1 if shared else len(leaves)
    bnds = _parse_bounds(bounds, count)
    dtype = leaves[0].dtype
    u0 = jnp.asarray([b.inverse(x, name, dtype) for b, x, name in zip(bnds, starts[:count], names[:count], strict=True)], dtype)
    u_starts = [u0]
    if restarts:
        noise = jax.random.normal(jax.random.key(0) if key is None else key, (restarts, count), dtype)
        u_starts += list(u0 + jitter * noise)
    optimizer = optax.adam(0.05) if optimizer is None else optimizer

    loss_dtype = jnp.result_type(float)  # losses are kept in the default float dtype

    def params_of(u):
        return jnp.stack([b.to(ui) for b, ui in zip(bnds, u, strict=True)])

    def build(u):
        vals = params_of(u)
        vals = jnp.broadcast_to(vals, (len(leaves),)) if shared else vals
        return eqx.tree_at(lambda f: _select(where, f), flt, tuple(v.astype(leaf.dtype) for v, leaf in zip(vals, leaves, strict=True)))

    def loss_of(u):
        return objective(build(u))

    vg = value_and_grad(loss_of, mode=mode)

    def small(new, old):
        return jnp.all(jnp.abs(new - old) <= tol * jnp.abs(old))  # False while `old` is NaN

    def step(carry):
        """Loss at `u`; convergence test against the previous iterate; optimizer update
        unless converged. Returns the new carry and the record `(u, params(u), loss)`."""
        u, opt_state, prev_loss, prev_params, streak, _ = carry
        loss, grad = vg(u)
        loss, params = loss.astype(loss_dtype), params_of(u)
        streak = jnp.where(small(loss, prev_loss) & small(params, prev_params), streak + 1, 0) if tol is not None else streak
        done = streak >= patience
        with jax.numpy_dtype_promotion("standard"):  # optax mixes int counters and floats
            upd, new_opt_state = optimizer.update(grad, opt_state, u)
        new_u = jnp.where(done, u, optax.apply_updates(u, upd))
        return (new_u, new_opt_state, loss, params, streak, done), (u, params, loss)

    def initial(u):
        return (u, optimizer.init(u), jnp.full((), jnp.nan, loss_dtype), jnp.full((count,), jnp.nan, dtype), jnp.zeros((), jnp.int32), jnp.zeros((), bool))

    @eqx.filter_jit
    def scanned(u):
        def body(carry, _):
            def skip(c):
                return c, (c[0], c[3], c[2])

            done = carry[-1]
            carry, record = jax.lax.cond(done, skip, step, carry)
            return carry, (record, ~done)

        return jax.lax.scan(body, initial(u), None, length=steps)

    jit_step, jit_initial, jit_loss = eqx.filter_jit(step), eqx.filter_jit(initial), eqx.filter_jit(loss_of)
    runs, us = [], []
    with _progress.reporter(show).phase(f"tuning {count} parameter{'s' if count > 1 else ''}", steps * len(u_starts), "step") as phase:
        for s, u_start in enumerate(u_starts):
            if scan:
                carry, ((u_hist, p_hist, l_hist), taken) = scanned(u_start)
                n = int(np.sum(np.asarray(taken)))
                phase.update(steps)
                u_hist, p_hist, l_hist = list(u_hist[:n]), list(np.asarray(p_hist[:n])), [float(x) for x in np.asarray(l_hist[:n])]
            else:
                carry, u_hist, p_hist, l_hist = jit_initial(u_start), [], [], []
                for i in range(steps):
                    carry, (u, p, loss) = jit_step(carry)
                    u_hist.append(u)
                    p_hist.append(np.asarray(p))
                    l_hist.append(float(loss))
                    phase.update(1)
                    if callback is not None:
                        callback(s, i, l_hist[-1], p_hist[-1])
                    if bool(carry[-1]):
                        break
            converged = bool(carry[-1])
            if not converged:  # the iterate after the last step
                u_hist.append(carry[0])
                p_hist.append(np.asarray(params_of(carry[0])))
                l_hist.append(float(jit_loss(carry[0])))
            losses = np.asarray(l_hist)
            best = 0 if np.all(np.isnan(losses)) else int(np.nanargmin(losses))
            runs.append(FitRun(params=np.stack(p_hist), losses=losses, best_step=best, converged=converged))
            us.append(u_hist[best])
    bests = np.asarray([r.losses[r.best_step] for r in runs])
    start = 0 if np.all(np.isnan(bests)) else int(np.nanargmin(bests))
    run = runs[start]
    return FitResult(
        filter=build(us[start]),
        loss=float(run.losses[run.best_step]),
        params=run.params,
        losses=run.losses,
        best_step=run.best_step,
        converged=run.converged,
        start=start,
        runs=tuple(runs),
    )


class GridResult(eqx.Module):
    """Result of `grid_search`: the best `filter`, the `grid` `(G, k)` and `losses` `(G,)`."""

    filter: PyTree
    loss: float
    grid: np.ndarray
    losses: np.ndarray


def grid_search(
    flt: AbstractFilter,
    objective: Callable[[AbstractFilter], Float[Array, ""]],
    *,
    where: Callable[[AbstractFilter], Array | tuple[Array, ...]],
    grid: Float[ArrayLike, " G"] | Float[ArrayLike, "G k"],
    chunk_size: int | None = None,
    progress: bool = False,
) -> GridResult:
    """Evaluate `objective` with the leaves `where(filter)` set to each row of `grid`
    (a 1-D grid sets every selected leaf to the same value) and return the best.

    The grid is evaluated `chunk_size` points per compiled call (default: about a tenth
    of the grid; the last chunk is padded and its padding discarded), one `lax.map` per
    call, so a progress bar (`progress=True`, or a reporter installed by the caller)
    shows the rate and time left."""
    leaves = _leaves(where, flt)
    grid = np.asarray(grid, dtype=np.float64)
    grid = np.repeat(grid[:, None], len(leaves), axis=1) if grid.ndim == 1 else grid
    if grid.ndim != 2 or grid.shape[1] != len(leaves) or len(grid) == 0:
        raise ValueError(f"grid must have shape (G,) or (G, {len(leaves)}) with G >= 1, got {grid.shape}")
    size = len(grid)
    chunk = -(-size // 10) if chunk_size is None else min(check_count("chunk_size", chunk_size), size)

    def set_(vals):
        return eqx.tree_at(lambda f: _select(where, f), flt, tuple(v.astype(leaf.dtype) for v, leaf in zip(vals, leaves, strict=True)))

    evaluate = eqx.filter_jit(lambda g: jax.lax.map(lambda v: objective(set_(v)), g))
    padded = np.concatenate([grid, np.repeat(grid[-1:], -size % chunk, axis=0)])
    losses = []
    with _progress.reporter(progress).phase(f"grid search ({size} points)", size, "point") as phase:
        for lo in range(0, size, chunk):
            losses.append(np.asarray(evaluate(jnp.asarray(padded[lo:lo + chunk], leaves[0].dtype))))
            phase.update(min(chunk, size - lo))
    losses = np.concatenate(losses)[:size]
    best = int(np.nanargmin(losses))
    return GridResult(filter=set_(jnp.asarray(grid[best], leaves[0].dtype)), loss=float(losses[best]), grid=grid, losses=losses)
