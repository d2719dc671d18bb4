import gc

import jax
import numpy as np
import pytest

import jdrkf

# Test configuration, before any JAX computation: a large CPU pool against jaxlib 0.10's
# batched-LAPACK deadlock (see jdrkf.use_large_cpu_pool). Subprocesses inherit it.
jdrkf.use_large_cpu_pool()


jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_dtype_promotion", "strict")


@pytest.fixture
def getkey():
    """A fresh PRNG key on each call."""
    counter = iter(range(10**9))
    return lambda: jax.random.key(next(counter))


@pytest.fixture
def rng():
    return np.random.default_rng(0)


@pytest.fixture(autouse=True, scope="module")
def _fresh_compilation_caches():
    """Drop compiled executables after each test module. The full suite compiles
    hundreds of programs in one process; keeping them all made XLA's CPU compiler
    crash late in the run (seen twice in tests/test_tuning.py, never when run alone)."""
    yield
    jax.clear_caches()
    gc.collect()
