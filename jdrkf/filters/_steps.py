"""Step pieces shared by the Gaussian filters: the measurement of a step with missing
components decoupled, the per-step result code and the constant-gain step.

Package-internal: the filters import these names; they are not part of the public API.
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Array, Bool, Float

from .. import linalg
from .._gaussian import Gaussian, log_density
from .._models import LinearModel
from .._validation import psd_rtol
from ._base import RESULTS, StepOutput


def masked_measurement(
    mdl: LinearModel, y: Float[Array, " m"], observed: Bool[Array, " m"], noise_cov: Float[Array, "m m"] | None = None
):
    """Rows of missing components (`observed` false) are decoupled: `H` row and residual
    set to zero and the `R` (or `noise_cov`) row/column replaced by the identity's. The
    update then equals the update with only the observed rows, with static shapes."""
    obs_f = observed.astype(y.dtype)
    h = mdl.H * obs_f[:, None]
    r = (mdl.R if noise_cov is None else noise_cov) * (obs_f[:, None] * obs_f[None, :]) + jnp.diag(1.0 - obs_f)
    resid = jnp.where(observed, y - mdl.noise_mean, 0.0)
    return observed, h, r, resid


def measurement(model: LinearModel, y: Float[Array, " m"], t, observed: Bool[Array, " m"] | None):
    """`(observed, H, R, y − μ_v)` of step `t`, with the rows that `observed` marks missing
    decoupled (`observed=None`: all rows used, nothing depends on `y` but the residual)."""
    mdl = model.at(t)
    if observed is not None:
        return masked_measurement(mdl, y, observed)
    return jnp.ones(y.shape, bool), mdl.H, mdl.R, y - mdl.noise_mean


def is_psd(cov: Float[Array, "n n"]) -> Bool[Array, ""]:
    """`λ_min(cov) ≥ −c n eps · Tr cov` (`c` of `psd_rtol`): the Cholesky factor of
    `cov + (c n eps Tr(cov) + tiny) I` is finite (singular PSD matrices, zero included, pass).
    False for non-finite entries."""
    n = cov.shape[-1]
    shift = psd_rtol(cov.dtype, n) * jnp.abs(jnp.trace(cov)) + jnp.finfo(cov.dtype).tiny
    return jnp.all(jnp.isfinite(linalg.cholesky(cov + shift * jnp.eye(n, dtype=cov.dtype))))


def step_result(failed, belief: Gaussian) -> RESULTS:
    """Per-step code from the covariance path (the means are checked once per run by
    `AbstractFilter.__call__`, so this costs nothing per run when the covariances are shared):
    a failed update, a non-finite covariance, or one that lost positive semidefiniteness
    beyond rounding (float32 on ill-conditioned systems)."""
    finite = jnp.all(jnp.isfinite(belief.cov))
    psd = is_psd(belief.cov)
    code = RESULTS.where(psd, RESULTS.successful, RESULTS.indefinite_covariance)
    return RESULTS.where(failed, RESULTS.nonpositive_innovation, RESULTS.where(finite, code, RESULTS.nonfinite_state))


def constant_gain_step(model, state, y, u, noise_cov, observed, converged=True):
    """One step with the constant gain of `state = (mean, SteadyStateGain, chol(S))`;
    `noise_cov` is the measurement covariance behind `S` (default `R`; used for missing data)."""
    mean, ss, chol_s = state
    mm = linalg.matmul
    mean_pred = mm(model.F, mean) + mm(model.G, model.process_mean)
    if model.B is not None:
        mean_pred = mean_pred + mm(model.B, u)
    innov = y - model.noise_mean - mm(model.H, mean_pred)
    if observed is not None:
        # Drop missing components; the log-likelihood is the marginal of N(0, S) on the rest.
        _, h, r, _ = masked_measurement(model, y, observed, noise_cov)
        innov = jnp.where(observed, innov, 0.0)
        chol_obs = linalg.cholesky(linalg.symmetrize(h @ ss.predicted_cov @ h.T + r))
        num_observed = jnp.sum(observed.astype(innov.dtype))
    else:
        chol_obs, num_observed = chol_s, y.shape[0]
    mean_filt = mean_pred + mm(ss.gain, innov)
    loglik = log_density(chol_obs, innov, num_observed)
    pred = Gaussian(mean_pred, ss.predicted_cov)
    filt = Gaussian(mean_filt, ss.filtered_cov)
    failed = ~jnp.all(jnp.isfinite(chol_s))
    result = step_result(failed, filt)
    result = RESULTS.where((result == RESULTS.successful) & ~jnp.asarray(converged), RESULTS.solver_not_converged, result)
    out = StepOutput(predicted=pred, filtered=filt, loglik=loglik, info=None, result=result)
    return (mean_filt, ss, chol_s), out
