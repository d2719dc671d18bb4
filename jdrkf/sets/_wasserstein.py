"""Wasserstein (Gelbrich) ball of Gaussian laws and its closed-form linear oracle."""

from __future__ import annotations

import jax.numpy as jnp
from jax import lax
from jaxtyping import Array, ArrayLike, Float

from .. import linalg
from .._root import bracketed_newton
from .._validation import check_scalar, in_range, renamed, renamed_attribute
from ._base import AbstractAmbiguitySet, warm_start

_NEWTON_MAX_ITER = 100


class Wasserstein(AbstractAmbiguitySet):
    """Type-2 Wasserstein ball `{N(μ̂, Σ) : W₂ ≤ θ}` of radius `radius = θ` around `N(μ̂, Σ̂)`.

    Between Gaussians with equal means `W₂` is the Bures (Gelbrich) distance
    `√Tr(Σ + Σ̂ − 2(Σ̂^½ Σ Σ̂^½)^½)` (Wang & Ye 2022, eq. 19 and Theorem 2b;
    Shafieezadeh-Abadeh et al. 2018). `radius` is in the units of the state
    (`theta=` is a deprecated alias of `radius`).

    The linear oracle is closed form up to one scalar (`docs/math/wasserstein.md`): for
    `D ⪰ 0` it is `T Σ̂ T` with `T = (I − θ s D)⁻¹`, where `s ∈ (0, 1/(θ λ_max(D)))`
    solves `Tr(Σ̂ (s D T)²) = 1`. (`s = t/θ` with `t = 1/γ` of the paper's dual; this
    scaling keeps the multiplier finite at `θ = 0`, so derivatives in `θ` exist there.)
    `s` is found by safeguarded Newton steps on the equivalent `s − 1/g(s) = 0`,
    `g(s)² = Tr(Σ̂(DT)²)`, which is nearly linear near the pole `1/(θ λ_max(D))` (2–5 steps),
    from the upper end of the root's bracket or from `oracle`'s `guess`.
    """

    radius: Float[Array, ""]

    def __init__(self, radius: Float[ArrayLike, ""] = None, *, theta: Float[ArrayLike, ""] = None):
        self.radius = check_scalar("radius", renamed("theta", theta, "radius", radius, "Wasserstein"))

    theta = renamed_attribute("theta", "radius")

    def is_nominal(self):
        return self.radius == 0

    def valid(self):
        return in_range(self.radius, 0.0)

    def oracle(self, direction, nominal, guess=None):
        rho = lax.stop_gradient(self.radius).astype(nominal.dtype)
        direction, nominal = lax.stop_gradient(linalg.symmetrize(direction)), lax.stop_gradient(nominal)
        d, v = jnp.linalg.eigh(direction)
        d = jnp.maximum(d, 0.0)
        mdiag = jnp.sum(v * (nominal @ v), axis=0)  # diag(VᵀΣ̂V)
        d1 = d[-1]
        active = d1 > 0
        d1 = jnp.where(active, d1, 1.0)
        tiny = jnp.finfo(nominal.dtype).eps * jnp.trace(nominal)
        s_lo = 1.0 / (d1 * (rho + jnp.sqrt(jnp.trace(nominal))))
        s_hi = 1.0 / (d1 * (rho + jnp.sqrt(jnp.maximum(mdiag[-1], tiny))))

        def h_and_slope(s):
            # q = s² g(s)² − 1 with g = ‖Σ̂_V^½ u‖, u = d/(1 − θsd) (Σ̂_V = diag(VᵀΣ̂V)); the search runs on
            # h = s − 1/g, which has the same root, is increasing, and near the pole (g ∝ 1/(pole − s)) is
            # nearly linear: Newton on q itself only moves a factor 3/2 away from the pole per step.
            u = d / (1.0 - rho * s * d)
            g = jnp.maximum(jnp.sqrt(jnp.sum(mdiag * u * u)), tiny)
            return s - 1.0 / g, 1.0 + rho * jnp.sum(mdiag * u * u * u) / g**3

        # The root lies in [s_lo, s_hi] (the bounds keep all of Tr Σ̂, or only its component along
        # the top direction); h → pole > 0 at the pole 1/(θ d₁), the other end of the bracket.
        pole = jnp.where(rho > 0, 1.0 / (jnp.where(rho > 0, rho, 1.0) * d1), jnp.inf)
        start = warm_start(guess, s_lo, s_hi, pole)
        s = bracketed_newton(h_and_slope, start, s_lo, pole, _NEWTON_MAX_ITER, has_slope=True).x
        tdiag = 1.0 / (1.0 - rho * s * d)
        t = (v * tdiag) @ v.T
        cov = linalg.symmetrize(t @ nominal @ t)
        exact = ~active | (rho == 0)
        return jnp.where(exact, nominal, cov), jnp.where(active, s, 1.0)

    def residual(self, cov, multiplier, direction, nominal):
        r, q, _ = oracle_residual(self.radius.astype(nominal.dtype), cov, multiplier, direction, nominal)
        return r, q


def oracle_residual(rho, cov, s, direction, nominal):
    """The oracle's optimality system `(Σ − TΣ̂T, s² Tr(Σ̂(DT)²) − 1)` (or `s − 1` for an
    inactive set, `Tr D = 0`) and `T = (I − θsD)⁻¹` (`linalg.psd_inv`: its derivative is
    products, so Newton and implicit-derivative Jacobians batch)."""
    eye = jnp.eye(nominal.shape[-1], dtype=nominal.dtype)
    mm = linalg.matmul
    t = linalg.psd_inv(eye - rho * s * direction)  # I − θsD ≻ 0 in the bracket
    dt = mm(direction, t)
    q = s * s * jnp.sum(nominal * mm(dt, dt).T) - 1.0
    active = jnp.trace(direction) > 0
    return cov - linalg.symmetrize(mm(mm(t, nominal), t)), jnp.where(active, q, s - 1.0), t
