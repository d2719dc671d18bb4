"""Sampling laws for process and measurement noise (and for `x_0`).

Each law draws one vector per call, `sample(key, t)`, and can split it as
`sample_parts(key, t) -> (nominal, outlier)` with `sample = nominal + outlier`:
`nominal` is what the outlier-free law would have produced with the same random
numbers. Wang & Ye's (2022) clairvoyant TMKF filters the outlier-free measurements
`H x + nominal`.
"""

from __future__ import annotations

import abc
import math
from typing import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
from jax import lax
from jaxtyping import Array, ArrayLike, Float, Int, PRNGKeyArray

from . import linalg
from ._gaussian import log_density, quadratic_and_logdet
from ._validation import as_float_array, check_covariance, check_fraction, check_shape, is_concrete, psd_rtol


class AbstractNoise(eqx.Module):
    """A law to sample noise vectors of dimension `dim` from, at time index `t`."""

    @property
    @abc.abstractmethod
    def dim(self) -> int:
        """Dimension of one draw."""

    @abc.abstractmethod
    def sample_parts(self, key: PRNGKeyArray, t: Int[ArrayLike, ""] = 0) -> tuple[Float[Array, " d"], Float[Array, " d"]]:
        """One draw split into `(nominal, outlier)` parts."""

    def sample(self, key: PRNGKeyArray, t: Int[ArrayLike, ""] = 0) -> Float[Array, " d"]:
        """One draw at time index `t`."""
        nominal, outlier = self.sample_parts(key, t)
        return nominal + outlier

    @property
    @abc.abstractmethod
    def mean(self) -> Float[Array, " d"]:
        """Mean of the law (at `t = 0` for time-varying laws)."""

    @property
    @abc.abstractmethod
    def cov(self) -> Float[Array, "d d"]:
        """Covariance of the law (at `t = 0` for time-varying laws)."""

    def check_horizon(self, num_steps: int) -> None:
        """Eager check that a time-varying law covers `num_steps` steps (no-op here)."""


def sampling_root(cov: Float[Array, "d d"]) -> Float[Array, "d d"]:
    """Symmetric square root `cov^½` used to draw `N(μ, cov) = μ + cov^½ z`.

    Exact for any positive-semidefinite `cov`, singular ones included (the principal
    root of `jdrkf.linalg.psd_sqrt`, which zeroes only round-off negative eigenvalues).
    An indefinite `cov`, `λ_min < −psd_rtol · max|λ|` (the tolerance of the eager
    covariance checks), has no square root: the result is then all NaN, so that draws
    from it are NaN rather than draws from a silently clipped covariance. Concrete
    covariances are rejected earlier, when the law or model is built; this guards
    covariances that arrive traced.
    """
    cov = linalg.symmetrize(cov)
    lam = lax.stop_gradient(jnp.linalg.eigvalsh(cov))
    top = jnp.maximum(jnp.max(jnp.abs(lam)), jnp.finfo(cov.dtype).tiny)
    psd = lam[0] >= -psd_rtol(cov.dtype, cov.shape[-1]) * top
    return jnp.where(psd, linalg.psd_sqrt(cov), jnp.nan)


def _cov_and_mean(cov, mean):
    cov = as_float_array("cov", cov, (2,))
    check_covariance("cov", cov)
    d = cov.shape[0]
    mean = jnp.zeros(d, cov.dtype) if mean is None else as_float_array("mean", mean, (1,))
    check_shape("mean", mean, (d,), f"to match cov ({d}x{d})")
    dtype = jnp.result_type(cov, mean)
    return cov.astype(dtype), mean.astype(dtype)


def _mahalanobis_and_logdet(x, mean, cov):
    """`((x − mean)ᵀ cov⁻¹ (x − mean), log det cov)` for `x` of shape `(..., d)`."""
    return quadratic_and_logdet(linalg.cholesky(linalg.symmetrize(cov)), jnp.asarray(x, cov.dtype) - mean)


