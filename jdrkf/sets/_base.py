"""Interface of ambiguity sets of Gaussian laws around a nominal covariance."""

from __future__ import annotations

import abc

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float

from .._validation import as_float_array, is_concrete


def radius(name: str, x: ArrayLike, lower: float = 0.0) -> Float[Array, ""]:
    """A scalar hyper-parameter `>= lower` as a float array (checked when concrete)."""
    x = as_float_array(name, x, (0,))
    if is_concrete(x):
        v = float(np.asarray(x))
        if not np.isfinite(v) or v < lower:
            raise ValueError(f"{name} must be a finite number >= {lower:g}, got {v:g}")
    return x


def in_range(
    x: Float[ArrayLike, "*d"],
    lower: float,
    upper: float = np.inf,
    *,
    lower_open: bool = False,
    upper_open: bool = False,
    allow_inf: bool = False,
) -> Bool[Array, ""]:
    """Traced range check of a hyper-parameter (the run-time counterpart of the eager
    checks): every entry of `x` lies in the interval from `lower` to `upper` (open or
    closed ends) and is finite (`+inf` too with `allow_inf`); `False` for NaN. A few
    scalar comparisons, unbatched under `vmap` over data."""
    x = jnp.asarray(x)
    above = x > lower if lower_open else x >= lower
    below = x < upper if upper_open else x <= upper
    finite = (x == jnp.inf) | jnp.isfinite(x) if allow_inf else jnp.isfinite(x)
    return jnp.all(above & below & finite)


class AbstractAmbiguitySet(eqx.Module):
    """A ball of Gaussian laws `N(μ̂, Σ)` around a nominal `N(μ̂, Σ̂)`.

    The worst-case mean of every set in jdrkf is the nominal one (Wang & Ye 2022,
    Theorem 2), so a set acts on covariances only. The solvers in `jdrkf.sets`
    need two things from a set: its linear oracle (`lmo`) for Frank–Wolfe, and the
    residual of its optimality conditions for implicit differentiation.
    """

    @abc.abstractmethod
    def oracle(
        self, direction: Float[Array, "d d"], nominal: Float[Array, "d d"]
    ) -> tuple[Float[Array, "d d"], Float[Array, ""]]:
        """Maximizer of `⟨direction, Σ⟩` over the set (for PSD `direction`) and the
        scalar multiplier that determines it. Forward pass only: not differentiable."""

    @abc.abstractmethod
    def residual(
        self,
        cov: Float[Array, "d d"],
        multiplier: Float[Array, ""],
        direction: Float[Array, "d d"],
        nominal: Float[Array, "d d"],
    ) -> tuple[Float[Array, "d d"], Float[Array, ""]]:
        """Residual of `cov = oracle(direction)` and of the multiplier's equation,
        written with solves only (differentiable, safe with repeated eigenvalues)."""

    @abc.abstractmethod
    def is_nominal(self) -> Bool[Array, ""]:
        """Whether the set contains only the nominal law (zero radius)."""

    @abc.abstractmethod
    def valid(self) -> Bool[Array, ""]:
        """Whether the parameters are in range (checked eagerly when concrete; this is the
        traced check, which filters turn into `RESULTS.invalid_hyperparameter`)."""

    def lmo(self, direction: Float[ArrayLike, "d d"], nominal: Float[ArrayLike, "d d"]) -> Float[Array, "d d"]:
        """Linear maximization oracle: `argmax ⟨direction, Σ⟩` over the set."""
        direction, nominal = jnp.asarray(direction), jnp.asarray(nominal)
        return self.oracle(direction, nominal)[0]
