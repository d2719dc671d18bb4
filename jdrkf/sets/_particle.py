"""Worst-case priors and likelihoods of the distributionally robust particle filter of
Wang (2022), "Distributionally Robust State Estimation for Nonlinear Systems", IEEE TSP:
Step 2 (Methods 1–2) and Step 3 (Methods 3–5) of Algorithm 2, as used by
`jdrkf.DRParticleFilter`.

Each is an `eqx.Module` whose radii and inflation are array leaves (reached by
`eqx.filter_grad` and `eqx.tree_at`), checked eagerly when concrete and by `valid()` when
traced; integer counts are static. The maximum-entropy problems themselves are solved by
`maxent_kl_solve` (Theorem 6), `maxent_transport_solve` (Theorem 5) and
`maxent_wasserstein_continuous` (Theorem 3).
"""

from __future__ import annotations

import abc
import math
from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
from jax import lax
from jax.scipy.special import logsumexp
from jaxtyping import Array, ArrayLike, Bool, Float, PRNGKeyArray

from .. import linalg
from .._gaussian import log_density
from .._nonlinear import NonlinearModel
from .._validation import check_positive_int, check_scalar, in_range
from ._maxent import (
    MaxEntContinuous,
    maxent_kl_solve,
    maxent_transport_solve,
    maxent_wasserstein_continuous,
)

__all__ = [
    "AbstractParticleLikelihood",
    "AbstractParticlePrior",
    "AugmentedWassersteinLikelihood",
    "InflatedLikelihood",
    "ParticleKL",
    "ParticleWasserstein",
    "ParticleWassersteinSample",
    "WassersteinLikelihood",
]


def _map_all(fn, *args, default_batch):
    """Default particle mapping outside the filter: `vmap` over all particles, or
    `lax.map` in batches of `default_batch` (one at a time for `1`)."""
    if default_batch is None:
        return jax.vmap(fn)(*args)
    return lax.map(lambda a: fn(*a), args, batch_size=None if default_batch == 1 else default_batch)


# --------------------------------------------------------------------------- the solves


def _pairwise(a: Float[Array, "N d"], b: Float[Array, "M d"]) -> Float[Array, "N M"]:
    """Euclidean distances `‖a_i − b_j‖`, with a zero (and a zero gradient) on coincident points."""
    d2 = jnp.sum((a[:, None, :] - b[None, :, :]) ** 2, axis=-1)
    pos = d2 > 0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, d2, 1.0)), 0.0)


def _radial_points(key, support, q, radius, num_points):
    """Importance-sampling discretization of Theorem 3 around the atoms `support`.

    Points `z_k = x_{i_k} + ρ_k u_k` with `i_k ~ a = (q + 1/N)/2`, `u_k` uniform on the
    sphere and `ρ_k ~ Gamma(d, rate d/(2θ))` (mean `2θ`, twice the average transport
    distance the budget allows); quadrature weights `w_k = 1/(K g(z_k))` with `g` the
    mixture density. This resolves the worst case at every scale of `θ` (uniform points
    in a box do not when `θ` is small compared with the box)."""
    num, dim = support.shape
    dtype = support.dtype
    k_atom, k_dir, k_rad = jax.random.split(key, 3)
    log_a = jnp.log(0.5 * q + 0.5 / num)
    atoms = jax.random.categorical(k_atom, log_a, shape=(num_points,))
    z = jax.random.normal(k_dir, (num_points, dim), dtype)
    u = z / jnp.linalg.norm(z, axis=1, keepdims=True)
    tiny = jnp.asarray(1e-12, dtype) * (1.0 + jnp.max(jnp.abs(support)))
    scale = jnp.maximum(2.0 * radius / dim, tiny)
    rho = jax.random.gamma(k_rad, jnp.asarray(float(dim), dtype), (num_points,), dtype) * scale
    pts = support[atoms] + rho[:, None] * u
    # log g_r(z) = −ρ/s − d log s − log Γ(d) − log S_{d−1},  S_{d−1} = 2π^{d/2}/Γ(d/2).
    log_sphere = math.log(2.0) + 0.5 * dim * math.log(math.pi) - math.lgamma(0.5 * dim)
    log_g = (
        logsumexp(log_a - _pairwise(pts, support) / scale, axis=1)
        - dim * jnp.log(scale)
        - math.lgamma(dim)
        - log_sphere
    )
    return pts, jnp.exp(-log_g) / num_points


