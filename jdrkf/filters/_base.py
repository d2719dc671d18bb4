"""Filter interface: `init`/`step` pairs scanned by `__call__`."""

from __future__ import annotations

import abc
import copy
from typing import Any, ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
from jax import lax
from jaxtyping import Array, ArrayLike, Float, Int, PRNGKeyArray, PyTree

from .._gaussian import Gaussian
from .._models import LinearModel
from .._validation import as_float_array


class RESULTS(eqx.Enumeration):
    """Outcome codes of a filter run (`FilterResult.result`).

    Compare with `result == jdrkf.RESULTS.successful`; under `vmap` this gives one
    boolean per run. A run reports the first failure that occurred in it.
    """

    successful = ""
    nonpositive_innovation = (
        "The innovation covariance H P Hᵀ + R was not numerically positive definite, so the "
        "Kalman update could not be computed. Check that R is positive definite, that the "
        "state covariance stays PSD (run in float64), and that the model is not diverging."
    )
    solver_not_converged = (
        "The worst-case covariance solver of a distributionally robust filter did not reach its "
        "tolerance within max_iter iterations. Raise max_iter, loosen rtol (float32 needs about "
        "1e-5), or check that the nominal covariances are well conditioned."
    )
    risk_sensitive_breakdown = (
        "The risk-sensitive inflation I − θ P was not positive definite (θ ≥ 1/λ_max of the predicted "
        "covariance), so the risk-sensitive recursion does not exist from this step on. Decrease theta, "
        "or use TauKF, which picks θ at each step."
    )
    nonfinite_state = (
        "The filtered mean or covariance became non-finite (inf/NaN). Common causes: NaN or inf "
        "in the inputs, an unstable model over a long horizon in float32, or an upstream bug."
    )


class StepOutput(eqx.Module):
    """What one `step` reports: the predicted and filtered laws of `x_k`, the
    log-likelihood increment `log p(y_k | y_{1:k-1})`, diagnostics and a result code."""

    predicted: Gaussian
    filtered: Gaussian
    loglik: Float[Array, ""]
    info: PyTree
    result: RESULTS


class FilterResult(eqx.Module):
    """Output of a filter run over `T` steps (index `t` holds step `k = t + 1`).

    **Fields:**

    - `filtered_means`, `filtered_covariances`: `(T, n)`, `(T, n, n)`, the law of `x_k | y_{1:k}`.
    - `predicted_means`, `predicted_covariances`: the law of `x_k | y_{1:k-1}`.
    - `marginal_loglik`: `log p(y_{1:T})` where the filter defines it (NaN otherwise).
    - `loglik_increments`: `(T,)`, its per-step terms.
    - `info`: filter-specific diagnostics, stacked over time.
    - `result`: a `RESULTS` code, the first failure of the run.
    """

    filtered_means: Float[Array, "T n"]
    filtered_covariances: Float[Array, "T n n"]
    predicted_means: Float[Array, "T n"]
    predicted_covariances: Float[Array, "T n n"]
    marginal_loglik: Float[Array, ""]
    loglik_increments: Float[Array, " T"]
    info: PyTree
    result: RESULTS


def check_observations(
    model: Any, prior: Gaussian, ys: Any, inputs: Any, model_types: tuple[type, ...] = (LinearModel,)
) -> tuple[Array, Array | None]:
    """Eager checks of a filter call; returns `ys` and `inputs` as arrays.

    `model` must be an instance of one of `model_types`; each must provide `state_dim`,
    `obs_dim`, `check_horizon(T)` and `check_inputs(inputs, T)`.
    """
    if not isinstance(model, model_types):
        names = " or ".join(f"jdrkf.{t.__name__}" for t in model_types)
        raise ValueError(f"model must be a {names}, got {type(model).__name__}")
    if not isinstance(prior, Gaussian):
        raise ValueError(f"prior must be a jdrkf.Gaussian, got {type(prior).__name__}")
    n, m = model.state_dim, model.obs_dim
    if prior.mean.shape != (n,):
        raise ValueError(f"prior has dimension {prior.mean.shape[-1]} but the state dimension is {n}")
    ys = as_float_array("ys", ys, (2,))
    if ys.shape[1] != m:
        raise ValueError(f"ys has shape {tuple(ys.shape)} but expected (T, {m}) (H has {m} rows)")
    model.check_horizon(ys.shape[0])
    if inputs is not None:
        inputs = as_float_array("inputs", inputs, (2,))
    model.check_inputs(inputs, ys.shape[0])
    return ys, inputs


