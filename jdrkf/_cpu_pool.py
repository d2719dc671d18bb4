"""Work around a CPU deadlock of batched LAPACK in jaxlib 0.10.0–0.11.0.

jaxlib 0.10 splits a batched LAPACK custom call (Cholesky, LU, `eigh`, triangular
solves under `vmap`) into chunks with `jax::ParallelBatchMap`, runs them on XLA's CPU
intra-op pool and blocks until they finish. XLA starts independent custom calls
concurrently on that same pool, so once as many batched LAPACK calls run as the pool
has threads (2 on a 2-core machine), every thread waits for chunks no free thread can
run. A pool larger than the number of concurrent LAPACK calls avoids it; its size is
read from `PJRT_NPROC` when JAX creates its CPU client (at the first computation, not
at `import jax`). `tests/test_batched_lapack.py` reproduces the hang and checks the fix.
"""

from __future__ import annotations

import importlib.metadata
import os

_AFFECTED = ((0, 10, 0), (0, 11, 1))  # [first, fixed)
POOL_THREADS = 16


def _version(dist: str) -> tuple[int, ...] | None:
    try:
        return tuple(int(p) for p in importlib.metadata.version(dist).split(".")[:3])
    except (importlib.metadata.PackageNotFoundError, ValueError):
        return None


def ensure_cpu_pool() -> None:
    """Set `PJRT_NPROC` to at least `POOL_THREADS` for affected jaxlib versions, unless
    the user has set `PJRT_NPROC` or `NPROC`. No effect if JAX already ran a computation."""
    if "PJRT_NPROC" in os.environ or "NPROC" in os.environ:
        return
    version = _version("jaxlib")
    if version is None or not _AFFECTED[0] <= version < _AFFECTED[1]:
        return
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    os.environ["PJRT_NPROC"] = str(max(POOL_THREADS, cores))


ensure_cpu_pool()  # on import: `jdrkf/__init__.py` imports this module first