def _continuous(q, support, radius, key, num_points) -> MaxEntContinuous:
    """Theorem 3 (`maxent_wasserstein_continuous`) on the points of `_radial_points`.
    Inputs carry no gradient: the solver has implicit derivatives, but its quadrature
    points are drawn with a scale set by the radius, so Methods 2 and 4 are left
    undifferentiated."""
    q, support, radius = lax.stop_gradient((q, support, radius))
    pts, w = _radial_points(key, support, q, radius, num_points)
    return maxent_wasserstein_continuous(q, support, radius, points=pts, weights=w)


def _continuous_loglik(ys: Float[Array, "R m"], y: Float[Array, " m"], radius, key, num_points) -> Float[Array, ""]:
    """Method 4: `log p*(y)` of the continuous Theorem-3 worst case around the uniform
    nominal on the likelihood particles `{y^r}` (eq. 16, evaluated at `y` wherever it is)."""
    num = ys.shape[0]
    q = jnp.full((num,), 1.0 / num, ys.dtype)
    return _continuous(q, ys, radius, key, num_points).log_density(y)


def _augmented_loglik(ys: Float[Array, "R m"], y: Float[Array, " m"], radius) -> Float[Array, ""]:
    """Method 5: `log p*(y)`, the mass that the discrete Theorem-5 worst case puts on `y`
    when `y` is appended to the support `{y^r}` of the uniform nominal: with
    `c_r = (‖y^r − y‖, ‖y^r − y^s‖_s)` and the dual `v₀` of `maxent_transport_solve`,
    `p*(y) = Σ_r (1/R) softmax(−v₀ c_r)_0` (eq. 28), summed in the log domain."""
    num = ys.shape[0]
    dtype = ys.dtype
    support_p = jnp.concatenate([y[None], ys])
    cost = _pairwise(ys, support_p)
    q = jnp.full((num,), 1.0 / num, dtype)
    v0 = maxent_transport_solve(q, cost, radius).dual
    return logsumexp(jax.nn.log_softmax(-v0 * cost, axis=1)[:, 0]) - math.log(num)


def gaussian_loglik_particles(model: NonlinearModel, y, hx, observed):
    """`log N(y; h(x_i), R)` for all particles with ONE Cholesky of `R` (rows of `y` that
    `observed` marks missing decoupled: zero residual, unit variance, the observed count as
    the dimension): all the residuals enter one solve (`log_density`), so no batched LAPACK
    call under `vmap` over particles. The bootstrap filter's likelihood, and Method 3's at
    `θ = 1` (bitwise)."""
    r = model.R
    if observed is not None:
        obs_f = observed.astype(r.dtype)
        r = r * (obs_f[:, None] * obs_f[None, :]) + jnp.diag(1.0 - obs_f)
        resid = jnp.where(observed[None, :], y[None, :] - hx, jnp.zeros((), hx.dtype))
        num_obs = jnp.sum(obs_f)
    else:
        resid = y[None, :] - hx
        num_obs = jnp.asarray(y.shape[0], r.dtype)
    return log_density(linalg.cholesky(linalg.symmetrize(r)), resid, num_obs)


def skip_incomplete(loglik_fn, y, observed):
    """Per-particle log-likelihoods `loglik_fn(y)`, zero for an observation with a missing
    entry (non-Gaussian noise laws are not marginalized)."""
    if observed is None:
        return loglik_fn(y)
    complete = jnp.all(observed)
    ll = loglik_fn(jnp.where(observed, y, jnp.zeros((), y.dtype)))
    return jnp.where(complete, ll, jnp.zeros_like(ll))


