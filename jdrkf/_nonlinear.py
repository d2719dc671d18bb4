"""Nonlinear state-space models (Wang 2022, eqs. (1)–(2)) and their Monte Carlo simulation."""

from __future__ import annotations

import math
from typing import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
from jax import lax
from jaxtyping import Array, ArrayLike, Float, Int, PRNGKeyArray

from . import linalg
from ._gaussian import Gaussian, log_density
from ._noise import AbstractNoise
from ._simulate import AbstractSelfSimulatingModel, Trajectories, check_law
from ._validation import as_float_array, check_covariance, check_positive_int


def _time_struct():
    # Filters and the simulator pass `t` as an element of `jnp.arange(T)`.
    return jax.ShapeDtypeStruct((), jnp.arange(1).dtype)


def _check_callable_output(name, fn, args, signature, expected_shape, dtype):
    if not callable(fn):
        raise ValueError(f"{name} must be a callable {signature}, got {type(fn).__name__}")
    try:
        out = jax.eval_shape(fn, *args)
    except Exception as e:  # noqa: BLE001 - re-raised with the expected signature
        shapes = ", ".join(str(tuple(a.shape)) for a in args)
        raise ValueError(f"calling {name}{signature} with argument shapes {shapes} failed: {e}") from e
    if not isinstance(out, jax.ShapeDtypeStruct) or out.shape != expected_shape:
        got = getattr(out, "shape", type(out).__name__)
        raise ValueError(f"{name}{signature} must return an array of shape {expected_shape}, got {got}")
    if out.dtype != dtype:
        raise ValueError(f"{name}{signature} returns dtype {out.dtype} but the model has dtype {dtype} (that of Q and R)")


def _gaussian_logpdf(resid: Float[Array, " m"], cov: Float[Array, "m m"]) -> Float[Array, ""]:
    """`log N(resid; 0, cov)`; NaN entries of `resid` are missing (marginalized out)."""
    observed = ~jnp.isnan(resid)
    obs_f = observed.astype(resid.dtype)
    cov = cov * (obs_f[:, None] * obs_f[None, :]) + jnp.diag(1.0 - obs_f)
    resid = jnp.where(observed, resid, 0.0)
    return log_density(linalg.cholesky(linalg.symmetrize(cov)), resid, jnp.sum(obs_f))


