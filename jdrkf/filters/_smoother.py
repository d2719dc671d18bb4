"""Rauch–Tung–Striebel smoothing on the outputs of any Gaussian filter of a linear model."""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
from jax import lax
from jaxtyping import Array, ArrayLike, Bool, Float, PRNGKeyArray

from .. import linalg
from .._gaussian import Gaussian
from .._models import LinearModel
from .._multisensor import MultiSensorModel
from .._validation import psd_rtol
from ._base import RESULTS, AbstractFilter, FilterResult, raise_if_failed, with_outputs
from ._dr_particle import DRParticleFilter
from ._particle import BootstrapPF
from ._unscented import EnsembleKF


_LINEAR_MODELS = (LinearModel, MultiSensorModel)
_SAMPLING_FILTERS = (BootstrapPF, DRParticleFilter, EnsembleKF)
NEEDED_OUTPUTS = ("filtered_means", "filtered_covariances", "predicted_means", "predicted_covariances")


class SmootherResult(eqx.Module):
    """Output of an RTS smoother over `T` steps (index `t` holds `x_k`, `k = t + 1`, as in
    `FilterResult`).

    **Fields:**

    - `smoothed_means`, `smoothed_covariances`: `(T, n)`, `(T, n, n)`, the law of `x_k | y_{1:T}`.
    - `smoothed_cross_covariances`: `(T, n, n)`, entry `t` is `Cov(x_k, x_{k−1} | y_{1:T})`
      (`k = t + 1`; entry 0 pairs `x_1` with `x_0`). dynamax's field of the same name holds
      `E[z_t z_{t+1}ᵀ | y]` instead: the transpose of our entry `t + 1` plus
      `m_{t+1|T} m_{t+2|T}ᵀ` (its states are our `x_1..x_T`).
    - `smoothed_initial_mean`, `smoothed_initial_covariance`: the law of `x_0 | y_{1:T}`
      (the prior, which no observation measures, smoothed).
    - `marginal_loglik`: the filter's `log p(y_{1:T})` (`None` if it was not requested,
      NaN where the filter defines none).
    - `filter_result`: the `FilterResult` of the forward pass.
    - `result`: a `RESULTS` code; the filter's code if its run failed, else
      `RESULTS.nonpositive_predicted_covariance` if a smoother gain could not be formed.
    """

    smoothed_means: Float[Array, "T n"]
    smoothed_covariances: Float[Array, "T n n"]
    smoothed_cross_covariances: Float[Array, "T n n"]
    smoothed_initial_mean: Float[Array, " n"]
    smoothed_initial_covariance: Float[Array, "n n"]
    marginal_loglik: Float[Array, ""] | None
    filter_result: FilterResult
    result: RESULTS


def _check_model(model: Any) -> None:
    if not isinstance(model, _LINEAR_MODELS):
        raise ValueError(
            f"model must be a jdrkf.LinearModel or jdrkf.MultiSensorModel (RTS smoothing needs a linear "
            f"transition), got {type(model).__name__}"
        )