def _inflated_loglik(model: NonlinearModel, particles, y, t, theta):
    """Method 3: `log p_v(y − h(x^j))` for the additive noise law rescaled about its mean,
    `v → μ + √θ (v − μ)` (covariance `θR`): `log p_v(μ + (y − h − μ)/√θ) − (m/2) log θ`,
    `m` the number of components. At `θ = 1` the factor `1/√θ − 1` is exactly
    zero, so the values are bitwise those of `BootstrapPF`."""
    mu = model.measurement_mean
    shrink = 1.0 / jnp.sqrt(theta) - 1.0
    num_obs = jnp.asarray(y.shape[0], theta.dtype)

    def one(x):
        y_eff = y + shrink * (y - model.h(x, t) - mu)
        return model.measurement_logpdf(y_eff, x, t)

    return jax.vmap(one)(particles) - 0.5 * num_obs * jnp.log(theta)


def _likelihood_particles(
    model: NonlinearModel, particles: Float[Array, "M n"], key: PRNGKeyArray, t, num: int
) -> Float[Array, "M R m"]:
    """Nominal likelihood particles `y^r | x^j = h(x^j, v^r)` (Algorithm 2, lines 10–15):
    `(M, R, m)`, with independent `v^r ~` the model's measurement-noise law for every particle."""
    m = particles.shape[0]
    v = model.sample_measurement_noise(key, t, shape=(m, num))
    return jax.vmap(jax.vmap(lambda x, v: model.observe(x, v, t), (None, 0)))(particles, v)


def _observed_only(y, ys, observed):
    """Zero the missing components of `y` and of the likelihood particles `ys`, so
    that Euclidean distances use the observed components only."""
    return jnp.where(observed, y, 0.0), jnp.where(observed, ys, 0.0)


# --------------------------------------------------------------------------- priors (Step 2)


class AbstractParticlePrior(eqx.Module):
    """Step 2 of Wang (2022), Algorithm 2: the worst-case prior particles, the least
    informative (maximum-entropy) law within an ambiguity ball around the propagated,
    weighted particles (ambiguity in the process model)."""

    @abc.abstractmethod
    def worst_case(
        self,
        particles: Float[Array, "N n"],
        log_weights: Float[Array, " N"],
        key: PRNGKeyArray | None = None,
        num_particles: int | None = None,
    ) -> tuple[Float[Array, "M n"], Float[Array, " M"]]:
        """The worst-case prior `(particles, normalized log_weights)` around the cloud
        `(particles, log_weights)` (normalized log-weights); `key` and `num_particles` (`M`,
        default `N`) are used by samplers only."""

    @abc.abstractmethod
    def valid(self) -> Bool[Array, ""]:
        """Whether the parameters are in range (checked eagerly when concrete; this is the
        traced check, which filters turn into `RESULTS.invalid_hyperparameter`)."""


class ParticleKL(AbstractParticlePrior):
    """KL worst-case prior: Wang (2022), Method 1 with Theorem 6. The particles are kept and
    reweighted to the maximum-entropy law within `KL(p‖q) ≤ radius` of their weights `q`,
    `p ∝ q^β` (`β ∈ [0, 1]` from `maxent_kl_solve`; uniform once `radius ≥ KL(u‖q)`, no
    effect on uniform weights, i.e. right after resampling).

    **Arguments:**

    - `radius`: the KL radius, `>= 0` (array: differentiable, implicit derivatives).
    """

    radius: Float[Array, ""]

    def __init__(self, radius: Float[ArrayLike, ""]):
        self.radius = check_scalar("radius", radius)

    def valid(self) -> Bool[Array, ""]:
        """`radius >= 0`."""
        return in_range(self.radius, 0.0)

    def worst_case(self, particles, log_weights, key=None, num_particles=None):
        """Theorem 6: the same particles with log-weights `β log q − logsumexp(β log q)`."""
        q = jnp.exp(log_weights)
        radius = self.radius.astype(particles.dtype)
        beta = maxent_kl_solve(q, radius).dual
        z = jnp.where(jnp.isfinite(log_weights), beta * log_weights, -jnp.inf)
        return particles, z - logsumexp(z)


