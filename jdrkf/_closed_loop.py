"""Closed-loop simulation: true system, state estimator and controller in one `lax.scan`.

Jang, Hakobyan & Yang (2025) compare estimators inside an LQR tracking loop, where
the estimate feeds back into the trajectory. `closed_loop` runs the true system, any
`jdrkf` filter and a controller together, so that Monte Carlo runs are a `jax.vmap`
over keys and the closed-loop cost can be differentiated with respect to the filter's
hyper-parameters (e.g. a robustness radius) with `jax.grad`.
"""

from __future__ import annotations

from typing import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
from jax import lax
from jaxtyping import Array, ArrayLike, Float, PRNGKeyArray

from . import linalg
from ._gaussian import Gaussian
from ._models import LinearModel
from ._noise import AbstractNoise
from ._simulate import check_law
from ._validation import as_float_array, check_shape
from .filters._base import RESULTS, AbstractFilter, raise_if_failed


@jax.jit
def _lqr_gain(A, B, Q, R):
    # Control DARE = filtering DARE of the dual system (F, H) = (Aᵀ, Bᵀ).
    P = linalg.solve_dare(A.T, B.T, linalg.symmetrize(Q), linalg.symmetrize(R))
    bp = B.T @ P
    return linalg.psd_solve(R + bp @ B, bp @ A)


class LQRController(eqx.Module):
    r"""Static state-feedback tracking controller `u = −K (x̂ − r)`.

    `gain` (`K`, shape `(p, n)`) is an array field, so it can be differentiated or
    vmapped like a filter hyper-parameter. Build the infinite-horizon LQR gain with
    `LQRController.design(A, B, Q, R)`.
    """

    gain: Float[Array, "p n"]

    def __init__(self, gain: Float[ArrayLike, "p n"]):
        self.gain = as_float_array("gain", gain, (2,))

    @staticmethod
    def design(
        A: Float[ArrayLike, "n n"], B: Float[ArrayLike, "n p"], Q: Float[ArrayLike, "n n"], R: Float[ArrayLike, "p p"]
    ) -> "LQRController":
        r"""Infinite-horizon discrete LQR for `x⁺ = A x + B u` and stage cost `xᵀQx + uᵀRu`.

        The control Riccati equation `P = AᵀPA − AᵀPB(R + BᵀPB)⁻¹BᵀPA + Q` is the
        filtering DARE of `jdrkf.linalg.solve_dare` with `F = Aᵀ`, `H = Bᵀ` (duality);
        `K = (R + BᵀPB)⁻¹BᵀPA`. Requires `(A, B)` stabilizable, `(A, Q^½)` detectable
        and `R` positive definite. Differentiable in all four matrices.
        """
        A = as_float_array("A", A, (2,))
        n = A.shape[0]
        check_shape("A", A, (n, n), "(A must be square)")
        B = as_float_array("B", B, (2,))
        check_shape("B", B, (n, None), f"since A is {n}x{n}")
        p = B.shape[1]
        Q = as_float_array("Q", Q, (2,))
        check_shape("Q", Q, (n, n), f"since A is {n}x{n}")
        R = as_float_array("R", R, (2,))
        check_shape("R", R, (p, p), f"since B has {p} columns")
        dtype = jnp.result_type(A, B, Q, R)
        return LQRController(_lqr_gain(*(x.astype(dtype) for x in (A, B, Q, R))))

    def __call__(self, estimate: Float[Array, " n"], reference: Float[Array, " n"]) -> Float[Array, " p"]:
        """`u = −K (x̂ − r)`."""
        return -self.gain @ (estimate - reference)


