"""Kullback–Leibler ball of Gaussian laws and its closed-form linear oracle."""

from __future__ import annotations

import jax.numpy as jnp
from jax import lax
from jaxtyping import Array, ArrayLike, Float

from .. import linalg
from .._root import bracketed_newton
from .._validation import check_scalar, in_range, renamed, renamed_attribute
from ._base import AbstractAmbiguitySet, warm_start

_NEWTON_MAX_ITER = 200
# φ(x) = 1/(1 − x) − 1 + ln(1 − x) = Σ_{k≥2} (1 − 1/k) xᵏ: below this size of x the closed
# form cancels catastrophically (its value is ≈ x²/2), so the series is used instead.
_SERIES_BELOW = 0.05
_SERIES_TERMS = 14


def _phi(x):
    """`φ(x)` elementwise, accurate for small `x` (series) and up to the pole at 1."""
    small = jnp.abs(x) < _SERIES_BELOW
    xs = jnp.where(small, x, 0.0)
    series = sum((1.0 - 1.0 / k) * xs**k for k in range(2, _SERIES_TERMS))
    xl = jnp.where(small, 0.5, x)
    return jnp.where(small, series, xl / (1.0 - xl) + jnp.log1p(-xl))


def _phi_trace(x, a_inv, logdet_a):
    """`Tr φ(X)` for symmetric `X` with `A = I − X` (inverse `a_inv`, `log det A`),
    written with inverses and matrix powers only (differentiable with repeated
    eigenvalues)."""
    d = x.shape[-1]
    small = jnp.sqrt(jnp.sum(x * x)) < _SERIES_BELOW
    xs = jnp.where(small, x, 0.0)
    power, series = xs, jnp.zeros((), x.dtype)
    for k in range(2, _SERIES_TERMS):
        power = power @ xs
        series = series + (1.0 - 1.0 / k) * jnp.trace(power)
    closed = jnp.trace(a_inv) - d + logdet_a
    return jnp.where(small, series, closed)


class KL(AbstractAmbiguitySet):
    """Kullback–Leibler ball `{N(μ̂, Σ) : KL(N(μ̂, Σ) ‖ N(μ̂, Σ̂)) ≤ c}` of radius `radius = c`
    (`c=` is a deprecated alias of `radius`).

    `KL = ½[Tr(Σ̂⁻¹Σ) − d − ln det(Σ̂⁻¹Σ)]` (Wang & Ye 2022, eqs. 18, 21 and
    Theorem 2a; note that Zorzi's τ-KF code compares *twice* this quantity with its
    tolerance, see `jdrkf.TauKF`). The paper skipped this set as "difficult"; here
    its linear oracle is closed form up to one scalar (`docs/math/wasserstein.md`): with
    `Σ̂ = R Rᵀ` (Cholesky) and `W = Rᵀ D R`, the maximizer of `⟨D, Σ⟩` is
    `R (I − t W)⁻¹ Rᵀ`, where `t ∈ (0, 1/λ_max(W))` solves
    `½[Tr((I − tW)⁻¹) − d + ln det(I − tW)] = c`, found by Newton's method from
    the right (monotone, the residual is convex increasing in `t`).

    The worst case grows like `√c`, so its derivative in `c` is infinite at
    `c = 0`; there jdrkf reports a zero derivative in `c` (derivatives with
    respect to everything else stay exact).
    """

    radius: Float[Array, ""]

    def __init__(self, radius: Float[ArrayLike, ""] = None, *, c: Float[ArrayLike, ""] = None):
        self.radius = check_scalar("radius", renamed("c", c, "radius", radius, "KL"))

    c = renamed_attribute("c", "radius")

    def is_nominal(self):
        return self.radius == 0

    def valid(self):
        return in_range(self.radius, 0.0)

    def oracle(self, direction, nominal, guess=None):
        c = lax.stop_gradient(self.radius).astype(nominal.dtype)
        direction, nominal = lax.stop_gradient(linalg.symmetrize(direction)), lax.stop_gradient(nominal)
        r = linalg.cholesky(nominal)
        mu, q = jnp.linalg.eigh(linalg.symmetrize(r.T @ direction @ r))
        mu = jnp.maximum(mu, 0.0)
        mu_max = mu[-1]
        active = (mu_max > 0) & (c > 0)
        mu_max = jnp.where(active, mu_max, 1.0)

        def g_and_slope(t):
            w = 1.0 / (1.0 - t * mu)
            return 0.5 * jnp.sum(_phi(t * mu)) - c, 0.5 * jnp.sum(t * mu * mu * w * w)

        # Start right of the root: ½ φ(1 − δ) ≥ c for δ = 1/(4c + 20). Convex and
        # increasing in t on [0, 1/μ_max): Newton decreases monotonically to the root.
        t0 = (1.0 - 1.0 / (4.0 * c + 20.0)) / mu_max
        start = warm_start(guess, 0.0, t0, 1.0 / mu_max)
        t = bracketed_newton(g_and_slope, start, 0.0, 1.0 / mu_max, _NEWTON_MAX_ITER, has_slope=True).x
        rq = r @ q
        cov = linalg.symmetrize((rq / (1.0 - t * mu)) @ rq.T)
        return jnp.where(active, cov, nominal), jnp.where(active, t, 0.0)

    def residual(self, cov, multiplier, direction, nominal):
        c = self.radius.astype(nominal.dtype)
        t = multiplier
        r = linalg.cholesky(nominal)
        w = linalg.symmetrize(r.T @ direction @ r)
        a = jnp.eye(nominal.shape[-1], dtype=nominal.dtype) - t * w
        a_inv = linalg.psd_inv(a)  # derivatives by products: the Newton/IFT Jacobians batch
        g = 0.5 * _phi_trace(t * w, a_inv, linalg.psd_logdet(a)) - c
        active = (c > 0) & (jnp.trace(w) > 0)
        return cov - linalg.symmetrize(r @ a_inv @ r.T), jnp.where(active, g, t)
