"""Batched LAPACK under `vmap` on CPU must not deadlock (jaxlib 0.10.x workaround).

jaxlib 0.10.x splits a batched LAPACK custom call (potrf, getrf, syevd, trsm, ...)
into chunks with `jax::ParallelBatchMap`, schedules them on XLA's CPU intra-op pool
("XLAEigen") and blocks on a `BlockingCounter` until they are done. The thunk
executor runs independent custom calls concurrently on that same pool, so when as
many batched LAPACK calls as the pool has threads (2 on a 2-core box) start at once,
every pool thread waits for chunks that no free thread can run: a deadlock (native
stacks: all `tf_XLAEigen` threads in `BlockingCounter::Wait` under
`lapack_dpotrf_ffi` / `lapack_dgetrf_ffi`). Measured on 2 cores, unfixed: about half
of the runs of the workload below hang within 6 s; `OPENBLAS_NUM_THREADS=1` and
`XLA_FLAGS=--xla_cpu_multi_thread_eigen=false` do not change that.

The workaround is to give the pool more threads than there can be concurrent LAPACK
calls: `PJRT_NPROC` (read when JAX creates its CPU client, i.e. at the first
computation, so setting it after `import jax` but before any computation works).
`import jdrkf` leaves the environment alone; `jdrkf.use_large_cpu_pool()` is the opt-in
(jdrkf/_cpu_pool.py; the test suite applies it in conftest.py, the CLI in `main`). The
tests run child processes with `PJRT_NPROC` and `NPROC` unset: the workload under a
timeout after the opt-in, checked against NumPy; a bare `import jdrkf`, which must change
neither `os.environ` nor JAX's configuration nor create JAX's backend (so the opt-in
after it still works); and an opt-in after the first computation, which must warn and
change nothing.
"""

import json
import os
import subprocess
import sys
import textwrap

import pytest

from jdrkf import _cpu_pool


_CHILD = textwrap.dedent(
    """
    import os
    import time

    import jdrkf

    jdrkf.use_large_cpu_pool()  # before any JAX computation

    import numpy as np
    import jax
    import jax.numpy as jnp
    from jax import lax

    jax.config.update("jax_enable_x64", True)
    B, n, steps = 256, 16, 10


    def body(carry, _):
        A, C = carry
        # four independent batched LAPACK calls per step (potrf x2, getrf, syevd):
        # the thunk executor starts them concurrently on the intra-op pool
        L1 = jnp.linalg.cholesky(A)
        L2 = jnp.linalg.cholesky(C)
        X = jnp.linalg.solve(A, C)
        w, V = jnp.linalg.eigh(C)
        eye = jnp.eye(n, dtype=A.dtype)
        LLt = L1 @ jnp.swapaxes(L1, -1, -2)
        A2 = 0.25 * (LLt + jnp.swapaxes(L2, -1, -2) @ L2) + eye
        A2 = A2 + 1e-3 * (X + jnp.swapaxes(X, -1, -2))
        C2 = 0.5 * (V * jnp.abs(w)[..., None, :]) @ jnp.swapaxes(V, -1, -2) + eye
        return (A2, C2), None


    run = jax.jit(lambda A, C: lax.scan(body, (A, C), None, length=steps)[0])

    rng = np.random.default_rng(0)
    G, H = rng.standard_normal((2, B, n, n))
    A0 = G @ G.transpose(0, 2, 1) + n * np.eye(n)
    C0 = H @ H.transpose(0, 2, 1) + n * np.eye(n)
    A, C = jnp.asarray(A0), jnp.asarray(C0)
    out = jax.block_until_ready(run(A, C))
    t0, calls = time.perf_counter(), 0
    while time.perf_counter() - t0 < float(os.environ["WORK_S"]) or calls < 5:
        out = jax.block_until_ready(run(A, C))
        calls += 1

    # independent NumPy re-implementation of the recursion
    An, Cn = A0.copy(), C0.copy()
    for _ in range(steps):
        L1, L2 = np.linalg.cholesky(An), np.linalg.cholesky(Cn)
        X = np.linalg.solve(An, Cn)
        w, V = np.linalg.eigh(Cn)
        LLt = L1 @ L1.transpose(0, 2, 1)
        A2 = 0.25 * (LLt + L2.transpose(0, 2, 1) @ L2) + np.eye(n)
        A2 = A2 + 1e-3 * (X + X.transpose(0, 2, 1))
        Cn = 0.5 * (V * np.abs(w)[..., None, :]) @ V.transpose(0, 2, 1) + np.eye(n)
        An = A2
    err = max(
        float(np.max(np.abs(np.asarray(out[0]) - An)) / np.max(np.abs(An))),
        float(np.max(np.abs(np.asarray(out[1]) - Cn)) / np.max(np.abs(Cn))),
    )

    pool = -1  # size of XLA's CPU intra-op pool, from the thread names (Linux)
    if os.path.isdir("/proc/self/task"):
        names = []
        for t in os.listdir("/proc/self/task"):
            try:
                with open(f"/proc/self/task/{t}/comm") as f:
                    names.append(f.read().strip())
            except OSError:
                pass
        pool = sum("XLAEigen" in s for s in names)
    print(f"DONE calls={calls} err={err:.3e} pool={pool}", flush=True)
    """
)