class ClosedLoopResult(eqx.Module):
    """One closed-loop run (index `t = 0..T`; under `jax.vmap`, a leading run axis).

    - `states`: `(T+1, n)`, true `x_0..x_T`.
    - `estimates`: `(T+1, n)`, the filter's `x̂_0..x̂_T` (filtered means).
    - `covariances`: `(T+1, n, n)`, the filter's reported filtered covariances.
    - `controls`: `(T+1, p)`, `u_0..u_T` (`u_T` is computed but not applied).
    - `observations`: `(T+1, m)`, `y_0..y_T`.
    - `reference`: `(T+1, n)`, the reference `r_0..r_T`.
    - `results`: `(T+1,)` per-step `RESULTS` codes (index 0: the update on `y_0`;
      `successful` there when `measure_initial=False`); `result`: the first failure.
    - `initial_state`: `(n,)`, `process_noise`: `(T, q)`, `measurement_noise`:
      `(T+1, m)`: the draws of `x_0`, `w_0..w_{T-1}` and `v_0..v_T`, so that an
      independent implementation can replay the run.
    """

    states: Float[Array, "T+1 n"]
    estimates: Float[Array, "T+1 n"]
    covariances: Float[Array, "T+1 n n"]
    controls: Float[Array, "T+1 p"]
    observations: Float[Array, "T+1 m"]
    reference: Float[Array, "T+1 n"]
    results: RESULTS
    result: RESULTS
    initial_state: Float[Array, " n"]
    process_noise: Float[Array, "T q"]
    measurement_noise: Float[Array, "T+1 m"]

    def cost(self, Q: Float[ArrayLike, "n n"], R: Float[ArrayLike, "p p"]) -> Float[Array, "..."]:
        """Quadratic tracking cost `Σ_{t=0}^{T} (x_t − r_t)ᵀQ(x_t − r_t) + u_tᵀ R u_t`
        (the `J` of Jang, Hakobyan & Yang 2025, which includes `u_T`). One value per run."""
        n, p = self.states.shape[-1], self.controls.shape[-1]
        Q = as_float_array("Q", Q, (2,))
        check_shape("Q", Q, (n, n), f"since the state dimension is {n}")
        R = as_float_array("R", R, (2,))
        check_shape("R", R, (p, p), f"since the control dimension is {p}")
        dtype = self.states.dtype
        e = self.states - self.reference
        u = self.controls
        return jnp.einsum("...ti,ij,...tj->...", e, Q.astype(dtype), e) + jnp.einsum(
            "...ti,ij,...tj->...", u, R.astype(dtype), u
        )

    def mse(self) -> Float[Array, "..."]:
        """Mean over `t = 0..T` of `‖x̂_t − x_t‖²` (Jang et al.'s "average MSE"). One value per run."""
        return jnp.mean(jnp.sum((self.estimates - self.states) ** 2, axis=-1), axis=-1)


def _initial_update_model(model: LinearModel) -> LinearModel:
    """Copy of the step-0 model with identity dynamics and no process noise or control:
    `F = I`, `Q = 0`, `μ_w = 0`, `B = None`. Every jdrkf prediction `F m + B u + G μ_w`,
    `F P Fᵀ + G Q Gᵀ` is then the identity, so one `filter.step` on it is the filter's
    measurement update of the prior with `y_0` (H, R, μ_v of step 0)."""
    mdl = model.at(0)
    n, q = mdl.state_dim, mdl.Q.shape[-1]
    dtype = mdl.F.dtype
    mdl = eqx.tree_at(
        lambda m: (m.F, m.Q, m.process_mean),
        mdl,
        (jnp.eye(n, dtype=dtype), jnp.zeros((q, q), dtype), jnp.zeros(q, dtype)),
    )
    return eqx.tree_at(lambda m: m.B, mdl, None)


def _draw_sequence(law, key, times, mean_fn, cov_fn):
    """One draw per entry of `times` (`law.sample(key_i, times[i])`), or Gaussian with the
    model's step-`t` mean and covariance when `law` is `None`."""
    keys = jax.random.split(key, times.shape[0])
    if law is not None:
        return jax.vmap(law.sample)(keys, times)

    def gaussian(k, t):
        mean = mean_fn(t)
        return mean + linalg.psd_sqrt(cov_fn(t)) @ jax.random.normal(k, mean.shape, mean.dtype)

    return jax.vmap(gaussian)(keys, times)


