"""Dense linear algebra for covariance matrices, with gradients that stay finite.

Every function works on float32 and float64 inputs and is safe under `jax.jit`,
`jax.vmap` and `jax.grad`. Rules followed here (see `docs/design.md`):

- covariances are symmetrized after every update;
- systems are solved with Cholesky factors, never with explicit inverses;
- `eigh` is used in forward passes only: derivatives of matrix functions come from
  closed-form rules that divide by *sums* of eigenvalues, never by their gaps, so
  repeated eigenvalues are harmless.
"""

from __future__ import annotations

import contextlib
import contextvars

import jax
import jax.numpy as jnp
from jax import lax
from jaxtyping import Array, ArrayLike, Float

from ._root import implicit_root

__all__ = [
    "symmetrize",
    "matmul",
    "cholesky",
    "cho_solve",
    "psd_solve",
    "psd_inv",
    "gauss_jordan_solve",
    "psd_solve_fwd",
    "psd_logdet",
    "psd_sqrt",
    "psd_factor",
    "tria",
    "bures_distance",
    "bures_distance_squared",
    "solve_dare",
    "lapack_only",
    "unrolls",
]


def symmetrize(a: Float[ArrayLike, "... n n"]) -> Float[Array, "... n n"]:
    """Return `(a + aᵀ) / 2` (batched over leading axes)."""
    a = jnp.asarray(a)
    return 0.5 * (a + jnp.swapaxes(a, -1, -2))


# Matrices up to this size are factorized and solved with unrolled elementwise code.
# Under `vmap` over many runs, XLA's per-matrix LAPACK calls for tiny matrices dominate
# the Kalman step; unrolled code vectorizes across the batch instead (3x faster at
# n = 1, see benchmarks/kf_throughput.py). The arithmetic is the same algorithm.
UNROLL_MAX = 6
_UNROLL = contextvars.ContextVar("jdrkf_unroll", default=True)


@contextlib.contextmanager
def lapack_only():
    """Within this context (at trace time), `cholesky` and `cho_solve` call LAPACK for
    every size. Solvers with large one-off graphs (Newton on a dense Jacobian) use it:
    unrolled code multiplies their compile time, and they are not vmapped over runs."""
    token = _UNROLL.set(False)
    try:
        yield
    finally:
        _UNROLL.reset(token)


def unrolls(n: int) -> bool:
    """Whether `n × n` matrices use the unrolled elementwise code here: `n ≤ UNROLL_MAX`,
    outside `lapack_only` (read at trace time)."""
    return n <= UNROLL_MAX and _UNROLL.get()


def matmul(a: Float[ArrayLike, "*m k"], b: Float[ArrayLike, "k *p"]) -> Float[Array, "*m *p"]:
    """`a @ b` for vectors and matrices; a contraction of size up to `UNROLL_MAX` is written
    as a sum of column scalings, `Σ_j a[:, j] b[j]`, which XLA fuses with the neighbouring
    elementwise work. Under `vmap` over runs a small dot otherwise becomes a library call
    on a `(B, n)` operand whose layout costs more than the arithmetic (the Kalman mean
    update: ~1.7x the time per step in float32 on a CPU, see benchmarks/kf_throughput.py).
    Elementwise products are exact in float32 on GPUs too (no TF32)."""
    a, b = jnp.asarray(a), jnp.asarray(b)
    k = a.shape[-1]
    if not (1 <= k and unrolls(k)) or a.ndim > 2 or b.ndim > 2:
        return a @ b
    if a.ndim == 1:
        return sum((a[j] * b[j] for j in range(1, k)), start=a[0] * b[0])  # b[j]: a row or a scalar
    col = (lambda j: a[:, j]) if b.ndim == 1 else (lambda j: a[:, j, None])
    return sum((col(j) * b[j] for j in range(1, k)), start=col(0) * b[0])


