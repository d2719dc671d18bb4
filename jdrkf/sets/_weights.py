"""Weight functions `d_ν(e)` of robust losses for iteratively reweighted Kalman updates
(Li, Shi, Yu, Shi, "Variational Robust Kalman Filters: A Unified Framework", eq. 17
and Table I).

A loss `J(e) = Σ_i J_{ν_i}(e_i)` of the whitened residual `e` has `∂J/∂e_i = d_{ν_i}(e_i) e_i`;
the IRLS update inflates channel `i` by `1 / d_{ν_i}(e_i)`. Each weight module maps a
residual vector `e` to weights componentwise; its parameters are scalars or
per-channel vectors (broadcast against `e`). A channel is *disabled* (Gaussian loss,
weight `1/τ²`, i.e. `1` for `τ² = 1`) by `ν = inf` (Student-t, Gaussian kernel,
pseudo-Huber, Huber) or `ν = 2` (Barron): Proposition 1. Infinite parameters are
handled with `jnp.where` on both branches, so gradients stay finite.
"""

from __future__ import annotations

import abc

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from typing import ClassVar

from jaxtyping import Array, ArrayLike, Bool, Float

from .._validation import as_float_array, in_range, is_concrete

__all__ = [
    "AbstractWeight",
    "Barron",
    "GaussianKernel",
    "Huber",
    "PseudoHuber",
    "StudentT",
    "channel_param",
    "student_t_weight",
]


def channel_param(
    name: str,
    value: ArrayLike,
    *,
    lower: float = 0.0,
    upper: float | None = None,
    lower_open: bool = True,
    upper_open: bool = False,
    allow_inf: bool = False,
) -> Float[Array, "*d"]:
    """A hyper-parameter that is a scalar or a per-channel vector, as a float array;
    its values are checked (eagerly, when concrete) to lie in the given interval."""
    arr = as_float_array(name, value, (0, 1))
    if is_concrete(arr):
        v = np.asarray(arr, dtype=np.float64)
        lo_ok = (v > lower) if lower_open else (v >= lower)
        hi_ok = np.ones_like(lo_ok) if upper is None else ((v < upper) if upper_open else (v <= upper))
        fin_ok = ~np.isnan(v) & (np.isfinite(v) | (allow_inf & (v > 0)))
        if not np.all(lo_ok & hi_ok & fin_ok):
            lo = "(" if lower_open else "["
            hi = "inf)" if upper is None else (f"{upper:g})" if upper_open else f"{upper:g}]")
            inf = " (inf allowed)" if allow_inf else ""
            raise ValueError(f"{name} must lie in {lo}{lower:g}, {hi}{inf}, got {v}")
    return arr


def _fin(x, fill=1.0):
    """`(isfinite(x), x with non-finite entries replaced by fill)` for safe `where`s."""
    ok = jnp.isfinite(x)
    return ok, jnp.where(ok, x, fill)


def student_t_weight(e: Float[Array, " d"], nu: Float[ArrayLike, "*d"], tau2: Float[ArrayLike, "*d"]) -> Float[Array, " d"]:
    """Eq. 17: `d_ν(e) = ν / (ν τ² + e²)`; `ν = inf` gives `1/τ²`."""
    finite, nu_s = _fin(jnp.asarray(nu))
    w = jnp.where(finite, nu_s / (nu_s * tau2 + e**2), 1.0 / tau2)
    return jnp.broadcast_to(w, e.shape)


class AbstractWeight(eqx.Module):
    """A componentwise weight `e ↦ d(e)` of a robust loss (`J'(e) = d(e) e`).

    `ranges` (class variable): each array field's interval, as keyword arguments of
    `channel_param` — checked eagerly at construction and, traced, by `valid()`."""

    ranges: ClassVar[dict[str, dict]] = {}

    def _param(self, name: str, value: ArrayLike) -> Float[Array, "*d"]:
        return channel_param(name, value, **self.ranges[name])

    def valid(self) -> Bool[Array, ""]:
        """Traced range check of every parameter (the filters turn `False` into
        `RESULTS.invalid_hyperparameter`)."""
        ok = jnp.asarray(True)
        for name, spec in self.ranges.items():
            upper = spec.get("upper")
            ok = ok & in_range(
                getattr(self, name), spec.get("lower", 0.0), np.inf if upper is None else upper,
                lower_open=spec.get("lower_open", True), upper_open=spec.get("upper_open", False),
                allow_inf=spec.get("allow_inf", False),
            )
        return ok

    @abc.abstractmethod
    def __call__(self, e: Float[Array, " d"]) -> Float[Array, " d"]:
        """Weights of the whitened residual `e` (same shape)."""

    def check_size(self, name: str, size: int) -> None:
        """Raise `ValueError` if a per-channel parameter does not have `size` entries."""
        for field, value in vars(self).items():
            if isinstance(value, Array | np.ndarray) and value.ndim == 1 and value.shape[0] != size:
                raise ValueError(
                    f"{name}.{field} has {value.shape[0]} entries but there are {size} channels"
                )


