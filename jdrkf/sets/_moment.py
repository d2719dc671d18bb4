"""Moment-based ambiguity set (closed-form worst case)."""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from .._validation import check_scalar, in_range, is_concrete
from ._base import AbstractAmbiguitySet


class Moment(AbstractAmbiguitySet):
    """Moment set `{N(μ, Σ) : (μ − μ̂)ᵀΣ̂⁻¹(μ − μ̂) ≤ θ₃, θ₁Σ̂ ⪯ E(x − μ̂)(x − μ̂)ᵀ ⪯ θ₂Σ̂}`
    (Wang & Ye 2022, eq. 20).

    The worst case of every MMSE problem in jdrkf is `Σ = θ₂ Σ̂` (Theorem 5: the
    objective is Loewner-nondecreasing), so only `theta2 ≥ 1` matters; `theta1 ∈
    [0, 1]` is accepted (keyword) for completeness and checked, but unused
    (Algorithm 1, remark). `theta2 = 1` is the nominal law.
    """

    theta2: Float[Array, ""]
    theta1: Float[Array, ""]

    def __init__(self, theta2: Float[ArrayLike, ""], *, theta1: Float[ArrayLike, ""] = 0.0):
        self.theta2 = check_scalar("theta2", theta2, lower=1.0)
        self.theta1 = check_scalar("theta1", theta1)
        if is_concrete(self.theta1) and float(self.theta1) > 1.0:
            raise ValueError(f"theta1 must be in [0, 1], got {float(self.theta1):g}")

    def is_nominal(self):
        return self.theta2 == 1

    def valid(self):
        return in_range(self.theta2, 1.0) & in_range(self.theta1, 0.0, 1.0)

    def worst_case(self, nominal: Float[Array, "d d"]) -> Float[Array, "d d"]:
        """`θ₂ Σ̂` (Theorem 5)."""
        return self.theta2.astype(nominal.dtype) * nominal

    def oracle(self, direction, nominal, guess=None):
        return self.worst_case(nominal), jnp.zeros((), nominal.dtype)

    def residual(self, cov, multiplier, direction, nominal):
        return cov - self.worst_case(nominal), multiplier