class ParticleWasserstein(AbstractParticlePrior):
    """Wasserstein worst-case prior on the particles themselves: Wang (2022), Method 1 with
    Theorem 5. The maximum-entropy coupling with row marginal `q` (the weights) on the
    support `{x^i}`, cost `‖x^i − x^j‖` and transport budget `radius`; the new weights are
    its column marginal `p_j = Σ_i q_i softmax_j(−v₀ c_i·)` (`maxent_transport_solve`).

    **Arguments:**

    - `radius`: the transport budget (W₁ radius), `>= 0` (array: differentiable).
    """

    radius: Float[Array, ""]

    def __init__(self, radius: Float[ArrayLike, ""]):
        self.radius = check_scalar("radius", radius)

    def valid(self) -> Bool[Array, ""]:
        """`radius >= 0`."""
        return in_range(self.radius, 0.0)

    def worst_case(self, particles, log_weights, key=None, num_particles=None):
        """Theorem 5 with support = the particles: the same particles, new weights."""
        q = jnp.exp(log_weights)
        radius = self.radius.astype(particles.dtype)
        cost = _pairwise(particles, particles)
        v0 = maxent_transport_solve(q, cost, radius).dual
        return particles, logsumexp(log_weights[:, None] + jax.nn.log_softmax(-v0 * cost, axis=1), axis=0)


class ParticleWassersteinSample(AbstractParticlePrior):
    """Sampled Wasserstein worst-case prior: Wang (2022), Method 2 with Theorem 3. `M`
    fresh particles, weights `1/M`, drawn from the continuous maximum-entropy density
    within `W₁ ≤ radius` of the weighted particles (`maxent_wasserstein_continuous` on
    `num_integration_points` Monte Carlo points importance-sampled around the atoms; a
    cell `j ~ q`, then a point of that cell).

    **Arguments:**

    - `radius`: the W₁ radius, `> 0` (a density needs room). No gradient reaches it
      (the integration points are drawn at its scale).
    - `num_integration_points`: Monte Carlo points of the Theorem-3 solve (static).
    """

    radius: Float[Array, ""]
    num_integration_points: int = eqx.field(static=True)

    def __init__(self, radius: Float[ArrayLike, ""], num_integration_points: int = 1000):
        self.radius = check_scalar("radius", radius, strict=True, hint=" (Method 2 samples from a continuous density)")
        self.num_integration_points = check_positive_int("num_integration_points", num_integration_points)

    def valid(self) -> Bool[Array, ""]:
        """`radius > 0`."""
        return in_range(self.radius, 0.0, lower_open=True)

    def worst_case(self, particles, log_weights, key=None, num_particles=None):
        """Method 2: `num_particles` (default `N`) draws with weights `1/num_particles`;
        `key` is split into the integration points' key and the draws' key."""
        if key is None:
            raise ValueError("ParticleWassersteinSample.worst_case needs a PRNG key")
        num = particles.shape[0] if num_particles is None else num_particles
        q = jnp.exp(log_weights)
        radius = self.radius.astype(particles.dtype)
        k_points, k_draw = jax.random.split(key)
        sol = _continuous(q, particles, radius, k_points, self.num_integration_points)
        new_x, _ = sol.sample(k_draw, num)
        return new_x, jnp.full((num,), -math.log(num), log_weights.dtype)


# ---------------------------------------------------------------------- likelihoods (Step 3)


MapParticles = Callable[..., Array]
"""`map_particles(fn, *args, default_batch)`: maps `fn` over the leading (particle) axis of
`args`; the filter's batching (`DRParticleFilter(batch_size=...)`)."""


