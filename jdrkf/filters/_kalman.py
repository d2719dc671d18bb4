"""Kalman filter (time-varying and steady-state)."""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
from jax import lax
from jaxtyping import Array, ArrayLike, Bool, Float, Int, PRNGKeyArray

from .. import linalg
from .._gaussian import Gaussian, log_density
from .._models import LinearModel
from .._validation import is_concrete, psd_rtol
from . import _entrywise, _sqrt
from ._base import RESULTS, AbstractFilter, StepOutput
from ._steps import constant_gain_step, measurement, step_result


def predict(model: LinearModel, belief: Gaussian, t: Int[ArrayLike, ""], u: Float[Array, " p"] | None = None) -> Gaussian:
    """Time update `x_{k-1} → x_k` with the step-`t` model (`t = k − 1`):
    `m⁻ = F m + B u + G μ_w`, `P⁻ = F P Fᵀ + G Q Gᵀ`."""
    mdl = model.at(t)
    mm = linalg.matmul
    mean = mm(mdl.F, belief.mean) + mm(mdl.G, mdl.process_mean)
    if mdl.B is not None:
        mean = mean + mm(mdl.B, u)
    cov = linalg.symmetrize(mm(mm(mdl.F, belief.cov), mdl.F.T) + mm(mm(mdl.G, mdl.Q), mdl.G.T))
    return Gaussian(mean, cov)


def update(
    model: LinearModel,
    predicted: Gaussian,
    y: Float[Array, " m"],
    t: Int[ArrayLike, ""],
    *,
    observed: Bool[Array, " m"] | None = None,
) -> tuple[Gaussian, Float[Array, ""], Bool[Array, ""]]:
    """Measurement update of `x_k` with `y_k`, Joseph form.

    With `observed`, only the components it marks update (the others are missing).
    Returns the filtered Gaussian, the log-likelihood increment
    `log N(y_k; H m⁻ + μ_v, H P⁻ Hᵀ + R)` over the observed components, and a flag that
    is `True` when the innovation covariance was not positive definite.
    """
    observed, h, r, resid = measurement(model, y, t, observed)
    mm = linalg.matmul
    innov = resid - mm(h, predicted.mean)
    hp = mm(h, predicted.cov)
    s = linalg.symmetrize(mm(hp, h.T) + r)
    chol_s = linalg.cholesky(s)
    failed = ~jnp.all(jnp.isfinite(chol_s))
    gain = linalg.cho_solve(chol_s, hp).T
    mean = predicted.mean + mm(gain, innov)
    a = jnp.eye(predicted.mean.shape[0], dtype=s.dtype) - mm(gain, h)
    cov = linalg.symmetrize(mm(mm(a, predicted.cov), a.T) + mm(mm(gain, r), gain.T))
    loglik = log_density(chol_s, innov, jnp.sum(observed.astype(innov.dtype)))
    return Gaussian(mean, cov), loglik, failed


def update_sqrt(
    model: LinearModel,
    mean: Float[Array, " n"],
    chol: Float[Array, "n n"],
    y: Float[Array, " m"],
    t: Int[ArrayLike, ""],
    *,
    observed: Bool[Array, " m"] | None = None,
):
    """`update` in square-root form, from the predicted factor `S⁻` (`P⁻ = S⁻S⁻ᵀ`): the
    array form `tria([[S_R, H S⁻], [0, S⁻]]) = [[L_s, 0], [L_k, L]]` gives the innovation
    factor `L_s`, the gain `K = L_k L_s⁻¹` and the filtered factor `L`
    (`L Lᵀ = (I − K H) P⁻`); `m = m⁻ + K (y − μ_v − H m⁻)`.

    Returns the filtered mean and factor, the log-likelihood increment and the failure
    flag of `update`.
    """
    observed, h, r, resid = measurement(model, y, t, observed)
    chol_s, cross, chol_filt, failed = _sqrt.split(_sqrt.array_update(chol, h, linalg.psd_factor(r)), h.shape[0])
    innov = resid - h @ mean
    loglik = log_density(chol_s, innov, jnp.sum(observed.astype(innov.dtype)))
    return mean + _sqrt.gain(chol_s, cross) @ innov, chol_filt, loglik, failed