def rts_backward(model: LinearModel | MultiSensorModel, prior: Gaussian, result: FilterResult) -> SmootherResult:
    r"""Rauch–Tung–Striebel backward pass on a filter's own moments (Rauch, Tung & Striebel 1965).

    For `k = T−1, …, 0`, from `m_{T|T}`, `P_{T|T}` (the last filtered law):

    $$G_k = P_{k|k} F_{k+1}^\top P_{k+1|k}^{-1},\quad
    m_{k|T} = m_{k|k} + G_k (m_{k+1|T} - m_{k+1|k}),$$

    $$P_{k|T} = P_{k|k} + G_k (P_{k+1|T} - P_{k+1|k}) G_k^\top,\quad
    \mathrm{Cov}(x_{k+1}, x_k \mid y_{1:T}) = P_{k+1|T} G_k^\top,$$

    where `F_{k+1}` is the matrix of step `k + 1`, `x_k → x_{k+1}` (`model.F`, or the
    array entry `model.F[k]` of a time-varying model), `m_{k|k}`, `P_{k|k}` and `m_{k+1|k}`, `P_{k+1|k}` are the filter's
    filtered and predicted moments, and `k = 0` uses the prior (`m_{0|0}`, `P_{0|0}`).
    The predicted moments are the filter's own: for a distributionally robust filter,
    `P_{k+1|k}` is its worst-case (least-favourable) predicted covariance, and controls,
    noise means and missing data act only through them (the backward pass needs no `y`).

    `result` must hold `filtered_means`, `filtered_covariances`, `predicted_means` and
    `predicted_covariances` (run the filter with `outputs="all"`, or use `jdrkf.smooth`).
    Covariances and gains are computed from covariances only, so under `jax.vmap` over
    runs they stay unbatched whenever the filter's covariances are. A predicted covariance
    that is not numerically positive definite gives `RESULTS.nonpositive_predicted_covariance`
    (the smoothed moments are then NaN); one that does not dominate `F_{k+1} P_{k|k} F_{k+1}ᵀ`
    (an indefinite implied process noise, which a Wasserstein worst case can produce) gives
    `RESULTS.inconsistent_predicted_covariance`: no joint Gaussian law of `(x_k, x_{k+1})` has
    those moments, and the smoothed covariances may be indefinite. A failed filter run keeps
    its own code.
    """
    _check_model(model)
    if not isinstance(prior, Gaussian):
        raise ValueError(f"prior must be a jdrkf.Gaussian, got {type(prior).__name__}")
    if not isinstance(result, FilterResult):
        raise ValueError(f"result must be a jdrkf.FilterResult, got {type(result).__name__}")
    missing = [name for name in NEEDED_OUTPUTS if getattr(result, name) is None]
    if missing:
        raise ValueError(
            f"result has no {', '.join(missing)}: run the filter with outputs='all' (or with these names), "
            "or call jdrkf.smooth(filter, model, prior, ys)"
        )
    n = model.state_dim
    means, covs = result.filtered_means, result.filtered_covariances
    if means.ndim != 2 or means.shape[1] != n or prior.mean.shape != (n,):
        raise ValueError(
            f"result.filtered_means has shape {tuple(means.shape)} and the prior dimension {prior.mean.shape[-1]}, "
            f"but the state dimension is {n} (expected (T, {n}); for vmapped results, vmap rts_backward too)"
        )
    num_steps = means.shape[0]
    if isinstance(model, LinearModel):
        model.check_horizon(num_steps)
    with jax.default_matmul_precision("highest"):
        # Laws of x_0..x_T given y up to their own time: the prior, then the filtered ones.
        filt_means = jnp.concatenate([prior.mean[None], means])
        filt_covs = jnp.concatenate([prior.cov[None], covs])

        def body(carry, xs):
            mean_next, cov_next = carry  # law of x_{k+1} | y_{1:T}
            t, mean_f, cov_f, mean_p, cov_p = xs  # x_k | y_{1:k}; x_{k+1} | y_{1:k}; t = k
            f = model.F if model.F.ndim == 2 else model.F[t]
            fp = f @ cov_f
            gain = linalg.psd_solve(cov_p, fp).T  # G_k = P_{k|k} Fᵀ P_{k+1|k}⁻¹
            mean = mean_f + gain @ (mean_next - mean_p)
            cov = linalg.symmetrize(cov_f + gain @ (cov_next - cov_p) @ gain.T)
            # The joint law of (x_k, x_{k+1}) | y_{1:k} exists iff P_{k+1|k} − F P_{k|k} Fᵀ ⪰ 0.
            implied = jnp.linalg.eigvalsh(linalg.symmetrize(cov_p - fp @ f.T))[0]
            consistent = implied >= -psd_rtol(cov_p.dtype, n) * jnp.max(jnp.abs(cov_p))
            return (mean, cov), (mean, cov, cov_next @ gain.T, consistent)

        xs = (jnp.arange(num_steps), filt_means[:-1], filt_covs[:-1], result.predicted_means, result.predicted_covariances)
        (init_mean, init_cov), (sm_means, sm_covs, cross, consistent) = lax.scan(
            body, (filt_means[-1], filt_covs[-1]), xs, reverse=True
        )
    # A failed gain (non-PD P_{k+1|k}) makes P_{k|T} and every earlier one NaN.
    finite = jnp.all(jnp.isfinite(sm_covs))
    ok = result.result == RESULTS.successful
    code = RESULTS.where(ok & ~finite, RESULTS.nonpositive_predicted_covariance, result.result)
    code = RESULTS.where(ok & finite & ~jnp.all(consistent), RESULTS.inconsistent_predicted_covariance, code)
    return SmootherResult(
        smoothed_means=jnp.concatenate([sm_means[1:], means[-1:]]),
        smoothed_covariances=jnp.concatenate([sm_covs[1:], covs[-1:]]),
        smoothed_cross_covariances=cross,
        smoothed_initial_mean=init_mean,
        smoothed_initial_covariance=init_cov,
        marginal_loglik=result.marginal_loglik,
        filter_result=result,
        result=code,
    )


