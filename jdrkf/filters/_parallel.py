r"""Parallel-in-time Kalman filter and RTS smoother (associative scans).

Särkkä & García-Fernández (2021, "Temporal parallelization of Bayesian smoothers") write the
filtering and smoothing recursions of a linear-Gaussian model as all-prefix sums of an
associative operator, which `jax.lax.associative_scan` evaluates in `O(log T)` sequential
depth (`O(T)` work, about twice the sequential filter's, in `n × n` matrix–matrix products).
The results are those of `KalmanFilter` and `jdrkf.smooth`, up to round-off.
"""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
from jax import lax
from jaxtyping import ArrayLike, Bool, Float, PRNGKeyArray

from .. import linalg
from .._gaussian import Gaussian, log_density
from .._models import LinearModel
from ._base import (
    DEFAULT_OUTPUTS,
    OUTPUTS,
    RESULTS,
    AbstractFilter,
    FilterResult,
    StepOutput,
    raise_if_failed,
)
from ._kalman import predict, update
from ._smoother import NEEDED_OUTPUTS, SmootherResult, rts_backward
from ._steps import measurement, step_result


def _filter_element(f, pred: Gaussian, h, r, resid):
    r"""Element `a_k = (A_k, b_k, C_k, η_k, J_k)` of step `k`: the Kalman update of
    `pred = N(c, Q̄)`, the law of `x_k` given `x_{k−1} = 0`, with the measurement `(h, r, resid)`.

    With `S = h Q̄ hᵀ + r`, `K = Q̄ hᵀ S⁻¹` and `e = resid − h c` (Joseph form for `C`):
    `A = (I − K h) F`, `b = c + K e`, `C = (I − K h) Q̄ (I − K h)ᵀ + K r Kᵀ`,
    `η = (h F)ᵀ S⁻¹ e`, `J = (h F)ᵀ S⁻¹ h F`. Then `p(x_k | x_{k−1}, y_k) = N(A x_{k−1} + b, C)`
    and `p(y_k | x_{k−1}) ∝ exp(−½ x_{k−1}ᵀ J x_{k−1} + η ᵀ x_{k−1})`.
    """
    c, qbar = pred.mean, pred.cov
    chol = linalg.cholesky(linalg.symmetrize(h @ qbar @ h.T + r))
    gain = linalg.cho_solve(chol, h @ qbar).T
    innov = resid - h @ c
    a = jnp.eye(c.shape[0], dtype=c.dtype) - gain @ h
    hf = h @ f
    return (
        a @ f,
        c + gain @ innov,
        linalg.symmetrize(a @ qbar @ a.T + gain @ r @ gain.T),
        hf.T @ linalg.cho_solve(chol, innov),
        linalg.symmetrize(hf.T @ linalg.cho_solve(chol, hf)),
    )


def _combine_filter(first, second):
    r"""`a_i ⊗ a_j` (`a_i` earlier in time): with `M = I + C_i J_j`,

    `A = A_j M⁻¹ A_i`, `b = A_j M⁻¹ (b_i + C_i η_j) + b_j`, `C = A_j M⁻¹ C_i A_jᵀ + C_j`,
    `η = A_iᵀ M⁻ᵀ (η_j − J_j b_i) + η_i`, `J = A_iᵀ M⁻ᵀ J_j A_i + J_i`
    (`M⁻ᵀ = (I + J_j C_i)⁻¹`; one LU factorization of `M`, never singular: its
    eigenvalues are those of `I + C_i^½ J_j C_i^½ ⪰ I`)."""
    a1, b1, c1, eta1, j1 = first
    a2, b2, c2, eta2, j2 = second
    lu = jax.scipy.linalg.lu_factor(jnp.eye(a1.shape[0], dtype=a1.dtype) + c1 @ j2)
    left = jax.scipy.linalg.lu_solve(lu, a2.T, trans=1).T  # A_j M⁻¹
    right = jax.scipy.linalg.lu_solve(lu, a1).T  # A_iᵀ M⁻ᵀ
    return (
        left @ a1,
        left @ (b1 + c1 @ eta2) + b2,
        linalg.symmetrize(left @ c1 @ a2.T + c2),
        right @ (eta2 - j2 @ b1) + eta1,
        linalg.symmetrize(right @ j2 @ a1 + j1),
    )


