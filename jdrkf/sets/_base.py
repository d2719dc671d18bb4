"""Interface of ambiguity sets of Gaussian laws around a nominal covariance."""

from __future__ import annotations

import abc

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Bool, Float


class AbstractAmbiguitySet(eqx.Module):
    """A ball of Gaussian laws `N(μ̂, Σ)` around a nominal `N(μ̂, Σ̂)`.

    The worst-case mean of every set in jdrkf is the nominal one (Wang & Ye 2022,
    Theorem 2), so a set acts on covariances only. The solvers in `jdrkf.sets`
    need two things from a set: its linear oracle (`lmo`) for Frank–Wolfe, and the
    residual of its optimality conditions for implicit differentiation.
    """

    @abc.abstractmethod
    def oracle(
        self, direction: Float[Array, "d d"], nominal: Float[Array, "d d"], guess: Float[Array, ""] | None = None
    ) -> tuple[Float[Array, "d d"], Float[Array, ""]]:
        """Maximizer of `⟨direction, Σ⟩` over the set (for PSD `direction`) and the
        scalar multiplier that determines it. `guess`: a multiplier to start the set's
        scalar root search from (e.g. the previous Frank–Wolfe iterate's; any value is
        safe, the search is bracketed). Forward pass only: not differentiable."""

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


def warm_start(guess: Float[ArrayLike, ""] | None, lo, default, hi) -> Float[Array, ""]:
    """Start of a bracketed scalar root search on `(lo, hi)`: `guess` if it is given, finite
    and strictly inside, else `default`."""
    if guess is None:
        return default
    guess = jnp.asarray(guess, jnp.result_type(default))
    return jnp.where(jnp.isfinite(guess) & (guess > lo) & (guess < hi), guess, default)