class _NominalGaussianNoise(AbstractNoise):
    """Laws built on a nominal `N(mean, cov)` draw (shared fields and moments)."""

    _cov: Float[Array, "d d"]
    _mean: Float[Array, " d"]

    @property
    def dim(self):
        return self._cov.shape[-1]

    @property
    def mean(self):
        return self._mean

    @property
    def cov(self):
        return self._cov

    def _nominal(self, key):
        return self._mean + sampling_root(self._cov) @ jax.random.normal(key, (self.dim,), self._cov.dtype)


class GaussianNoise(_NominalGaussianNoise):
    """`N(mean, cov)` noise (all of it nominal)."""

    def __init__(self, cov: Float[ArrayLike, "d d"], mean: Float[ArrayLike, " d"] | None = None):
        self._cov, self._mean = _cov_and_mean(cov, mean)

    def sample_parts(self, key, t=0):
        return self._nominal(key), jnp.zeros(self.dim, self._cov.dtype)

    def log_prob(self, x: Float[ArrayLike, "... d"], t: Int[ArrayLike, ""] = 0) -> Float[Array, "..."]:
        """Log density `log N(x; mean, cov)` (requires positive-definite `cov`)."""
        return log_density(linalg.cholesky(linalg.symmetrize(self._cov)), jnp.asarray(x, self._cov.dtype) - self._mean)


class MixtureNoise(_NominalGaussianNoise):
    """Contaminated Gaussian `(1 − p) N(μ, R) + p N(μ, k R)` (`k = scale ≥ 1`).

    Drawn as `N(μ, R)` (nominal) plus, with probability `p` for the whole vector, an
    independent `N(0, (k − 1) R)` (outlier); the sum has exactly the mixture law.
    """

    p: Float[Array, ""]
    scale: Float[Array, ""]

    def __init__(self, cov, p, scale, mean=None):
        self._cov, self._mean = _cov_and_mean(cov, mean)
        self.p = check_fraction("p", p).astype(self._cov.dtype)
        scale = as_float_array("scale", scale, (0,))
        if is_concrete(scale) and float(scale) < 1.0:
            raise ValueError(f"scale must be >= 1 (the outlier component is N(0, scale * cov)), got {float(scale)}")
        self.scale = scale.astype(self._cov.dtype)

    @property
    def cov(self):
        return (1.0 - self.p + self.p * self.scale) * self._cov

    def sample_parts(self, key, t=0):
        k1, k2, k3 = jax.random.split(key, 3)
        extra = jnp.sqrt(self.scale - 1.0) * (self._nominal(k2) - self._mean)
        return self._nominal(k1), jnp.where(jax.random.bernoulli(k3, self.p), extra, 0.0)

    def log_prob(self, x: Float[ArrayLike, "... d"], t: Int[ArrayLike, ""] = 0) -> Float[Array, "..."]:
        """Log density `log((1 − p) N(x; μ, R) + p N(x; μ, k R))` (positive-definite `R`)."""
        quad, logdet = _mahalanobis_and_logdet(x, self._mean, self._cov)
        d = self.dim
        base = -0.5 * (logdet + d * math.log(2 * math.pi))
        nominal = base - 0.5 * quad
        outlier = base - 0.5 * (quad / self.scale + d * jnp.log(self.scale))
        return jnp.logaddexp(jnp.log1p(-self.p) + nominal, jnp.log(self.p) + outlier)


class OutlierNoise(_NominalGaussianNoise):
    """`N(μ, R)` plus, independently in each channel with probability `p`, an outlier
    `±magnitude` (sign equiprobable): the outliers of Wang & Ye (2022), Sec. VII (`magnitude = 100`)."""

    p: Float[Array, ""]
    magnitude: Float[Array, ""]

    def __init__(self, cov, p, magnitude, mean=None):
        self._cov, self._mean = _cov_and_mean(cov, mean)
        self.p = check_fraction("p", p).astype(self._cov.dtype)
        self.magnitude = as_float_array("magnitude", magnitude, (0,)).astype(self._cov.dtype)

    @property
    def cov(self):
        return self._cov + self.p * self.magnitude**2 * jnp.eye(self.dim, dtype=self._cov.dtype)

    def sample_parts(self, key, t=0):
        k1, k2, k3 = jax.random.split(key, 3)
        hit = jax.random.bernoulli(k2, self.p, (self.dim,))
        sign = jnp.where(jax.random.bernoulli(k3, 0.5, (self.dim,)), 1.0, -1.0)
        return self._nominal(k1), jnp.where(hit, sign * self.magnitude, 0.0).astype(self._cov.dtype)


