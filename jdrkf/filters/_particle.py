"""Bootstrap particle filter for `jdrkf.NonlinearModel` (the baseline of Wang 2022, Sec. V)."""

from __future__ import annotations

import math
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
from jax import lax
from jax.scipy.special import logsumexp
from jaxtyping import Array, Float, PRNGKeyArray

from .. import linalg
from .._gaussian import Gaussian
from .._nonlinear import NonlinearModel
from .._validation import check_positive_int
from ..sets._particle import gaussian_loglik_particles, skip_incomplete
from ._base import RESULTS, AbstractFilter, StepOutput
from ._resampling import RESAMPLERS

_ESTIMATES = ("weighted_mean", "resampled_mean")
_RESAMPLING_GRADIENTS = ("score", "ignore")


def check_resampling_gradient(value) -> None:
    if value not in _RESAMPLING_GRADIENTS:
        raise ValueError(f"resampling_gradient must be one of {list(_RESAMPLING_GRADIENTS)}, got {value!r}")


class ParticleState(eqx.Module):
    """Particle cloud `{x_i, w̄_i}`: `particles (N, n)` and normalized `log_weights (N,)`."""

    particles: Float[Array, "N n"]
    log_weights: Float[Array, " N"]


def particle_moments(particles: Float[Array, "N n"], log_weights: Float[Array, " N"]) -> Gaussian:
    """Weighted mean `Σ w̄_i x_i` and covariance `Σ w̄_i (x_i − m)(x_i − m)ᵀ` of a cloud
    with normalized log-weights (no matrix factorization, so safe under `vmap`)."""
    w = jnp.exp(log_weights)
    mean = w @ particles
    d = particles - mean
    cov = linalg.symmetrize((d * w[:, None]).T @ d)
    return Gaussian(mean, cov)


