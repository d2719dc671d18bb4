"""Distributionally robust particle filter of Wang (2022), "Distributionally Robust
State Estimation for Nonlinear Systems", IEEE TSP: Algorithm 2 with the
worst-case prior particles of Methods 1–2, the worst-case likelihoods of Methods 3–5
(both in `jdrkf.sets`) and the outlier treatment of Methods 6–7.

Every step runs the five steps of Algorithm 2:

1. propagate the particles through `f` with sampled process noise (exactly as
   `BootstrapPF`, same keys);
2. worst-case prior particles (`prior`, a `jdrkf.sets.AbstractParticlePrior`): none, Method 1
   reweighting of the propagated particles (support = the particles themselves) by
   Theorem 6 (`ParticleKL`, `p ∝ q^β`) or Theorem 5 (`ParticleWasserstein`), or Method 2
   (`ParticleWassersteinSample`: `N` fresh particles drawn from the continuous Theorem-3
   density, weights `1/N`);
3. worst-case likelihood `p*(y | x^j)` (`likelihood`, a
   `jdrkf.sets.AbstractParticleLikelihood`): Method 3 (`InflatedLikelihood`: the additive
   noise law with covariance `θR`, i.e. `v → μ + √θ (v − μ)`), or, from `R` likelihood
   particles `y^r = h(x^j, v^r)` per particle (any noise, additive or not), Method 4
   (`WassersteinLikelihood`: the continuous Theorem-3 worst case around the `y^r`,
   evaluated at `y`) or Method 5 (`AugmentedWassersteinLikelihood`: `y` appended to the
   support, discrete Theorem 5, the mass it receives);
4. Methods 6–7 (`outlier`): `y` is an outlier when `max_j p*(y | x^j) ≤ ε`; it is then
   dropped (`DropOutliers`: weights unchanged, the authors' gating with `ε = 1e-6`) or
   replaced by the likelihood particle of the most likely prior particle that is
   nearest to `y` (`NearestOutliers`); weights `u_j ← u_j p*(y | x^j)`, normalized;
5. resampling when `ESS < ess_threshold · N` (as `BootstrapPF`).

The estimate is the weighted mean before resampling.
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Sequence
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
from jax import lax
from jaxtyping import Array, ArrayLike, Bool, Float, PRNGKeyArray

from .._gaussian import Gaussian
from .._nonlinear import NonlinearModel
from .._validation import check_positive_int, check_scalar, in_range, is_concrete
from ..sets._particle import (
    AbstractParticleLikelihood,
    AbstractParticlePrior,
    AugmentedWassersteinLikelihood,
    InflatedLikelihood,
    ParticleKL,
    ParticleWasserstein,
    ParticleWassersteinSample,
    WassersteinLikelihood,
)
from . import _resampling
from ._base import DEFAULT_OUTPUTS, RESULTS, AbstractFilter, StepOutput
from ._particle import (
    ParticleState,
    check_resampling_gradient,
    particle_moments,
    weigh_and_resample,
)

__all__ = ["DRParticleFilter", "DropOutliers", "NearestOutliers"]

# Extra randomness (beyond BootstrapPF's) comes from `fold_in(key, tag)` so that the
# bootstrap keys are untouched: with no prior, InflatedLikelihood and no NearestOutliers
# treatment the filter draws exactly BootstrapPF's random numbers.
_TAG_PRIOR = 0x5052  # Method 2 sampling
_TAG_LIKELIHOOD = 0x4C4B  # likelihood particles v^r (Methods 4, 5, 7)


# --------------------------------------------------------------------------- outliers


class DropOutliers(eqx.Module):
    """Outlier treatment "drop": Wang (2022), Methods 6–7. `y` is an outlier when
    `max_j p*(y | x^j) ≤ threshold` (Method 6); its update is then skipped: the weights
    stay those of the worst-case prior and the log-likelihood increment is `0`. With
    `InflatedLikelihood` and `threshold=1e-6` this is the authors' gating.

    **Arguments:**

    - `threshold`: `ε >= 0`, a likelihood (not a log-likelihood). Array; the decision is
      piecewise constant in it, so its gradient is zero almost everywhere.
    """

    threshold: Float[Array, ""]

    def __init__(self, threshold: Float[ArrayLike, ""] = 1e-6):
        self.threshold = check_scalar("threshold", threshold)

    def valid(self) -> Bool[Array, ""]:
        """`threshold >= 0`."""
        return in_range(self.threshold, 0.0)


class NearestOutliers(eqx.Module):
    """Outlier treatment "nearest": Wang (2022), Methods 6–7. `y` is an outlier when
    `max_j p*(y | x^j) ≤ threshold` (Method 6); it is then replaced by the likelihood
    particle of the most likely prior particle that is nearest to `y` (Method 7), and the
    likelihoods are evaluated again there.

    **Arguments:**

    - `threshold`: `ε >= 0`, a likelihood (not a log-likelihood). Array; the decision is
      piecewise constant in it, so its gradient is zero almost everywhere.
    - `num_particles`: `R`, the likelihood particles drawn for the most likely prior
      particle when the likelihood has none of its own (`InflatedLikelihood`); Methods 4–5
      use theirs. Static.
    """

    threshold: Float[Array, ""]
    num_particles: int = eqx.field(static=True)

    def __init__(self, threshold: Float[ArrayLike, ""] = 1e-6, num_particles: int = 50):
        self.threshold = check_scalar("threshold", threshold)
        self.num_particles = check_positive_int("num_particles", num_particles)

    def valid(self) -> Bool[Array, ""]:
        """`threshold >= 0`."""
        return in_range(self.threshold, 0.0)


_OUTLIER_TYPES = (DropOutliers, NearestOutliers)

# --------------------------------------------------------------------------- deprecated strings

_PRIORS = ("none", "kl", "wasserstein", "wasserstein_sample")
_LIKELIHOODS = ("inflate", "wasserstein", "wasserstein_augmented")
_OUTLIERS = ("drop", "nearest")
_SETS = "jdrkf.sets."
# The keywords of the previous release, each with its replacement (for the messages).
_LEGACY_KEYWORDS = {
    "prior_radius": f"prior={_SETS}ParticleKL(radius) (or ParticleWasserstein, ParticleWassersteinSample)",
    "theta": f"likelihood={_SETS}InflatedLikelihood(inflation)",
    "likelihood_radius": f"likelihood={_SETS}WassersteinLikelihood(radius) or AugmentedWassersteinLikelihood(radius)",
    "num_likelihood_particles": (
        f"num_particles of {_SETS}WassersteinLikelihood, {_SETS}AugmentedWassersteinLikelihood or jdrkf.NearestOutliers"
    ),
    "outlier_threshold": "outlier=jdrkf.DropOutliers(threshold) or jdrkf.NearestOutliers(threshold)",
    "num_integration_points": f"num_integration_points of {_SETS}ParticleWassersteinSample or {_SETS}WassersteinLikelihood",
}


def _legacy_arguments(prior, likelihood, outlier, old: dict):
    """The objects for the string spellings and keywords of the previous release
    (`prior="kl"`, `prior_radius=`, `likelihood="inflate"`, `theta=`, …), and the
    deprecation notes. An old keyword next to an object that it would configure is a
    `ValueError`; one that had no effect in the previous release has none now."""
    unknown = sorted(set(old) - set(_LEGACY_KEYWORDS))
    if unknown:
        raise TypeError(f"DRParticleFilter.__init__() got an unexpected keyword argument {unknown[0]!r}")
    # Eager checks under the old names, as the previous release made them.
    for name, strict in (("prior_radius", False), ("theta", True), ("likelihood_radius", False), ("outlier_threshold", False)):
        if name in old:
            old[name] = check_scalar(name, old[name], strict=strict)
    for name in ("num_likelihood_particles", "num_integration_points"):
        if name in old:
            old[name] = check_positive_int(name, old[name])
    # Objects the caller passed (not converted from strings): old keywords may not configure them.
    prior_object = prior is not None and not isinstance(prior, str)
    likelihood_object = likelihood is not None and not isinstance(likelihood, str)
    outlier_object = outlier is not None and not isinstance(outlier, str)
    notes, used = [], set()

    def note(spelling, keywords, replacement):
        parts = ([spelling] if spelling else []) + [f"{k}=" for k in keywords if k in old and k not in used]
        used.update(keywords)
        if parts:
            notes.append(f"{', '.join(parts)} {'is' if len(parts) == 1 else 'are'} deprecated; use {replacement}")

    if isinstance(prior, str):  # Step 2
        if prior not in _PRIORS:
            raise ValueError(f"prior must be None or a jdrkf.sets.AbstractParticlePrior, got {prior!r}")
        spelling, radius = f"prior={prior!r}", old.get("prior_radius", 0.0)
        if prior == "none":
            note(spelling, (), "prior=None")
            prior = None
        elif prior == "kl":
            note(spelling, ("prior_radius",), f"prior={_SETS}ParticleKL(radius)")
            prior = ParticleKL(radius)
        elif prior == "wasserstein":
            note(spelling, ("prior_radius",), f"prior={_SETS}ParticleWasserstein(radius)")
            prior = ParticleWasserstein(radius)
        else:
            if is_concrete(radius) and float(radius) <= 0:
                raise ValueError("prior='wasserstein_sample' (Method 2) needs prior_radius > 0")
            note(spelling, ("prior_radius", "num_integration_points"),
                 f"prior={_SETS}ParticleWassersteinSample(radius, num_integration_points)")
            prior = ParticleWassersteinSample(radius, old.get("num_integration_points", 1000))
    if isinstance(likelihood, str):  # Step 3
        if likelihood not in _LIKELIHOODS:
            raise ValueError(f"likelihood must be a jdrkf.sets.AbstractParticleLikelihood, got {likelihood!r}")
        spelling, radius = f"likelihood={likelihood!r}", old.get("likelihood_radius", 0.1)
        num = old.get("num_likelihood_particles", 50)
        if likelihood == "inflate":
            note(spelling, ("theta",), f"likelihood={_SETS}InflatedLikelihood(inflation)")
            likelihood = InflatedLikelihood(old.get("theta", 5.0))
        elif likelihood == "wasserstein":
            if is_concrete(radius) and float(radius) <= 0:
                raise ValueError("likelihood='wasserstein' (Method 4) needs likelihood_radius > 0")
            note(spelling, ("likelihood_radius", "num_likelihood_particles", "num_integration_points"),
                 f"likelihood={_SETS}WassersteinLikelihood(radius, num_particles, num_integration_points)")
            likelihood = WassersteinLikelihood(radius, num, old.get("num_integration_points", 1000))
        else:
            note(spelling, ("likelihood_radius", "num_likelihood_particles"),
                 f"likelihood={_SETS}AugmentedWassersteinLikelihood(radius, num_particles)")
            likelihood = AugmentedWassersteinLikelihood(radius, num)
    elif likelihood is None and "theta" in old:
        note(None, ("theta",), _LEGACY_KEYWORDS["theta"])
        likelihood = InflatedLikelihood(old["theta"])
    if isinstance(outlier, str):  # Methods 6–7
        if outlier not in _OUTLIERS:
            raise ValueError(f"outlier must be None, a jdrkf.DropOutliers or a jdrkf.NearestOutliers, got {outlier!r}")
        spelling, threshold = f"outlier={outlier!r}", old.get("outlier_threshold", 1e-6)
        if outlier == "drop":
            note(spelling, ("outlier_threshold",), "outlier=jdrkf.DropOutliers(threshold)")
            outlier = DropOutliers(threshold)
        else:
            note(spelling, ("outlier_threshold", "num_likelihood_particles"), "outlier=jdrkf.NearestOutliers(threshold, num_particles)")
            outlier = NearestOutliers(threshold, old.get("num_likelihood_particles", 50))
    # Keywords left over: in conflict with an object they would configure, or without effect
    # (as in the previous release, e.g. prior_radius without a prior).
    homes = {
        "prior_radius": prior_object,
        "theta": likelihood_object,
        "likelihood_radius": likelihood_object,
        "num_likelihood_particles": likelihood_object or outlier_object,
        "outlier_threshold": outlier_object,
        "num_integration_points": prior_object or likelihood_object,
    }
    for name, replacement in _LEGACY_KEYWORDS.items():
        if name in old and name not in used:
            if homes[name]:
                raise ValueError(
                    f"{name}= (deprecated) conflicts with the prior/likelihood/outlier object given; "
                    f"set it on the object instead: {replacement}"
                )
            note(None, (name,), f"{replacement} (here it has no effect)")
    return prior, likelihood, outlier, notes


# --------------------------------------------------------------------------- the filter


class DRParticleFilter(AbstractFilter):
    """Distributionally robust particle filter (Wang 2022, Algorithm 2, Methods 1–7) for
    `jdrkf.NonlinearModel`.

    **Arguments:**

    - `num_particles`: `N` (also `M`: worst-case prior particles keep the count).
    - `prior`: Step 2, the worst-case prior particles (ambiguity in the process model), a
      `jdrkf.sets.AbstractParticlePrior`: `None` (default) — the propagated particles;
      `jdrkf.sets.ParticleKL(radius)` — Method 1 with Theorem 6 on the propagated
      particles, weights `∝ q^β` with `KL(p‖q) = radius` (no effect on uniform weights, i.e.
      right after resampling); `jdrkf.sets.ParticleWasserstein(radius)` — Method 1 with
      Theorem 5 (support = the particles, cost `‖x^i − x^j‖`);
      `jdrkf.sets.ParticleWassersteinSample(radius, num_integration_points)` — Method 2, `N`
      new particles drawn from the continuous Theorem-3 density within `W₁ ≤ radius` of the
      weighted particles, weights `1/N`.
    - `likelihood`: Steps 3–4, the worst-case likelihood `p*(y | x^j)`, a
      `jdrkf.sets.AbstractParticleLikelihood`: `jdrkf.sets.InflatedLikelihood(inflation)`
      — Method 3, additive noise only, the noise law rescaled about its mean to covariance
      `θR` (for Gaussian noise: `N(y; h(x) + μ, θR)`; default (`None`):
      `InflatedLikelihood(5.0)`, the authors' `θ`);
      `jdrkf.sets.WassersteinLikelihood(radius, num_particles, num_integration_points)` —
      Method 4, the density at `y` of the continuous Theorem-3 worst case within
      `W₁ ≤ radius` of the `R = num_particles` likelihood particles `y^r = h(x^j, v^r)`;
      `jdrkf.sets.AugmentedWassersteinLikelihood(radius, num_particles)` — Method 5, the
      mass on `y` of the discrete Theorem-5 worst case on the support `{y} ∪ {y^r}`.
      Methods 4–5 sample `v` from the model's noise law and work for additive and
      non-additive models alike.
    - `outlier`: Methods 6–7, `None` (off), `DropOutliers(threshold)` or
      `NearestOutliers(threshold)`. `y` is an outlier when `max_j p*(y | x^j) ≤ threshold`.
      `DropOutliers`: the weights are not updated (posterior = worst-case prior;
      `DropOutliers(1e-6)` with Method 3 is the authors' gating); `NearestOutliers`: `y` is
      replaced by the likelihood particle of the most likely prior particle that is nearest
      to `y` (for Method 3, `NearestOutliers.num_particles` likelihood particles of that
      particle are drawn), and the likelihoods are evaluated again there.
    - `batch_size`: particles whose likelihood solves (Methods 4–5) run together
      (`jax.lax.map(..., batch_size=...)`); default: all for Method 5, one at a time for
      Method 4 (its Newton solve factorizes a small matrix per particle).
    - `resampling`, `ess_threshold`, `estimate`, `resampling_gradient`: Step 5, the
      reported estimate and the gradient of resampling, as in `BootstrapPF`
      (`ess_threshold=1`: every step). The authors' RPF (their MATLAB code
      `Spratm-Asleaf/DRSE-Nonlinear`) is `DRParticleFilter(N,
      likelihood=jdrkf.sets.InflatedLikelihood(5.0), outlier=DropOutliers(1e-6),
      resampling="multinomial", ess_threshold=1.0, estimate="resampled_mean")` (their KL
      prior reweighting is disabled).
    - `return_particles`: add to `info` the worst-case prior cloud of every step
      (`particles`, `prior_log_weights`) and the updated `log_weights` (before
      resampling); memory `T·N·(n + 2)` per run.
    - `throw`, `outputs`: as in `KalmanFilter`. Missing components are dropped
      from the likelihood (Method 3: the Gaussian marginal; Methods 4–5: the distances);
      an all-missing `y` leaves the weights unchanged.

    The radii, the inflation and the thresholds are array leaves of the objects
    (`eqx.tree_at(lambda f: f.likelihood.inflation, flt, 2.0)`, `eqx.filter_grad`); out of
    range under tracing, the run reports `RESULTS.invalid_hyperparameter`.

    Deprecated (one release): the string spellings `prior="kl" | "wasserstein" |
    "wasserstein_sample" | "none"`, `likelihood="inflate" | "wasserstein" |
    "wasserstein_augmented"`, `outlier="drop" | "nearest"` and the keywords `prior_radius`,
    `theta`, `likelihood_radius`, `num_likelihood_particles`, `outlier_threshold`,
    `num_integration_points` are converted to the objects with a `DeprecationWarning`.

    With no prior, `InflatedLikelihood(1.0)` and no outlier treatment the filter is
    `BootstrapPF` with the same random numbers. Randomness beyond the bootstrap's
    (Method 2, likelihood particles) comes from `fold_in(step_key, tag)`.

    The estimate (`filtered`) is the weighted mean and covariance before resampling;
    `predicted` those of the worst-case prior particles; `loglik` the log of
    `Σ_j u_j p*(y | x^j)` (for Method 5 a probability mass, not a density; `0` for a
    dropped or missing `y`). `info`: `ess` (after the update, before resampling),
    `resampled`, `outlier`, `max_loglik` (`max_j log p*(y | x^j)` before the treatment).

    Gradients: without resampling (`ess_threshold=0`) the filter is a smooth function of
    the inflation, the Method-1 radii and the Method-5 radius for a fixed key. Resampling
    is differentiated as in `BootstrapPF` (`resampling_gradient`, default `"score"`: the
    stop-gradient resampling of Ścibior & Wood 2021, forward values unchanged). With no
    prior and no outlier treatment the filter is a bootstrap PF with per-particle
    potentials `p*(y | x^j)`, so `∇ exp(marginal_loglik)` is an unbiased estimate of the
    gradient of the expected likelihood estimate (for Method 3 with Gaussian noise: of
    `p(y_{1:T})` under `R → θR`), and `∇ marginal_loglik` is consistent but biased at
    finite `N`. The worst-case priors (Methods 1–2) and the outlier treatments (Methods
    6–7: a decision on the whole cloud, not differentiated) act on the whole cloud, and
    carry no such guarantee. Methods 2 and 4 pass no gradient to their radii.
    """

    model_types: ClassVar[tuple[type, ...]] = (NonlinearModel,)
    stochastic_init: ClassVar[bool] = True

    prior: AbstractParticlePrior | None
    likelihood: AbstractParticleLikelihood
    outlier: DropOutliers | NearestOutliers | None
    num_particles: int = eqx.field(static=True)
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
        prior: AbstractParticlePrior | None = None,
        likelihood: AbstractParticleLikelihood | None = None,
        outlier: DropOutliers | NearestOutliers | None = None,
        batch_size: int | None = None,
        resampling: str = "systematic",
        ess_threshold: float = 0.5,
        estimate: str = "weighted_mean",
        resampling_gradient: str = "score",
        return_particles: bool = False,
        throw: bool = True,
        outputs: str | Sequence[str] = DEFAULT_OUTPUTS,
        **deprecated,
    ):
        self.num_particles = check_positive_int("num_particles", num_particles)
        if deprecated or any(isinstance(a, str) for a in (prior, likelihood, outlier)):
            prior, likelihood, outlier, notes = _legacy_arguments(prior, likelihood, outlier, dict(deprecated))
            if notes:  # stacklevel: the caller, past equinox's Module metaclass
                warnings.warn("DRParticleFilter: " + ". ".join(notes) + ".", DeprecationWarning, stacklevel=4)
        if likelihood is None:
            likelihood = InflatedLikelihood(5.0)
        if prior is not None and not isinstance(prior, AbstractParticlePrior):
            raise ValueError(
                "prior must be None or a jdrkf.sets.AbstractParticlePrior (ParticleKL, ParticleWasserstein, "
                f"ParticleWassersteinSample), got {prior!r}"
            )
        if not isinstance(likelihood, AbstractParticleLikelihood):
            raise ValueError(
                "likelihood must be a jdrkf.sets.AbstractParticleLikelihood (InflatedLikelihood, WassersteinLikelihood, "
                f"AugmentedWassersteinLikelihood), got {likelihood!r}"
            )
        if outlier is not None and not isinstance(outlier, _OUTLIER_TYPES):
            raise ValueError(f"outlier must be None, a jdrkf.DropOutliers or a jdrkf.NearestOutliers, got {outlier!r}")
        if resampling not in _resampling.RESAMPLERS:
            raise ValueError(f"resampling must be one of {tuple(_resampling.RESAMPLERS)}, got {resampling!r}")
        ess_threshold = float(ess_threshold)
        if not 0.0 <= ess_threshold <= 1.0:
            raise ValueError(f"ess_threshold must be in [0, 1], got {ess_threshold}")
        self.prior, self.likelihood, self.outlier = prior, likelihood, outlier
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
        """Step 2 (`self.prior`, Methods 1–2); the prior's key is `fold_in(key, tag)`."""
        if self.prior is None:
            return x, logw
        return self.prior.worst_case(x, logw, jax.random.fold_in(key, _TAG_PRIOR), self.num_particles)

    def _map_particles(self, fn, *args, default_batch):
        batch = self.batch_size if self.batch_size is not None else default_batch
        if batch is None:
            return jax.vmap(fn)(*args)
        return lax.map(lambda a: fn(*a), args, batch_size=None if batch == 1 else batch)

    def _likelihoods(self, model, x, ys, y, t, key, observed):
        """Step 3: `log p*(y | x^j)` of every particle (`self.likelihood`, Methods 3–5)."""
        return self.likelihood.loglik(model, x, ys, y, t, key, observed, self._map_particles)

    def _valid(self) -> Bool[Array, ""]:
        """Traced range check of the objects' eager checks (a few scalar comparisons)."""
        valid = self.likelihood.valid()
        for part in (self.prior, self.outlier):
            if part is not None:
                valid = valid & part.valid()
        return valid

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
        self.likelihood.check_model(model)
        n_part = self.num_particles
        # Step 1: as BootstrapPF (same keys).
        k_noise, k_res = jax.random.split(key)
        w = model.sample_process_noise(k_noise, t, (n_part,))
        x = jax.vmap(lambda xi, wi: model.transition(xi, wi, t))(state.particles, w)
        # Step 2: worst-case prior particles and weights.
        x, logq = self._worst_case_prior(x, state.log_weights, key)
        pred = particle_moments(x, logq)
        # Step 3: worst-case likelihoods (from likelihood particles for Methods 4–5).
        k_lik, k_points, k_near = jax.random.split(jax.random.fold_in(key, _TAG_LIKELIHOOD), 3)
        ys = self.likelihood.likelihood_particles(model, x, k_lik, t)
        ll = self._likelihoods(model, x, ys, y, t, k_points, observed)
        max_ll = jnp.max(ll)
        # Methods 6–7: outlier identification and treatment.
        if self.outlier is None:
            outlier = jnp.asarray(False)
        else:
            eps = self.outlier.threshold.astype(ll.dtype)
            outlier = max_ll <= jnp.log(eps)
            if observed is not None:
                outlier = outlier & jnp.any(observed)
            if isinstance(self.outlier, DropOutliers):
                ll = jnp.where(outlier, jnp.zeros_like(ll), ll)
            else:
                best = jnp.argmax(ll)
                if ys is not None:
                    cand = ys[best]
                else:
                    v = model.sample_measurement_noise(k_near, t, (self.outlier.num_particles,))
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
        result = RESULTS.where(self._valid(), result, RESULTS.invalid_hyperparameter)
        out = StepOutput(predicted=pred, filtered=filt, loglik=loglik, info=info, result=result)
        return ParticleState(new_x, new_lw), out

    def check_model(self, model: NonlinearModel) -> None:
        self.likelihood.check_model(model)
