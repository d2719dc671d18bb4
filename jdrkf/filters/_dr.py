"""The distributionally robust state estimator of Wang & Ye (2022) and its special
cases used as baselines: the Huber KF and the Wasserstein KF."""

from __future__ import annotations

from collections.abc import Sequence
from typing import ClassVar

import equinox as eqx
import jax.numpy as jnp
from jax.scipy.linalg import solve_triangular
from jaxtyping import Array, ArrayLike, Float, PRNGKeyArray

from .. import linalg
from .._gaussian import Gaussian, log_density
from .._validation import check_scalar, renamed, renamed_attribute
from ..sets._base import AbstractAmbiguitySet
from ..sets._outliers import AbstractOutlierModel, EpsContamination
from ..sets._solve import worst_case, worst_case_joint
from ..sets._wasserstein import Wasserstein
from . import _sqrt
from ._base import DEFAULT_OUTPUTS, RESULTS, AbstractFilter, StepOutput
from ._kalman import predict
from ._steps import measurement, step_result


def _result(failed, sol, filt, parts):
    """Step code; an out-of-range traced hyper-parameter of any of `parts` (sets, outlier
    model; `None` skipped) takes precedence over the failures it causes."""
    res = step_result(failed, filt)
    res = RESULTS.where((res == RESULTS.successful) & ~sol.converged, RESULTS.solver_not_converged, res)
    for part in parts:
        if part is not None:
            res = RESULTS.where(part.valid(), res, RESULTS.invalid_hyperparameter)
    return res


def decoupled_step(flt, model, state, y, t, u, observed, state_set, noise_set, outliers):
    """Algorithm 1 / Theorem 9: nominal prediction (eqs. 46–47), worst-case covariances
    (eq. 34 or 36), robust update (eqs. 48–49)."""
    pred = predict(model, state, t, u)
    observed, h, r, resid = measurement(model, y, t, observed)
    num_obs = jnp.sum(observed.astype(resid.dtype))
    dtype = pred.cov.dtype
    i_min = jnp.ones((), dtype) if outliers is None else outliers.i_min().astype(dtype)
    sol = worst_case(state_set, noise_set, pred.cov, h, r, i_min=i_min, rtol=flt.rtol, max_iter=flt.max_iter)
    sx, sv = sol.state_cov, sol.noise_cov
    innov = resid - h @ pred.mean
    chol = linalg.cholesky(linalg.symmetrize(h @ sx @ h.T + sv))
    failed = ~jnp.all(jnp.isfinite(chol))
    if outliers is None:
        z = linalg.cho_solve(chol, innov)
    else:  # S^{-1/2} ψ(S^{-1/2} s) with the Cholesky square root S = L Lᵀ
        mu = solve_triangular(chol, innov, lower=True)
        z = solve_triangular(chol.T, outliers.psi(mu).astype(dtype), lower=False)
    mean = pred.mean + sx @ h.T @ z
    gain = linalg.cho_solve(chol, h @ sx).T
    a = jnp.eye(sx.shape[0], dtype=dtype) - gain @ h
    # Eq. 49, Σx − i Σx Hᵀ S⁻¹ H Σx, written as a convex combination of PSD terms.
    cov = linalg.symmetrize((1.0 - i_min) * sx + i_min * (a @ sx @ a.T + gain @ sv @ gain.T))
    filt = Gaussian(mean, cov)
    info = {"nominal_prior_cov": pred.cov, "noise_cov": sv, "iterations": sol.iterations, "gap": sol.gap}
    out = StepOutput(
        predicted=Gaussian(pred.mean, sx),
        filtered=filt,
        loglik=log_density(chol, innov, num_obs),
        info=info,
        result=_result(failed, sol, filt, (state_set, noise_set, outliers)),
    )
    return filt, out


