"""Opt-in workaround for a CPU deadlock of batched LAPACK in jaxlib 0.10.0–0.11.0.

jaxlib 0.10 splits a batched LAPACK custom call (Cholesky, LU, `eigh`, triangular
solves under `vmap`) into chunks with `jax::ParallelBatchMap`, runs them on XLA's CPU
intra-op pool and blocks until they finish. XLA starts independent custom calls
concurrently on that same pool, so once as many batched LAPACK calls run as the pool
has threads (2 on a 2-core machine), every thread waits for chunks no free thread can
run. A pool larger than the number of concurrent LAPACK calls avoids it; its size is
read from the `PJRT_NPROC` environment variable when JAX creates its CPU client (at the
first computation, not at `import jax`), so it can only be chosen before that.

`import jdrkf` changes nothing; a program opts in with `jdrkf.use_large_cpu_pool()`
before its first JAX computation (the `jdrkf` command line does), or by exporting
`PJRT_NPROC=16`.
"""

from __future__ import annotations

import importlib.metadata
import os
import warnings

_AFFECTED = ((0, 10, 0), (0, 11, 1))  # [first, fixed)
POOL_THREADS = 16


def _version(dist: str) -> tuple[int, ...] | None:
    try:
        return tuple(int(p) for p in importlib.metadata.version(dist).split(".")[:3])
    except (importlib.metadata.PackageNotFoundError, ValueError):
        return None


def affected() -> bool:
    """Whether the installed jaxlib has the batched-LAPACK deadlock on CPU."""
    version = _version("jaxlib")
    return version is not None and _AFFECTED[0] <= version < _AFFECTED[1]


def use_large_cpu_pool() -> None:
    """Give XLA's CPU thread pool enough threads to avoid jaxlib 0.10's batched-LAPACK deadlock.

    Call it once, before the first JAX computation of the process (right after
    `import jdrkf`). On jaxlib 0.10.0–0.11.0 it sets the environment variable
    `PJRT_NPROC` to `max(16, number of usable cores)`; child processes inherit it.
    It does nothing on other jaxlib versions or when `PJRT_NPROC` or `NPROC` is already
    set (your choice wins). Called after JAX has created its CPU client, it cannot take
    effect: it then warns and leaves the environment alone. Equivalent without Python:
    `export PJRT_NPROC=16`.
    """
    if not affected() or "PJRT_NPROC" in os.environ or "NPROC" in os.environ:
        return
    from jax._src import xla_bridge  # present in every affected jaxlib's jax

    if xla_bridge.backends_are_initialized():
        warnings.warn(
            "jdrkf.use_large_cpu_pool() was called after JAX's first computation, so it has no effect; "
            "call it before any JAX computation or export PJRT_NPROC=16 (batched LAPACK under vmap can "
            f"deadlock on CPU with jaxlib {importlib.metadata.version('jaxlib')})",
            RuntimeWarning,
            stacklevel=2,
        )
        return
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    os.environ["PJRT_NPROC"] = str(max(POOL_THREADS, cores))
