import jax
import numpy as np
import pytest


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