class StudentTNoise(_NominalGaussianNoise):
    """Multivariate Student-t with `dof > 2` degrees of freedom, scaled so that its
    covariance is `cov`: `μ + sqrt((ν − 2)/g) · cov^½ z`, `g ~ χ²_ν`, `z ~ N(0, I)`.
    Heavy-tailed but outlier-free in the `sample_parts` sense (all of it nominal)."""

    dof: Float[Array, ""]

    def __init__(self, cov, dof, mean=None):
        self._cov, self._mean = _cov_and_mean(cov, mean)
        dof = as_float_array("dof", dof, (0,))
        if is_concrete(dof) and float(dof) <= 2.0:
            raise ValueError(f"dof must be > 2 for the covariance to exist, got {float(dof)}")
        self.dof = dof.astype(self._cov.dtype)

    def sample_parts(self, key, t=0):
        k1, k2 = jax.random.split(key)
        g = 2.0 * jax.random.gamma(k2, self.dof / 2.0, dtype=self._cov.dtype)
        x = self._mean + jnp.sqrt((self.dof - 2.0) / g) * (self._nominal(k1) - self._mean)
        return x, jnp.zeros_like(x)

    def log_prob(self, x: Float[ArrayLike, "... d"], t: Int[ArrayLike, ""] = 0) -> Float[Array, "..."]:
        """Log density of the multivariate t with `ν = dof`, location `μ` and scale
        matrix `Σ = (ν − 2)/ν · cov`: `log Γ((ν+d)/2) − log Γ(ν/2) − (d/2) log(νπ)
        − ½ log det Σ − ((ν+d)/2) log(1 + δ/ν)`, `δ = (x − μ)ᵀ Σ⁻¹ (x − μ)`."""
        nu, d = self.dof, self.dim
        ratio = (nu - 2.0) / nu
        quad, logdet = _mahalanobis_and_logdet(x, self._mean, self._cov)
        delta = quad / ratio
        logdet_scale = logdet + d * jnp.log(ratio)
        return (
            jax.scipy.special.gammaln(0.5 * (nu + d))
            - jax.scipy.special.gammaln(0.5 * nu)
            - 0.5 * d * jnp.log(nu * math.pi)
            - 0.5 * logdet_scale
            - 0.5 * (nu + d) * jnp.log1p(delta / nu)
        )


class UQuadraticNoise(AbstractNoise):
    """Independent U-quadratic components on the box `[low, high]` (Jang, Hakobyan & Yang 2025, Sec. 5.2):
    density `α (x − β)²`, `α = 12/(b − a)³`, `β = (a + b)/2`; variance `3 (b − a)²/20`.
    Sampled by the inverse CDF `x = β + cbrt(3u/α − (β − a)³)`."""

    low: Float[Array, " d"]
    high: Float[Array, " d"]

    def __init__(self, low, high):
        low = as_float_array("low", low, (1,))
        high = as_float_array("high", high, (1,))
        if low.shape != high.shape:
            raise ValueError(f"low has shape {tuple(low.shape)} but high has shape {tuple(high.shape)}")
        if is_concrete(low) and is_concrete(high) and not bool(jnp.all(high > low)):
            raise ValueError("high must exceed low in every component")
        dtype = jnp.result_type(low, high)
        self.low, self.high = low.astype(dtype), high.astype(dtype)

    @property
    def dim(self):
        return self.low.shape[-1]

    @property
    def mean(self):
        return 0.5 * (self.low + self.high)

    @property
    def cov(self):
        return jnp.diag(0.15 * (self.high - self.low) ** 2)

    def sample_parts(self, key, t=0):
        a, b = self.low, self.high
        alpha = 12.0 / (b - a) ** 3
        beta = 0.5 * (a + b)
        u = jax.random.uniform(key, (self.dim,), a.dtype)
        x = beta + jnp.cbrt(3.0 * u / alpha - (beta - a) ** 3)
        return x, jnp.zeros_like(x)

    def log_prob(self, x: Float[ArrayLike, "... d"], t: Int[ArrayLike, ""] = 0) -> Float[Array, "..."]:
        """Log density `Σ_i log(α_i (x_i − β_i)²)` on the box, `−inf` outside."""
        a, b = self.low, self.high
        x = jnp.asarray(x, a.dtype)
        alpha = 12.0 / (b - a) ** 3
        beta = 0.5 * (a + b)
        inside = jnp.all((x >= a) & (x <= b), axis=-1)
        return jnp.where(inside, jnp.sum(jnp.log(alpha) + 2.0 * jnp.log(jnp.abs(x - beta)), axis=-1), -jnp.inf)


