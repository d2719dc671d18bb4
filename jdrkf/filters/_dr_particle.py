"""Distributionally robust particle filter of Wang (2022), "Distributionally Robust
State Estimation for Nonlinear Systems", IEEE TSP: Algorithm 2 with the
worst-case prior particles of Methods 1–2, the worst-case likelihoods of Methods 3–5
and the outlier treatment of Methods 6–7.

Every step runs the five steps of Algorithm 2:

1. propagate the particles through `f` with sampled process noise (exactly as
   `BootstrapPF`, same keys);
2. worst-case prior particles (`prior`): `"none"`, Method 1 reweighting of the
   propagated particles (support = the particles themselves) by Theorem 6 (`"kl"`,
   `p ∝ q^β`) or Theorem 5 (`"wasserstein"`), or Method 2 (`"wasserstein_sample"`: `N`
   fresh particles drawn from the continuous Theorem-3 density, weights `1/N`);
3. worst-case likelihood `p*(y | x^j)` (`likelihood`): Method 3 (`"inflate"`: the
   additive noise law with covariance `θR`, i.e. `v → μ + √θ (v − μ)`), or, from `R`
   likelihood particles `y^r = h(x^j, v^r)` per particle (any noise, additive or not),
   Method 4 (`"wasserstein"`: the continuous Theorem-3 worst case around the `y^r`,
   evaluated at `y`) or Method 5 (`"wasserstein_augmented"`: `y` appended to the
   support, discrete Theorem 5, the mass it receives);
4. Methods 6–7 (`outlier`): `y` is an outlier when `max_j p*(y | x^j) ≤ ε`; it is then
   dropped (`"drop"`: weights unchanged, the authors' gating with `ε = 1e-6`) or
   replaced by the likelihood particle of the most likely prior particle that is
   nearest to `y` (`"nearest"`); weights `u_j ← u_j p*(y | x^j)`, normalized;
5. resampling when `ESS < ess_threshold · N` (as `BootstrapPF`).

The estimate is the weighted mean before resampling.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
from jax import lax
from jax.scipy.special import logsumexp
from jaxtyping import Array, ArrayLike, Float, PRNGKeyArray

from .._gaussian import Gaussian
from .._nonlinear import NonlinearModel
from .._validation import as_float_array, check_positive_int, in_range, is_concrete
from ..sets._maxent import maxent_kl_solve, maxent_transport_solve, maxent_wasserstein_continuous
from . import _resampling
from ._base import DEFAULT_OUTPUTS, RESULTS, AbstractFilter, StepOutput
from ._particle import (
    ParticleState,
    check_resampling_gradient,
    gaussian_loglik_particles,
    particle_moments,
    skip_incomplete,
    weigh_and_resample,
)

__all__ = ["DRParticleFilter"]

_PRIORS = ("none", "kl", "wasserstein", "wasserstein_sample")
_LIKELIHOODS = ("inflate", "wasserstein", "wasserstein_augmented")
_OUTLIERS = (None, "drop", "nearest")

# Extra randomness (beyond BootstrapPF's) comes from `fold_in(key, tag)` so that the
# bootstrap keys are untouched: with prior="none", likelihood="inflate" and no
# "nearest" treatment the filter draws exactly BootstrapPF's random numbers.
_TAG_PRIOR = 0x5052  # Method 2 sampling
_TAG_LIKELIHOOD = 0x4C4B  # likelihood particles v^r (Methods 4, 5, 7)


def _scalar(name, value, *, lower=None, strict=True):
    arr = as_float_array(name, value, (0,))
    if is_concrete(arr):
        v = float(arr)
        if not math.isfinite(v):
            raise ValueError(f"{name} must be finite, got {v}")
        if lower is not None and (v <= lower if strict else v < lower):
            raise ValueError(f"{name} must be {'>' if strict else '>='} {lower}, got {v}")
    return arr


# --------------------------------------------------------------------------- likelihoods


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


def _likelihood_particles(model: NonlinearModel, particles, key, t, num):
    """Nominal likelihood particles `y^r | x^j = h(x^j, v^r)` (Algorithm 2, lines 10–15):
    `(M, R, m)`, with independent `v^r` for every particle."""
    m = particles.shape[0]
    v = model.sample_measurement_noise(key, t, shape=(m, num))
    return jax.vmap(jax.vmap(lambda x, v: model.observe(x, v, t), (None, 0)))(particles, v)


def _observed_only(y, ys, observed):
    """Zero the missing components of `y` and of the likelihood particles `ys`, so
    that Euclidean distances use the observed components only."""
    return jnp.where(observed, y, 0.0), jnp.where(observed, ys, 0.0)


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


def _pairwise(a, b):
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
    log_g = logsumexp(log_a - _pairwise(pts, support) / scale, axis=1) - dim * jnp.log(scale) - math.lgamma(dim) - log_sphere
    return pts, jnp.exp(-log_g) / num_points


def _continuous(q, support, radius, key, num_points):
    """Theorem 3 (`maxent_wasserstein_continuous`) on the points of `_radial_points`.
    Inputs carry no gradient: the solver has implicit derivatives, but its quadrature
    points are drawn with a scale set by the radius, so Method 4 is left undifferentiated."""
    q, support, radius = lax.stop_gradient((q, support, radius))
    pts, w = _radial_points(key, support, q, radius, num_points)
    return maxent_wasserstein_continuous(q, support, radius, points=pts, weights=w)


def _continuous_loglik(ys, y, radius, key, num_points):
    """Method 4: `log p*(y)` of the continuous Theorem-3 worst case around the uniform
    nominal on the likelihood particles `{y^r}` (eq. 16, evaluated at `y` wherever it is)."""
    num = ys.shape[0]
    q = jnp.full((num,), 1.0 / num, ys.dtype)
    return _continuous(q, ys, radius, key, num_points).log_density(y)


# --------------------------------------------------------------------------- the filter


class DRParticleFilter(AbstractFilter):
    """Distributionally robust particle filter (Wang 2022, Algorithm 2, Methods 1–7) for
    `jdrkf.NonlinearModel`.

    **Arguments:**

    - `num_particles`: `N` (also `M`: worst-case prior particles keep the count).
    - `prior`: Step 2, the worst-case prior particles (ambiguity in the process model):
      `"none"`; `"kl"` — Method 1 with Theorem 6 on the propagated particles, weights
      `∝ q^β` with `KL(p‖q) = prior_radius` (no effect on uniform weights, i.e. right after
      resampling); `"wasserstein"` — Method 1 with Theorem 5 (support = the particles,
      cost `‖x^i − x^j‖`); `"wasserstein_sample"` — Method 2, `N` new particles drawn from
      the continuous Theorem-3 density within `W₁ ≤ prior_radius` of the weighted
      particles, weights `1/N`.
    - `prior_radius`: the radius of that ambiguity set (array: differentiable for
      `"kl"`, `"wasserstein"`).
    - `likelihood`: Steps 3–4, the worst-case likelihood `p*(y | x^j)`: `"inflate"` —
      Method 3, additive noise only, the noise law rescaled about its mean to covariance
      `θR` (for Gaussian noise: `N(y; h(x) + μ, θR)`); `"wasserstein"` — Method 4, the
      density at `y` of the continuous Theorem-3 worst case within `W₁ ≤
      likelihood_radius` of the `R` likelihood particles `y^r = h(x^j, v^r)`;
      `"wasserstein_augmented"` — Method 5, the mass on `y` of the discrete Theorem-5
      worst case on the support `{y} ∪ {y^r}`. Methods 4–5 sample `v` from the model's
      noise law and work for additive and non-additive models alike.
    - `theta`: Method 3's inflation `θ` (`> 0`; the paper takes `θ ≥ 1`; the authors' code
      `θ = 5`). Array: `eqx.filter_grad` reaches it.
    - `likelihood_radius`: Methods 4–5's Wasserstein radius (array).
    - `num_likelihood_particles`: `R`.
    - `outlier`: Methods 6–7. `y` is an outlier when `max_j p*(y | x^j) ≤
      outlier_threshold`. `"drop"`: the weights are not updated (posterior = worst-case
      prior; `outlier_threshold=1e-6` with Method 3 is the authors' gating);
      `"nearest"`: `y` is replaced by the likelihood particle of the most likely prior
      particle that is nearest to `y` (for Method 3, `R` likelihood particles of that
      particle are drawn), and the likelihoods are evaluated again there. `None`: off.
    - `outlier_threshold`: `ε` (a likelihood, not a log-likelihood).
    - `num_integration_points`: Monte Carlo points of the continuous Theorem-3 solves
      (Methods 2 and 4), importance-sampled around the atoms.
    - `batch_size`: particles whose likelihood solves (Methods 4–5) run together
      (`jax.lax.map(..., batch_size=...)`); default: all for Method 5, one at a time for
      Method 4 (its Newton solve factorizes a small matrix per particle).
    - `resampling`, `ess_threshold`, `estimate`, `resampling_gradient`: Step 5, the
      reported estimate and the gradient of resampling, as in `BootstrapPF`
      (`ess_threshold=1`: every step). The authors' RPF (their MATLAB code
      `Spratm-Asleaf/DRSE-Nonlinear`) is `DRParticleFilter(N, theta=5.0, outlier="drop",
      outlier_threshold=1e-6, resampling="multinomial", ess_threshold=1.0,
      estimate="resampled_mean")` (their KL prior reweighting is disabled).
    - `return_particles`: add to `info` the worst-case prior cloud of every step
      (`particles`, `prior_log_weights`) and the updated `log_weights` (before
      resampling); memory `T·N·(n + 2)` per run.
    - `throw`, `outputs`: as in `KalmanFilter`. Missing components are dropped
      from the likelihood (Method 3: the Gaussian marginal; Methods 4–5: the distances);
      an all-missing `y` leaves the weights unchanged.

    With `prior="none"`, `likelihood="inflate"`, `theta=1` and `outlier=None` the filter
    is `BootstrapPF` with the same random numbers. Randomness beyond the bootstrap's
    (Method 2, likelihood particles) comes from `fold_in(step_key, tag)`.

    The estimate (`filtered`) is the weighted mean and covariance before resampling;
    `predicted` those of the worst-case prior particles; `loglik` the log of
    `Σ_j u_j p*(y | x^j)` (for Method 5 a probability mass, not a density; `0` for a
    dropped or missing `y`). `info`: `ess` (after the update, before resampling),
    `resampled`, `outlier`, `max_loglik` (`max_j log p*(y | x^j)` before the treatment).

    Gradients: without resampling (`ess_threshold=0`) the filter is a smooth function of
    `theta`, `prior_radius` (Methods 1) and `likelihood_radius` (Method 5) for a fixed key.
    Resampling is differentiated as in `BootstrapPF` (`resampling_gradient`, default
    `"score"`: the stop-gradient resampling of Ścibior & Wood 2021, forward values
    unchanged). With `prior="none"` and `outlier=None` the filter is a bootstrap PF with
    per-particle potentials `p*(y | x^j)`, so `∇ exp(marginal_loglik)` is an unbiased
    estimate of the gradient of the expected likelihood estimate (for Method 3 with
    Gaussian noise: of `p(y_{1:T})` under `R → θR`), and `∇ marginal_loglik` is
    consistent but biased at finite `N`. The worst-case priors (Methods 1–2) and the
    outlier treatments (Methods 6–7: a decision on the whole cloud, not differentiated)
    act on the whole cloud, and carry no such guarantee. Methods 2 and 4 pass no gradient
    to the radii.
    """

    model_types: ClassVar[tuple[type, ...]] = (NonlinearModel,)
    stochastic_init: ClassVar[bool] = True

    prior_radius: Float[Array, ""]
    theta: Float[Array, ""]
    likelihood_radius: Float[Array, ""]
    outlier_threshold: Float[Array, ""]
    num_particles: int = eqx.field(static=True)
    prior: str = eqx.field(static=True)
    likelihood: str = eqx.field(static=True)
    num_likelihood_particles: int = eqx.field(static=True)
    outlier: str | None = eqx.field(static=True)
    num_integration_points: int = eqx.field(static=True)
    batch_size: int | None = eqx.field(static=True)
    resampling: str = eqx.field(static=True)
    ess_threshold: float = eqx.field(static=True)
    estimate: str = eqx.field(static=True)
    resampling_gradient: str = eqx.field(static=True)
    return_particles: bool = eqx.field(static=True)

    def __init__(
        self,
        num_particles: int,
        *,
        prior: str = "none",
        prior_radius: Float[ArrayLike, ""] = 0.0,
        likelihood: str = "inflate",
        theta: Float[ArrayLike, ""] = 5.0,
        likelihood_radius: Float[ArrayLike, ""] = 0.1,
        num_likelihood_particles: int = 50,
        outlier: str | None = None,
        outlier_threshold: Float[ArrayLike, ""] = 1e-6,
        num_integration_points: int = 1000,
        batch_size: int | None = None,
        resampling: str = "systematic",
        ess_threshold: float = 0.5,
        estimate: str = "weighted_mean",
        resampling_gradient: str = "score",
        return_particles: bool = False,
        throw: bool = True,
        outputs: str | Sequence[str] = DEFAULT_OUTPUTS,
    ):
        self.num_particles = check_positive_int("num_particles", num_particles)
        if prior not in _PRIORS:
            raise ValueError(f"prior must be one of {_PRIORS}, got {prior!r}")
        if likelihood not in _LIKELIHOODS:
            raise ValueError(f"likelihood must be one of {_LIKELIHOODS}, got {likelihood!r}")
        if outlier not in _OUTLIERS:
            raise ValueError(f"outlier must be one of {_OUTLIERS}, got {outlier!r}")
        if resampling not in _resampling.RESAMPLERS:
            raise ValueError(f"resampling must be one of {tuple(_resampling.RESAMPLERS)}, got {resampling!r}")
        ess_threshold = float(ess_threshold)
        if not 0.0 <= ess_threshold <= 1.0:
            raise ValueError(f"ess_threshold must be in [0, 1], got {ess_threshold}")
        self.prior_radius = _scalar("prior_radius", prior_radius, lower=0.0, strict=False)
        self.theta = _scalar("theta", theta, lower=0.0)
        self.likelihood_radius = _scalar("likelihood_radius", likelihood_radius, lower=0.0, strict=False)
        self.outlier_threshold = _scalar("outlier_threshold", outlier_threshold, lower=0.0, strict=False)
        if prior == "wasserstein_sample" and is_concrete(self.prior_radius) and float(self.prior_radius) <= 0:
            raise ValueError("prior='wasserstein_sample' (Method 2) needs prior_radius > 0")
        if likelihood == "wasserstein" and is_concrete(self.likelihood_radius) and float(self.likelihood_radius) <= 0:
            raise ValueError("likelihood='wasserstein' (Method 4) needs likelihood_radius > 0")
        self.prior, self.likelihood, self.outlier = prior, likelihood, outlier
        self.num_likelihood_particles = check_positive_int("num_likelihood_particles", num_likelihood_particles)
        self.num_integration_points = check_positive_int("num_integration_points", num_integration_points)
        self.batch_size = None if batch_size is None else check_positive_int("batch_size", batch_size)
        if estimate not in ("weighted_mean", "resampled_mean"):
            raise ValueError(f"estimate must be 'weighted_mean' or 'resampled_mean', got {estimate!r}")
        self.resampling, self.ess_threshold, self.estimate = resampling, ess_threshold, estimate
        check_resampling_gradient(resampling_gradient)
        self.resampling_gradient = resampling_gradient
        self.return_particles = bool(return_particles)
        self.throw, self.outputs = bool(throw), outputs

    # ----------------------------------------------------------------- pieces of a step

    def _worst_case_prior(self, x, logw, key):
        """Step 2: Method 1 (`"kl"`, `"wasserstein"`) or Method 2 (`"wasserstein_sample"`)."""
        if self.prior == "none":
            return x, logw
        q = jnp.exp(logw)
        radius = self.prior_radius.astype(x.dtype)
        if self.prior == "kl":  # Theorem 6: p ∝ q^β
            beta = maxent_kl_solve(q, radius).dual
            z = jnp.where(jnp.isfinite(logw), beta * logw, -jnp.inf)
            return x, z - logsumexp(z)
        if self.prior == "wasserstein":  # Theorem 5 on the particles themselves
            cost = _pairwise(x, x)
            v0 = maxent_transport_solve(q, cost, radius).dual
            return x, logsumexp(logw[:, None] + jax.nn.log_softmax(-v0 * cost, axis=1), axis=0)
        # Method 2: N draws from the continuous Theorem-3 density, weights 1/N.
        k_points, k_draw = jax.random.split(jax.random.fold_in(key, _TAG_PRIOR))
        sol = _continuous(q, x, radius, k_points, self.num_integration_points)
        new_x, _ = sol.sample(k_draw, self.num_particles)
        return new_x, jnp.full_like(logw, -math.log(self.num_particles))

    def _map_particles(self, fn, *args, default_batch):
        batch = self.batch_size if self.batch_size is not None else default_batch
        if batch is None:
            return jax.vmap(fn)(*args)
        return lax.map(lambda a: fn(*a), args, batch_size=None if batch == 1 else batch)

    def _loglik_inflate(self, model, x, y, t, observed):
        """Method 3 (additive noise): `log p_v(y − h(x^j))` with the law's covariance `θR`."""
        theta = self.theta.astype(x.dtype)
        if model.measurement_noise is None:  # N(y; h(x), θR); θ = 1 is bitwise BootstrapPF
            hx = jax.vmap(lambda xi: model.h(xi, t))(x)
            scaled = eqx.tree_at(lambda m: m.R, model, theta * model.R)
            return gaussian_loglik_particles(scaled, y, hx, observed)
        return skip_incomplete(lambda y: _inflated_loglik(model, x, y, t, theta), y, observed)

    def _loglik_particles(self, ys, y, key, observed):
        """Methods 4–5 from the likelihood particles `ys (M, R, m)`; `key` draws Method 4's
        integration points (one set per particle)."""
        radius = self.likelihood_radius.astype(ys.dtype)
        if observed is not None:
            y, ys = _observed_only(y, ys, observed)
        if self.likelihood == "wasserstein_augmented":
            ll = self._map_particles(lambda yr: _augmented_loglik(yr, y, radius), ys, default_batch=None)
        else:
            keys = jax.random.split(key, ys.shape[0])
            fn = lambda yr, k: _continuous_loglik(yr, y, radius, k, self.num_integration_points)  # noqa: E731
            ll = self._map_particles(fn, ys, keys, default_batch=1)
        return ll

    def _likelihoods(self, model, x, ys, y, t, key, observed):
        if self.likelihood == "inflate":
            return self._loglik_inflate(model, x, y, t, observed)
        ll = self._loglik_particles(ys, y, key, observed)
        if observed is not None:
            ll = jnp.where(jnp.any(observed), ll, jnp.zeros_like(ll))
        return ll

    # ------------------------------------------------------------------- filter API

    def init(self, model: NonlinearModel, prior: Gaussian, key: PRNGKeyArray | None = None) -> ParticleState:
        """`N` draws from `prior` with equal weights (as `BootstrapPF.init`)."""
        if key is None:
            raise ValueError("DRParticleFilter.init needs a PRNG key (e.g. jax.random.key(0))")
        x0 = prior.sample(key, (self.num_particles,)).astype(model.dtype)
        lw = jnp.full((self.num_particles,), -math.log(self.num_particles), model.dtype)
        return ParticleState(x0, lw)

    def step(self, model: NonlinearModel, state: ParticleState, y, t, u=None, key: PRNGKeyArray | None = None, observed=None):
        """Algorithm 2, Steps 1–5 (see the class docstring)."""
        if key is None:
            raise ValueError("DRParticleFilter.step needs a PRNG key")
        if self.likelihood == "inflate" and not model.additive:
            raise ValueError(
                "likelihood='inflate' (Method 3) needs additive measurement noise (model.additive=True); "
                "use likelihood='wasserstein' or 'wasserstein_augmented' (Methods 4-5) for additive=False"
            )
        n_part = self.num_particles
        # Step 1: as BootstrapPF (same keys).
        k_noise, k_res = jax.random.split(key)
        w = model.sample_process_noise(k_noise, t, (n_part,))
        x = jax.vmap(lambda xi, wi: model.transition(xi, wi, t))(state.particles, w)
        # Step 2: worst-case prior particles and weights.
        x, logq = self._worst_case_prior(x, state.log_weights, key)
        pred = particle_moments(x, logq)
        # Step 3: worst-case likelihoods.
        k_lik, k_points, k_near = jax.random.split(jax.random.fold_in(key, _TAG_LIKELIHOOD), 3)
        need_ys = self.likelihood != "inflate"
        ys = _likelihood_particles(model, x, k_lik, t, self.num_likelihood_particles) if need_ys else None
        ll = self._likelihoods(model, x, ys, y, t, k_points, observed)
        max_ll = jnp.max(ll)
        # Methods 6–7: outlier identification and treatment.
        if self.outlier is None:
            outlier = jnp.asarray(False)
        else:
            eps = self.outlier_threshold.astype(ll.dtype)
            outlier = max_ll <= jnp.log(eps)
            if observed is not None:
                outlier = outlier & jnp.any(observed)
            if self.outlier == "drop":
                ll = jnp.where(outlier, jnp.zeros_like(ll), ll)
            else:
                best = jnp.argmax(ll)
                if need_ys:
                    cand = ys[best]
                else:
                    v = model.sample_measurement_noise(k_near, t, (self.num_likelihood_particles,))
                    cand = jax.vmap(lambda vr: model.observe(x[best], vr, t))(v)
                use = jnp.ones(y.shape, bool) if observed is None else observed
                diff = jnp.where(use, cand - y, 0.0)
                nearest = cand[jnp.argmin(jnp.sum(diff * diff, axis=1))]
                y_near = jnp.where(use, nearest, y)
                ll_near = self._likelihoods(model, x, ys, y_near, t, k_points, observed)
                ll = jnp.where(outlier, ll_near, ll)
        # Steps 4-5: weight update and resampling (as BootstrapPF).
        unnorm = logq + ll
        new_x, new_lw, lw, filt, loglik, ess, do_resample, result = weigh_and_resample(self, x, unnorm, k_res)
        info = {"ess": ess, "resampled": do_resample, "outlier": outlier, "max_loglik": max_ll}
        if self.return_particles:
            info.update(particles=x, prior_log_weights=logq, log_weights=lw)
        # Traced range check of the constructor's eager checks (a few scalar comparisons).
        valid = in_range(self.prior_radius, 0.0, lower_open=self.prior == "wasserstein_sample")
        valid = valid & in_range(self.theta, 0.0, lower_open=True) & in_range(self.outlier_threshold, 0.0)
        valid = valid & in_range(self.likelihood_radius, 0.0, lower_open=self.likelihood == "wasserstein")
        result = RESULTS.where(valid, result, RESULTS.invalid_hyperparameter)
        out = StepOutput(predicted=pred, filtered=filt, loglik=loglik, info=info, result=result)
        return ParticleState(new_x, new_lw), out

    def check_model(self, model: NonlinearModel) -> None:
        if self.likelihood == "inflate" and not model.additive:
            raise ValueError(
                "likelihood='inflate' (Method 3) needs additive measurement noise (model.additive=True); "
                "use likelihood='wasserstein' or 'wasserstein_augmented' (Methods 4-5) for additive=False"
            )