def _unrolled_cholesky(a):
    n = a.shape[-1]
    low = [[None] * n for _ in range(n)]
    for j in range(n):
        s = a[j, j] - sum((low[j][k] ** 2 for k in range(j)), start=jnp.zeros((), a.dtype))
        # Non-positive pivot -> NaN, as jnp.linalg.cholesky reports failure.
        d = jnp.where(s > 0, jnp.sqrt(jnp.where(s > 0, s, 1.0)), jnp.nan)
        low[j][j] = d
        for i in range(j + 1, n):
            low[i][j] = (a[i, j] - sum((low[i][k] * low[j][k] for k in range(j)), start=jnp.zeros((), a.dtype))) / d
    zero = jnp.zeros((), a.dtype)
    return jnp.stack([jnp.stack([low[i][j] if j <= i else zero for j in range(n)]) for i in range(n)])


def cholesky(a: Float[ArrayLike, "n n"]) -> Float[Array, "n n"]:
    """Lower Cholesky factor of a symmetric positive-definite matrix.

    NaN entries signal a matrix that is not numerically positive definite (the
    convention of `jnp.linalg.cholesky`). Matrices up to `UNROLL_MAX` in size use
    unrolled elementwise code, which is much faster under `vmap`.
    """
    a = jnp.asarray(a)
    return _unrolled_cholesky(a) if unrolls(a.shape[-1]) else jnp.linalg.cholesky(a)


def _unrolled_cho_solve(chol, b):
    n = chol.shape[-1]
    z = []
    for i in range(n):  # forward substitution L z = b
        z.append((b[i] - sum((chol[i, k] * z[k] for k in range(i)), start=jnp.zeros_like(b[i]))) / chol[i, i])
    x = [None] * n
    for i in reversed(range(n)):  # back substitution Lᵀ x = z
        x[i] = (z[i] - sum((chol[k, i] * x[k] for k in range(i + 1, n)), start=jnp.zeros_like(b[i]))) / chol[i, i]
    return jnp.stack(x)


def cho_solve(chol: Float[Array, "n n"], b: Float[ArrayLike, "n ..."]) -> Float[Array, "n ..."]:
    """Solve `(L Lᵀ) x = b` given the lower Cholesky factor `L`."""
    b = jnp.asarray(b)
    if unrolls(chol.shape[-1]):
        return _unrolled_cho_solve(chol, b)
    vec = b.ndim == 1
    b2 = b[:, None] if vec else b
    z = jax.scipy.linalg.solve_triangular(chol, b2, lower=True)
    x = jax.scipy.linalg.solve_triangular(chol, z, lower=True, trans="T")
    return x[:, 0] if vec else x


def psd_solve(a: Float[ArrayLike, "n n"], b: Float[ArrayLike, "n ..."]) -> Float[Array, "n ..."]:
    """Solve `a x = b` for symmetric positive-definite `a` via its Cholesky factor.

    Returns NaNs when `a` is not numerically positive definite (JAX's Cholesky
    convention); callers turn that into a result code.
    """
    return cho_solve(cholesky(symmetrize(a)), b)


@jax.custom_jvp
def psd_inv(a: Float[ArrayLike, "n n"]) -> Float[Array, "n n"]:
    """Inverse of a symmetric positive-definite matrix, for solvers that need it as a
    matrix (e.g. `T = (I − θsD)⁻¹`): `gauss_jordan_solve(a, I)` (unrolled up to
    `UNROLL_MAX`, else the Cholesky solve), symmetrized.

    Derivative `−X dA X` (`X = a⁻¹`, `dA` symmetrized): matrix products only, so a forward-mode Jacobian
    over many tangents is a few batched products rather than one triangular solve
    per tangent. NaNs when `a` is not numerically positive definite.
    """
    a = jnp.asarray(a)
    return symmetrize(gauss_jordan_solve(a, jnp.eye(a.shape[-1], dtype=a.dtype)))


@psd_inv.defjvp
def _psd_inv_jvp(primals, tangents):
    (a,), (da,) = primals, tangents
    x = psd_inv(a)
    return x, -x @ symmetrize(da) @ x