def closed_loop(
    key: PRNGKeyArray,
    filter: AbstractFilter,
    model: LinearModel,
    prior: Gaussian,
    controller: Callable[[Float[Array, " n"], Float[Array, " n"]], Float[Array, " p"]],
    reference: Float[ArrayLike, "T+1 n"],
    *,
    true_model: LinearModel | None = None,
    initial_state: Gaussian | AbstractNoise | None = None,
    process_noise: AbstractNoise | None = None,
    measurement_noise: AbstractNoise | None = None,
    measure_initial: bool = True,
) -> ClosedLoopResult:
    r"""Simulate a true system driven by a controller acting on a filter's estimates.

    Timeline (the `main.py` of Jang, Hakobyan & Yang's code), with `T = reference.shape[0] − 1`:
    `x_0 ~ initial_state`, `y_0 = H x_0 + v_0`; `x̂_0` is the prior mean updated with
    `y_0` (or the prior mean if `measure_initial=False`); for `t = 0..T−1`:
    `u_t = controller(x̂_t, r_t)`, `x_{t+1} = F_t x_t + B_t u_t + G_t w_t`,
    `y_{t+1} = H_t x_{t+1} + v_{t+1}`, and `x̂_{t+1}` is the filter's step `t`
    (predict with `u_t` under the nominal `model`, update with `y_{t+1}`). Finally
    `u_T = controller(x̂_T, r_T)` (reported, for the cost). Everything runs in one
    `lax.scan`.

    **Arguments:**

    - `key`: PRNG key. All random draws (`x_0`, `w`, `v`) come from it independently
      of the filter and controller (common random numbers: the same key gives the same
      noise whichever filter runs); stochastic filters get their own sub-keys.
    - `filter`: any `jdrkf.AbstractFilter`; `model`: its nominal `jdrkf.LinearModel`,
      which must have a control matrix `B`; `prior`: its `jdrkf.Gaussian` law of `x_0`.
    - `controller`: `(x̂_t, r_t) -> u_t` of shape `(p,)`, e.g. `jdrkf.LQRController`.
    - `reference`: `(T+1, n)` reference states `r_0..r_T`.
    - `true_model`: the simulated system (default `model`); same `n`, `m`, `p`.
    - `initial_state`: law of `x_0`, a `jdrkf.Gaussian` or any noise law (e.g.
      `jdrkf.UQuadraticNoise`); default `prior`.
    - `process_noise`, `measurement_noise`: true laws of `w` and `v`; default Gaussian
      with `true_model`'s means and covariances.
    - `measure_initial`: apply the update on `y_0` (Jang, Hakobyan & Yang do, for all filters but
      the risk-sensitive one).

    **The update on `y_0`** has no prediction before it. It is one `filter.step` on a copy
    of the step-0 nominal model with `F = I`, `Q = 0`, `μ_w = 0` and no control, which
    makes the prediction the identity for every jdrkf filter (`KalmanFilter`, `DRKF`,
    ...; `SteadyStateKalmanFilter` keeps the steady gain of `model`, computed in
    `init`). It is a full filter step otherwise: robust filters robustify the prior there
    (e.g. `DRKF` with a `Moment` set inflates `P_0`). `y_0` uses the step-0 `H`, `R`
    and noise law index 0, as `y_1` does; `v_{t+1}` is drawn with time index `t`.

    If `filter.throw`, a failed run raises (see `jdrkf.RESULTS`); otherwise inspect
    `result`. Differentiable with respect to array fields of `filter`, `controller`
    and `model` (e.g. `jax.grad` of `closed_loop(...).cost(Q, R)`).

    **Example:**

    ```python
    lqr = jdrkf.LQRController.design(model.F, model.B, Q_lqr, R_lqr)
    runs = jax.vmap(lambda k: jdrkf.closed_loop(k, jdrkf.KalmanFilter(), model, prior, lqr, ref))(keys)
    runs.cost(Q_lqr, R_lqr).mean(), runs.mse().mean()
    ```
    """
    if key is None:
        raise ValueError("closed_loop needs a PRNG key, e.g. jax.random.key(0)")
    if not isinstance(filter, AbstractFilter):
        raise ValueError(f"filter must be a jdrkf filter (jdrkf.AbstractFilter), got {type(filter).__name__}")
    if not isinstance(model, LinearModel):
        raise ValueError(f"model must be a jdrkf.LinearModel, got {type(model).__name__}")
    if model.B is None:
        raise ValueError("model has no control matrix B; closed_loop needs LinearModel(..., B=...) of shape (n, p)")
    true_model = model if true_model is None else true_model
    if not isinstance(true_model, LinearModel):
        raise ValueError(f"true_model must be a jdrkf.LinearModel, got {type(true_model).__name__}")
    if true_model.B is None:
        raise ValueError("true_model has no control matrix B; closed_loop needs LinearModel(..., B=...) of shape (n, p)")
    n, m, p = model.state_dim, model.obs_dim, model.B.shape[-1]
    got = (true_model.state_dim, true_model.obs_dim, true_model.B.shape[-1])
    if got != (n, m, p):
        raise ValueError(f"true_model has (n, m, p) = {got} but model has {(n, m, p)}; they must agree")
    dtype = model.F.dtype
    if true_model.F.dtype != dtype:
        raise ValueError(f"true_model has dtype {true_model.F.dtype} but model has dtype {dtype}; build both in one precision")
    if not isinstance(prior, Gaussian):
        raise ValueError(f"prior must be a jdrkf.Gaussian, got {type(prior).__name__}")
    if prior.mean.shape != (n,):
        raise ValueError(f"prior has dimension {prior.mean.shape[-1]} but the state dimension is {n}")
    if prior.mean.dtype != dtype:
        raise ValueError(f"prior has dtype {prior.mean.dtype} but the model has dtype {dtype}; build both in one precision")
    if not isinstance(measure_initial, bool):
        raise ValueError(f"measure_initial must be a bool, got {type(measure_initial).__name__}")
    reference = as_float_array("reference", reference, (2,))
    if reference.shape[1] != n or reference.shape[0] < 2:
        raise ValueError(f"reference has shape {tuple(reference.shape)} but expected (T+1, {n}) with T >= 1 (one row per time 0..T)")
    reference = reference.astype(dtype)
    num_steps = reference.shape[0] - 1
    model.check_horizon(num_steps)
    true_model.check_horizon(num_steps)
    initial_state = check_law("initial_state", prior if initial_state is None else initial_state, n, dtype)
    process_noise = check_law("process_noise", process_noise, true_model.Q.shape[-1], dtype)
    measurement_noise = check_law("measurement_noise", measurement_noise, m, dtype)
    for law in (process_noise, measurement_noise):
        if law is not None:
            law.check_horizon(num_steps)
    if not callable(controller):
        raise ValueError(f"controller must be callable as controller(estimate, reference_t), got {type(controller).__name__}")
    u_shape = jax.eval_shape(controller, prior.mean, reference[0])
    if getattr(u_shape, "shape", None) != (p,) or u_shape.dtype != dtype:
        shown = getattr(u_shape, "shape", type(u_shape).__name__)
        raise ValueError(f"controller(estimate, reference_t) must return a ({p},) array of dtype {dtype} (B has {p} columns), got {shown}")
    return _closed_loop(
        key, filter, model, prior, controller, reference, true_model, initial_state, process_noise, measurement_noise, measure_initial
    )