def _joint_step(flt, model, state, y, t, u, observed, joint_set):
    """Theorem 8: one ambiguity set on the covariance of `(x_k, y_k)`; the estimate is
    the conditional mean under the worst-case joint Gaussian."""
    pred = predict(model, state, t, u)
    observed, h, r, resid = measurement(model, y, t, observed)
    num_obs = jnp.sum(observed.astype(resid.dtype))
    n = pred.cov.shape[0]
    cross = pred.cov @ h.T
    joint = jnp.block([[pred.cov, cross], [cross.T, h @ cross + r]])
    sol = worst_case_joint(joint_set, linalg.symmetrize(joint), n, rtol=flt.rtol, max_iter=flt.max_iter)
    sxx, sxy, syy = sol.cov[:n, :n], sol.cov[:n, n:], sol.cov[n:, n:]
    chol = linalg.cholesky(syy)
    failed = ~jnp.all(jnp.isfinite(chol))
    gain = linalg.cho_solve(chol, sxy.T).T
    innov = resid - h @ pred.mean
    filt = Gaussian(pred.mean + gain @ innov, linalg.symmetrize(sxx - gain @ sxy.T))
    info = {"nominal_prior_cov": pred.cov, "joint_cov": sol.cov, "iterations": sol.iterations, "gap": sol.gap}
    out = StepOutput(
        predicted=Gaussian(pred.mean, sxx),
        filtered=filt,
        loglik=log_density(chol, innov, num_obs),
        info=info,
        result=_result(failed, sol, filt, (joint_set,)),
    )
    return filt, out


def _decoupled_step_sqrt(flt, model, state, y, t, u, observed, state_set, noise_set, outliers):
    """`decoupled_step` in square-root form (state `(x̂, S)`, `P = S Sᵀ`): nominal
    prediction `S⁻ = tria([F S, G S_Q])`, the worst-case covariances as factors
    (`√θ₂ S⁻` for moment sets, else the Cholesky factor of the solver's matrix), the
    array-form update `tria([[S_v*, H S_x*], [0, S_x*]]) = [[L, 0], [L_k, L_p]]`, the mean
    `x̂⁻ + L_k ψ(L⁻¹ s)` (eq. 48; `L_k = Σx*HᵀL⁻ᵀ`) and the factor
    `tria([√(1 − i) S_x*, √i L_p])` of eq. 49's `(1 − i) Σx* + i L_p L_pᵀ`."""
    mean_pred, chol_pred = _sqrt.predict_sqrt(model, *state, t, u)
    observed, h, r, resid = measurement(model, y, t, observed)
    num_obs = jnp.sum(observed.astype(resid.dtype))
    nominal = _sqrt.outer(chol_pred)
    dtype = nominal.dtype
    i_min = jnp.ones((), dtype) if outliers is None else outliers.i_min().astype(dtype)
    sol = worst_case(state_set, noise_set, nominal, h, r, i_min=i_min, rtol=flt.rtol, max_iter=flt.max_iter)
    sx = _sqrt.worst_case_factor(state_set, chol_pred, sol.state_cov)
    sv = _sqrt.worst_case_factor(noise_set, linalg.psd_factor(r), sol.noise_cov)
    chol_s, cross, chol, failed = _sqrt.split(_sqrt.array_update(sx, h, sv), h.shape[0])
    innov = resid - h @ mean_pred
    if outliers is None:
        mean = mean_pred + _sqrt.gain(chol_s, cross) @ innov
    else:
        mean = mean_pred + cross @ outliers.psi(solve_triangular(chol_s, innov, lower=True)).astype(dtype)
        chol = linalg.tria(jnp.concatenate([jnp.sqrt(1.0 - i_min) * sx, jnp.sqrt(i_min) * chol], axis=1))
    filt = Gaussian(mean, _sqrt.outer(chol))
    info = {"nominal_prior_cov": nominal, "noise_cov": sol.noise_cov, "iterations": sol.iterations, "gap": sol.gap,
            "predicted_chol_cov": sx, "filtered_chol_cov": chol}
    out = StepOutput(
        predicted=Gaussian(mean_pred, sol.state_cov),
        filtered=filt,
        loglik=log_density(chol_s, innov, num_obs),
        info=info,
        result=_result(failed, sol, filt, (state_set, noise_set, outliers)),
    )
    return (mean, chol), out


