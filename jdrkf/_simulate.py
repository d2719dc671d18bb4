"""Monte Carlo simulation of linear state-space models."""

from __future__ import annotations

import abc
from typing import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
from jax import lax
from jaxtyping import Array, ArrayLike, Bool, Float, Int, PRNGKeyArray

from ._gaussian import Gaussian
from ._models import LinearModel
from ._noise import AbstractNoise, GaussianNoise, sampling_root
from ._validation import as_float_array, check_count, check_covariance


class Trajectories(eqx.Module):
    """Simulated runs (leading axis: run; then time index `t`, holding step `k = t + 1`).

    - `initial_states`: `(runs, n)`, the draws of `x_0`.
    - `states`: `(runs, T, n)`, `x_1..x_T`.
    - `observations`: `(runs, T, m)`, `y_1..y_T` (with outliers, if any).
    - `clean_observations`: `(runs, T, m)`, `H x + nominal noise`: the same draws without outliers.
    - `outliers`: `(runs, T, m)` boolean, where an outlier was added.
    - `transition_matrices`: `(runs, T, n, n)`, the true `F_t` when a perturbation was
      applied, else `None`.
    """

    initial_states: Float[Array, "runs n"]
    states: Float[Array, "runs T n"]
    observations: Float[Array, "runs T m"]
    clean_observations: Float[Array, "runs T m"]
    outliers: Bool[Array, "runs T m"]
    transition_matrices: Float[Array, "runs T n n"] | None

    @property
    def num_runs(self) -> int:
        return self.states.shape[0]

    @property
    def num_steps(self) -> int:
        return self.states.shape[1]


class AbstractSelfSimulatingModel(eqx.Module):
    """A model whose noise laws are fields of the model and that takes no inputs
    (`NonlinearModel`, `MultiSensorModel`): `simulate` hands it the checked key, prior and
    counts, so this module never imports the model types that build on `Trajectories`."""

    @abc.abstractmethod
    def _simulate_runs(self, key: PRNGKeyArray, prior: Gaussian | AbstractNoise, num_steps: int, num_runs: int) -> Trajectories:
        """`num_runs` independent runs of `num_steps` steps from `x_0 ~ prior`."""


def check_law(name: str, law, dim: int, dtype) -> AbstractNoise | None:
    if law is None:
        return None
    if isinstance(law, Gaussian):
        law = GaussianNoise(law.cov, law.mean)
    if not isinstance(law, AbstractNoise):
        raise ValueError(f"{name} must be a jdrkf noise law (e.g. jdrkf.GaussianNoise) or a jdrkf.Gaussian, got {type(law).__name__}")
    if law.dim != dim:
        raise ValueError(f"{name} draws vectors of dimension {law.dim} but {dim} is needed")
    if law.mean.dtype != dtype:
        raise ValueError(f"{name} has dtype {law.mean.dtype} but the model has dtype {dtype}; build both in one precision")
    check_covariance(f"{name}.cov", law.cov)
    return law


