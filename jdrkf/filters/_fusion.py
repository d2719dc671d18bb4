"""Centralized multi-sensor fusion filters (Chen, Li, Liu, He 2025, IEEE SPL): the centralized
KF, covariance intersection of local KF updates, and the marginal DR Kalman filter (Algorithm 1)."""

from __future__ import annotations

from typing import ClassVar, Literal

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import PRNGKeyArray

from .. import linalg
from .._gaussian import Gaussian, log_density
from .._multisensor import MultiSensorModel
from ..sets._intersection import covariance_intersection
from ..sets._marginal import AbstractMarginalSet, marginal_mmse
from ._base import RESULTS, AbstractFilter, StepOutput
from ._kalman import predict, update
from ._steps import step_result


class CKF(AbstractFilter):
    """Centralized Kalman filter: `jdrkf.KalmanFilter` on `model.as_linear()` (stacked
    measurements, block-diagonal `R` plus the known `cross_cov`). `ys` are the stacked
    measurements `(T, m)`; `throw`, `outputs` as in `jdrkf.KalmanFilter`."""

    shared_covariance: ClassVar[bool] = True
    model_types: ClassVar[tuple[type, ...]] = (MultiSensorModel,)

    def init(self, model: MultiSensorModel, prior: Gaussian) -> Gaussian:
        return prior

    def step(self, model, state, y, t, u=None, key: PRNGKeyArray | None = None, observed=None):
        lin = model.as_linear()
        pred = predict(lin, state, t, u)
        filt, loglik, failed = update(lin, pred, y, t, observed=observed)
        return filt, StepOutput(predicted=pred, filtered=filt, loglik=loglik, info=None, result=step_result(failed, filt))


# ----------------------------------------------------------------------------------------
# Covariance intersection
# ----------------------------------------------------------------------------------------


class CovarianceIntersection(AbstractFilter):
    """Covariance-intersection fusion of local Kalman updates (the CI baseline of Chen et al.
    2025, as in the authors' MATLAB code `lylechan42/MDRKF`).

    Each step predicts from the previous CI estimate (the common fused prior), lets every
    sensor `i` update it with its own `y^i` (local KF, `R_i`), and fuses the `p` local
    posteriors by CI (`covariance_intersection`): `ω` minimizes `log det P_CI`
    (`criterion="det"`) or `Tr P_CI` (`"trace"`). (MATLAB's `fusecovint`, which Chen et
    al.'s code calls, names these criteria but sets `ω_i ∝ 1 / det P_i` without minimizing.) The fused
    estimate is the next prior. The covariance path does not depend on the data.

    `ω` is found by projected gradient (see `ci_weights`); it is not differentiated.
    `info` holds `weights`, `gap`, `iterations`, `converged`; a non-converged weight search
    reports `RESULTS.solver_not_converged`. `loglik` is not defined (NaN). Missing
    observations are not supported (`observed` must be `None`).
    """

    criterion: Literal["det", "trace"] = eqx.field(default="det", static=True)
    rtol: float | None = eqx.field(default=None, static=True, kw_only=True)
    max_iter: int = eqx.field(default=200, static=True, kw_only=True)
    model_types: ClassVar[tuple[type, ...]] = (MultiSensorModel,)
    shared_covariance: ClassVar[bool] = True
    supports_missing: ClassVar[bool] = False

    def __check_init__(self):
        if self.criterion not in ("det", "trace"):
            raise ValueError(f"criterion must be 'det' or 'trace', got {self.criterion!r}")
        if int(self.max_iter) < 1:
            raise ValueError(f"max_iter must be a positive integer, got {self.max_iter}")

    def init(self, model: MultiSensorModel, prior: Gaussian) -> Gaussian:
        return prior

    def step(self, model, state, y, t, u=None, key: PRNGKeyArray | None = None, observed=None):
        pred = predict(model.as_linear(), state, t, u)
        offs = [0]
        for d in model.dims:
            offs.append(offs[-1] + d)
        locals_, failed = [], jnp.zeros((), bool)
        for i in range(model.num_sensors):
            filt_i, _, failed_i = update(model.sensor(i), pred, y[offs[i]:offs[i + 1]], t)
            locals_.append(filt_i)
            failed = failed | failed_i
        means = jnp.stack([g.mean for g in locals_])
        covs = jnp.stack([g.cov for g in locals_])
        fused, sol = covariance_intersection(means, covs, self.criterion, rtol=self.rtol, max_iter=self.max_iter)
        res = step_result(failed, fused)
        res = RESULTS.where((res == RESULTS.successful) & ~sol.converged, RESULTS.solver_not_converged, res)
        info = {"weights": sol.weights, "gap": sol.gap, "iterations": sol.iterations, "converged": sol.converged}
        nan = jnp.asarray(jnp.nan, fused.mean.dtype)
        return fused, StepOutput(predicted=pred, filtered=fused, loglik=nan, info=info, result=res)