def _joint_step_sqrt(flt, model, state, y, t, u, observed, joint_set):
    """`_joint_step` in square-root form: with `(y, x)` ordered first, the factor of the
    worst-case joint covariance is `[[L, 0], [L_k, L_p]]` (`√θ₂` times the array-form
    factor of the nominal for a moment set, else the Cholesky factor of the solver's
    matrix), so the conditional mean is `x̂⁻ + L_k L⁻¹ s` and `L_p` is the factor of the
    Schur complement `S_xx − S_xy S_yy⁻¹ S_yx`."""
    mean_pred, chol_pred = _sqrt.predict_sqrt(model, *state, t, u)
    observed, h, r, resid = measurement(model, y, t, observed)
    num_obs = jnp.sum(observed.astype(resid.dtype))
    n, m = chol_pred.shape[0], h.shape[0]
    pred_cov = _sqrt.outer(chol_pred)
    cross = pred_cov @ h.T
    joint = jnp.block([[pred_cov, cross], [cross.T, h @ cross + r]])
    sol = worst_case_joint(joint_set, linalg.symmetrize(joint), n, rtol=flt.rtol, max_iter=flt.max_iter)
    yx = jnp.concatenate([jnp.arange(n, n + m), jnp.arange(n)])
    nominal_factor = _sqrt.array_update(chol_pred, h, linalg.psd_factor(r))
    low = _sqrt.worst_case_factor(joint_set, nominal_factor, sol.cov[yx][:, yx])
    chol_s, cross_f, chol, failed = _sqrt.split(low, m)
    innov = resid - h @ mean_pred
    filt = Gaussian(mean_pred + _sqrt.gain(chol_s, cross_f) @ innov, _sqrt.outer(chol))
    info = {"nominal_prior_cov": pred_cov, "joint_cov": sol.cov, "iterations": sol.iterations, "gap": sol.gap,
            "predicted_chol_cov": linalg.tria(low[m:]), "filtered_chol_cov": chol}
    out = StepOutput(
        predicted=Gaussian(mean_pred, sol.cov[:n, :n]),
        filtered=filt,
        loglik=log_density(chol_s, innov, num_obs),
        info=info,
        result=_result(failed, sol, filt, (joint_set,)),
    )
    return (filt.mean, chol), out


def _check_set(name, s):
    if s is not None and not isinstance(s, AbstractAmbiguitySet):
        raise ValueError(f"{name} must be a jdrkf.sets ambiguity set (Wasserstein, KL, Moment) or None, got {type(s).__name__}")
    return s


