"""Extended Kalman filters for `jdrkf.NonlinearModel`: the EKF, the iterated EKF, and any
Gaussian filter of a linear model (the distributionally robust ones included) applied to the
model linearised at each step."""

from __future__ import annotations

from collections.abc import Sequence
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
from jax import lax
from jaxtyping import Array, ArrayLike, Bool, Float, Int, PRNGKeyArray, PyTree

from .. import linalg
from .._gaussian import Gaussian
from .._models import LinearModel
from .._nonlinear import NonlinearModel
from .._validation import check_count, is_concrete
from ._base import DEFAULT_OUTPUTS, RESULTS, AbstractFilter, StepOutput
from ._kalman import KalmanFilter


def _jacobians(fn, x, noise_mean):
    """`(∂fn/∂x, ∂fn/∂e)` at `(x, noise_mean)` by forward mode, and `fn(x, noise_mean)`."""
    jac = jax.jacfwd(lambda a, b: (fn(a, b), fn(a, b)), argnums=(0, 1), has_aux=True)
    (dx, de), value = jac(x, noise_mean)
    return dx, de, value


class _Transition(eqx.Module):
    """Linearised transition of one step: `F`, `G` at `(m, μ_w)`, `m⁻ = f(m, μ_w)`."""

    f_x: Float[Array, "n n"]
    f_w: Float[Array, "n q"]
    pred_mean: Float[Array, " n"]


def _linearize_transition(model: NonlinearModel, mean: Float[Array, " n"], t) -> _Transition:
    f_x, f_w, pred_mean = _jacobians(lambda x, w: model.transition(x, w, t), mean, model.process_mean)
    return _Transition(f_x, f_w, pred_mean)


def _linearize(model: NonlinearModel, mean: Float[Array, " n"], t, tr: _Transition, point: Float[Array, " n"]):
    r"""The linear model of step `t`, by first-order Taylor expansion of the transition at the
    filtered mean `m` of `x_{k-1}` (`tr`) and of the observation at the point `x̄`:

    $$x_k \approx m^- + F (x_{k-1} - m) + G (w - \mu_w),\qquad
      y_k \approx h(\bar x, \mu_v) + H (x_k - \bar x) + D (v - \mu_v),$$

    `H = ∂h/∂x (x̄, μ_v)`, `D = ∂h/∂v (x̄, μ_v)` (`G = D = I` for additive noise), written as a
    `LinearModel` (`F`, `G`, `Q`, `process_mean = μ_w`, control matrix `B = I`; `H`,
    `D R Dᵀ`, `noise_mean = h(x̄, μ_v) − H x̄`) with the input `u = m⁻ − F m − G μ_w`, so that
    its Kalman predict and update are the extended Kalman filter's. Returns
    `(model, u, finite)`, `finite` when all four Jacobians are finite."""
    h_x, h_v, y_hat = _jacobians(lambda x, v: model.observe(x, v, t), point, model.measurement_mean)
    r = model.R if model.additive else linalg.symmetrize(h_v @ model.R @ h_v.T)
    lin = LinearModel(
        F=tr.f_x, H=h_x, Q=model.Q, R=r, G=tr.f_w, B=jnp.eye(mean.shape[0], dtype=mean.dtype),
        process_mean=model.process_mean, noise_mean=y_hat - h_x @ point,
    )
    u = tr.pred_mean - tr.f_x @ mean - tr.f_w @ model.process_mean
    finite = jnp.all(jnp.array([jnp.all(jnp.isfinite(j)) for j in (tr.f_x, tr.f_w, h_x, h_v)]))
    return lin, u, finite