def simulate(
    key: PRNGKeyArray,
    model: LinearModel,
    prior: Gaussian | AbstractNoise,
    num_steps: int,
    num_runs: int,
    *,
    process_noise: AbstractNoise | None = None,
    measurement_noise: AbstractNoise | None = None,
    inputs: Float[ArrayLike, "T p"] | None = None,
    transition_perturbation: Callable[[PRNGKeyArray, Int[Array, ""]], Float[Array, "n n"]] | None = None,
) -> Trajectories:
    """Simulate `num_runs` independent runs of `num_steps` steps of `model`.

    `x_0 ~ prior`; for `k = 1..T`: `x_k = (F_t + Δ_t) x_{k-1} + B_t u_t + G_t w_t` and
    `y_k = H_t x_k + v_t` (`t = k − 1`).

    **Arguments:**

    - `key`: a PRNG key (required; no default randomness).
    - `model`: the *true* model to simulate (filters may use a different, nominal one): a
      `LinearModel`, or a `NonlinearModel` (then `x_k = f(x_{k-1}, w, t)`, `y_k = h(x_k, v, t)`
      with the model's own noise laws), or a `MultiSensorModel` (sensor noises correlated with
      the previous process noise, Chen et al. 2025, eq. 34); for these two the keyword arguments
      below do not apply.
    - `prior`: law of `x_0`: a `jdrkf.Gaussian` or any noise law (e.g. `UQuadraticNoise`).
    - `process_noise`, `measurement_noise`: true laws of `w` and `v`; by default
      Gaussian with the model's (possibly time-varying) means and covariances.
    - `inputs`: `(T, p)` controls, shared by all runs (required iff the model has `B`).
    - `transition_perturbation`: `(key, t) -> Δ_t`, an `(n, n)` random perturbation
      added to `F_t` each step (e.g. `jdrkf.UniformPerturbation`); the true
      matrices are returned in `Trajectories.transition_matrices`.
    - `num_steps`, `num_runs`: positive integers (`2.0`, `True` are rejected).

    Runs are independent: run `r` uses `jax.random.fold_in(key, r)`, so the first
    runs of a larger simulation equal a smaller one with the same key.

    Gaussian draws use the exact square root of each covariance (singular ones
    included); an indefinite covariance is never clipped: it raises `ValueError`
    when concrete and gives NaN draws when traced.
    """
    if key is None:
        raise ValueError("simulate needs a PRNG key, e.g. jax.random.key(0)")
    num_steps, num_runs = check_count("num_steps", num_steps), check_count("num_runs", num_runs)
    if isinstance(model, AbstractSelfSimulatingModel):
        extra = [n for n, v in (("process_noise", process_noise), ("measurement_noise", measurement_noise), ("inputs", inputs), ("transition_perturbation", transition_perturbation)) if v is not None]
        if extra:
            raise ValueError(f"{', '.join(extra)} cannot be given for a jdrkf.{type(model).__name__}: its noise laws are fields of the model, and it takes no inputs")
        return model._simulate_runs(key, prior, num_steps, num_runs)
    if not isinstance(model, LinearModel):
        raise ValueError(f"model must be a jdrkf.LinearModel, NonlinearModel or MultiSensorModel, got {type(model).__name__}")
    # The model may have been edited (e.g. eqx.tree_at) after its checked construction.
    check_covariance("model.Q", model.Q)
    check_covariance("model.R", model.R)
    model.check_horizon(num_steps)
    if inputs is not None:
        inputs = as_float_array("inputs", inputs, (2,))
    model.check_inputs(inputs, num_steps)
    n, m, q = model.state_dim, model.obs_dim, model.Q.shape[-1]
    dtype = model.F.dtype
    prior = check_law("prior", prior, n, dtype)
    process_noise = check_law("process_noise", process_noise, q, dtype)
    measurement_noise = check_law("measurement_noise", measurement_noise, m, dtype)
    for law in (process_noise, measurement_noise):
        if law is not None:
            law.check_horizon(num_steps)
    return _simulate(key, model, prior, process_noise, measurement_noise, inputs, transition_perturbation, num_steps, num_runs)


def _gaussian_draw(key, mean, root):
    return mean + root @ jax.random.normal(key, mean.shape, mean.dtype)


def _batched_sqrt(cov):
    return sampling_root(cov) if cov.ndim == 2 else jax.vmap(sampling_root)(cov)


@eqx.filter_jit
def _simulate(key, model, prior, process_noise, measurement_noise, inputs, perturbation, num_steps, num_runs):
    m = model.obs_dim
    # Square roots of Q and R once (per time step if time-varying), not per draw.
    roots = eqx.tree_at(lambda mdl: (mdl.Q, mdl.R), model, (_batched_sqrt(model.Q), _batched_sqrt(model.R)))

    def one_run(run_key):
        k0, kseq = jax.random.split(run_key)
        x0 = prior.sample(k0, 0)

        def body(x, xs):
            t, u, kt = xs
            kw, kv, kp = jax.random.split(kt, 3)
            mdl, root = model.at(t), roots.at(t)
            f = mdl.F if perturbation is None else mdl.F + perturbation(kp, t)
            w = _gaussian_draw(kw, mdl.process_mean, root.Q) if process_noise is None else process_noise.sample(kw, t)
            x_new = f @ x + mdl.G @ w
            if mdl.B is not None:
                x_new = x_new + mdl.B @ u
            if measurement_noise is None:
                v_nom, v_out = _gaussian_draw(kv, mdl.noise_mean, root.R), jnp.zeros(m, x.dtype)
            else:
                v_nom, v_out = measurement_noise.sample_parts(kv, t)
            clean = mdl.H @ x_new + v_nom
            return x_new, (x_new, clean + v_out, clean, v_out != 0, None if perturbation is None else f)

        xs = (jnp.arange(num_steps), inputs, jax.random.split(kseq, num_steps))
        _, (states, ys, clean, outl, fs) = lax.scan(body, x0, xs)
        return x0, states, ys, clean, outl, fs

    run_keys = jax.vmap(lambda r: jax.random.fold_in(key, r))(jnp.arange(num_runs))
    x0, states, ys, clean, outl, fs = jax.vmap(one_run)(run_keys)
    return Trajectories(
        initial_states=x0,
        states=states,
        observations=ys,
        clean_observations=clean,
        outliers=outl,
        transition_matrices=fs,
    )