class DRKF(AbstractFilter):
    """Distributionally robust state estimator (Wang & Ye 2022, Algorithm 1, Theorem 9).

    Each step predicts with the nominal model (eqs. 46–47), finds the least-favourable
    prior `Σx*` in `state_set` around the predicted covariance and noise covariance
    `Σv*` in `noise_set` around `R` (eq. 34, 36 or the KL version; solved by
    `jdrkf.sets.worst_case`), then updates with the influence function `ψ` of the
    outlier model applied to the whitened innovation (eq. 48) and the worst-case
    posterior covariance `Σx* − i_min Σx*HᵀS*⁻¹HΣx*` (eq. 49).

    With `joint_set` instead (Theorem 8, outlier-free), one set bounds the covariance
    of `(x_k, y_k)` and the estimate is the worst-case conditional mean: with
    `Wasserstein(ρ)` this is the Wasserstein KF (`jdrkf.WassersteinKF`).

    Special cases (Theorem 10): all sets `None` or of zero radius → the Kalman filter;
    `Moment(θ)` for both state and noise → the fading-memory KF (`P* = θ P`);
    `outliers=EpsContamination(ε)` with zero radii → the Huber KF (`jdrkf.HuberKF`).

    **Arguments:**

    - `state_set`, `noise_set`: ambiguity sets (`jdrkf.sets.Wasserstein`, `KL`,
      `Moment`) for the prior of `x_k` and the law of `v_k`; `None` = nominal.
    - `outliers`: `jdrkf.sets.EpsContamination` or `EpsNormal`, or `None` (Gaussian).
    - `joint_set`: alternative to the two sets above (no outliers allowed).
    - `rtol`, `max_iter`: Frank–Wolfe tolerance (relative duality gap) and cap; a
      step that does not converge reports `RESULTS.solver_not_converged`.
    - `square_root` (keyword): carry Cholesky factors of the covariances (see
      `jdrkf.KalmanFilter`): worst cases of moment sets (and none) are factors in closed
      form, `√θ₂ S`; those of Wasserstein and KL sets are factored after each solve.
      The posterior of eq. 49 with outliers is `tria([√(1 − i) S_x*, √i L])`.
    - `throw`, `outputs`: as in `jdrkf.KalmanFilter`.

    Out-of-range set or outlier parameters raise `ValueError` when concrete; traced
    (under `jit`, `vmap`, `grad`) every step reports `RESULTS.invalid_hyperparameter`.

    The whitening `S*^{-1/2}` of eq. 48 is the Cholesky factor `L⁻¹` of `S* = L Lᵀ`
    (any square root is valid; for one output all coincide). `predicted` holds the
    worst-case prior `N(x̂_{k|k-1}, Σx*)`; `info` has the nominal prior covariance,
    the worst-case noise (or joint) covariance and the solver's iterations and gap.
    `loglik` is the log-density of `y_k` under the worst-case Gaussian predictive.

    **Example:**

    ```python
    from jdrkf.sets import Moment, EpsContamination
    mkf = jdrkf.DRKF(state_set=Moment(1.02), noise_set=Moment(1.02), outliers=EpsContamination(0.05, k=1.4))
    result = mkf(model, prior, ys)
    ```
    """

    state_set: AbstractAmbiguitySet | None = None
    noise_set: AbstractAmbiguitySet | None = None
    outliers: AbstractOutlierModel | None = None
    joint_set: AbstractAmbiguitySet | None = None
    rtol: float | None = eqx.field(default=None, static=True)
    max_iter: int = eqx.field(default=500, static=True)
    square_root: bool = eqx.field(default=False, static=True, kw_only=True)
    shared_covariance: ClassVar[bool] = True

    def __check_init__(self):
        _check_set("state_set", self.state_set)
        _check_set("noise_set", self.noise_set)
        _check_set("joint_set", self.joint_set)
        if self.outliers is not None and not isinstance(self.outliers, AbstractOutlierModel):
            raise ValueError(f"outliers must be jdrkf.sets.EpsContamination, EpsNormal or None, got {type(self.outliers).__name__}")
        if self.joint_set is not None and (self.state_set, self.noise_set, self.outliers) != (None, None, None):
            raise ValueError("joint_set excludes state_set, noise_set and outliers (Theorem 8 models (x, y) jointly, without outliers)")

    def init(self, model, prior: Gaussian):
        return _sqrt.initial(prior) if self.square_root else prior

    def step(self, model, state, y, t, u=None, key: PRNGKeyArray | None = None, observed=None):
        if self.joint_set is not None:
            joint_step = _joint_step_sqrt if self.square_root else _joint_step
            return joint_step(self, model, state, y, t, u, observed, self.joint_set)
        step_fn = _decoupled_step_sqrt if self.square_root else decoupled_step
        return step_fn(self, model, state, y, t, u, observed, self.state_set, self.noise_set, self.outliers)