def _combine_smoother(later, earlier):
    r"""Smoothing operator, scanned backward in time (`earlier` = element `k`):
    `E = E_k E_l`, `g = E_k g_l + g_k`, `L = E_k L_l E_kᵀ + L_k`."""
    e2, g2, l2 = later
    e1, g1, l1 = earlier
    return e1 @ e2, e1 @ g2 + g1, linalg.symmetrize(e1 @ l2 @ e1.T + l1)


def _first_failure(codes: RESULTS) -> RESULTS:
    """The first non-successful code of a stacked sequence (successful if none)."""
    idx = jnp.argmax(codes != RESULTS.successful)
    return jax.tree.map(lambda v: v[idx], codes)


class ParallelKalmanFilter(AbstractFilter):
    r"""The Kalman filter evaluated in parallel over time (Särkkä & García-Fernández 2021).

    A call runs `jax.lax.associative_scan` over one element per step instead of a sequential
    `lax.scan`: `O(log T)` sequential depth for `O(T)` work of `n × n` matrix products, which
    pays off on GPUs for long series (on a CPU the sequential `KalmanFilter` is faster; see
    `benchmarks/parallel_kf.py`). It returns the same `FilterResult` as `KalmanFilter` with the
    same `outputs` (filtered and predicted moments, log-likelihood increments and their sum),
    and the same result codes.

    It is a filter (an `AbstractFilter`) rather than a function so that every consumer of
    filters accepts it: `jax.vmap` over runs, `jdrkf.smooth` / `RTSSmoother`, `montecarlo`.
    `init`/`step` are the Kalman filter's (one step has nothing to parallelize); only the
    call over a whole series differs. `jdrkf.parallel_smooth` adds the parallel backward pass.

    **Elements** (`k = 1..T`, array index `t = k − 1`; `F_t`, `H_t`, `R_t`, bias
    `c_t = B_t u_t + G_t μ_w`, `Q̄_t = G_t Q_t G_tᵀ`): element `k` describes step `k` on its own,
    `p(x_k | x_{k−1}, y_k) = N(A_k x_{k−1} + b_k, C_k)` and `p(y_k | x_{k−1}) ∝
    exp(−½ x_{k−1}ᵀ J_k x_{k−1} + η_kᵀ x_{k−1})`, from the Kalman update of `N(c_t, Q̄_t)` with
    `y_k`: `S = H Q̄ Hᵀ + R`, `K = Q̄ Hᵀ S⁻¹`, `A_k = (I − K H) F`, `b_k = c + K (y_k − μ_v − H c)`,
    `C_k = (I − K H) Q̄`, `η_k = Fᵀ Hᵀ S⁻¹ (y_k − μ_v − H c)`, `J_k = Fᵀ Hᵀ S⁻¹ H F`. Element 1
    absorbs the prior: the same update of the prediction `N(F m_0 + c, F P_0 Fᵀ + Q̄)` with
    `A_1 = 0`, `η_1 = 0`, `J_1 = 0`. The operator (with `M = I + C_i J_j`)

    $$A_{ij} = A_j M^{-1} A_i,\quad b_{ij} = A_j M^{-1}(b_i + C_i \eta_j) + b_j,\quad
    C_{ij} = A_j M^{-1} C_i A_j^\top + C_j,$$

    $$\eta_{ij} = A_i^\top M^{-\top}(\eta_j - J_j b_i) + \eta_i,\quad
    J_{ij} = A_i^\top M^{-\top} J_j A_i + J_i$$

    is associative, and the prefix `a_1 ⊗ … ⊗ a_k` has `b = m_{k|k}`, `C = P_{k|k}`. The
    predicted moments then follow in parallel from the filtered ones (`predict`), and the
    log-likelihood increments `log N(y_k; H m_{k|k−1} + μ_v, H P_{k|k−1} Hᵀ + R)` from them.

    Missing entries (`observed` false) drop their rows from `H`, `R` and the residual, as in
    `KalmanFilter`; a fully missing step is the element `(F, c, Q̄, 0, 0)`. Each element needs
    `H Q̄ Hᵀ + R ≻ 0` on the observed rows (always true for `R ≻ 0`). Under `vmap` over runs
    without a per-run mask, `A, C, J` and every covariance stay unbatched.

    **Arguments:**

    - `throw`: raise (through `eqx.error_if`) when a run fails; else only set `result`.
    - `outputs`: the `FilterResult` fields to fill (see `jdrkf.AbstractFilter`).

    **Example:**

    ```python
    result = jdrkf.ParallelKalmanFilter(outputs="all")(model, prior, ys)
    ```
    """

    throw: bool = eqx.field(default=True, static=True)  # positional here: AbstractFilter's, not keyword-only
    shared_covariance: ClassVar[bool] = True

    def init(self, model: LinearModel, prior: Gaussian) -> Gaussian:
        return prior

    def step(self, model, state, y, t, u=None, key: PRNGKeyArray | None = None, observed=None):
        pred = predict(model, state, t, u)
        filt, loglik, failed = update(model, pred, y, t, observed=observed)
        return filt, StepOutput(predicted=pred, filtered=filt, loglik=loglik, info=None, result=step_result(failed, filt))

    def _run(self, model, prior, ys, key, inputs, observed) -> FilterResult:
        if ys.shape[0] == 0:
            return super()._run(model, prior, ys, key, inputs, observed)
        res = _parallel_filter(model, prior, ys, inputs, observed)
        outs = {name: res[name] if name in self.outputs else None for name in OUTPUTS}
        out = FilterResult(**outs, result=res["result"])
        return raise_if_failed(out, out.result) if self.throw else out