def _unrolled_gauss_jordan(a, b):
    n = a.shape[-1]
    for k in range(n):
        piv = a[k, k]
        piv = jnp.where(piv > 0, piv, jnp.nan)  # a symmetric matrix is PD iff its pivots are
        row_a, row_b = a[k] / piv, b[k] / piv
        col = a[:, k].at[k].set(0.0)
        a = (a - col[:, None] * row_a[None, :]).at[k].set(row_a)
        b = (b - col[:, None] * row_b[None, :]).at[k].set(row_b)
    return b


def gauss_jordan_solve(a: Float[ArrayLike, "n n"], b: Float[ArrayLike, "n ..."]) -> Float[Array, "n ..."]:
    """Solve `a x = b` for symmetric positive-definite `a`; NaNs when `a` is not
    numerically positive definite (a non-positive pivot).

    Matrices up to `UNROLL_MAX` use Gauss–Jordan elimination without pivoting (stable for
    positive-definite `a`), unrolled over the `n` pivots with whole-row updates: XLA fuses
    each elimination step, so one solve runs a few kernels (the unrolled Cholesky of
    `psd_solve` runs `O(n²)` scalar ones) and it still vectorizes under `vmap` (5 × 5:
    about 5× faster than `psd_solve` alone and 3.5× under `vmap`). Larger ones use `psd_solve`.
    """
    a, b = jnp.asarray(a), jnp.asarray(b)
    if not unrolls(a.shape[-1]):
        return psd_solve(a, b)
    vec = b.ndim == 1
    x = _unrolled_gauss_jordan(symmetrize(a), b[:, None] if vec else b)
    return x[:, 0] if vec else x


@jax.custom_jvp
def psd_solve_fwd(a: Float[ArrayLike, "n n"], b: Float[ArrayLike, "n ..."]) -> Float[Array, "n ..."]:
    """`psd_solve(a, b)` (the backward-stable Cholesky solve) with the derivative
    `dx = a⁻¹(db − dA x)` taken through `psd_inv(a)`: for residuals differentiated by
    `jax.jacfwd` over many tangents, whose solves would otherwise run one triangular
    solve per tangent."""
    return psd_solve(a, b)


@psd_solve_fwd.defjvp
def _psd_solve_fwd_jvp(primals, tangents):
    (a, b), (da, db) = primals, tangents
    x = psd_solve(a, b)
    return x, psd_inv(a) @ (db - symmetrize(da) @ x)


@jax.custom_jvp
def psd_logdet(a: Float[ArrayLike, "n n"]) -> Float[Array, ""]:
    """`log det a` of a symmetric positive-definite matrix from its Cholesky factor (NaN
    when `a` is not numerically positive definite), with the derivative `Tr(a⁻¹ dA)`
    through `psd_inv` (batched products under `jax.jacfwd`)."""
    chol = cholesky(symmetrize(a))
    return 2.0 * jnp.sum(jnp.log(jnp.diagonal(chol)))


@psd_logdet.defjvp
def _psd_logdet_jvp(primals, tangents):
    (a,), (da,) = primals, tangents
    return psd_logdet(a), jnp.sum(psd_inv(a) * symmetrize(da))


@jax.custom_jvp
def psd_sqrt(a: Float[ArrayLike, "n n"]) -> Float[Array, "n n"]:
    """Principal square root of a symmetric PSD matrix.

    Forward: `eigh`, with negative round-off eigenvalues clipped to zero.
    Derivative: the solution `dX` of the Sylvester equation `X dX + dX X = dA`,
    i.e. `dX̃ᵢⱼ = dÃᵢⱼ / (√λᵢ + √λⱼ)` in the eigenbasis — finite for repeated
    eigenvalues (only exactly singular directions are floored).
    """
    lam, vec = jnp.linalg.eigh(symmetrize(a))
    root = jnp.sqrt(jnp.clip(lam, 0.0))
    return symmetrize((vec * root) @ vec.T)