class AbstractParticleLikelihood(eqx.Module):
    """Step 3 of Wang (2022), Algorithm 2: the worst-case likelihood `p*(y | x^j)` of every
    particle (ambiguity in the measurement model)."""

    def likelihood_particles(
        self, model: NonlinearModel, particles: Float[Array, "M n"], key: PRNGKeyArray, t
    ) -> Float[Array, "M R m"] | None:
        """The likelihood particles `y^r = h(x^j, v^r)`, `(M, R, m)`, that the likelihood is
        built from, or `None` when it needs none (the default)."""
        return None

    @abc.abstractmethod
    def loglik(
        self,
        model: NonlinearModel,
        particles: Float[Array, "M n"],
        ys: Float[Array, "M R m"] | None,
        y: Float[Array, " m"],
        t,
        key: PRNGKeyArray | None = None,
        observed=None,
        map_particles: MapParticles | None = None,
    ) -> Float[Array, " M"]:
        """`log p*(y | x^j)` for every particle, from `ys = likelihood_particles(...)`.
        `observed` (boolean `(m,)`) marks the components of `y` that are present; an
        all-missing `y` gives zeros. `key` draws any Monte Carlo points;
        `map_particles(fn, *args, default_batch)` maps per-particle solves (default:
        `vmap`, or `lax.map` in batches of `default_batch`)."""

    @abc.abstractmethod
    def valid(self) -> Bool[Array, ""]:
        """Whether the parameters are in range (checked eagerly when concrete; this is the
        traced check, which filters turn into `RESULTS.invalid_hyperparameter`)."""

    def check_model(self, model: NonlinearModel) -> None:
        """Raise a `ValueError` if the likelihood cannot be used with `model`."""


class InflatedLikelihood(AbstractParticleLikelihood):
    """Inflated likelihood: Wang (2022), Method 3. The additive measurement-noise law is
    rescaled about its mean to covariance `θR`, `v → μ + √θ (v − μ)` (for Gaussian noise
    `p*(y | x) = N(y; h(x) + μ, θR)`), which flattens the weights as a hedge against a
    wrong likelihood. Additive noise only (`model.additive=True`).

    **Arguments:**

    - `inflation`: `θ > 0` (the paper takes `θ ≥ 1`, the authors' code `θ = 5`; `θ = 1` is
      the nominal likelihood, bitwise `BootstrapPF`'s). Array: differentiable.

    Missing components: the Gaussian marginal of the observed ones (Gaussian noise); for
    other noise laws an incomplete `y` leaves the weights unchanged.
    """

    inflation: Float[Array, ""]

    def __init__(self, inflation: Float[ArrayLike, ""] = 5.0):
        self.inflation = check_scalar("inflation", inflation, strict=True)

    def valid(self) -> Bool[Array, ""]:
        """`inflation > 0`."""
        return in_range(self.inflation, 0.0, lower_open=True)

    def check_model(self, model: NonlinearModel) -> None:
        if not model.additive:
            raise ValueError(
                "InflatedLikelihood (Method 3) needs additive measurement noise (model.additive=True); "
                "use WassersteinLikelihood or AugmentedWassersteinLikelihood (Methods 4-5) for additive=False"
            )

    def loglik(self, model, particles, ys, y, t, key=None, observed=None, map_particles=None):
        """`log p_v(y − h(x^j))` with the law's covariance `θR` (`ys`, `key` unused)."""
        theta = self.inflation.astype(particles.dtype)
        if model.measurement_noise is None:  # N(y; h(x), θR)
            hx = jax.vmap(lambda xi: model.h(xi, t))(particles)
            scaled = eqx.tree_at(lambda m: m.R, model, theta * model.R)
            return gaussian_loglik_particles(scaled, y, hx, observed)
        return skip_incomplete(lambda y: _inflated_loglik(model, particles, y, t, theta), y, observed)