@jax.jit
def _parallel_filter(model: LinearModel, prior: Gaussian, ys, inputs, observed) -> dict:
    """Every `FilterResult` field of the Kalman filter from one associative scan (jitted: the
    scan is many small operations, slow to dispatch one by one in an eager call)."""
    ts = jnp.arange(ys.shape[0])
    point = Gaussian(jnp.zeros_like(prior.mean), jnp.zeros_like(prior.cov))  # x_{k−1} = 0
    obs, h, r, resid = jax.vmap(lambda t, y, o: measurement(model, y, t, o))(ts, ys, observed)
    # Element k: the step-t transition from x_{k−1} = 0; element 1 from the prior (F replaced by 0).
    fs = jax.vmap(lambda t: model.at(t).F)(ts)
    fs = fs.at[0].set(jnp.zeros_like(fs[0]))
    preds = jax.vmap(lambda t, u: predict(model, point, t, u))(ts, inputs)
    first = predict(model, prior, 0, None if inputs is None else inputs[0])
    preds = jax.tree.map(lambda stacked, x: stacked.at[0].set(x), preds, first)
    elements = jax.vmap(_filter_element)(fs, preds, h, r, resid)
    _, means, covs, _, _ = lax.associative_scan(jax.vmap(_combine_filter), elements)

    # Predicted moments from the filtered ones, then the log-likelihood increments.
    prev_means = jnp.concatenate([prior.mean[None], means[:-1]])
    prev_covs = jnp.concatenate([prior.cov[None], covs[:-1]])
    predicted = jax.vmap(lambda t, m, p, u: predict(model, Gaussian(m, p), t, u))(ts, prev_means, prev_covs, inputs)

    def loglik(pred, o, h, r, resid):
        chol = linalg.cholesky(linalg.symmetrize(h @ pred.cov @ h.T + r))
        increment = log_density(chol, resid - h @ pred.mean, jnp.sum(o.astype(resid.dtype)))
        return increment, ~jnp.all(jnp.isfinite(chol))

    increments, failed = jax.vmap(loglik)(predicted, obs, h, r, resid)
    codes = jax.vmap(lambda f, m, p: step_result(f, Gaussian(m, p)))(failed, means, covs)
    result = _first_failure(codes)
    # As in AbstractFilter.__call__: a non-finite mean persists, so the last one is checked.
    result = RESULTS.where((result == RESULTS.successful) & ~jnp.all(jnp.isfinite(means[-1])), RESULTS.nonfinite_state, result)
    nan = jnp.isnan(ys) if observed is None else jnp.isnan(ys) & observed
    result = RESULTS.where(jnp.any(nan), RESULTS.nan_observation, result)
    return {
        "filtered_means": means,
        "filtered_covariances": covs,
        "predicted_means": predicted.mean,
        "predicted_covariances": predicted.cov,
        "loglik_increments": increments,
        "marginal_loglik": jnp.sum(increments),
        "info": None,
        "result": result,
    }