class ScaledNoise(AbstractNoise):
    """Time-varying scale of a base law: covariance `a(t) · cov` (`R_t = a(t) R`).

    Draws `μ + sqrt(a(t)) (x − μ)` from a base draw `x`. `scale` is an array of
    length `T` (indexed by `t`) or a function `t -> a(t)` (traceable).
    """

    base: AbstractNoise
    scale: Float[Array, " T"] | Callable

    def __init__(self, base: AbstractNoise, scale: Float[ArrayLike, " T"] | Callable):
        if not isinstance(base, AbstractNoise):
            raise ValueError(f"base must be a jdrkf noise law, got {type(base).__name__}")
        if not callable(scale):
            scale = as_float_array("scale", scale, (1,)).astype(base.cov.dtype)
            if is_concrete(scale) and bool(jnp.any(scale < 0)):
                raise ValueError("scale must be nonnegative (it multiplies a covariance)")
        self.base, self.scale = base, scale

    def check_horizon(self, num_steps: int) -> None:
        if not callable(self.scale) and self.scale.shape[0] < num_steps:
            raise ValueError(f"scale has {self.scale.shape[0]} entries but {num_steps} steps were requested")
        self.base.check_horizon(num_steps)

    @property
    def dim(self):
        return self.base.dim

    @property
    def mean(self):
        return self.base.mean

    def _a(self, t):
        return self.scale(t) if callable(self.scale) else jnp.asarray(self.scale)[t]

    @property
    def cov(self):
        return self._a(0) * self.base.cov

    def sample_parts(self, key, t=0):
        nominal, outlier = self.base.sample_parts(key, t)
        root = jnp.sqrt(self._a(t))
        return self.base.mean + root * (nominal - self.base.mean), root * outlier

    def log_prob(self, x: Float[ArrayLike, "... d"], t: Int[ArrayLike, ""] = 0) -> Float[Array, "..."]:
        """Log density at step `t`: `log p_base(μ + (x − μ)/√a(t)) − (d/2) log a(t)`
        (requires `a(t) > 0` and a base law with a density)."""
        if not hasattr(self.base, "log_prob"):
            raise ValueError(f"the base law ({type(self.base).__name__}) has no density")
        a = self._a(t)
        mean = self.base.mean
        inner = mean + (jnp.asarray(x, mean.dtype) - mean) / jnp.sqrt(a)
        return self.base.log_prob(inner, t) - 0.5 * self.dim * jnp.log(a)


class UniformPerturbation(eqx.Module):
    """Random additive perturbation of the transition matrix, `F_t = F + α Δ_t D`
    with `Δ_t ~ U[−1, 1]` i.i.d. per step (Wang & Ye 2022, Sec. VII: `D = [[0, 1], [0, 0]]`)."""

    direction: Float[Array, "n n"]
    alpha: Float[Array, ""]

    def __init__(self, direction, alpha):
        self.direction = as_float_array("direction", direction, (2,))
        self.alpha = as_float_array("alpha", alpha, (0,)).astype(self.direction.dtype)

    def __call__(self, key: PRNGKeyArray, t: Int[ArrayLike, ""]) -> Float[Array, "n n"]:
        delta = jax.random.uniform(key, (), self.direction.dtype, -1.0, 1.0)
        return self.alpha * delta * self.direction
