"""Eager input checks shared by models, noise laws and filters.

All checks run on concrete shapes before tracing and raise `ValueError` naming the
argument and the expected shape. Value checks (symmetry) run only on concrete
arrays, so they are skipped silently under `jit`/`vmap` tracing.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np


def as_float_array(name: str, x, ndim: tuple[int, ...]):
    """Convert `x` to a JAX float array and check that its rank is one of `ndim`."""
    try:
        arr = jnp.asarray(x)
    except TypeError as e:
        dtype = getattr(x, "dtype", None)
        got = type(x).__name__ + ("" if dtype is None else f" of dtype {dtype}")
        raise ValueError(f"{name} must be a numeric array, got {got}") from e
    if not jnp.issubdtype(arr.dtype, jnp.inexact):
        if jnp.issubdtype(arr.dtype, jnp.integer) or arr.dtype == bool:
            arr = arr.astype(jnp.result_type(float))
        else:
            raise ValueError(f"{name} must have a floating dtype, got {arr.dtype}")
    if arr.ndim not in ndim:
        want = " or ".join(str(d) for d in ndim)
        raise ValueError(f"{name} must have {want} dimensions, got shape {arr.shape}")
    return arr


def is_concrete(x) -> bool:
    return not isinstance(x, jax.core.Tracer)


def check_shape(name: str, x, expected: tuple, what: str = "") -> None:
    """Check the trailing shape of `x` against `expected` (`None` = any size)."""
    tail = x.shape[x.ndim - len(expected):] if len(expected) else ()
    ok = len(tail) == len(expected) and all(e is None or e == s for e, s in zip(expected, tail, strict=True))
    if not ok:
        shown = "(" + ", ".join("?" if e is None else str(e) for e in expected) + ("," if len(expected) == 1 else "") + ")"
        extra = f" {what}" if what else ""
        raise ValueError(f"{name} has shape {tuple(x.shape)} but expected trailing shape {shown}{extra}")


def check_covariance(name: str, x) -> None:
    """Square last two axes; symmetric (to 1e-6 relative) when the value is concrete."""
    if x.shape[-1] != x.shape[-2]:
        raise ValueError(f"{name} must be square, got shape {tuple(x.shape)}")
    if is_concrete(x):
        a = np.asarray(x, dtype=np.float64)
        if not np.all(np.isfinite(a)):
            raise ValueError(f"{name} contains non-finite entries")
        asym = np.max(np.abs(a - np.swapaxes(a, -1, -2)), initial=0.0)
        scale = max(np.max(np.abs(a), initial=0.0), 1e-300)
        if asym > 1e-6 * scale:
            raise ValueError(f"{name} must be symmetric (max |{name} - {name}ᵀ| = {asym:.3g})")
        diag = np.diagonal(a, axis1=-2, axis2=-1)
        if np.any(diag < 0):
            raise ValueError(f"{name} must be positive semidefinite (it has a negative diagonal entry)")


def check_time_axis(name: str, x, base_ndim: int, num_steps: int | None) -> int | None:
    """Return the time length of `x` if it carries a leading time axis, checking consistency."""
    if x.ndim == base_ndim + 1:
        t = x.shape[0]
        if num_steps is not None and t != num_steps:
            raise ValueError(
                f"{name} has a time axis of length {t} but other time-varying fields have length {num_steps}"
            )
        return t
    return num_steps