def parallel_smooth(
    model: LinearModel,
    prior: Gaussian,
    ys: Float[ArrayLike, "T m"],
    *,
    inputs: Float[ArrayLike, "T p"] | None = None,
    observed: Bool[ArrayLike, "T m"] | None = None,
    throw: bool = True,
) -> SmootherResult:
    r"""Rauch–Tung–Striebel smoother evaluated in parallel over time (Särkkä & García-Fernández 2021).

    Runs `ParallelKalmanFilter` (outputs: the default ones and the predicted moments), then a
    reverse `jax.lax.associative_scan` over one element per state `x_k`, `k = 0..T`. With the
    filtered moments `m_{k|k}`, `P_{k|k}` (the prior for `k = 0`), the predicted ones
    `m_{k+1|k}`, `P_{k+1|k}` and `F` of the transition `x_k → x_{k+1}` (array index `k`),
    element `k < T` is `p(x_k | x_{k+1}, y_{1:k}) = N(E_k x_{k+1} + g_k, L_k)`:

    $$E_k = P_{k|k} F^\top P_{k+1|k}^{-1},\quad g_k = m_{k|k} - E_k m_{k+1|k},\quad
    L_k = P_{k|k} - E_k P_{k+1|k} E_k^\top,$$

    element `T` is `(0, m_{T|T}, P_{T|T})`, and the operator, applied from the end,

    $$E_{kl} = E_k E_l,\quad g_{kl} = E_k g_l + g_k,\quad L_{kl} = E_k L_l E_k^\top + L_k$$

    gives `g = m_{k|T}`, `L = P_{k|T}` for the suffix `a_k ⊗ … ⊗ a_T`; the lag-one
    cross-covariances are `Cov(x_{k+1}, x_k | y_{1:T}) = P_{k+1|T} E_kᵀ`. The result equals
    `jdrkf.smooth(jdrkf.KalmanFilter(), model, prior, ys, ...)` up to round-off (the same
    `SmootherResult` fields and result codes). A function rather than a smoother class: only
    the Kalman filter has this parallel form (the DR filters' covariance recursions are not
    associative); `jdrkf.smooth(jdrkf.ParallelKalmanFilter(), ...)` runs the parallel filter
    with the sequential backward pass.

    **Arguments:** `model`, `prior`, `ys` (`ys[t] = y_{t+1}`), `inputs`, `observed` as for a
    filter call; `throw`: raise (through `eqx.error_if`) when the filter or the backward pass
    fails, else only set `result`.
    """
    flt = ParallelKalmanFilter(throw=False, outputs=DEFAULT_OUTPUTS + NEEDED_OUTPUTS)
    res = flt(model, prior, ys, inputs=inputs, observed=observed)
    if res.filtered_means.shape[0] == 0:
        out = rts_backward(model, prior, res)
    else:
        with jax.default_matmul_precision("highest"):  # as in filter calls: no TF32 on GPUs
            out = _parallel_backward(model, prior, res)
    return raise_if_failed(out, out.result) if throw else out


@jax.jit
def _parallel_backward(model: LinearModel, prior: Gaussian, res: FilterResult) -> SmootherResult:
    means, covs = res.filtered_means, res.filtered_covariances
    # Laws of x_k | y_{1:k} for k = 0..T−1 (the prior first).
    prev_means = jnp.concatenate([prior.mean[None], means[:-1]])
    prev_covs = jnp.concatenate([prior.cov[None], covs[:-1]])

    def element(t, m, p, m_pred, p_pred):
        e = linalg.psd_solve(p_pred, model.at(t).F @ p).T  # E_k = P_{k|k} Fᵀ P_{k+1|k}⁻¹
        return e, m - e @ m_pred, linalg.symmetrize(p - e @ p_pred @ e.T)

    ts = jnp.arange(means.shape[0])
    gains, g, low = jax.vmap(element)(ts, prev_means, prev_covs, res.predicted_means, res.predicted_covariances)
    last = (jnp.zeros_like(covs[-1]), means[-1], covs[-1])
    elements = jax.tree.map(lambda a, b: jnp.concatenate([a, b[None]]), (gains, g, low), last)
    _, sm_means, sm_covs = lax.associative_scan(jax.vmap(_combine_smoother), elements, reverse=True)
    cross = sm_covs[1:] @ jnp.swapaxes(gains, -1, -2)
    # A predicted covariance that is not positive definite makes its gain NaN.
    ok = res.result == RESULTS.successful
    code = RESULTS.where(ok & ~jnp.all(jnp.isfinite(sm_covs)), RESULTS.nonpositive_predicted_covariance, res.result)
    return SmootherResult(
        smoothed_means=sm_means[1:],
        smoothed_covariances=sm_covs[1:],
        smoothed_cross_covariances=cross,
        smoothed_initial_mean=sm_means[0],
        smoothed_initial_covariance=sm_covs[0],
        marginal_loglik=res.marginal_loglik,
        filter_result=res,
        result=code,
    )