class AbstractFilter(eqx.Module):
    """Base class of all filters.

    Subclasses are `eqx.Module`s whose array fields are hyper-parameters (so
    `eqx.filter_grad` differentiates through them) and implement `init` and `step`.
    `__call__` scans `step` over the observations with `lax.scan`.

    `throw` (static): if `True`, a failed run raises through `eqx.error_if` (under
    `vmap`: if any run fails). Set `throw=False` for Monte Carlo sweeps and inspect
    `FilterResult.result` instead.

    `model_types` (class variable): the model classes `__call__` accepts (default
    `LinearModel`; multi-sensor and nonlinear filters override it). `stochastic_init`
    (class variable): `init(model, prior, key)` draws (particle filters); `__call__` then
    requires a key and uses `k_init, k_steps = split(key)`. `shared_covariance` (class
    variable): the covariance recursion depends on which observations are missing but
    not on their values, so `batch` computes it once for all runs when none is missing.
    """

    throw: eqx.AbstractVar[bool]
    model_types: ClassVar[tuple[type, ...]] = (LinearModel,)
    stochastic_init: ClassVar[bool] = False
    shared_covariance: ClassVar[bool] = False

    @abc.abstractmethod
    def init(self, model: LinearModel, prior: Gaussian) -> PyTree:
        """Filter state before the first step (from the law of `x_0`)."""

    def check_model(self, model: Any) -> None:
        """Eager, filter-specific checks of `model` in `__call__` (default: none)."""

    @abc.abstractmethod
    def step(
        self,
        model: LinearModel,
        state: PyTree,
        y: Float[Array, " m"],
        t: Int[ArrayLike, ""],
        u: Float[Array, " p"] | None = None,
        key: PRNGKeyArray | None = None,
    ) -> tuple[PyTree, StepOutput]:
        """Advance from `x_{k-1}` to `x_k` with `y = y_k` (array index `t = k − 1`)."""

    def __call__(
        self,
        model: LinearModel,
        prior: Gaussian,
        ys: Float[ArrayLike, "T m"],
        key: PRNGKeyArray | None = None,
        *,
        inputs: Float[ArrayLike, "T p"] | None = None,
    ) -> FilterResult:
        """Filter `ys` (`ys[t] = y_{t+1}`; NaN entries are missing) from the prior of `x_0`.

        `key` is positional so that `jax.vmap(filter, in_axes=(None, None, 0, 0))`
        maps over runs and keys; deterministic filters ignore it.
        """
        ys, inputs = check_observations(model, prior, ys, inputs, self.model_types)
        self.check_model(model)
        num_steps = ys.shape[0]
        if self.stochastic_init:
            if key is None:
                raise ValueError(f"{type(self).__name__} needs a PRNG key: flt(model, prior, ys, jax.random.key(0))")
            k_init, key = jax.random.split(key)
            state0 = self.init(model, prior, k_init)
        else:
            state0 = self.init(model, prior)
        keys = None if key is None else jax.random.split(key, num_steps)

        def body(carry, xs):
            state, result = carry
            t, y, u, k = xs
            state, out = self.step(model, state, y, t, u, k)
            result = RESULTS.where(result == RESULTS.successful, out.result, result)
            return (state, result), out

        xs = (jnp.arange(num_steps), ys, inputs, keys)
        (_, result), outs = lax.scan(body, (state0, RESULTS.successful), xs)
        res = FilterResult(
            filtered_means=outs.filtered.mean,
            filtered_covariances=outs.filtered.cov,
            predicted_means=outs.predicted.mean,
            predicted_covariances=outs.predicted.cov,
            marginal_loglik=jnp.sum(outs.loglik),
            loglik_increments=outs.loglik,
            info=outs.info,
            result=result,
        )
        if self.throw:
            res = result.error_if(res, result != RESULTS.successful)
        return res

    def batch(
        self,
        model: LinearModel,
        prior: Gaussian,
        ys: Float[ArrayLike, "B T m"],
        keys: PRNGKeyArray | None = None,
        *,
        inputs: Float[ArrayLike, "B T p"] | None = None,
    ) -> FilterResult:
        """Filter `B` Monte Carlo runs `ys[b]` that share `model` and `prior`; the result
        has a leading run axis and equals `jax.vmap(self)` run by run.

        For filters with `shared_covariance` (the Kalman filter and the linear robust
        filters) the covariance recursion, including every worst-case solve, is computed
        once for the batch instead of once per run whenever no entry of `ys` is NaN. On
        concrete `ys` this is decided in Python; under `jit` by a `lax.cond` on the whole
        batch (both branches are compiled; under `vmap` the cond runs both).
        `keys`: `(B,)` keys for stochastic filters; `inputs`: `(B, T, p)`.
        """
        ys = as_float_array("ys", ys, (3,))
        num_runs = ys.shape[0]
        if keys is not None and jnp.shape(keys)[:1] != (num_runs,):
            raise ValueError(f"keys must hold one key per run, shape ({num_runs},), got {jnp.shape(keys)}")
        if inputs is not None:
            inputs = as_float_array("inputs", inputs, (3,))
            if inputs.shape[0] != num_runs:
                raise ValueError(f"inputs must have shape ({num_runs}, T, p) like ys, got {inputs.shape}")
        missing = jnp.any(jnp.isnan(ys))
        return self._batch(model, prior, ys, keys, inputs, missing if isinstance(missing, jax.core.Tracer) else bool(missing))

    def _batch(self, model, prior, ys, keys, inputs, missing: bool | Array) -> FilterResult:
        """`batch` with `missing` (any NaN in `ys`) given: a Python bool picks the branch
        when tracing (as `montecarlo` does), a traced one becomes a `lax.cond`."""

        def run(flt):
            return jax.vmap(lambda y, k, u: flt(model, prior, y, k, inputs=u))(ys, keys, inputs)

        if not (self.shared_covariance and self.nan_as_missing):
            return run(self)
        dense = copy.copy(self)  # the same filter, with the masking of missing rows compiled out
        object.__setattr__(dense, "nan_as_missing", False)
        if isinstance(missing, bool):
            return run(self if missing else dense)
        return lax.cond(missing, lambda: run(self), lambda: run(dense))
