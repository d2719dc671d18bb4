"""Run several filters on the same simulated runs (common random numbers)."""

from __future__ import annotations

from typing import Callable, Mapping

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec
from jaxtyping import Array, PRNGKeyArray

from . import _progress, metrics as _metrics
from ._gaussian import Gaussian
from ._models import LinearModel
from ._simulate import Trajectories
from ._validation import check_count
from .filters._base import AbstractFilter, FilterResult, RESULTS, with_outputs


class Clairvoyant(eqx.Module):
    """Wrap a filter so that Monte Carlo gives it what a real filter cannot know:

    - `true_model=True`: the simulated model, with the per-run true transition
      matrices when the simulation perturbed them;
    - `clean=True`: the outlier-free observations.

    Wang & Ye's (2022) TMKF is `Clairvoyant(KalmanFilter())`.
    """

    filter: AbstractFilter
    true_model: bool = eqx.field(default=True, static=True)
    clean: bool = eqx.field(default=True, static=True)


Metric = Callable[[Trajectories, FilterResult], Array]

DEFAULT_METRICS: dict[str, Metric] = {"rmse": lambda traj, res: _metrics.rmse(traj.states, res.filtered_means)}


def _run_chunk(filters, model, true_model, prior, chunk: Trajectories, keys, metrics, missing, clean_missing):
    """`missing`, `clean_missing` (static): whether the observations / the outlier-free
    ones hold any NaN (then treated as missing), decided eagerly: without them no filter
    gets a mask, so plain `vmap` shares the covariance recursion across runs."""
    out = {}
    for name, flt in filters.items():
        mdl, ys, per_run_F, nan = model, chunk.observations, None, missing
        if isinstance(flt, Clairvoyant):
            if flt.true_model:
                mdl, per_run_F = true_model, chunk.transition_matrices
            if flt.clean:
                ys, nan = chunk.clean_observations, clean_missing
            flt = flt.filter
        flt = with_outputs(flt, "all")  # the metrics read what they need; XLA drops the rest

        def run(y, k, F, flt=flt, mdl=mdl, nan=nan):
            m = mdl if F is None else eqx.tree_at(lambda mm: mm.F, mdl, F)
            return flt(m, prior, y, k, observed=~jnp.isnan(y) if nan else None)

        res = jax.vmap(run)(ys, keys, per_run_F)
        vals = jax.vmap(lambda traj, r: {mname: fn(traj, r) for mname, fn in metrics.items()})(chunk, res)
        out[name] = {**vals, "success": res.result == RESULTS.successful}
    return out


_run_chunk_jit = eqx.filter_jit(_run_chunk)

# Runs per call when many runs are split into chunks for progress: on 2 CPU cores a
# call of a 2-state filter bank costs about the same for 10, 25 or 100 runs (loop
# overhead), so smaller chunks would slow the run down.
_MIN_CHUNK, _PROGRESS_CHUNKS = 100, 10


def _global_array(a: np.ndarray, sharding: NamedSharding) -> Array:
    """The run-sharded global array of `a`: every process holds all of `a` and gives each of
    its devices that device's slice (one process: the same as `jax.device_put`)."""
    return jax.make_array_from_callback(a.shape, sharding, lambda index: a[index])


def _to_host(a: Array) -> np.ndarray:
    """All of a run-sharded result on this host; across processes, gathered from all of them."""
    if jax.process_count() == 1:
        return np.asarray(a)
    from jax.experimental import multihost_utils

    return np.asarray(multihost_utils.process_allgather(a, tiled=True))