class ExtendedKF(AbstractFilter):
    r"""Extended Kalman filter for `jdrkf.NonlinearModel`, optionally iterated, and its
    distributionally robust versions by linearisation.

    Each step linearises the model with `jax.jacfwd`: the transition at the filtered mean
    `m = m_{k-1}` and the noise mean `μ_w` (`F = ∂f/∂x`, `G = ∂f/∂w`), the observation at the
    predicted mean `m⁻ = f(m, μ_w)` and `μ_v` (`H = ∂h/∂x`, `D = ∂h/∂v`; `G = D = I` for
    additive noise). The step of `filter`, a filter of linear models, then runs on that linear
    model. With the default `KalmanFilter()` this is the EKF
    (Särkkä, *Bayesian Filtering and Smoothing*, Sec. 5.2; non-additive noise through `G`, `D`):

    $$m^- = f(m, \mu_w),\quad P^- = F P F^\top + G Q G^\top,\quad
      S = H P^- H^\top + D R D^\top,\quad K = P^- H^\top S^{-1},$$

    $$m_k = m^- + K\,(y_k - h(m^-, \mu_v)),\quad P_k = (I - K H) P^- (I - K H)^\top + K D R D^\top K^\top.$$

    With `filter=DRKF(state_set=..., noise_set=..., outliers=...)` (or `WassersteinKF`,
    `HuberKF`, `TauKF`, `RiskSensitiveKF`, …) the worst case of the filter's ambiguity sets is
    taken around the linearised `P⁻` and `D R Dᵀ` and the robust update uses the linearised
    `H`: the DR filter applied to the EKF step. On a `NonlinearModel` whose `f`, `h` are
    linear the result equals that filter on the corresponding `LinearModel`.

    `iterations = N > 1` gives the iterated EKF (Bell & Cathey 1993): the observation is
    relinearised `N − 1` times at the last updated mean, a Gauss–Newton iteration for the MAP
    estimate of `x_k` (for the Kalman filter),

    $$x^{(i+1)} = m^- + K_i\,\big(y_k - h(x^{(i)}, \mu_v) - H_i (m^- - x^{(i)})\big),
      \qquad x^{(0)} = m^-,$$

    with `H_i`, `D_i`, `K_i` at `x^{(i)}`; the reported update (mean, covariance and
    log-likelihood) is the last one. With a DR `filter` every iteration is that filter's
    update (its worst case solved again), so the cost grows `N`-fold.

    **Arguments:**

    - `filter`: a filter of `jdrkf.LinearModel`s whose state is its filtered `Gaussian`
      (default `KalmanFilter()`); its own `throw` and `outputs` are not used.
    - `iterations`: `N ≥ 1` linearisations of the observation per step (1: the EKF).
    - `throw`, `outputs`: as in `jdrkf.KalmanFilter`.

    A step whose Jacobians are not finite reports `RESULTS.nonfinite_jacobian` (a concrete
    prior at which they are not finite raises `ValueError`); the other codes are those of
    `filter`. `info` holds the Jacobians `F`, `H` of the step and `filter`'s own `info`.
    The covariances depend on the data through the linearisation points, so under `vmap`
    they are computed per run. The loglik is `filter`'s, on the linearised model.

    **Example:**

    ```python
    ekf = jdrkf.ExtendedKF()(model, prior, ys)
    iekf = jdrkf.ExtendedKF(iterations=5)(model, prior, ys)
    dr_ekf = jdrkf.ExtendedKF(jdrkf.DRKF(state_set=Wasserstein(0.1), noise_set=Wasserstein(0.1)))
    ```
    """

    filter: AbstractFilter
    iterations: int = eqx.field(static=True)
    model_types: ClassVar[tuple[type, ...]] = (NonlinearModel,)

    def __init__(
        self,
        filter: AbstractFilter | None = None,
        *,
        iterations: int = 1,
        throw: bool = True,
        outputs: str | Sequence[str] = DEFAULT_OUTPUTS,
    ):
        filter = KalmanFilter() if filter is None else filter
        if not isinstance(filter, AbstractFilter) or LinearModel not in filter.model_types or filter.stochastic_init:
            raise ValueError(
                "filter must be a deterministic jdrkf filter of linear models (KalmanFilter, DRKF, WassersteinKF, "
                f"HuberKF, ...), got {type(filter).__name__}"
            )
        self.filter = filter
        self.iterations = check_count("iterations", iterations)
        self.throw, self.outputs = bool(throw), outputs

    def init(self, model: NonlinearModel, prior: Gaussian) -> PyTree:
        if not isinstance(prior, Gaussian):
            raise ValueError(f"prior must be a jdrkf.Gaussian, got {type(prior).__name__}")
        t = jnp.zeros((), jnp.arange(1).dtype)
        tr = _linearize_transition(model, prior.mean, t)
        lin, _, finite = _linearize(model, prior.mean, t, tr, tr.pred_mean)
        if is_concrete(finite) and not bool(finite):
            raise ValueError("prior: the Jacobians of f and h at the prior mean (and its prediction) are not finite")
        if not isinstance(eqx.filter_eval_shape(self.filter.init, lin, prior), Gaussian):
            raise ValueError(
                f"filter: {type(self.filter).__name__} keeps a state other than its filtered Gaussian, "
                "so it cannot be linearised around (use KalmanFilter, DRKF, WassersteinKF, HuberKF, TauKF, ...)"
            )
        return self.filter.init(lin, prior)

    def step(
        self,
        model: NonlinearModel,
        state: Gaussian,
        y: Float[Array, " m"],
        t: Int[ArrayLike, ""],
        u: None = None,
        key: PRNGKeyArray | None = None,
        observed: Bool[Array, " m"] | None = None,
    ) -> tuple[Gaussian, StepOutput]:
        if observed is not None and not self.filter.supports_missing:
            raise ValueError(f"{type(self.filter).__name__} does not support missing observations (observed must be None)")

        tr = _linearize_transition(model, state.mean, t)

        def linear_step(point):
            lin, u_lin, finite = _linearize(model, state.mean, t, tr, point)
            new_state, out = self.filter.step(lin, state, y, t, u_lin, key, observed)
            return lin, finite, new_state, out

        point = tr.pred_mean
        if self.iterations > 1:  # x⁽ⁱ⁺¹⁾ = the mean updated with the observation linearised at x⁽ⁱ⁾
            point = lax.fori_loop(0, self.iterations - 1, lambda _, p: linear_step(p)[3].filtered.mean, point)
        lin, finite, new_state, out = linear_step(point)
        result = RESULTS.where(finite, out.result, RESULTS.nonfinite_jacobian)
        info = {"transition_jacobian": lin.F, "observation_jacobian": lin.H, "filter": out.info}
        out = StepOutput(predicted=out.predicted, filtered=out.filtered, loglik=out.loglik, info=info, result=result)
        return new_state, out