class NonlinearModel(AbstractSelfSimulatingModel):
    r"""Nonlinear state-space model (Wang 2022, eqs. (1)–(2)); `prior` is the law of `x_0`.

    For `k = 1..T` (array index `t = k − 1`), with `additive=True` (default):

    $$x_k = f(x_{k-1}, t) + w_t,\qquad y_k = h(x_k, t) + v_t,$$

    and with `additive=False` (general noise entering the functions):

    $$x_k = f(x_{k-1}, w_t, t),\qquad y_k = h(x_k, v_t, t).$$

    **Arguments:**

    - `f`, `h`: JAX-traceable functions (static fields: a new function means a new
      compilation). `t` is passed as an integer array scalar.
    - `Q`: `(q, q)` nominal covariance of `w` (`q = n` in the additive case).
    - `R`: `(r, r)` nominal covariance of `v` (`r = m` in the additive case).
    - `additive`: which of the two forms `f` and `h` have.
    - `state_dim`, `obs_dim`: `n`, `m`; required when `additive=False`, otherwise
      taken from `Q` and `R` (and checked if given).
    - `process_noise`, `measurement_noise`: laws of `w` and `v` (any `jdrkf` noise
      law, or a `jdrkf.Gaussian`) used to simulate and by particle filters to sample
      and weigh; default `N(0, Q)` and `N(0, R)`. Gaussian-approximation filters
      (UKF, EnKF) use the laws' means and the nominal `Q`, `R`.

    `f` and `h` are evaluated once on abstract inputs at construction, so a wrong
    output shape or dtype raises here rather than inside a filter.
    """

    f: Callable = eqx.field(static=True)
    h: Callable = eqx.field(static=True)
    Q: Float[Array, "q q"]
    R: Float[Array, "r r"]
    process_noise: AbstractNoise | None
    measurement_noise: AbstractNoise | None
    additive: bool = eqx.field(static=True)
    state_dim: int = eqx.field(static=True)
    obs_dim: int = eqx.field(static=True)

    def __init__(
        self,
        f: Callable,
        h: Callable,
        Q: Float[ArrayLike, "q q"],
        R: Float[ArrayLike, "r r"],
        *,
        additive: bool = True,
        state_dim: int | None = None,
        obs_dim: int | None = None,
        process_noise: AbstractNoise | Gaussian | None = None,
        measurement_noise: AbstractNoise | Gaussian | None = None,
    ):
        Q = as_float_array("Q", Q, (2,))
        R = as_float_array("R", R, (2,))
        check_covariance("Q", Q)
        check_covariance("R", R)
        dtype = jnp.result_type(Q, R)
        Q, R = Q.astype(dtype), R.astype(dtype)
        q, r = Q.shape[0], R.shape[0]
        additive = bool(additive)
        for name, value in (("state_dim", state_dim), ("obs_dim", obs_dim)):
            if value is not None:
                check_positive_int(name, value)
        if additive:
            if state_dim is not None and state_dim != q:
                raise ValueError(f"state_dim={state_dim} but Q has shape {tuple(Q.shape)}; with additive noise Q must be (n, n)")
            if obs_dim is not None and obs_dim != r:
                raise ValueError(f"obs_dim={obs_dim} but R has shape {tuple(R.shape)}; with additive noise R must be (m, m)")
            n, m = q, r
        else:
            if state_dim is None or obs_dim is None:
                raise ValueError("with additive=False, state_dim and obs_dim are required (f(x, w, t), h(x, v, t) do not reveal them)")
            n, m = state_dim, obs_dim
        x = jax.ShapeDtypeStruct((n,), dtype)
        w = jax.ShapeDtypeStruct((q,), dtype)
        v = jax.ShapeDtypeStruct((r,), dtype)
        t = _time_struct()
        if additive:
            _check_callable_output("f", f, (x, t), "(x, t)", (n,), dtype)
            _check_callable_output("h", h, (x, t), "(x, t)", (m,), dtype)
        else:
            _check_callable_output("f", f, (x, w, t), "(x, w, t)", (n,), dtype)
            _check_callable_output("h", h, (x, v, t), "(x, v, t)", (m,), dtype)
        self.f, self.h, self.Q, self.R = f, h, Q, R
        self.process_noise = check_law("process_noise", process_noise, q, dtype)
        self.measurement_noise = check_law("measurement_noise", measurement_noise, r, dtype)
        self.additive, self.state_dim, self.obs_dim = additive, n, m

    @property
    def process_noise_dim(self) -> int:
        """`q`, the dimension of `w`."""
        return self.Q.shape[-1]

    @property
    def measurement_noise_dim(self) -> int:
        """`r`, the dimension of `v`."""
        return self.R.shape[-1]

    @property
    def dtype(self):
        return self.Q.dtype

    @property
    def process_mean(self) -> Float[Array, " q"]:
        """Mean of `w`: that of `process_noise`, zero by default."""
        return jnp.zeros(self.process_noise_dim, self.dtype) if self.process_noise is None else self.process_noise.mean

    @property
    def measurement_mean(self) -> Float[Array, " r"]:
        """Mean of `v`: that of `measurement_noise`, zero by default."""
        return jnp.zeros(self.measurement_noise_dim, self.dtype) if self.measurement_noise is None else self.measurement_noise.mean

    def transition(self, x: Float[Array, " n"], w: Float[Array, " q"], t: Int[ArrayLike, ""]) -> Float[Array, " n"]:
        """`x_k` from `x_{k-1}` and the noise `w_t` (both forms)."""
        return self.f(x, t) + w if self.additive else self.f(x, w, t)

    def observe(self, x: Float[Array, " n"], v: Float[Array, " r"], t: Int[ArrayLike, ""]) -> Float[Array, " m"]:
        """`y_k` from `x_k` and the noise `v_t` (both forms)."""
        return self.h(x, t) + v if self.additive else self.h(x, v, t)

    def sample_process_noise(self, key: PRNGKeyArray, t: Int[ArrayLike, ""] = 0, shape: tuple[int, ...] = ()) -> Float[Array, "... q"]:
        """Draw(s) of `w_t` from `process_noise` (default `N(0, Q)`), of shape `shape + (q,)`."""
        return _sample(self.process_noise, self.Q, key, t, shape)

    def sample_measurement_noise(self, key: PRNGKeyArray, t: Int[ArrayLike, ""] = 0, shape: tuple[int, ...] = ()) -> Float[Array, "... r"]:
        """Draw(s) of `v_t` from `measurement_noise` (default `N(0, R)`), of shape `shape + (r,)`."""
        return _sample(self.measurement_noise, self.R, key, t, shape)

    def measurement_logpdf(self, y: Float[ArrayLike, " m"], x: Float[Array, " n"], t: Int[ArrayLike, ""] = 0) -> Float[Array, ""]:
        """`log p(y_k | x_k)` (additive noise only): `log p_v(y − h(x, t))` with the
        density of `measurement_noise`, or `log N(y; h(x, t), R)` by default (then NaN
        entries of `y` are missing and marginalized out). Raises `ValueError` for
        `additive=False` or a law without a density (e.g. `OutlierNoise`)."""
        if not self.additive:
            raise ValueError(
                "measurement_logpdf needs additive measurement noise (y = h(x, t) + v); with additive=False "
                "p(y | x) has no closed form (Wang 2022, Section IV-C: estimate it by sampling v)"
            )
        resid = jnp.asarray(y, self.dtype) - self.h(x, t)
        if self.measurement_noise is None:
            return _gaussian_logpdf(resid, self.R)
        law = self.measurement_noise
        if not _has_density(law):
            raise ValueError(f"measurement_noise ({type(law).__name__}) has no density, so p(y | x) is not defined")
        return law.log_prob(resid, t)

    def check_horizon(self, num_steps: int) -> None:
        """Eager check that time-varying noise laws cover `num_steps` steps."""
        for law in (self.process_noise, self.measurement_noise):
            if law is not None:
                law.check_horizon(num_steps)

    def check_inputs(self, inputs, num_steps: int) -> None:
        """Nonlinear models take no control inputs: `inputs` must be `None`."""
        if inputs is not None:
            raise ValueError("inputs were given but jdrkf.NonlinearModel takes no controls (put them inside f as a function of t)")

    def _simulate_runs(self, key, prior, num_steps, num_runs):
        return _simulate_nonlinear(key, self, prior, num_steps, num_runs)


