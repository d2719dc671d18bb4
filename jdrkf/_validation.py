"""Eager input checks shared by models, noise laws and filters.

All checks run on concrete shapes before tracing and raise `ValueError` naming the
argument and the expected shape. Value checks (symmetry, positive semidefiniteness)
run only on concrete arrays, so they are skipped under `jit`/`vmap` tracing.
"""

from __future__ import annotations

import operator
import warnings

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Float


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


PSD_TOLERANCE_FACTOR = 100
"""`c` in the PSD tolerance `c · n · eps(dtype)` of `psd_rtol`."""


def psd_rtol(dtype, n: int) -> float:
    """Relative tolerance `c · n · eps(dtype)` (`c = PSD_TOLERANCE_FACTOR = 100`) of the
    positive-semidefiniteness test `λ_min ≥ −c · n · eps · max(|λ|_max, tiny)`.

    Round-off in forming an `n × n` covariance (e.g. `G Gᵀ`, `F P Fᵀ + Q`) perturbs
    its eigenvalues by a few `n · eps · |λ|_max` (Weyl's inequality); `c = 100` leaves
    a wide margin for that while still rejecting any genuinely indefinite matrix
    whose negative eigenvalue is above the precision of its dtype.
    """
    return PSD_TOLERANCE_FACTOR * n * float(jnp.finfo(dtype).eps)


def check_covariance(name: str, x) -> None:
    """Square last two axes; when the value is concrete: finite, symmetric (to 1e-6
    relative) and positive semidefinite, `λ_min(x) ≥ −psd_rtol(dtype, n) · max(|λ|_max, tiny)`
    per matrix (eigenvalues of the symmetric part; singular matrices pass).

    A leading time axis is checked matrix by matrix. Traced values are not checked here.
    """
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
        n = a.shape[-1]
        if n == 0:
            return
        lam = np.linalg.eigvalsh(0.5 * (a + np.swapaxes(a, -1, -2)))
        lam_min = lam[..., 0]
        top = np.maximum(np.max(np.abs(lam), axis=-1), float(jnp.finfo(x.dtype).tiny))
        tol = psd_rtol(x.dtype, n) * top
        bad = lam_min < -tol
        if np.any(bad):
            idx = tuple(int(i) for i in np.argwhere(bad)[0])
            where = f"{name}[{', '.join(map(str, idx))}]" if idx else name
            raise ValueError(
                f"{name} must be positive semidefinite: {where} has smallest eigenvalue {lam_min[idx]:.6g} "
                f"(largest |eigenvalue| {top[idx]:.3g}; {x.dtype} round-off allows down to {-tol[idx]:.3g})"
            )


def check_count(name: str, value, minimum: int = 1) -> int:
    """`value` as a Python `int`, checked to be an integer (Python, NumPy or a concrete
    0-d integer array; not `bool`, not a float such as `2.0`) with `value ≥ minimum`."""
    if isinstance(value, (bool, np.bool_)) or getattr(value, "dtype", None) == bool:
        raise ValueError(f"{name} must be an integer, got the boolean {value!r}")
    try:
        count = operator.index(value)
    except TypeError:
        raise ValueError(f"{name} must be an integer (and concrete), got {value!r} of type {type(value).__name__}") from None
    if count < minimum:
        raise ValueError(f"{name} must be >= {minimum}, got {count}")
    return count


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


def check_positive_int(name: str, value, hint: str = "") -> int:
    """`value` as a Python `int`, checked to be an integer (Python or NumPy; not `bool`)
    `>= 1`; `hint` follows the expectation in the message."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)) or value < 1:
        raise ValueError(f"{name} must be a positive int{hint}, got {value!r}")
    return int(value)


def check_scalar(name: str, x: Float[ArrayLike, ""], lower: float = 0.0, *, strict: bool = False, hint: str = "") -> Float[Array, ""]:
    """A scalar hyper-parameter `>= lower` (`> lower` with `strict`) as a float array
    (checked when concrete; `hint` ends the error message)."""
    x = as_float_array(name, x, (0,))
    if is_concrete(x):
        v = float(np.asarray(x))
        if not np.isfinite(v) or (v <= lower if strict else v < lower):
            raise ValueError(f"{name} must be a finite number {'>' if strict else '>='} {lower:g}{hint}, got {v:g}")
    return x


def check_fraction(name: str, x: Float[ArrayLike, ""], upper: float = 1.0, *, closed: bool = True, hint: str = "") -> Float[Array, ""]:
    """A scalar in `[0, upper]` (`[0, upper)` with `closed=False`) as a float array, checked
    when concrete; the comparison is made in the precision of `x`."""
    x = as_float_array(name, x, (0,))
    if is_concrete(x):
        value, top = float(x), float(np.asarray(upper, x.dtype))
        if not (0.0 <= value <= top if closed else 0.0 <= value < top):
            raise ValueError(f"{name} must lie in [0, {upper}{']' if closed else ')'}, got {value}{hint}")
    return x


def in_range(
    x: Float[ArrayLike, "*d"],
    lower: float,
    upper: float = np.inf,
    *,
    lower_open: bool = False,
    upper_open: bool = False,
    allow_inf: bool = False,
) -> Bool[Array, ""]:
    """Traced range check of a hyper-parameter (the run-time counterpart of the eager
    checks): every entry of `x` lies in the interval from `lower` to `upper` (open or
    closed ends) and is finite (`+inf` too with `allow_inf`); `False` for NaN. A few
    scalar comparisons, unbatched under `vmap` over data."""
    x = jnp.asarray(x)
    above = x > lower if lower_open else x >= lower
    below = x < upper if upper_open else x <= upper
    finite = (x == jnp.inf) | jnp.isfinite(x) if allow_inf else jnp.isfinite(x)
    return jnp.all(above & below & finite)


def renamed(old_name: str, old_value, new_name: str, new_value, owner: str, *, stacklevel: int = 5):
    """Resolve a keyword argument renamed under the naming rule (deprecated alias, kept
    for one release): `new_value` if only it is given; `old_value` with a
    `DeprecationWarning` naming `new_name` if only the old keyword is given; a
    `TypeError` if both or neither are given. `None` means "not given" (radii and the
    other renamed parameters are never `None`)."""
    if old_value is None:
        if new_value is None:
            raise TypeError(f"{owner}() missing required argument '{new_name}'")
        return new_value
    if new_value is not None:
        raise TypeError(f"{owner}() got both '{new_name}' and its deprecated alias '{old_name}'; pass only {new_name}=")
    warnings.warn(f"{owner}({old_name}=...) is deprecated; use {new_name}= instead", DeprecationWarning, stacklevel=stacklevel)
    return old_value


def renamed_attribute(old_name: str, new_name: str) -> property:
    """A read-only property `old_name` that returns `self.<new_name>` with a
    `DeprecationWarning` (the deprecated alias of a renamed field; not a pytree leaf)."""

    def get(self):
        warnings.warn(f"{type(self).__name__}.{old_name} is deprecated; use .{new_name} instead", DeprecationWarning, stacklevel=3)
        return getattr(self, new_name)

    return property(get, doc=f"Deprecated alias of `{new_name}` (read-only).")