@psd_sqrt.defjvp
def _psd_sqrt_jvp(primals, tangents):
    (a,), (da,) = primals, tangents
    lam, vec = jnp.linalg.eigh(symmetrize(a))
    root = jnp.sqrt(jnp.clip(lam, 0.0))
    x = symmetrize((vec * root) @ vec.T)
    tiny = jnp.finfo(x.dtype).tiny ** 0.5
    denom = jnp.maximum(root[:, None] + root[None, :], tiny)
    dx = vec @ ((vec.T @ symmetrize(da) @ vec) / denom) @ vec.T
    return x, symmetrize(dx)


def psd_factor(a: Float[ArrayLike, "n n"]) -> Float[Array, "n n"]:
    """Lower-triangular square root `L` (nonnegative diagonal, `L Lᵀ = a`) of a symmetric
    PSD matrix: the Cholesky factor when `a` is numerically positive definite, else
    `tria(psd_sqrt(a))` (singular PSD matrices: a known initial state, a rank-deficient
    noise covariance, round-off below zero).

    The Cholesky branch is fed the identity when it is not taken, so its derivative
    stays finite; only the branch taken is evaluated (outside `vmap` over `a`).
    """
    a = symmetrize(jnp.asarray(a))
    ok = jnp.all(jnp.isfinite(cholesky(lax.stop_gradient(a))))
    chol = cholesky(jnp.where(ok, a, jnp.eye(a.shape[-1], dtype=a.dtype)))
    return lax.cond(ok, lambda: chol, lambda: tria(psd_sqrt(a)))


def tria(a: Float[ArrayLike, "n k"]) -> Float[Array, "n n"]:
    """Triangularization: the lower-triangular `L` with nonnegative diagonal and
    `L Lᵀ = a aᵀ`, from the QR decomposition `aᵀ = Q R` as `L = Rᵀ D` with
    `D = diag(sign Rᵢᵢ)` (`L` is then the Cholesky factor of `a aᵀ` when that is positive
    definite). A wide `a` (`k < n`) is padded with zero columns. The derivative (through
    the QR's) needs `a aᵀ` positive definite.
    """
    a = jnp.asarray(a)
    n, k = a.shape
    if k < n:
        a = jnp.concatenate([a, jnp.zeros((n, n - k), a.dtype)], axis=1)
    low = jnp.linalg.qr(a.T, mode="r").T
    sign = jnp.where(jnp.diagonal(low) < 0, -1.0, 1.0).astype(a.dtype)
    return low * sign[None, :]


@jax.custom_jvp
def _nuclear_norm(m: Float[Array, "n n"]) -> Float[Array, ""]:
    return jnp.sum(jnp.linalg.svd(m, compute_uv=False))


@_nuclear_norm.defjvp
def _nuclear_norm_jvp(primals, tangents):
    # d‖M‖_* = ⟨U Vᵀ, dM⟩: the polar factor, well defined for nonsingular M even
    # when singular values repeat (unlike the SVD's own JVP).
    (m,), (dm,) = primals, tangents
    u, s, vt = jnp.linalg.svd(m, full_matrices=False)
    return jnp.sum(s), jnp.sum((u @ vt) * dm)


def bures_distance_squared(a: Float[ArrayLike, "n n"], b: Float[ArrayLike, "n n"]) -> Float[Array, ""]:
    """Squared Bures (Gelbrich) distance `Tr(A + B − 2 (A^½ B A^½)^½)`.

    The fidelity term is computed without matrix square roots as the nuclear norm
    `‖L_Aᵀ L_B‖_*` of Cholesky factors (`Tr((A^½BA^½)^½)` for any `A = L_A L_Aᵀ`,
    `B = L_B L_Bᵀ`); `a` and `b` must be
    positive definite. Clipped at zero against round-off.
    """
    a, b = symmetrize(a), symmetrize(b)
    fid = _nuclear_norm(jnp.linalg.cholesky(a).T @ jnp.linalg.cholesky(b))
    return jnp.maximum(jnp.trace(a) + jnp.trace(b) - 2.0 * fid, 0.0)