def _run_child(code: str, timeout: float, **env_vars: str) -> str:
    env = {k: v for k, v in os.environ.items() if k not in ("PJRT_NPROC", "NPROC")}
    env.update(JAX_PLATFORMS="cpu", **env_vars)
    proc = subprocess.run(
        [sys.executable, "-c", code],
        env=env,
        capture_output=True,
        text=True,
        timeout=timeout,
    )
    assert proc.returncode == 0, proc.stderr[-2000:]
    return proc.stdout


def test_vmapped_lapack_completes_with_the_opt_in():
    """`jdrkf.use_large_cpu_pool()` enlarges the pool, so the workload (about half of the
    runs hang within 6 s without it on 2 cores) finishes."""
    try:
        out = _run_child(_CHILD, timeout=120.0, WORK_S="4.0")
    except subprocess.TimeoutExpired:
        pytest.fail("batched LAPACK under vmap deadlocked (child timed out) after jdrkf.use_large_cpu_pool()")
    line = [s for s in out.splitlines() if s.startswith("DONE")]
    assert line, out
    fields = dict(kv.split("=") for kv in line[0].split()[1:])
    assert int(fields["calls"]) >= 5
    assert float(fields["err"]) < 1e-10
    pool = int(fields["pool"])
    if _cpu_pool.affected():
        assert pool == -1 or pool == 0 or pool >= 16, f"PJRT_NPROC ignored: {pool} XLAEigen threads"


_IMPORT_CHILD = textwrap.dedent(
    """
    import json
    import os

    import equinox, jax, jaxtyping, numpy, optax  # jdrkf's dependencies (jax itself sets TF_CPP_* variables)
    from jax._src import xla_bridge

    env, config = dict(os.environ), dict(jax.config.values)
    import jdrkf
    print(json.dumps({
        "env": sorted(k for k in set(env) | set(os.environ) if env.get(k) != os.environ.get(k)),
        "config": sorted(k for k in set(config) | set(jax.config.values) if config.get(k) != jax.config.values.get(k)),
        "backend": xla_bridge.backends_are_initialized(),
    }))
    """
)


def test_import_changes_no_environment_or_config():
    out = json.loads(_run_child(_IMPORT_CHILD, timeout=120.0).strip().splitlines()[-1])
    assert out == {"env": [], "config": [], "backend": False}


_LATE_CHILD = textwrap.dedent(
    """
    import os
    import warnings

    import jax.numpy as jnp
    import jdrkf

    jnp.ones(2).block_until_ready()  # JAX's CPU client exists from here on
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        jdrkf.use_large_cpu_pool()
    print("WARNED", any(issubclass(w.category, RuntimeWarning) and "no effect" in str(w.message) for w in caught))
    print("SET", "PJRT_NPROC" in os.environ)
    """
)


@pytest.mark.skipif(not _cpu_pool.affected(), reason="the opt-in is a no-op on this jaxlib")
def test_opt_in_after_the_first_computation_warns_and_changes_nothing():
    out = _run_child(_LATE_CHILD, timeout=120.0)
    assert "WARNED True" in out and "SET False" in out, out


_CLI_CHILD = textwrap.dedent(
    """
    import contextlib
    import io
    import os

    from jdrkf import cli

    with contextlib.redirect_stdout(io.StringIO()):
        assert cli.main(["list"]) == 0
    print("PJRT_NPROC", os.environ.get("PJRT_NPROC"))
    """
)


@pytest.mark.skipif(not _cpu_pool.affected(), reason="the opt-in is a no-op on this jaxlib")
def test_command_line_applies_the_opt_in():
    out = _run_child(_CLI_CHILD, timeout=120.0)
    line = [s for s in out.splitlines() if s.startswith("PJRT_NPROC")]
    assert line and line[0].split()[1] != "None" and int(line[0].split()[1]) >= 16, out