def _has_density(law) -> bool:
    return hasattr(law, "log_prob")


def _sample(law, cov, key, t, shape):
    shape = tuple(shape)
    if law is None:
        z = jax.random.normal(key, shape + (cov.shape[-1],), cov.dtype)
        return z @ linalg.psd_sqrt(cov).T
    if not shape:
        return law.sample(key, t)
    size = math.prod(shape)
    draws = jax.vmap(lambda k: law.sample(k, t))(jax.random.split(key, size))
    return draws.reshape(shape + (law.dim,))


def _simulate_nonlinear(
    key: PRNGKeyArray,
    model: NonlinearModel,
    prior: Gaussian | AbstractNoise,
    num_steps: int,
    num_runs: int,
) -> Trajectories:
    """Simulate `num_runs` independent runs of `num_steps` steps of a `NonlinearModel`.

    `x_0 ~ prior`; for `t = 0..T−1`: `w ~ process_noise`, `x_{t+1} = transition(x_t, w, t)`,
    `(v, v_out) = measurement_noise.sample_parts`, `y = observe(x_{t+1}, v + v_out, t)`
    and `clean = observe(x_{t+1}, v, t)` (the same draw without its outlier part).

    Keys: run `r` uses `run_key = fold_in(key, r)`; `k0, kseq = split(run_key)`;
    `x_0 = prior.sample(k0, 0)`; step `t` uses `kw, kv = split(split(kseq, T)[t])`.
    `Trajectories.transition_matrices` is `None`.
    """
    if key is None:
        raise ValueError("_simulate_nonlinear needs a PRNG key, e.g. jax.random.key(0)")
    if not isinstance(model, NonlinearModel):
        raise ValueError(f"model must be a jdrkf.NonlinearModel, got {type(model).__name__}")
    num_steps, num_runs = int(num_steps), int(num_runs)
    if num_steps < 1 or num_runs < 1:
        raise ValueError(f"num_steps and num_runs must be positive, got {num_steps} and {num_runs}")
    model.check_horizon(num_steps)
    prior = check_law("prior", prior, model.state_dim, model.dtype)
    return _simulate_jit(key, model, prior, num_steps, num_runs)


@eqx.filter_jit
def _simulate_jit(key, model, prior, num_steps, num_runs):
    r = model.measurement_noise_dim

    def one_run(run_key):
        k0, kseq = jax.random.split(run_key)
        x0 = prior.sample(k0, 0)

        def body(x, xs):
            t, kt = xs
            kw, kv = jax.random.split(kt)
            x_new = model.transition(x, model.sample_process_noise(kw, t), t)
            if model.measurement_noise is None:
                v_nom, v_out = model.sample_measurement_noise(kv, t), jnp.zeros(r, x.dtype)
            else:
                v_nom, v_out = model.measurement_noise.sample_parts(kv, t)
            clean = model.observe(x_new, v_nom, t)
            y = model.observe(x_new, v_nom + v_out, t)
            outl = jnp.broadcast_to(jnp.any(v_out != 0), y.shape) if y.shape != v_out.shape else v_out != 0
            return x_new, (x_new, y, clean, outl)

        _, (states, ys, clean, outl) = lax.scan(body, x0, (jnp.arange(num_steps), jax.random.split(kseq, num_steps)))
        return x0, states, ys, clean, outl

    run_keys = jax.vmap(lambda i: jax.random.fold_in(key, i))(jnp.arange(num_runs))
    x0, states, ys, clean, outl = jax.vmap(one_run)(run_keys)
    return Trajectories(
        initial_states=x0,
        states=states,
        observations=ys,
        clean_observations=clean,
        outliers=outl,
        transition_matrices=None,
    )
