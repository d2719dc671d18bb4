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
fit.filter  # the tuned filter
```

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
from jaxtyping import Array, ArrayLike, Float, PyTree

from . import metrics
from ._gaussian import Gaussian
from ._models import LinearModel
from ._simulate import Trajectories
from ._validation import check_count
from .filters._base import AbstractFilter


__all__ = ["rmse_objective", "fit", "grid_search", "FitResult", "GridResult"]


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
        if self.upper is None:
            return self.lower + jax.nn.softplus(u)
        return self.lower + (self.upper - self.lower) * jax.nn.sigmoid(u)

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
            raise ValueError("where must select scalar float array leaves of the filter (e.g. lambda f: f.state_set.theta)")
    return leaves


class FitResult(eqx.Module):
    """Result of `fit`: the filter with the best parameters seen (`filter`), its
    objective `loss`, and per-step histories `params` `(steps + 1, k)` and `losses`."""

    filter: PyTree
    loss: float
    params: np.ndarray
    losses: np.ndarray


def fit(
    flt: AbstractFilter,
    objective: Callable[[AbstractFilter], Float[Array, ""]],
    *,
    where: Callable[[AbstractFilter], Array | tuple[Array, ...]],
    bounds: tuple | Sequence[tuple] | None = None,
    shared: bool = False,
    optimizer: optax.GradientTransformation | None = None,
    steps: int = 100,
) -> FitResult:
    """Minimize `objective(filter)` over the leaves `where(filter)` with optax.

    Each tuned leaf is `lower + softplus(u)` (or `lower + (upper − lower) sigmoid(u)`
    when `upper` is given) of an unconstrained `u`, so constraints such as `θ ≥ 0`,
    `θ₂ ≥ 1` (`bounds=(1.0, None)`) or `0 ≤ ε < 0.5` (`bounds=(0.0, 0.5)`) always
    hold. `bounds` is one `(lower, upper)` pair for all leaves or one per leaf
    (`lower` finite; `upper` finite, or `None` / `inf` for no upper bound);
    `shared=True` ties all selected leaves to one parameter (e.g. `θ₂ₓ = θ₂ᵥ`).
    The initial values are the filter's current ones (moved `1e-3` inside a bound
    they sit on, where the softplus gradient would vanish); a value outside its
    bounds raises `ValueError`, and so do unequal values of leaves tied by `shared`.
    `steps` is a positive integer. Default optimizer: `optax.adam(0.05)`. The whole
    step (filter runs, solver derivatives) is jitted.
    """
    steps = check_count("steps", steps)
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
    optimizer = optax.adam(0.05) if optimizer is None else optimizer

    def build(u):
        vals = jnp.stack([b.to(ui) for b, ui in zip(bnds, u, strict=True)])
        vals = jnp.broadcast_to(vals, (len(leaves),)) if shared else vals
        return eqx.tree_at(lambda f: _select(where, f), flt, tuple(v.astype(leaf.dtype) for v, leaf in zip(vals, leaves, strict=True)))

    def params_of(u):
        return jnp.stack([b.to(ui) for b, ui in zip(bnds, u, strict=True)])

    @eqx.filter_jit
    def update(u, opt_state):
        loss, grad = jax.value_and_grad(lambda u: objective(build(u)))(u)
        with jax.numpy_dtype_promotion("standard"):  # optax mixes int counters and floats
            upd, opt_state = optimizer.update(grad, opt_state, u)
        return optax.apply_updates(u, upd), opt_state, loss

    u, opt_state = u0, optimizer.init(u0)
    us, losses = [], []
    for _ in range(steps):
        new_u, opt_state, loss = update(u, opt_state)
        us.append(u)
        losses.append(float(loss))
        u = new_u
    us.append(u)
    losses.append(float(eqx.filter_jit(lambda u: objective(build(u)))(u)))
    best = int(np.nanargmin(losses))
    return FitResult(
        filter=build(us[best]),
        loss=losses[best],
        params=np.stack([np.asarray(params_of(x)) for x in us]),
        losses=np.asarray(losses),
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
) -> GridResult:
    """Evaluate `objective` with the leaves `where(filter)` set to each row of `grid`
    (a 1-D grid sets every selected leaf to the same value) and return the best."""
    leaves = _leaves(where, flt)
    grid = np.asarray(grid, dtype=np.float64)
    grid = np.repeat(grid[:, None], len(leaves), axis=1) if grid.ndim == 1 else grid
    if grid.ndim != 2 or grid.shape[1] != len(leaves):
        raise ValueError(f"grid must have shape (G,) or (G, {len(leaves)}), got {grid.shape}")

    def set_(vals):
        return eqx.tree_at(lambda f: _select(where, f), flt, tuple(v.astype(leaf.dtype) for v, leaf in zip(vals, leaves, strict=True)))

    losses = np.asarray(eqx.filter_jit(lambda g: jax.lax.map(lambda v: objective(set_(v)), g))(jnp.asarray(grid, leaves[0].dtype)))
    best = int(np.nanargmin(losses))
    return GridResult(filter=set_(jnp.asarray(grid[best], leaves[0].dtype)), loss=float(losses[best]), grid=grid, losses=losses)