# ----------------------------------------------------------------------------------------
# Marginal DR Kalman filter
# ----------------------------------------------------------------------------------------


class MarginalDRKF(AbstractFilter):
    """Marginal distributionally robust Kalman filter (Chen et al. 2025, Algorithm 1):
    MC-MDRKF with `jdrkf.sets.MarginalMoment(gamma1, gamma2)`, KL-MDRKF with
    `jdrkf.sets.MarginalKL(radius)`.

    Each step forms the nominal joint covariance `Σ` of `(x_k, y_k^1..y_k^p)` from the
    previous worst-case posterior covariance (eqs. 30–31, `model.joint_nominal_cov`), finds
    the least-favourable joint `S*` whose marginal blocks `(x, y^i)` lie in the per-sensor
    ambiguity sets (cross-sensor blocks free: the adversary picks the sensor correlations;
    problem (16), `jdrkf.sets.marginal_mmse`), and updates (eq. 32):
    `x̂ = F x̂⁻ + K*(y − H F x̂⁻)`, `K* = S*_xy S*_yy⁻¹`, `V = S*_xx − K* S*_yx`.

    The covariance path (`Σ`, `S*`, `K*`, `V`) does not depend on the data, so under
    `jax.vmap(flt, in_axes=(None, None, 0))` over Monte Carlo runs the worst-case problem is
    solved once per step for all runs, not once per run. With the call's `observed` mask,
    missing components are decoupled as in `jdrkf.KalmanFilter` (zero `H` row, unit noise,
    zero residual) before the worst case is solved: an approximation, and the covariance
    path then follows the mask (shared if the mask is).

    `predicted` holds `N(F x̂⁻, S*_xx)`; `loglik` is the log-density of `y_k` under the
    worst-case predictive `N(H F x̂⁻, S*_yy)`; `info` has the worst-case value, iterations,
    convergence flag, the nominal and worst-case joint covariances. Non-converged solves
    report `RESULTS.solver_not_converged`; radii out of range raise `ValueError` when
    concrete and report `RESULTS.invalid_hyperparameter` when traced.
    """

    set: AbstractMarginalSet  # noqa: A003
    rtol: float | None = eqx.field(default=None, static=True, kw_only=True)
    max_iter: int = eqx.field(default=2000, static=True, kw_only=True)
    shared_covariance: ClassVar[bool] = True
    model_types: ClassVar[tuple[type, ...]] = (MultiSensorModel,)

    def __check_init__(self):
        if not isinstance(self.set, AbstractMarginalSet):
            raise ValueError(f"set must be a marginal set (jdrkf.sets.MarginalMoment or MarginalKL), got {type(self.set).__name__}")

    def init(self, model: MultiSensorModel, prior: Gaussian) -> Gaussian:
        return prior

    def step(self, model, state, y, t, u=None, key: PRNGKeyArray | None = None, observed=None):
        n = model.state_dim
        dtype = state.cov.dtype
        mean_pred = model.F @ state.mean
        sigma = model.joint_nominal_cov(state.cov)
        if observed is not None:
            keep = jnp.concatenate([jnp.ones(n, bool), observed]).astype(dtype)
            unit = jnp.concatenate([jnp.zeros(n, dtype), 1.0 - observed.astype(dtype)])
            sigma = sigma * (keep[:, None] * keep[None, :]) + jnp.diag(unit)
            innov = jnp.where(observed, y - model.H @ mean_pred, 0.0)
            num_obs = jnp.sum(observed.astype(dtype))
        else:
            innov = y - model.H @ mean_pred
            num_obs = y.shape[0]
        res = marginal_mmse(sigma, n, model.dims, self.set, rtol=self.rtol, max_iter=self.max_iter)
        syy = linalg.symmetrize(res.cov[n:, n:])
        chol = linalg.cholesky(syy)
        failed = ~jnp.all(jnp.isfinite(chol))
        filt = Gaussian(mean_pred + res.gain @ innov, linalg.symmetrize(res.posterior_cov))
        result = step_result(failed, filt)
        result = RESULTS.where((result == RESULTS.successful) & ~res.converged, RESULTS.solver_not_converged, result)
        result = RESULTS.where(self.set.valid(), result, RESULTS.invalid_hyperparameter)
        info = {
            "value": res.value,
            "iterations": res.iterations,
            "converged": res.converged,
            "nominal_cov": sigma,
            "worst_case_cov": res.cov,
        }
        out = StepOutput(
            predicted=Gaussian(mean_pred, linalg.symmetrize(res.cov[:n, :n])),
            filtered=filt,
            loglik=log_density(chol, innov, num_obs),
            info=info,
            result=result,
        )
        return filt, out