class WassersteinLikelihood(AbstractParticleLikelihood):
    """Continuous Wasserstein worst-case likelihood: Wang (2022), Method 4 with Theorem 3.
    For every particle `x^j`, `R` likelihood particles `y^r = h(x^j, v^r)` are drawn from
    the model's noise law (additive or not), and `p*(y | x^j)` is the density at `y` of the
    maximum-entropy density within `W₁ ≤ radius` of their uniform law (eq. 16).

    **Arguments:**

    - `radius`: the W₁ radius, `> 0`. No gradient reaches it (the integration points
      are drawn at its scale).
    - `num_particles`: `R` (static).
    - `num_integration_points`: Monte Carlo points of each Theorem-3 solve (static),
      importance-sampled around the likelihood particles.

    One Newton solve per particle and step (run one particle at a time by default; see
    `DRParticleFilter(batch_size=...)`). Distances use the observed components only.
    """

    radius: Float[Array, ""]
    num_particles: int = eqx.field(static=True)
    num_integration_points: int = eqx.field(static=True)

    def __init__(self, radius: Float[ArrayLike, ""] = 0.1, num_particles: int = 50, num_integration_points: int = 1000):
        self.radius = check_scalar("radius", radius, strict=True, hint=" (Method 4 needs a density)")
        self.num_particles = check_positive_int("num_particles", num_particles)
        self.num_integration_points = check_positive_int("num_integration_points", num_integration_points)

    def valid(self) -> Bool[Array, ""]:
        """`radius > 0`."""
        return in_range(self.radius, 0.0, lower_open=True)

    def likelihood_particles(self, model, particles, key, t):
        return _likelihood_particles(model, particles, key, t, self.num_particles)

    def loglik(self, model, particles, ys, y, t, key=None, observed=None, map_particles=None):
        """Eq. (16) at `y` around each particle's `ys[j]`; `key` draws the integration
        points (one set per particle)."""
        if key is None:
            raise ValueError("WassersteinLikelihood.loglik needs a PRNG key (its integration points)")
        map_particles = _map_all if map_particles is None else map_particles
        radius = self.radius.astype(ys.dtype)
        if observed is not None:
            y, ys = _observed_only(y, ys, observed)
        keys = jax.random.split(key, ys.shape[0])
        fn = lambda yr, k: _continuous_loglik(yr, y, radius, k, self.num_integration_points)
        ll = map_particles(fn, ys, keys, default_batch=1)
        if observed is not None:
            ll = jnp.where(jnp.any(observed), ll, jnp.zeros_like(ll))
        return ll


class AugmentedWassersteinLikelihood(AbstractParticleLikelihood):
    """Augmented-support Wasserstein worst-case likelihood: Wang (2022), Method 5 with
    Theorem 5. For every particle `x^j`, `R` likelihood particles `y^r = h(x^j, v^r)` are
    drawn from the model's noise law (additive or not), `y` is appended to their support,
    and `p*(y | x^j)` is the mass that the discrete maximum-entropy coupling (transport
    budget `radius`, cost `‖·‖`) puts on `y` (eq. 28): a probability mass, not a density.

    **Arguments:**

    - `radius`: the transport budget, `>= 0` (array: differentiable; beyond the largest
      useful budget every row is uniform and `p* = 1/(R + 1)`).
    - `num_particles`: `R` (static).

    Distances use the observed components only.
    """

    radius: Float[Array, ""]
    num_particles: int = eqx.field(static=True)

    def __init__(self, radius: Float[ArrayLike, ""] = 0.1, num_particles: int = 50):
        self.radius = check_scalar("radius", radius)
        self.num_particles = check_positive_int("num_particles", num_particles)

    def valid(self) -> Bool[Array, ""]:
        """`radius >= 0`."""
        return in_range(self.radius, 0.0)

    def likelihood_particles(self, model, particles, key, t):
        return _likelihood_particles(model, particles, key, t, self.num_particles)

    def loglik(self, model, particles, ys, y, t, key=None, observed=None, map_particles=None):
        """Eq. (28): the mass on `y` of each particle's augmented Theorem-5 worst case
        (`key` unused)."""
        map_particles = _map_all if map_particles is None else map_particles
        radius = self.radius.astype(ys.dtype)
        if observed is not None:
            y, ys = _observed_only(y, ys, observed)
        ll = map_particles(lambda yr: _augmented_loglik(yr, y, radius), ys, default_batch=None)
        if observed is not None:
            ll = jnp.where(jnp.any(observed), ll, jnp.zeros_like(ll))
        return ll