def bures_distance(a: Float[ArrayLike, "n n"], b: Float[ArrayLike, "n n"]) -> Float[Array, ""]:
    """Bures distance, the 2-Wasserstein distance between `N(0, a)` and `N(0, b)`.

    The gradient at `a == b` (where the square root is not differentiable) is set to 0.
    """
    d2 = bures_distance_squared(a, b)
    pos = d2 > 0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, d2, 1.0)), 0.0)


def _dare_residual(p, f, h, gqg, r):
    s = h @ p @ h.T + r
    fph = f @ p @ h.T
    return symmetrize(f @ p @ f.T - fph @ jnp.linalg.solve(s, fph.T) + gqg) - p


def _dare_doubling(f, h, gqg, r, max_iter, rtol):
    # Structure-preserving doubling for the filtering DARE (dual of the control DARE
    # with A = Fᵀ, B = Hᵀ). Converges quadratically: error ~ ρ^(2^k) for the
    # closed-loop spectral radius ρ.
    n = f.shape[0]
    eye = jnp.eye(n, dtype=f.dtype)
    a0 = f.T
    g0 = symmetrize(h.T @ jnp.linalg.solve(r, h))
    h0 = symmetrize(gqg)

    def body(carry):
        a, g, hh, _, k = carry
        w = eye + g @ hh
        w_inv_a = jnp.linalg.solve(w, a)
        a_new = a @ w_inv_a
        g_new = symmetrize(g + a @ jnp.linalg.solve(w, g) @ a.T)
        h_new = symmetrize(hh + a.T @ hh @ w_inv_a)
        delta = jnp.max(jnp.abs(h_new - hh)) / jnp.maximum(jnp.max(jnp.abs(h_new)), 1.0)
        return a_new, g_new, h_new, delta, k + 1

    def cond(carry):
        *_, delta, k = carry
        return (delta > rtol) & (k < max_iter)

    init = (a0, g0, h0, jnp.asarray(jnp.inf, f.dtype), jnp.asarray(0))
    _, _, p, _, _ = lax.while_loop(cond, body, init)
    return p


def solve_dare(
    F: Float[ArrayLike, "n n"],
    H: Float[ArrayLike, "m n"],
    Q: Float[ArrayLike, "n n"],
    R: Float[ArrayLike, "m m"],
    *,
    max_iter: int = 64,
) -> Float[Array, "n n"]:
    """Steady-state *predicted* covariance of the Kalman filter.

    Solves the filtering discrete algebraic Riccati equation
    `P = F P Fᵀ − F P Hᵀ (H P Hᵀ + R)⁻¹ H P Fᵀ + Q` (here `Q` is the process
    covariance in state coordinates, i.e. `G Q Gᵀ`) by the structure-preserving
    doubling algorithm, entirely in JAX. Requires (F, H) detectable and (F, Q^½)
    stabilizable. Derivatives come from the implicit function theorem on the
    Riccati residual (`lax.custom_root`), not from the doubling iterations.
    """
    F, H, Q, R = (jnp.asarray(x) for x in (F, H, Q, R))
    dtype = jnp.result_type(F, H, Q, R)
    F, H, Q, R = (x.astype(dtype) for x in (F, H, Q, R))
    rtol = 10 * jnp.finfo(dtype).eps
    n = F.shape[0]

    def residual(p):
        return _dare_residual(p, F, H, Q, R)

    def solve(guess):
        del guess
        return _dare_doubling(*jax.tree.map(lax.stop_gradient, (F, H, Q, R)), max_iter, rtol), ()

    # The linearized Riccati equation (n² unknowns) is solved densely.
    return implicit_root(residual, solve, jnp.zeros((n, n), dtype))[0]
