"""Error metrics of the five papers, and confidence intervals.

Arrays follow `Trajectories`/`FilterResult`: `(..., T, n)` with time then state axis.
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from . import linalg


__all__ = ["rmse", "rtamse", "squared_error", "mse_per_step", "nees", "mean_ci"]


def squared_error(states: Float[ArrayLike, "... T n"], estimates: Float[ArrayLike, "... T n"]) -> Float[Array, "... T"]:
    """`e_k = ‖x_k − x̂_k‖²` at every step."""
    return jnp.sum((jnp.asarray(states) - jnp.asarray(estimates)) ** 2, axis=-1)


def rmse(states: Float[ArrayLike, "... T n"], estimates: Float[ArrayLike, "... T n"]) -> Float[Array, "..."]:
    """Per-run RMSE over time, `sqrt((1/T) Σ_k ‖x_k − x̂_k‖²)` (Wang & Ye 2022, Sec. VII-B).

    Identical to the root time-averaged MSE (RTAMSE) of Wang (2022, nonlinear systems, Sec. VI),
    which is exported as `rtamse` under that name.
    """
    return jnp.sqrt(jnp.mean(squared_error(states, estimates), axis=-1))


rtamse = rmse


def mse_per_step(
    states: Float[ArrayLike, "runs T n"], estimates: Float[ArrayLike, "runs T n"], components=None
) -> Float[Array, " T"]:
    """Per-step MSE across runs, `(1/N) Σ_j ‖x_t^j − x̂_t^j‖²` (Chen et al. 2025, Fig. 1).

    `components` (indices into the state) restricts the norm, e.g. to position only.
    """
    states, estimates = jnp.asarray(states), jnp.asarray(estimates)
    if components is not None:
        idx = jnp.asarray(components)
        states, estimates = states[..., idx], estimates[..., idx]
    return jnp.mean(squared_error(states, estimates), axis=0)


def nees(
    states: Float[ArrayLike, "... T n"], means: Float[ArrayLike, "... T n"], covariances: Float[ArrayLike, "... T n n"]
) -> Float[Array, "... T"]:
    """Normalized estimation error squared `(x − x̂)ᵀ P⁻¹ (x − x̂)`; `n` on average for a consistent filter."""
    err = jnp.asarray(states) - jnp.asarray(means)
    solve = jnp.vectorize(linalg.psd_solve, signature="(n,n),(n)->(n)")
    return jnp.sum(err * solve(jnp.asarray(covariances), err), axis=-1)


def t_quantile(p: float, dof: int) -> float:
    """Quantile of Student's t by bisection on its CDF (regularized incomplete beta)."""
    if dof > 1e6:
        return math.sqrt(2.0) * float(jax.scipy.special.erfinv(2.0 * p - 1.0))

    def cdf(t):
        x = dof / (dof + t * t)
        tail = 0.5 * float(jax.scipy.special.betainc(dof / 2.0, 0.5, x))
        return 1.0 - tail if t > 0 else tail

    lo, hi = 0.0, 1.0
    while cdf(hi) < p:
        hi *= 2.0
    for _ in range(80):
        mid = 0.5 * (lo + hi)
        lo, hi = (mid, hi) if cdf(mid) < p else (lo, mid)
    return 0.5 * (lo + hi)


def mean_ci(values: ArrayLike, level: float = 0.95, *, scale: str = "linear") -> tuple[float, tuple[float, float]]:
    """Sample mean `m` and a two-sided `level` confidence interval for the population mean
    (Student t, `N − 1` dof, standard error `se = s/√N`).

    - `scale="linear"`: `m ± t·se`.
    - `scale="log"`, for strictly positive quantities (an RMSE, a cost): the same interval
      built for `log μ` by the delta method, `se(log m) ≈ se/m`, and mapped back,
      `[m·exp(−t·se/m), m·exp(t·se/m)]`. It stays positive and agrees with the linear
      one to first order when `se ≪ m`.

    NaN values are an error (a failed run must not vanish from the average). With a
    single value the interval is `(nan, nan)`.
    """
    v = np.asarray(values, dtype=np.float64).ravel()
    if v.size == 0:
        raise ValueError("values is empty")
    if not np.all(np.isfinite(v)):
        raise ValueError(f"values contains {int(np.sum(~np.isfinite(v)))} non-finite entries")
    if not 0.0 < level < 1.0:
        raise ValueError(f"level must lie in (0, 1), got {level}")
    if scale not in ("linear", "log"):
        raise ValueError(f"scale must be 'linear' or 'log', got {scale!r}")
    if scale == "log" and not np.all(v > 0):
        raise ValueError("scale='log' needs strictly positive values")
    mean = float(v.mean())
    if v.size == 1:
        return mean, (float("nan"), float("nan"))
    half = t_quantile(0.5 + level / 2.0, v.size - 1) * float(v.std(ddof=1)) / math.sqrt(v.size)
    if scale == "log":
        return mean, (mean * math.exp(-half / mean), mean * math.exp(half / mean))
    return mean, (mean - half, mean + half)