class RTSSmoother(eqx.Module):
    """Forward filter + Rauch–Tung–Striebel backward pass (`jdrkf.rts_backward`) on the
    filter's own moments, for any filter of jdrkf that reports Gaussian moments of a
    linear model (`jdrkf.LinearModel`, or `jdrkf.MultiSensorModel` for the fusion filters).

    With a distributionally robust filter the backward pass uses its worst-case predicted
    covariances, so the smoothed estimate is consistent with the filter's robust model
    (DR-consistent; with zero radii it is the classical RTS smoother).

    **Arguments:**

    - `filter`: the forward filter. Its `outputs` gain the four fields the backward pass
      needs; `throw=True` also raises on a failed backward pass.

    Not supported (`ValueError`): sampling filters (`BootstrapPF`, `DRParticleFilter`,
    `EnsembleKF`), whose moments are Monte Carlo estimates, and filters of nonlinear
    models (`UnscentedKF`), whose transition is not a matrix `F`.

    Call it like a filter: `RTSSmoother(flt)(model, prior, ys, key=None, *, inputs=None,
    observed=None) -> SmootherResult`. Missing data enter through the filter's `observed`
    mask. Under `jax.vmap(smoother, in_axes=(None, None, 0))` with no mask (or one shared
    mask), the covariances and gains of both passes are computed once for all runs.

    **Example:**

    ```python
    sm = jdrkf.RTSSmoother(jdrkf.WassersteinDRKF(0.1, 0.1))(model, prior, ys)
    sm.smoothed_means, sm.smoothed_covariances, sm.smoothed_cross_covariances
    ```
    """

    filter: AbstractFilter

    def __check_init__(self):
        flt = self.filter
        if not isinstance(flt, AbstractFilter):
            raise ValueError(f"filter must be a jdrkf filter (an AbstractFilter), got {type(flt).__name__}")
        name = type(flt).__name__
        if isinstance(flt, _SAMPLING_FILTERS) or type(flt).stochastic_init:
            raise ValueError(
                f"RTS smoothing needs a filter with Gaussian moments of a linear model; {name} is a sampling filter "
                "(BootstrapPF, DRParticleFilter and EnsembleKF report Monte Carlo moments)"
            )
        if not any(issubclass(t, _LINEAR_MODELS) for t in flt.model_types):
            raise ValueError(
                f"RTS smoothing needs a filter of a linear model (LinearModel or MultiSensorModel); {name} runs on "
                f"{', '.join(t.__name__ for t in flt.model_types)} (UnscentedKF and the particle filters are not supported)"
            )

    def __call__(
        self,
        model: LinearModel | MultiSensorModel,
        prior: Gaussian,
        ys: Float[ArrayLike, "T m"],
        key: PRNGKeyArray | None = None,
        *,
        inputs: Float[ArrayLike, "T p"] | None = None,
        observed: Bool[ArrayLike, "T m"] | None = None,
    ) -> SmootherResult:
        """Filter `ys` (`ys[t] = y_{t+1}`; arguments as in the filter's call), then smooth."""
        _check_model(model)
        flt = with_outputs(self.filter, tuple(set(self.filter.outputs) | set(NEEDED_OUTPUTS)))
        res = rts_backward(model, prior, flt(model, prior, ys, key, inputs=inputs, observed=observed))
        return raise_if_failed(res, res.result) if self.filter.throw else res


def smooth(
    flt: AbstractFilter,
    model: LinearModel | MultiSensorModel,
    prior: Gaussian,
    ys: Float[ArrayLike, "T m"],
    key: PRNGKeyArray | None = None,
    *,
    inputs: Float[ArrayLike, "T p"] | None = None,
    observed: Bool[ArrayLike, "T m"] | None = None,
) -> SmootherResult:
    """`RTSSmoother(flt)(model, prior, ys, key, inputs=inputs, observed=observed)`: run
    `flt` and the RTS backward pass on its moments (see `jdrkf.RTSSmoother`)."""
    return RTSSmoother(flt)(model, prior, ys, key, inputs=inputs, observed=observed)