class HuberKF(AbstractFilter):
    """Huber (M-estimation) Kalman filter as used by Wang & Ye (2022), i.e. Algorithm 1
    with ε-contamination outliers and no ambiguity (Theorem 10, case 5; Schick &
    Mitter's robust KF [34, Thm. 3]).

    Update: `x̂ = x̂⁻ + P⁻Hᵀ S^{-1/2} ψ_k(S^{-1/2} s)` with Huber's clip `ψ_k` at `k`
    (eq. 39) and `P = P⁻ − (1 − ε)(1 − 2Φ(−k)) P⁻HᵀS⁻¹HP⁻` (eqs. 42, 49). `k`
    defaults to `K(ε)` of Lemma 1; the paper's experiments use `ε = 0.05, k = 1.4`.
    Equal to `DRKF(outliers=EpsContamination(eps, k))`; `square_root` as there.
    """

    outliers: EpsContamination
    rtol: float | None = eqx.field(static=True)
    max_iter: int = eqx.field(static=True)
    square_root: bool = eqx.field(static=True)
    shared_covariance: ClassVar[bool] = True

    def __init__(self, eps: Float[ArrayLike, ""] = 0.05, k: Float[ArrayLike, ""] | None = None, *, throw: bool = True,
                 square_root: bool = False, outputs: str | Sequence[str] = DEFAULT_OUTPUTS):
        self.outliers = EpsContamination(eps, k)
        self.rtol, self.max_iter = None, 500
        self.throw, self.square_root, self.outputs = throw, square_root, outputs

    def init(self, model, prior: Gaussian):
        return _sqrt.initial(prior) if self.square_root else prior

    def step(self, model, state, y, t, u=None, key: PRNGKeyArray | None = None, observed=None):
        step_fn = _decoupled_step_sqrt if self.square_root else decoupled_step
        return step_fn(self, model, state, y, t, u, observed, None, None, self.outliers)


class WassersteinKF(AbstractFilter):
    """Wasserstein distributionally robust Kalman filter (Shafieezadeh-Abadeh, Nguyen,
    Kuhn, Mohajerin Esfahani, NeurIPS 2018): at each step the covariance of
    `(x_k, y_k)` predicted by the nominal model is replaced by the worst case in a
    `W₂` ball of radius `radius` (solved by `jdrkf.sets.wasserstein_mmse_joint`), and the
    estimate is the conditional mean under it. Equal to
    `DRKF(joint_set=Wasserstein(radius))` (Wang & Ye 2022, Theorem 10, case 6).

    The authors' Frank–Wolfe uses `2/(k+2)` steps, bisection and a relative gap of
    1e-4; jdrkf uses backtracking steps, Newton's method and a Newton polish, so its
    solution is exact to round-off (and differentiable in `radius`). `square_root=True`
    carries Cholesky factors: the worst-case joint covariance, ordered `(y, x)`, is
    factored after each solve, and its blocks give the gain and the filtered factor.
    (`rho=` is a deprecated alias of `radius`.)
    """

    radius: Float[Array, ""]
    rtol: float | None = eqx.field(static=True)
    max_iter: int = eqx.field(static=True)
    square_root: bool = eqx.field(static=True)
    shared_covariance: ClassVar[bool] = True

    def __init__(self, radius: Float[ArrayLike, ""] = None, *, rtol: float | None = None, max_iter: int = 500, throw: bool = True,
                 square_root: bool = False, outputs: str | Sequence[str] = DEFAULT_OUTPUTS, rho: Float[ArrayLike, ""] = None):
        self.radius = check_scalar("radius", renamed("rho", rho, "radius", radius, "WassersteinKF"))
        self.rtol, self.max_iter, self.throw, self.square_root, self.outputs = rtol, max_iter, throw, square_root, outputs

    rho = renamed_attribute("rho", "radius")

    def init(self, model, prior: Gaussian):
        return _sqrt.initial(prior) if self.square_root else prior

    def step(self, model, state, y, t, u=None, key: PRNGKeyArray | None = None, observed=None):
        joint_step = _joint_step_sqrt if self.square_root else _joint_step
        return joint_step(self, model, state, y, t, u, observed, Wasserstein(self.radius))