class KalmanFilter(AbstractFilter):
    """The Kalman filter for `jdrkf.LinearModel` (time-varying, controls, noise means).

    Each step predicts (`predict`) then updates (`update`, Joseph form; components of
    `y` that the call's `observed` mask marks missing are skipped). It is the `θ = 0`
    special case of every DR filter in jdrkf and the baseline `KF` / `TMKF` of Wang &
    Ye (2022).

    **Arguments:**

    - `throw`: raise (through `eqx.error_if`) when a run fails; else only set `result`.
    - `square_root` (keyword): carry Cholesky factors `P = S Sᵀ` instead of covariances,
      for float32 on ill-conditioned models: `S⁻ = tria([F S, G S_Q])` and the array-form
      update `update_sqrt` (QR triangularizations only; `jdrkf.linalg.tria`). The outputs
      are the same covariances; with `"info"` in `outputs`, `info` holds the factors
      (`predicted_chol_cov`, `filtered_chol_cov`).
    - `outputs`: the `FilterResult` fields to fill (see `jdrkf.AbstractFilter`).

    Under `jax.vmap` over runs the covariance recursion does not depend on the data
    and is computed once for all runs; missing data enter through `observed`. Small
    states (`n, m ≤ linalg.UNROLL_MAX`, without `square_root`) carry the entries of the
    mean and covariance through the scan and run the step entry by entry, which XLA
    fuses into a few loops over the runs under `vmap` (the same arithmetic).

    **Example:**

    ```python
    result = jdrkf.KalmanFilter()(model, prior, ys)   # ys: (T, m)
    runs = jax.vmap(jdrkf.KalmanFilter(), in_axes=(None, None, 0))(model, prior, ys_runs)
    missing = jdrkf.KalmanFilter()(model, prior, ys, observed=~jnp.isnan(ys))
    ```
    """

    throw: bool = eqx.field(default=True, static=True)  # positional here: AbstractFilter's, not keyword-only
    square_root: bool = eqx.field(default=False, static=True, kw_only=True)
    shared_covariance: ClassVar[bool] = True

    def init(self, model: LinearModel, prior: Gaussian):
        return _sqrt.initial(prior) if self.square_root else prior

    def step(self, model, state, y, t, u=None, key: PRNGKeyArray | None = None, observed=None):
        if self.square_root:
            mean_pred, chol_pred = _sqrt.predict_sqrt(model, *state, t, u)
            mean, chol, loglik, failed = update_sqrt(model, mean_pred, chol_pred, y, t, observed=observed)
            pred, filt = Gaussian(mean_pred, _sqrt.outer(chol_pred)), Gaussian(mean, _sqrt.outer(chol))
            info = {"predicted_chol_cov": chol_pred, "filtered_chol_cov": chol}
            return (mean, chol), StepOutput(predicted=pred, filtered=filt, loglik=loglik, info=info, result=step_result(failed, filt))
        if self._entrywise(model):
            _, out = _entrywise.kalman_step(model, _entrywise.gaussian(state), y, t, u, observed)
            return out.filtered, out
        pred = predict(model, state, t, u)
        filt, loglik, failed = update(model, pred, y, t, observed=observed)
        out = StepOutput(predicted=pred, filtered=filt, loglik=loglik, info=None, result=step_result(failed, filt))
        return filt, out

    def _entrywise(self, model: LinearModel) -> bool:
        return not self.square_root and _entrywise.applies(model.state_dim, model.obs_dim)

    def _scanned(self, model, state0):
        # Small states: the scan carries the entries of the mean and covariance (see
        # `_entrywise`), which under `vmap` are contiguous arrays over the runs.
        if not self._entrywise(model):
            return super()._scanned(model, state0)

        def step(model, state, y, t, u=None, key=None, observed=None):
            return _entrywise.kalman_step(model, state, y, t, u, observed)

        return _entrywise.gaussian(state0), step


class SteadyStateGain(eqx.Module):
    """Steady-state quantities of a time-invariant model: predicted covariance `P`
    (solution of the filtering DARE), innovation covariance `S = H P Hᵀ + R`, gain
    `K = P Hᵀ S⁻¹` and filtered covariance `(I − K H) P (I − K H)ᵀ + K R Kᵀ`.

    `converged` (boolean scalar) is the failure signal: `False` when these are not the
    stabilizing steady state (see `SteadyStateKalmanFilter.solve`; gains assembled by other
    solvers carry their solver's certificate).
    """

    predicted_cov: Float[Array, "n n"]
    innovation_cov: Float[Array, "m m"]
    gain: Float[Array, "n m"]
    filtered_cov: Float[Array, "n n"]
    converged: Bool[Array, ""]


def _is_stable(a: Float[Array, "n n"], squarings: int = 64) -> Bool[Array, ""]:
    """`ρ(a) < 1` (to working precision): `a^N → 0` for `N = 2^squarings` iff the
    spectral radius is below one, so `a` is squared repeatedly (matrix products only,
    no nonsymmetric eigensolver) and the result must be finite and below `1/2`."""
    with jax.default_matmul_precision("highest"):  # no TF32 rounding on GPUs
        power = lax.fori_loop(0, squarings, lambda _, b: b @ b, a)
    return jnp.all(jnp.isfinite(power)) & (jnp.max(jnp.abs(power)) < 0.5)