@eqx.filter_jit
def _closed_loop(key, flt, model, prior, controller, reference, true_model, x0_law, w_law, v_law, measure_initial):
    num_steps = reference.shape[0] - 1
    k_x0, k_w, k_v, k_flt = jax.random.split(key, 4)
    # --- all random draws first, from the key alone (common random numbers) ---
    x0 = x0_law.sample(k_x0, 0)
    w = _draw_sequence(
        w_law, k_w, jnp.arange(num_steps), lambda t: true_model.at(t).process_mean, lambda t: true_model.at(t).Q
    )
    # v_0 uses time index 0 (like v_1); v_{t+1} uses index t.
    v_times = jnp.concatenate([jnp.zeros(1, jnp.int32), jnp.arange(num_steps, dtype=jnp.int32)])
    v = _draw_sequence(v_law, k_v, v_times, lambda t: true_model.at(t).noise_mean, lambda t: true_model.at(t).R)
    flt_keys = jax.random.split(k_flt, num_steps + 1)

    # --- t = 0: measurement update of the prior with y_0 ---
    y0 = true_model.at(0).H @ x0 + v[0]
    state = flt.init(model, prior)
    if measure_initial:
        state, out0 = flt.step(_initial_update_model(model), state, y0, 0, None, flt_keys[0])
        est0, cov0, res0 = out0.filtered.mean, out0.filtered.cov, out0.result
    else:
        est0, cov0, res0 = prior.mean, prior.cov, RESULTS.successful

    def body(carry, xs):
        x, state, est, result = carry
        t, r_t, w_t, v_next, k = xs
        u = controller(est, r_t)
        tm = true_model.at(t)
        x_next = tm.F @ x + tm.B @ u + tm.G @ w_t
        y_next = tm.H @ x_next + v_next
        state, out = flt.step(model, state, y_next, t, u, k)
        result = RESULTS.where(result == RESULTS.successful, out.result, result)
        est_next = out.filtered.mean
        return (x_next, state, est_next, result), (x_next, est_next, out.filtered.cov, u, y_next, out.result)

    xs = (jnp.arange(num_steps), reference[:-1], w, v[1:], flt_keys[1:])
    (_, _, est_last, result), (xs_, ests, covs, us, ys, codes) = lax.scan(body, (x0, state, est0, res0), xs)
    u_last = controller(est_last, reference[-1])

    def cat(first, rest):
        return jnp.concatenate([first[None], rest])

    res = ClosedLoopResult(
        states=cat(x0, xs_),
        estimates=cat(est0, ests),
        covariances=cat(cov0, covs),
        controls=jnp.concatenate([us, u_last[None]]),
        observations=cat(y0, ys),
        reference=reference,
        results=jax.tree.map(cat, res0, codes),
        result=result,
        initial_state=x0,
        process_noise=w,
        measurement_noise=v,
    )
    return raise_if_failed(res, result) if flt.throw else res