def montecarlo(
    filters: Mapping[str, AbstractFilter | Clairvoyant],
    model: LinearModel,
    prior: Gaussian,
    trajectories: Trajectories,
    *,
    true_model: LinearModel | None = None,
    metrics: Mapping[str, Metric] | None = None,
    key: PRNGKeyArray | None = None,
    chunk_size: int = 1000,
    progress: bool = False,
) -> dict[str, dict[str, np.ndarray]]:
    """Run every filter on the same simulated runs and return per-run metrics.

    **Arguments:**

    - `filters`: name → filter (or `Clairvoyant(filter)`), all run on the same data.
    - `model`: the nominal model the filters use; `true_model`: the simulated one
      (for `Clairvoyant` entries; defaults to `model`).
    - `prior`: the filters' law of `x_0`.
    - `trajectories`: from `jdrkf.simulate`. NaN entries of its observations are
      missing data: each filter then gets `observed=~jnp.isnan(ys)`; without any, no
      mask is passed and every filter shares its covariance recursion across runs.
    - `metrics`: name → `fn(trajectories, result) -> per-run value`, evaluated inside
      the vmapped run (so `trajectories` and `result` are those of one run); default
      `{"rmse": ...}`. Every `FilterResult` field is available to them whatever the
      filters' `outputs` (inside the compiled call XLA computes only what they read). A `"success"` entry (result code is successful) is always added.
    - `key`: base key for stochastic filters; run `r` gets `fold_in(key, r)` for
      every filter (common random numbers).
    - `chunk_size`: runs per compiled call, bounding memory; the run axis of each
      chunk is sharded across all devices (`jax.sharding`), padded to a multiple of
      the device count. More than `_MIN_CHUNK` runs are split into up to
      `_PROGRESS_CHUNKS` chunks of at least `_MIN_CHUNK` runs, so progress moves while
      each call keeps a batch large enough to vectorize well.
    - `progress`: show the phases (compiling, then the runs chunk by chunk) as `tqdm`
      bars on stderr; a reporter installed with `jdrkf._progress.reporting` gets them
      whatever this flag.

    **Several processes or hosts.** After `jax.distributed.initialize(...)` in every
    process, call `montecarlo` with the same arguments in each (JAX's multi-controller
    model: every process simulates the same trajectories from the same key). The runs of
    each chunk are split over the devices of all processes, and every process returns the
    full results, equal bit for bit to a single process's on CPU.

    **Returns:** `{filter_name: {metric_name: np.ndarray of shape (runs, ...)}}`.
    Filters run with their own `throw` setting; use `throw=False` to keep going past
    failed runs and inspect `"success"`.
    """
    if not filters:
        raise ValueError("filters is empty")
    for name, flt in filters.items():
        if not isinstance(flt, (AbstractFilter, Clairvoyant)):
            raise ValueError(f"filters[{name!r}] must be a jdrkf filter or Clairvoyant(filter), got {type(flt).__name__}")
    chunk_size = check_count("chunk_size", chunk_size)
    metrics = dict(DEFAULT_METRICS if metrics is None else metrics)
    true_model = model if true_model is None else true_model
    num_runs = trajectories.num_runs
    if key is not None and not jnp.issubdtype(key.dtype, jax.dtypes.prng_key):
        key = jax.random.wrap_key_data(key)  # a legacy uint32 key
    run_key_data = None if key is None else jax.random.key_data(jax.vmap(lambda r: jax.random.fold_in(key, r))(jnp.arange(num_runs)))

    devices = jax.devices()  # every device of every process (one process: the local ones)
    sharding = NamedSharding(Mesh(np.asarray(devices), ("runs",)), PartitionSpec("runs"))
    chunk = min(chunk_size, num_runs, max(_MIN_CHUNK, -(-num_runs // _PROGRESS_CHUNKS)))
    chunk = -(-chunk // len(devices)) * len(devices)
    missing = bool(np.isnan(np.asarray(trajectories.observations)).any())
    clean_missing = bool(np.isnan(np.asarray(trajectories.clean_observations)).any())

    def chunk_args(start):
        idx = np.minimum(np.arange(start, start + chunk), num_runs - 1)  # pad with the last run
        data = jax.tree.map(lambda a: _global_array(np.asarray(a)[idx], sharding), (trajectories, run_key_data))
        keys = None if key is None else jax.random.wrap_key_data(data[1], impl=jax.random.key_impl(key))
        return dict(filters), model, true_model, prior, data[0], keys, metrics, missing, clean_missing

    reporter = _progress.reporter(progress)
    with reporter.phase(f"compiling Monte Carlo ({len(filters)} filter{'s' * (len(filters) > 1)}, {chunk} runs per call)"):
        # Ahead of time, so that compiling is a phase of its own; a call with the same
        # shapes and static arguments hits JAX's caches.
        run_chunk = _run_chunk_jit.lower(*chunk_args(0)).compile()
    pieces = []
    with reporter.phase("Monte Carlo", total=num_runs, unit="run") as bar:
        for start in range(0, num_runs, chunk):
            stop = min(start + chunk, num_runs)
            out = run_chunk(*chunk_args(start))
            pieces.append(jax.tree.map(lambda a: _to_host(a)[: stop - start], out))
            bar.update(stop - start)
    out = jax.tree.map(lambda *a: np.concatenate(a, axis=0), *pieces)
    # JAX flattens dicts in sorted key order, so its outputs are sorted: restore the caller's order.
    return {name: {m: out[name][m] for m in (*metrics, "success")} for name in filters}