class BootstrapPF(AbstractFilter):
    r"""Bootstrap (sequential importance resampling) particle filter.

    For additive-measurement `jdrkf.NonlinearModel`s (Wang 2022, eqs. (1)–(2); the PF of
    its Sec. V experiments). Step `k` (array index `t = k − 1`), with `N` particles:

    1. propagate: `x_k^i = transition(x_{k-1}^i, w^i, t)`, `w^i ~ process_noise` (default `N(0, Q)`);
    2. weigh: `ℓ_i ← log w̄_{k-1}^i + log p(y_k | x_k^i)` (`model.measurement_logpdf`; for the
       default Gaussian `v` one Cholesky of `R` per step serves all particles), normalized by
       log-sum-exp; the log-likelihood increment is
       `log p̂(y_k | y_{1:k-1}) = log Σ_i w̄_{k-1}^i p(y_k | x_k^i)` (the log of the mean
       incremental weight after a resampling step);
    3. estimate (`estimate="weighted_mean"`, default): the weighted mean and covariance of the
       weighted cloud, *before* resampling (lower variance than after);
    4. resample when `ESS = 1 / Σ w̄_i² < ess_threshold · N` (`ess_threshold = 1`: at every step),
       then `w̄_i = 1/N`.

    `estimate="resampled_mean"` reports the moments of the cloud *after* step 4 instead:
    with `resampling="multinomial", ess_threshold=1` this is the authors' MATLAB PF
    (multinomial resampling at every step, estimate = mean of the resampled particles;
    the authors' MATLAB code `Spratm-Asleaf/DRSE-Nonlinear`), which adds the resampling noise to the estimate.

    `predicted` is the weighted moments of the propagated cloud (before weighing), `filtered`
    those of step 3. `x_0`'s particles are `N` draws from `prior`.

    **Arguments:**

    - `num_particles`: `N ≥ 1` (static).
    - `resampling`: `"systematic"` (default), `"stratified"`, `"residual"` or `"multinomial"`
      (see `jdrkf.filters._resampling`).
    - `ess_threshold`: `c ∈ [0, 1]`; `0` never resamples (sequential importance sampling).
    - `estimate`: `"weighted_mean"` or `"resampled_mean"`.
    - `resampling_gradient`: `"score"` (default) or `"ignore"`, how gradients treat
      resampling (below).
    - `return_particles` (static): add the weighted cloud of every step (before resampling)
      to `info` — memory `T·N·(n + 1)` per run.
    - `throw`, `outputs`: as `jdrkf.KalmanFilter`. With the default Gaussian
      measurement noise, entries of `y` that the call's `observed` mask marks missing
      are marginalized out; with a `measurement_noise` law, an observation with any
      missing entry is skipped entirely.

    `info` holds `ess` (before resampling) and `resampled` per step.

    **Randomness.** All randomness comes from `key` (required; the initial draw uses
    `split(key)[0]`, step `t` uses `split(split(key)[1], T)[t]`).

    **Gradients.** For a fixed key, gradients flow through the propagated particles (the
    noise draws are reparametrized, e.g. `w = √Q z`) and the log-weights. The ancestor
    indices `a_i` of a resampling are integers; with `resampling_gradient="score"` the
    stop-gradient resampling of Ścibior & Wood (2021) gives particle `i` the log-weight
    `−log N + ℓ̄_{a_i} − ⊥(ℓ̄_{a_i})` (`ℓ̄` the normalized log-weights before resampling,
    `⊥` = `lax.stop_gradient`) instead of `−log N`. The added term is exactly zero, so
    every forward value is bitwise that of `"ignore"`, but it adds to the gradient the
    score `∇ℓ̄_{a_i}` of the ancestor's selection probability. Then:

    - `∇ p̂`, with `p̂ = exp(marginal_loglik)` the (unbiased) likelihood estimate, is an
      unbiased estimate of `∇ p(y_{1:T}; θ)`, for every scheme (each copies particle `i`
      `N w̄_i` times on average) and any `ess_threshold` (the decision to resample is
      not differentiated). More generally `∇ (p̂_t Σ_i w̄_t^i φ(x_t^i))` is unbiased for
      `∇ ∫ φ(x_t) p(x_t, y_{1:t}; θ) dx_t`.
    - `∇ marginal_loglik = ∇ p̂ / p̂` estimates the score `∇ log p(y_{1:T}; θ)`: a ratio,
      consistent as `N → ∞` but biased at finite `N`; the same holds for gradients of the
      self-normalized estimates (`filtered_means`, …). Its variance grows with `T`.

    With `"ignore"` the resampled particles get weight `1/N` and the gradient misses the
    resampling's dependence on `θ`: lower variance, but biased even as `N → ∞`. Without
    resampling (`ess_threshold=0`) both are the same smooth function's gradient. (Note
    that finite differences with a fixed key see `"ignore"`'s gradient: the indices are
    locally constant in `θ`.)

    **Example:**

    ```python
    pf = BootstrapPF(1000)
    result = pf(model, prior, ys, jax.random.key(0))
    runs = jax.vmap(pf, in_axes=(None, None, 0, 0))(model, prior, ys_runs, keys)
    ```
    """

    num_particles: int = eqx.field(static=True)
    resampling: str = eqx.field(default="systematic", static=True, kw_only=True)
    ess_threshold: float = eqx.field(default=0.5, static=True, kw_only=True)
    estimate: str = eqx.field(default="weighted_mean", static=True, kw_only=True)
    resampling_gradient: str = eqx.field(default="score", static=True, kw_only=True)
    return_particles: bool = eqx.field(default=False, static=True, kw_only=True)

    model_types: ClassVar[tuple[type, ...]] = (NonlinearModel,)
    stochastic_init: ClassVar[bool] = True

    def __check_init__(self):
        check_positive_int("num_particles", self.num_particles)
        if self.resampling not in RESAMPLERS:
            raise ValueError(f"resampling must be one of {sorted(RESAMPLERS)}, got {self.resampling!r}")
        c = self.ess_threshold
        if isinstance(c, bool) or not isinstance(c, (int, float)) or not (0.0 <= float(c) <= 1.0):
            raise ValueError(f"ess_threshold must be a number in [0, 1], got {c!r}")
        if self.estimate not in _ESTIMATES:
            raise ValueError(f"estimate must be one of {list(_ESTIMATES)}, got {self.estimate!r}")
        check_resampling_gradient(self.resampling_gradient)

    def init(self, model: NonlinearModel, prior: Gaussian, key: PRNGKeyArray | None = None) -> ParticleState:
        """`N` draws from `prior` with equal weights."""
        if key is None:
            raise ValueError("BootstrapPF.init needs a PRNG key (e.g. jax.random.key(0))")
        x0 = prior.sample(key, (self.num_particles,)).astype(model.dtype)
        lw = jnp.full((self.num_particles,), -math.log(self.num_particles), model.dtype)
        return ParticleState(x0, lw)

    def _loglik(self, model: NonlinearModel, y, particles, t, observed):
        hx = jax.vmap(lambda x: model.h(x, t))(particles)
        if model.measurement_noise is None:
            return gaussian_loglik_particles(model, y, hx, observed)
        return skip_incomplete(lambda y: jax.vmap(lambda x: model.measurement_logpdf(y, x, t))(particles), y, observed)

    def step(self, model: NonlinearModel, state: ParticleState, y, t, u=None, key: PRNGKeyArray | None = None, observed=None):
        if key is None:
            raise ValueError("BootstrapPF.step needs a PRNG key")
        n_part = self.num_particles
        k_noise, k_res = jax.random.split(key)
        w = model.sample_process_noise(k_noise, t, (n_part,))
        x = jax.vmap(lambda xi, wi: model.transition(xi, wi, t))(state.particles, w)
        pred = particle_moments(x, state.log_weights)
        unnorm = state.log_weights + self._loglik(model, y, x, t, observed)
        new_x, new_lw, lw, filt, loglik, ess, do_resample, result = weigh_and_resample(self, x, unnorm, k_res)
        info = {"ess": ess, "resampled": do_resample}
        if self.return_particles:
            info["particles"] = x
            info["log_weights"] = lw
        out = StepOutput(predicted=pred, filtered=filt, loglik=loglik, info=info, result=result)
        return ParticleState(new_x, new_lw), out

    def check_model(self, model: NonlinearModel) -> None:
        if not model.additive:
            raise ValueError("BootstrapPF needs a NonlinearModel with additive=True (it weighs by p(y | x) = p_v(y − h(x, t)))")


