"""Multivariate Gaussian as a pytree."""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float, PRNGKeyArray

from . import linalg
from ._validation import as_float_array, check_covariance


def quadratic_and_logdet(
    chol: Float[Array, "n n"], resid: Float[ArrayLike, "... n"]
) -> tuple[Float[Array, "..."], Float[Array, ""]]:
    """`(rᵀ (L Lᵀ)⁻¹ r, log det(L Lᵀ) = 2 Σᵢ log Lᵢᵢ)` for residuals `r` of shape `(..., n)`
    and a lower Cholesky factor `L`. All residuals enter one solve as right-hand sides (no
    factorization or solve per residual, so nothing is batched per particle or sample)."""
    resid = jnp.asarray(resid)
    n = chol.shape[-1]
    flat = resid.reshape(-1, n).T
    quad = jnp.sum(flat * linalg.cho_solve(chol, flat), axis=0).reshape(resid.shape[:-1])
    return quad, 2.0 * jnp.sum(jnp.log(jnp.diagonal(chol)))


def log_density(
    chol: Float[Array, "n n"], resid: Float[ArrayLike, "... n"], dim: Float[ArrayLike, ""] | int | None = None
) -> Float[Array, "..."]:
    """`log N(r; 0, L Lᵀ) = −½ (rᵀ (L Lᵀ)⁻¹ r + log det(L Lᵀ) + d log 2π)`, batched over the
    leading axes of `r` (the one Gaussian log-density of the package).

    `d` is `dim`, by default `n`; filters with missing components decouple them (zero
    residual, unit variance) and pass the number of observed components, which makes this
    the marginal density of the observed ones."""
    quad, logdet = quadratic_and_logdet(chol, resid)
    d = chol.shape[-1] if dim is None else dim
    return -0.5 * (quad + logdet + d * math.log(2 * math.pi))


class Gaussian(eqx.Module):
    """`N(mean, cov)`, the distribution of a state or noise vector.

    **Arguments:**

    - `mean`: shape `(n,)`.
    - `cov`: shape `(n, n)`, symmetric positive semidefinite.

    Used as the prior `p(x_0)` of every filter and as the simplest noise law in
    `jdrkf.simulate`. It is a pytree: `jax.vmap` over a batch of Gaussians works.
    """

    mean: Float[Array, " n"]
    cov: Float[Array, "n n"]

    def __init__(self, mean: Float[ArrayLike, " n"], cov: Float[ArrayLike, "n n"]):
        mean = as_float_array("mean", mean, (1,))
        cov = as_float_array("cov", cov, (2,))
        if cov.shape != (mean.shape[0], mean.shape[0]):
            raise ValueError(
                f"cov has shape {tuple(cov.shape)} but mean has shape {tuple(mean.shape)}; "
                f"expected cov of shape ({mean.shape[0]}, {mean.shape[0]})"
            )
        check_covariance("cov", cov)
        dtype = jnp.result_type(mean, cov)
        self.mean = mean.astype(dtype)
        self.cov = cov.astype(dtype)

    @property
    def dim(self) -> int:
        return self.mean.shape[-1]

    def sample(self, key: PRNGKeyArray, shape: tuple[int, ...] = ()) -> Float[Array, "... n"]:
        """Draw samples of shape `shape + (n,)` (PSD square root, so singular `cov` is fine)."""
        z = jax.random.normal(key, shape + (self.dim,), self.mean.dtype)
        return self.mean + z @ linalg.psd_sqrt(self.cov).T

    def log_prob(self, x: Float[ArrayLike, "... n"]) -> Float[Array, "..."]:
        """Log density at `x` (requires positive-definite `cov`)."""
        return log_density(linalg.cholesky(linalg.symmetrize(self.cov)), jnp.asarray(x) - self.mean)

    def kl_divergence(self, other: "Gaussian") -> Float[Array, ""]:
        """`KL(self ‖ other)` in nats."""
        chol_o = linalg.cholesky(linalg.symmetrize(other.cov))
        chol_s = linalg.cholesky(linalg.symmetrize(self.cov))
        tr = jnp.trace(linalg.cho_solve(chol_o, linalg.symmetrize(self.cov)))
        d = other.mean - self.mean
        logdet_o = 2.0 * jnp.sum(jnp.log(jnp.diagonal(chol_o)))
        logdet_s = 2.0 * jnp.sum(jnp.log(jnp.diagonal(chol_s)))
        return 0.5 * (tr + d @ linalg.cho_solve(chol_o, d) - self.dim + logdet_o - logdet_s)

    def gelbrich_distance(self, other: "Gaussian") -> Float[Array, ""]:
        """Gelbrich distance `sqrt(‖μ₁−μ₂‖² + B²(Σ₁, Σ₂))`: the 2-Wasserstein distance
        between the two Gaussians (and a lower bound for any laws with these moments)."""
        d2 = jnp.sum((self.mean - other.mean) ** 2) + linalg.bures_distance_squared(self.cov, other.cov)
        pos = d2 > 0
        return jnp.where(pos, jnp.sqrt(jnp.where(pos, d2, 1.0)), 0.0)
