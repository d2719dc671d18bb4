"""Multivariate Gaussian as a pytree."""

from __future__ import annotations

import math

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float, PRNGKeyArray

from . import linalg
from ._validation import as_float_array, check_covariance


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
        chol = jnp.linalg.cholesky(linalg.symmetrize(self.cov))
        diff = jnp.asarray(x) - self.mean
        z = jax.scipy.linalg.solve_triangular(chol, diff[..., None], lower=True)[..., 0]
        logdet = 2.0 * jnp.sum(jnp.log(jnp.diagonal(chol)))
        return -0.5 * (jnp.sum(z**2, axis=-1) + logdet + self.dim * math.log(2 * math.pi))

    def kl_divergence(self, other: "Gaussian") -> Float[Array, ""]:
        """`KL(self ‖ other)` in nats."""
        chol = jnp.linalg.cholesky(linalg.symmetrize(other.cov))
        a = jax.scipy.linalg.solve_triangular(chol, linalg.symmetrize(self.cov), lower=True)
        tr = jnp.trace(jax.scipy.linalg.solve_triangular(chol, a.T, lower=True))
        d = jax.scipy.linalg.solve_triangular(chol, other.mean - self.mean, lower=True)
        logdet_o = 2.0 * jnp.sum(jnp.log(jnp.diagonal(chol)))
        logdet_s = jnp.linalg.slogdet(self.cov)[1]
        return 0.5 * (tr + jnp.sum(d**2) - self.dim + logdet_o - logdet_s)

    def gelbrich_distance(self, other: "Gaussian") -> Float[Array, ""]:
        """Gelbrich distance `sqrt(‖μ₁−μ₂‖² + B²(Σ₁, Σ₂))`: the 2-Wasserstein distance
        between the two Gaussians (and a lower bound for any laws with these moments)."""
        d2 = jnp.sum((self.mean - other.mean) ** 2) + linalg.bures_distance_squared(self.cov, other.cov)
        pos = d2 > 0
        return jnp.where(pos, jnp.sqrt(jnp.where(pos, d2, 1.0)), 0.0)