__all__ = ["BootstrapPF", "ParticleState", "particle_moments"]


def weigh_and_resample(flt, x, unnorm, key):
    """The end of a particle-filter step (BootstrapPF and DRParticleFilter): normalize the
    log-weights `unnorm` (log-sum-exp = the log-likelihood increment), the weighted moments,
    the ESS, resampling with `flt.resampling` when ESS < `flt.ess_threshold`·N, and the
    result code. With `flt.resampling_gradient == "score"` the resampled log-weights are
    `−log N + ℓ̄_a − ⊥(ℓ̄_a)` (Ścibior & Wood 2021): `ℓ̄_a − ⊥(ℓ̄_a)` is exactly 0 in value
    (set to 0 for a non-finite `ℓ̄_a`, which only a failed step selects). The log-weights
    carried to the next step are then normalized in value but not in gradient. As a
    function of `θ`, with the random numbers, indices and resampling decisions held at
    their forward values, this is a particle filter whose resampling draws from the
    forward weights `w̄(θ₀)` and weighs the copies by `w̄_a(θ)/w̄_a(θ₀)`, unbiased for every
    `θ`: the next `loglik` is `log(S_k / S_{k-1})`, `S_k` its total unnormalized mass, and
    `E[S_T] = p(y_{1:T}; θ)`, so the gradient at `θ₀` of `exp(Σ loglik)` is unbiased for
    `∇ p(y_{1:T}; θ₀)`. Returns `(new_particles, new_log_weights, log_weights, filtered,
    loglik, ess, resampled, result)`."""
    n_part = flt.num_particles
    loglik = logsumexp(unnorm)
    degenerate = ~jnp.isfinite(loglik)
    lw = unnorm - loglik
    filt = particle_moments(x, lw)
    wn = jnp.exp(lw)
    ess = 1.0 / jnp.sum(wn * wn)
    resampler = RESAMPLERS[flt.resampling]

    def _resample(args):
        xs, lws = args
        idx = resampler(key, lws, throw=False)  # invalid weights: the step reports nonfinite_state
        new_lw = jnp.full_like(lws, -math.log(n_part))
        if flt.resampling_gradient == "score":
            sel = lws[idx]
            new_lw = new_lw + jnp.where(jnp.isfinite(sel), sel - lax.stop_gradient(sel), 0.0)
        return xs[idx], new_lw

    if flt.ess_threshold == 0.0:  # static: sequential importance sampling, no resampling code
        do_resample = jnp.asarray(False)
        new_x, new_lw = x, lw
    else:  # under vmap the cond becomes a select: the resampling runs for every run and step
        do_resample = jnp.asarray(True) if flt.ess_threshold >= 1.0 else ess < flt.ess_threshold * n_part
        new_x, new_lw = lax.cond(do_resample, _resample, lambda args: args, (x, lw))
    if flt.estimate == "resampled_mean":
        filt = particle_moments(new_x, new_lw)
    finite = jnp.all(jnp.isfinite(filt.mean)) & jnp.all(jnp.isfinite(filt.cov)) & ~degenerate
    result = RESULTS.where(finite, RESULTS.successful, RESULTS.nonfinite_state)
    return new_x, new_lw, lw, filt, loglik, ess, do_resample, result
