"""Filter interface: `init`/`step` pairs scanned by `__call__`."""

from __future__ import annotations

import abc
import copy
from collections.abc import Sequence
from typing import Any, ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
from jax import lax
from jaxtyping import Array, ArrayLike, Bool, Float, Int, PRNGKeyArray, PyTree

from .._gaussian import Gaussian
from .._models import LinearModel, check_observations


class RESULTS(eqx.Enumeration):
    """Outcome codes of a filter run (`FilterResult.result`).

    Compare with `result == jdrkf.RESULTS.successful`; under `vmap` this gives one
    boolean per run. A run reports the first failure that occurred in it, except that
    `nan_observation` (the cause of any later failure) takes precedence.
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
        "1e-5), or check that the nominal covariances are well conditioned. For SteadyStateKalmanFilter: "
        "no stabilizing steady-state gain was found; (F, H) must be detectable and (F, G Q^½) stabilizable."
    )
    risk_sensitive_breakdown = (
        "The risk-sensitive inflation I − θ P was not positive definite (θ ≥ 1/λ_max of the predicted "
        "covariance), so the risk-sensitive recursion does not exist from this step on. Decrease theta, "
        "or use TauKF, which picks θ at each step."
    )
    nonfinite_state = (
        "The filtered mean or covariance became non-finite (inf/NaN). Common causes: inf in the "
        "inputs, an unstable model over a long horizon in float32, or an upstream bug."
    )
    nonfinite_jacobian = (
        "A Jacobian of the transition or observation function of a nonlinear model (ExtendedKF) was "
        "not finite at the linearisation point (e.g. sqrt or log at 0, or a mean that diverged). Check "
        "f and h at the estimates, or use a derivative-free filter (UnscentedKF)."
    )
    indefinite_covariance = (
        "The filtered covariance lost positive semidefiniteness beyond rounding (its smallest "
        "eigenvalue fell below -100 n eps Tr P): the covariance recursion is numerically unstable "
        "in this precision, typically float32 on an ill-conditioned system (noise covariances with "
        "condition numbers near 1/eps). Run in float64 or rescale the state."
    )
    nan_observation = (
        "An observation that the filter was told to use is NaN. To treat NaN entries as missing, "
        "pass observed=~jnp.isnan(ys) (a boolean mask of the entries to use) to the filter call."
    )
    invalid_hyperparameter = (
        "A hyper-parameter that arrived traced (under jit, vmap or grad) is outside its valid "
        "range (e.g. a negative radius, a contamination ratio outside [0, 1), a moment bound "
        "below 1), so the filter's robust step is undefined. Concrete values are checked when "
        "the filter or set is built; see the docstring of the set or filter for each range."
    )
    inconsistent_predicted_covariance = (
        "The filter's predicted covariance P_{k+1|k} does not dominate F P_{k|k} Fᵀ: the process "
        "noise it implies is indefinite (a Wasserstein worst case may shrink some directions), so no "
        "joint Gaussian law of (x_k, x_{k+1}) has these moments and the RTS backward pass would give "
        "indefinite smoothed covariances. Smooth the Kalman filter or a DR filter whose worst case "
        "inflates (moment sets), or use smaller radii."
    )
    nonpositive_predicted_covariance = (
        "A predicted covariance P_{k+1|k} reported by the filter was not numerically positive "
        "definite, so the RTS smoother gain P_{k|k} Fᵀ P_{k+1|k}⁻¹ could not be computed (or the "
        "backward pass overflowed). Make the process noise G Q Gᵀ positive definite, or run in float64."
    )


OUTPUTS = (
    "filtered_means",
    "filtered_covariances",
    "predicted_means",
    "predicted_covariances",
    "loglik_increments",
    "marginal_loglik",
    "info",
)
DEFAULT_OUTPUTS = ("filtered_means", "filtered_covariances", "marginal_loglik")


def _as_outputs(value: str | Sequence[str]) -> tuple[str, ...]:
    """Validate a filter's `outputs`: `"all"`, one name or a sequence of names of `OUTPUTS`."""
    if isinstance(value, str):
        value = OUTPUTS if value == "all" else (value,)
    try:
        names = tuple(value)
    except TypeError:
        raise ValueError(f"outputs must be 'all', a name or a sequence of names from {OUTPUTS}, got {value!r}") from None
    unknown = [v for v in names if v not in OUTPUTS]
    if unknown:
        raise ValueError(f"outputs: unknown name(s) {unknown}; choose from {OUTPUTS} or 'all'")
    return tuple(v for v in OUTPUTS if v in names)


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

    A field is `None` unless its name is in the filter's `outputs` (default
    `filtered_means`, `filtered_covariances`, `marginal_loglik`; `outputs="all"` for all).

    **Fields:**

    - `filtered_means`, `filtered_covariances`: `(T, n)`, `(T, n, n)`, the law of `x_k | y_{1:k}`.
    - `predicted_means`, `predicted_covariances`: the law of `x_k | y_{1:k-1}`.
    - `marginal_loglik`: `log p(y_{1:T})` where the filter defines it (NaN otherwise).
    - `loglik_increments`: `(T,)`, its per-step terms.
    - `info`: filter-specific diagnostics, stacked over time.
    - `result`: a `RESULTS` code, the first failure of the run (always present).
    """

    filtered_means: Float[Array, "T n"] | None
    filtered_covariances: Float[Array, "T n n"] | None
    predicted_means: Float[Array, "T n"] | None
    predicted_covariances: Float[Array, "T n n"] | None
    marginal_loglik: Float[Array, ""] | None
    loglik_increments: Float[Array, " T"] | None
    info: PyTree
    result: RESULTS


class AbstractFilter(eqx.Module):
    """Base class of all filters.

    Subclasses are `eqx.Module`s whose array fields are hyper-parameters (so
    `eqx.filter_grad` differentiates through them) and implement `init` and `step`.
    `__call__` scans `step` over the observations with `lax.scan`.

    `throw` (static, keyword, default `True`): if `True`, a failed run raises through `eqx.error_if` (under
    `vmap`: if any run fails); should a runtime swallow that exception, the call's float
    outputs are NaN and `result` holds the codes. Set `throw=False` for Monte Carlo sweeps and
    inspect `FilterResult.result` instead.

    `outputs` (static, keyword): the `FilterResult` fields a call fills, `"all"` or a
    sequence of names (default `("filtered_means", "filtered_covariances",
    "marginal_loglik")`); the others are `None` and cost nothing. Writing outputs is
    a large part of a cheap step: ask only for what you use.

    Under `jax.vmap` over observations with no missing data, everything in a filter
    that does not depend on the data (the covariance recursion and, in the robust
    filters, every worst-case solve) is traced unbatched, so it runs once for all
    runs (`shared_covariance` class variable: the filter is written so). Missing
    data enter through the `observed` mask; a mask shared by all runs keeps that
    property, a per-run mask makes the covariance recursion per run.

    `model_types` (class variable): the model classes `__call__` accepts (default
    `LinearModel`; multi-sensor and nonlinear filters override it). `stochastic_init`
    (class variable): `init(model, prior, key)` draws (particle filters); `__call__` then
    requires a key and uses `k_init, k_steps = split(key)`. `supports_missing` (class
    variable): `step` honours `observed`.
    """

    throw: bool = eqx.field(default=True, static=True, kw_only=True)
    outputs: tuple[str, ...] = eqx.field(default=DEFAULT_OUTPUTS, static=True, kw_only=True, converter=_as_outputs)
    model_types: ClassVar[tuple[type, ...]] = (LinearModel,)
    stochastic_init: ClassVar[bool] = False
    shared_covariance: ClassVar[bool] = False
    supports_missing: ClassVar[bool] = True

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
        observed: Bool[Array, " m"] | None = None,
    ) -> tuple[PyTree, StepOutput]:
        """Advance from `x_{k-1}` to `x_k` with `y = y_k` (array index `t = k − 1`);
        `observed`: which components of `y` to use (`None`: all)."""

    def __call__(
        self,
        model: LinearModel,
        prior: Gaussian,
        ys: Float[ArrayLike, "T m"],
        key: PRNGKeyArray | None = None,
        *,
        inputs: Float[ArrayLike, "T p"] | None = None,
        observed: Bool[ArrayLike, "T m"] | None = None,
    ) -> FilterResult:
        """Filter `ys` (`ys[t] = y_{t+1}`) from the prior of `x_0`.

        `observed` (boolean, the shape of `ys`) marks the entries to use; the others are
        missing and their values ignored (e.g. `observed=~jnp.isnan(ys)`). Without it every
        entry is used, and a NaN raises (concrete `ys`) or gives `RESULTS.nan_observation`.
        `key` is positional so that `jax.vmap(filter, in_axes=(None, None, 0, 0))`
        maps over runs and keys; deterministic filters ignore it.
        """
        ys, inputs, observed = check_observations(model, prior, ys, inputs, observed, self.model_types)
        if observed is not None and not self.supports_missing:
            raise ValueError(f"{type(self).__name__} does not support missing observations (observed must be None)")
        self.check_model(model)
        # Full-precision products everywhere in the filter: GPUs may otherwise run float32
        # matmuls in TF32 (10-bit mantissa), which breaks covariance recursions. Trace-time
        # and local to this call: JAX's global configuration is untouched.
        with jax.default_matmul_precision("highest"):
            return self._run(model, prior, ys, key, inputs, observed)

    def _scanned(self, model, state0):
        """`(carry0, step_fn)` that `__call__` scans: by default `init`'s state and `step`.
        A filter may carry another representation of the same state (with a `step_fn` of
        `step`'s signature that reports the same `StepOutput`)."""
        return state0, self.step

    def _run(self, model, prior, ys, key, inputs, observed) -> FilterResult:
        num_steps = ys.shape[0]
        if self.stochastic_init:
            if key is None:
                raise ValueError(f"{type(self).__name__} needs a PRNG key: flt(model, prior, ys, jax.random.key(0))")
            k_init, key = jax.random.split(key)
            state0 = self.init(model, prior, k_init)
        else:
            state0 = self.init(model, prior)
        carry_state0, step = self._scanned(model, state0)
        keys = None if key is None else jax.random.split(key, num_steps)
        stacked = set(self.outputs) - {"marginal_loglik"}
        loglik0 = jnp.zeros((), prior.mean.dtype) if "marginal_loglik" in self.outputs else None
        # The last filtered mean (for the finiteness check below) comes from the stacked means
        # when they are requested; otherwise it is carried (a copy per step).
        mean0 = None if "filtered_means" in stacked else prior.mean

        def body(carry, xs):
            state, result, last_mean, loglik, nan = carry
            t, y, u, k, o = xs
            # NaN in an entry to use: checked here, where the step reads y anyway
            nan = nan | jnp.any(jnp.isnan(y) if o is None else jnp.isnan(y) & o)
            state, out = step(model, state, y, t, u, k, observed=o)
            result = RESULTS.where(result == RESULTS.successful, out.result, result)
            fields = {
                "filtered_means": out.filtered.mean,
                "filtered_covariances": out.filtered.cov,
                "predicted_means": out.predicted.mean,
                "predicted_covariances": out.predicted.cov,
                "loglik_increments": out.loglik,
                "info": out.info,
            }
            loglik = None if loglik is None else loglik + out.loglik
            last_mean = None if last_mean is None else out.filtered.mean
            return (state, result, last_mean, loglik, nan), {name: fields[name] for name in stacked}

        xs = (jnp.arange(num_steps), ys, inputs, keys, observed)
        carry0 = (carry_state0, RESULTS.successful, mean0, loglik0, jnp.zeros((), bool))
        (_, result, last_mean, loglik, nan), outs = lax.scan(body, carry0, xs)
        if last_mean is None:
            last_mean = outs["filtered_means"][-1] if num_steps else prior.mean
        # A non-finite mean persists through the (linear in the mean) recursions, so checking
        # the last one once replaces a per-step, per-run check.
        finite = jnp.all(jnp.isfinite(last_mean))
        result = RESULTS.where((result == RESULTS.successful) & ~finite, RESULTS.nonfinite_state, result)
        result = RESULTS.where(nan, RESULTS.nan_observation, result)
        outs["marginal_loglik"] = loglik
        res = FilterResult(**{name: outs.get(name) for name in OUTPUTS}, result=result)
        return raise_if_failed(res, result) if self.throw else res


def raise_if_failed(tree: PyTree, result: RESULTS) -> PyTree:
    """`throw=True`'s check: raise (through `eqx.error_if`) if `result` is not successful.

    Every float leaf of `tree` is multiplied by a checked gate, `where(ok, checked 1, NaN)`,
    so that the check survives whatever the caller keeps. (Passing the leaves themselves
    through the check's conditional costs a serial copy of each: XLA moves vmap's transpose
    into it.) The NaN branch covers a runtime that swallows the callback's exception instead
    of raising it: the floats are then NaN, never plausible numbers, and `result` still
    holds the codes. Under `vmap`, `ok` means every run succeeded (as the raise stops the
    whole call), so the gate stays unbatched and shared covariances stay shared.
    """
    ok = eqx.internal.unvmap_all(result == RESULTS.successful)
    one = result.error_if(jnp.ones(()), ~ok)
    gate = jnp.where(ok, one, jnp.nan)
    return jax.tree.map(lambda x: x * gate.astype(x.dtype) if jnp.issubdtype(x.dtype, jnp.inexact) else x, tree)


def with_outputs(flt: AbstractFilter, outputs: str | Sequence[str]) -> AbstractFilter:
    """A copy of `flt` with other `outputs` (for internal callers such as `montecarlo`,
    whose jitted metrics read what they need and let XLA drop the rest)."""
    new = copy.copy(flt)
    object.__setattr__(new, "outputs", _as_outputs(outputs))
    return new