def _steady_state_converged(model: LinearModel, p, s, gain) -> Bool[Array, ""]:
    """Checks that only the stabilizing solution of the filtering DARE passes:

    1. `P`, `S`, `K` finite;
    2. the Riccati residual `F P Fᵀ − F K H P Fᵀ + G Q Gᵀ − P` at most `√eps` times the
       sum of the norms (max-abs) of its four terms;
    3. `P` symmetric (to `√eps`) and positive semidefinite (`λ_min(P) ≥ −psd_rtol · |λ|_max`);
    4. the error dynamics `F (I − K H)` stable (spectral radius `< 1`).

    The stabilizing solution is the unique PSD solution meeting 4; it exists iff `(F, H)`
    is detectable and `(F, G Q^½)` has no uncontrollable mode on the unit circle, and the
    doubling solver reaches it when `(F, G Q^½)` is moreover stabilizable. Without it
    (e.g. an undetectable unstable mode) no gain passes 4.
    """
    p, s, gain = (lax.stop_gradient(x) for x in (p, s, gain))
    f, h = (lax.stop_gradient(x) for x in (model.F, model.H))
    gqg = lax.stop_gradient(model.G @ model.Q @ model.G.T)
    eps = jnp.finfo(p.dtype).eps
    finite = jnp.all(jnp.isfinite(p)) & jnp.all(jnp.isfinite(s)) & jnp.all(jnp.isfinite(gain))
    fpf, corr = f @ p @ f.T, f @ gain @ h @ p @ f.T
    norm = lambda x: jnp.max(jnp.abs(x), initial=0.0)
    residual = norm(fpf - corr + gqg - p) <= jnp.sqrt(eps) * (norm(fpf) + norm(corr) + norm(gqg) + norm(p))
    lam = jnp.linalg.eigvalsh(linalg.symmetrize(p))
    top = jnp.maximum(jnp.max(jnp.abs(lam)), jnp.finfo(p.dtype).tiny)
    symmetric = norm(p - p.T) <= jnp.sqrt(eps) * norm(p)
    psd = lam[0] >= -psd_rtol(p.dtype, p.shape[-1]) * top
    stable = _is_stable(f @ (jnp.eye(p.shape[-1], dtype=p.dtype) - gain @ h))
    return finite & residual & symmetric & psd & stable


class SteadyStateKalmanFilter(AbstractFilter):
    """Kalman filter with the constant (limiting) gain of a time-invariant model.

    `solve(model)` computes the steady state once (DARE by doubling, in JAX,
    differentiable by implicit differentiation — see `jdrkf.linalg.solve_dare`); each
    step then costs matrix–vector products only. The prior's mean starts the
    recursion; its covariance is not used (reported covariances are the steady ones
    from the first step on). Missing components of `y` (the call's `observed` mask)
    contribute no correction (their gain columns are dropped; the gain is not
    recomputed) and the log-likelihood marginalizes them, which costs an `m × m`
    Cholesky per step.

    A model without a stabilizing steady state (`solve(model).converged` false, e.g.
    `(F, H)` undetectable) raises `ValueError` when the model is concrete; a traced one
    gives `RESULTS.solver_not_converged` at every step.
    """

    throw: bool = eqx.field(default=True, static=True)  # positional here: AbstractFilter's, not keyword-only
    shared_covariance: ClassVar[bool] = True

    @staticmethod
    def solve(model: LinearModel) -> SteadyStateGain:
        """Steady-state covariances and gain of a time-invariant `model`.

        `converged` of the result is `False` when the stabilizing DARE solution does not
        exist or was not found (non-finite values, Riccati residual not small relative
        to its terms, `P` not symmetric PSD, or `F (I − K H)` not stable): e.g. for an
        undetectable `(F, H)`, or a mode on or outside the unit circle that the process
        noise does not excite.
        """
        if model.num_steps is not None:
            raise ValueError("SteadyStateKalmanFilter needs a time-invariant model (no leading time axis)")
        p = linalg.solve_dare(model.F, model.H, model.G @ model.Q @ model.G.T, model.R)
        s = linalg.symmetrize(model.H @ p @ model.H.T + model.R)
        gain = linalg.psd_solve(s, model.H @ p).T
        a = jnp.eye(model.state_dim, dtype=p.dtype) - gain @ model.H
        filt = linalg.symmetrize(a @ p @ a.T + gain @ model.R @ gain.T)
        converged = _steady_state_converged(model, p, s, gain)
        return SteadyStateGain(predicted_cov=p, innovation_cov=s, gain=gain, filtered_cov=filt, converged=converged)

    def init(self, model: LinearModel, prior: Gaussian):
        ss = self.solve(model)
        if is_concrete(ss.converged) and not bool(ss.converged):
            raise ValueError(
                "model: no stabilizing steady-state Kalman gain was found (SteadyStateKalmanFilter.solve(model)"
                ".converged is False); the steady state needs (F, H) detectable and (F, G Q^½) stabilizable. "
                "Use jdrkf.KalmanFilter for this model."
            )
        return prior.mean, ss, linalg.cholesky(ss.innovation_cov)

    def step(self, model, state, y, t, u=None, key: PRNGKeyArray | None = None, observed=None):
        state, out = constant_gain_step(model, state, y, u, None, observed)
        # A failed steady state (traced model) overrides the per-step codes it causes.
        result = RESULTS.where(state[1].converged, out.result, RESULTS.solver_not_converged)
        return state, StepOutput(predicted=out.predicted, filtered=out.filtered, loglik=out.loglik, info=out.info, result=result)