class StudentT(AbstractWeight):
    """Student-t loss `(ν/2) log(1 + e²/(ν τ²))` (eq. 14; Table I row 1), weight
    `ν / (ν τ² + e²)` (eq. 17). `nu = inf` disables the channel (weight `1/τ²`)."""

    nu: Float[Array, "*d"]
    tau2: Float[Array, "*d"]
    ranges: ClassVar[dict[str, dict]] = {"nu": {"allow_inf": True}, "tau2": {}}

    def __init__(self, nu: Float[ArrayLike, "*d"] = 4.0, tau2: Float[ArrayLike, "*d"] = 1.0):
        self.nu = self._param("nu", nu)
        self.tau2 = self._param("tau2", tau2)

    def __call__(self, e):
        return student_t_weight(e, self.nu, self.tau2)


class GaussianKernel(AbstractWeight):
    """Correntropy / Gaussian-kernel loss `σ²(1 − exp(−e²/(2σ²τ²)))` (Table I row 2, with
    `ν = σ`; MCKF / MKCKF), weight `exp(−e²/(2σ²τ²)) / τ²`, floored at `floor` (the
    authors' RBKF1 floors at 1e-4 / 4e-4; an exactly zero weight would make the
    inflated covariance infinite). `sigma = inf` disables the channel."""

    sigma: Float[Array, "*d"]
    tau2: Float[Array, "*d"]
    floor: Float[Array, "*d"]
    ranges: ClassVar[dict[str, dict]] = {"sigma": {"allow_inf": True}, "tau2": {}, "floor": {"lower_open": False}}

    def __init__(self, sigma: Float[ArrayLike, "*d"] = 2.0, tau2: Float[ArrayLike, "*d"] = 1.0, floor: Float[ArrayLike, "*d"] = 1e-8):
        self.sigma = self._param("sigma", sigma)
        self.tau2 = self._param("tau2", tau2)
        self.floor = self._param("floor", floor)

    def __call__(self, e):
        finite, s = _fin(self.sigma)
        w = jnp.where(finite, jnp.exp(-(e**2) / (2.0 * s**2 * self.tau2)), 1.0) / self.tau2
        return jnp.broadcast_to(jnp.maximum(w, self.floor), e.shape)


class Barron(AbstractWeight):
    """Barron's general (power) loss `((2−ν)/ν)(((e²/τ²)/(2−ν) + 1)^{ν/2} − 1)`, `ν ∈ (0, 2]`
    (Table I row 3, `ν = sigma`), weight `((e²/τ²)/(2−σ) + 1)^{σ/2−1} / τ²`, floored at
    `floor`. `sigma = 2` is the Gaussian loss (the limit; weight `1/τ²`)."""

    sigma: Float[Array, "*d"]
    tau2: Float[Array, "*d"]
    floor: Float[Array, "*d"]
    ranges: ClassVar[dict[str, dict]] = {"sigma": {"upper": 2.0}, "tau2": {}, "floor": {"lower_open": False}}

    def __init__(self, sigma: Float[ArrayLike, "*d"] = 1.0, tau2: Float[ArrayLike, "*d"] = 1.0, floor: Float[ArrayLike, "*d"] = 0.0):
        self.sigma = self._param("sigma", sigma)
        self.tau2 = self._param("tau2", tau2)
        self.floor = self._param("floor", floor)

    def __call__(self, e):
        gauss = self.sigma >= 2.0
        s = jnp.where(gauss, 1.0, self.sigma)
        w = jnp.where(gauss, 1.0, ((e**2 / self.tau2) / (2.0 - s) + 1.0) ** (0.5 * s - 1.0)) / self.tau2
        return jnp.broadcast_to(jnp.maximum(w, self.floor), e.shape)


class PseudoHuber(AbstractWeight):
    """Square-root / pseudo-Huber loss `sqrt(σ(σ + e²/τ²)) − σ` (Table I row 4, `ν = σ`;
    AORSE-sqrt), weight `1 / (τ² sqrt(1 + e²/(σ τ²)))`. `sigma = inf` disables the channel."""

    sigma: Float[Array, "*d"]
    tau2: Float[Array, "*d"]
    ranges: ClassVar[dict[str, dict]] = {"sigma": {"allow_inf": True}, "tau2": {}}

    def __init__(self, sigma: Float[ArrayLike, "*d"] = 1.0, tau2: Float[ArrayLike, "*d"] = 1.0):
        self.sigma = self._param("sigma", sigma)
        self.tau2 = self._param("tau2", tau2)

    def __call__(self, e):
        finite, s = _fin(self.sigma)
        w = jnp.where(finite, 1.0 / jnp.sqrt(1.0 + e**2 / (s * self.tau2)), 1.0) / self.tau2
        return jnp.broadcast_to(w, e.shape)


class Huber(AbstractWeight):
    """Huber loss (quadratic for `|e| ≤ k`, linear beyond), weight `min(1, k/|e|)`
    (HKF; `k = 1.345` gives 95% Gaussian efficiency). `k = inf` disables the channel."""

    k: Float[Array, "*d"]
    ranges: ClassVar[dict[str, dict]] = {"k": {"allow_inf": True}}

    def __init__(self, k: Float[ArrayLike, "*d"] = 1.345):
        self.k = self._param("k", k)

    def __call__(self, e):
        a = jnp.abs(e)
        clip = a > self.k
        return jnp.broadcast_to(jnp.where(clip, self.k / jnp.where(clip, a, 1.0), 1.0), e.shape)
