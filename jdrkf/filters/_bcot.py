"""Bicausal optimal-transport (BCOT) distributionally robust Kalman filter (Han 2023,
"Distributionally robust Kalman filtering with volatility uncertainty", arXiv
2302.05993), the baseline of Jang, Hakobyan & Yang (2025). The worst-case problem of a
step and its solver are in `jdrkf.sets` (`BCOT`, `bcot_worst_case`).
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import ClassVar

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float, PRNGKeyArray

from .. import linalg
from .._gaussian import Gaussian, log_density
from .._validation import check_positive_int
from ..sets._bcot import BCOT
from ._base import DEFAULT_OUTPUTS, RESULTS, AbstractFilter, StepOutput
from ._kalman import predict
from ._steps import measurement, step_result


class BCOTKF(AbstractFilter):
    """Bicausal optimal-transport DR Kalman filter (Han 2023), the BCOT baseline of Jang,
    Hakobyan & Yang (2025; their code `jangminhyuk/SteadyStateDRKF`, `BCOT.py`).

    Each step finds the worst-case prior `Σ*` (around the previous posterior
    covariance), process covariance `Q*` (around `G Q Gᵀ`) and measurement covariance
    `R*` (around `R`) under one joint transport budget (`jdrkf.sets.bcot_worst_case`, on the set `jdrkf.sets.BCOT(radius)`), then
    predicts **once**, `x̂⁻ = F x̂ + B u + G μ_w` (the reference code `BCOT.py` applies
    `F` twice), and updates with the worst case:
    `P⁻ = FΣ*Fᵀ + Q*`, `K = P⁻Hᵀ(HP⁻Hᵀ + R*)⁻¹`, `x̂ = x̂⁻ + K(y − Hx̂⁻ − μ_v)`,
    posterior `(I − KH)P⁻(I − KH)ᵀ + KR*Kᵀ` (Joseph form), carried to the next step.

    **Arguments:**

    - `radius`: budget `≥ 0` on the **squared** transport cost (the authors' convention:
      their grid values are not comparable with a `W₂` radius `θ`, whose analogue is
      `θ²`). `radius = 0` is exactly the Kalman filter. Differentiable for `radius > 0`.
      Negative: `ValueError` when concrete, `RESULTS.invalid_hyperparameter` when traced.
    - `max_iter`: Newton iterations per step; a step that does not converge reports
      `RESULTS.solver_not_converged`.
    - `throw`, `outputs`: as in `jdrkf.KalmanFilter`. Missing components (the
      call's `observed` mask) are dropped from `H` (also in the weight `H = I + FᵀF + FᵀHᵀHF` of the cost); their
      decoupled unit-variance noise takes no part of the budget.

    The nominal covariances (`G Q Gᵀ`, `R`, the prior's covariance) must be positive
    definite. Reported: `predicted = N(x̂⁻, P⁻)` (worst case), `loglik` under
    `N(Hx̂⁻ + μ_v, HP⁻Hᵀ + R*)`, `info = {"prior_cov": Σ*, "process_cov": Q*,
    "noise_cov": R*, "value", "multiplier", "iterations", "residual", "gap"}` (see
    `BCOTWorstCase`).

    **Example:**

    ```python
    result = jdrkf.BCOTKF(radius=0.1)(model, prior, ys)
    result.info["iterations"]      # (T,) Newton iterations per step
    ```
    """

    set: BCOT  # noqa: A003
    max_iter: int = eqx.field(static=True)
    shared_covariance: ClassVar[bool] = True

    def __init__(self, radius: Float[ArrayLike, ""], *, max_iter: int = 100, throw: bool = True, outputs: str | Sequence[str] = DEFAULT_OUTPUTS):
        self.set = BCOT(radius)
        self.max_iter, self.throw, self.outputs = check_positive_int("max_iter", max_iter), throw, outputs

    @property
    def radius(self) -> Float[Array, ""]:
        """The budget of `set` (`jdrkf.sets.BCOT`)."""
        return self.set.radius

    def init(self, model, prior: Gaussian) -> Gaussian:
        return prior

    def step(self, model, state, y, t, u=None, key: PRNGKeyArray | None = None, observed=None):
        mdl = model.at(t)
        pred = predict(model, state, t, u)
        observed, h, r, resid = measurement(model, y, t, observed)
        num_obs = jnp.sum(observed.astype(resid.dtype))
        dtype = pred.cov.dtype
        qp = linalg.symmetrize(mdl.G @ mdl.Q @ mdl.G.T)
        sol = self.set.worst_case(state.cov, qp, r, mdl.F, h, self.max_iter)
        p = linalg.symmetrize(mdl.F @ sol.prior_cov @ mdl.F.T + sol.process_cov)
        chol = linalg.cholesky(linalg.symmetrize(h @ p @ h.T + sol.noise_cov))
        failed = ~jnp.all(jnp.isfinite(chol))
        gain = linalg.cho_solve(chol, h @ p).T
        innov = resid - h @ pred.mean
        e = jnp.eye(p.shape[0], dtype=dtype) - gain @ h
        filt = Gaussian(pred.mean + gain @ innov, linalg.symmetrize(e @ p @ e.T + gain @ sol.noise_cov @ gain.T))
        res = step_result(failed, filt)
        res = RESULTS.where((res == RESULTS.successful) & ~sol.converged, RESULTS.solver_not_converged, res)
        res = RESULTS.where(self.set.valid(), res, RESULTS.invalid_hyperparameter)
        info = {
            "prior_cov": sol.prior_cov,
            "process_cov": sol.process_cov,
            "noise_cov": sol.noise_cov,
            "value": sol.value,
            "multiplier": sol.multiplier,
            "iterations": sol.iterations,
            "residual": sol.residual,
            "gap": sol.gap,
        }
        out = StepOutput(
            predicted=Gaussian(pred.mean, p),
            filtered=filt,
            loglik=log_density(chol, innov, num_obs),
            info=info,
            result=res,
        )
        return filt, out
