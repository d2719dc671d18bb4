"""θ_max: a sufficient Wasserstein radius for convergence of the DR Kalman filter
(Jang, Hakobyan & Yang, "On the steady-state distributionally robust Kalman filter",
Proposition 1 and Theorem 2, eqs. 17–20).

The computation follows the authors' `convergence_check.py` (`compute_matrices`,
`find_phi_T`, `compute_theta_max`; public code `jangminhyuk/SteadyStateDRKF`); see
`docs/math/steady_state.md`.
"""

from __future__ import annotations

import functools
import operator

import equinox as eqx
import jax
import jax.numpy as jnp
from jax import lax
from jax.scipy.linalg import solve_triangular
from jaxtyping import Array, ArrayLike, Bool, Float

from .. import linalg
from .._validation import as_float_array, check_covariance


__all__ = ["ThetaMax", "theta_max"]


class ThetaMax(eqx.Module):
    """Result of `theta_max`.

    - `theta_max`: the radius θ_max of eq. 20 (NaN when `valid` is false).
    - `phi_tilde`: φ̃_N of eq. 18.
    - `phi`: the φ_N ∈ [0, φ̃_N) found by bisection (0 when none is found).
    - `nominal_prior_cov`: Σ̄⁻_{x,q}, the nominal Kalman prior covariance after `q` steps.
    - `valid`: `φ_N > 0` and `φ_N λ_max(Σ̄⁻_{x,q}) < 1` (eq. 20 is then defined).
    """

    theta_max: Float[Array, ""]
    phi_tilde: Float[Array, ""]
    phi: Float[Array, ""]
    nominal_prior_cov: Float[Array, "n n"]
    valid: Bool[Array, ""]


def _block_matrices(A, C, chol_w, chol_v, N):
    """O_N, O_N^R, D_N, L_N, H_N of the downsampled model (Section 4.2), newest block first."""
    n = A.shape[0]
    dtype = A.dtype
    powers = [jnp.eye(n, dtype=dtype)]
    for _ in range(N - 1):
        powers.append(A @ powers[-1])  # powers[k] = A^k
    obs = jnp.concatenate([C @ powers[N - 1 - i] for i in range(N)], axis=0)  # (N m, n)
    obs_r = jnp.concatenate([powers[N - 1 - i] for i in range(N)], axis=0)  # (N n, n)
    zero = jnp.zeros((n, n), dtype)
    hankel = jnp.block([[powers[j - i - 1] @ chol_w if j > i else zero for j in range(N)] for i in range(N)])
    h = jnp.kron(jnp.eye(N, dtype=dtype), C) @ hankel  # (N m, N n)
    d = jnp.kron(jnp.eye(N, dtype=dtype), chol_v)  # (N m, N m), lower triangular
    return obs, obs_r, d, hankel, h


@functools.partial(jax.jit, static_argnames=("N", "max_iter"))
def _theta_max(A, C, Sigma_w, Sigma_v, q, tol, eig_tol, N, max_iter):
    dtype = A.dtype
    n = A.shape[0]
    chol_w = linalg.cholesky(linalg.symmetrize(Sigma_w))  # B = chol(Σ_w) plays Σ_w^{1/2}
    chol_v = linalg.cholesky(linalg.symmetrize(Sigma_v))
    obs, obs_r, d, hankel, h = _block_matrices(A, C, chol_w, chol_v, N)

    # Eq. 18: G = L (I + Hᵀ (D Dᵀ)⁻¹ H)⁻¹ Lᵀ and φ̃ = 1 / λ_max(G).
    dinv_h = solve_triangular(d, h, lower=True)  # D⁻¹ H
    inner = jnp.eye(N * n, dtype=dtype) + dinv_h.T @ dinv_h
    gram = linalg.symmetrize(hankel @ linalg.psd_solve(inner, hankel.T))
    phi_tilde = 1.0 / jnp.linalg.eigvalsh(gram)[-1]

    # Eq. 17 definitions: M = D Dᵀ + H Hᵀ, Ω_N = O_Nᵀ M⁻¹ O_N, J_N = O_N^R − L Hᵀ M⁻¹ O_N.
    mmat = linalg.symmetrize(d @ d.T + h @ h.T)
    minv_obs = linalg.psd_solve(mmat, obs)
    omega = linalg.symmetrize(obs.T @ minv_obs)
    jmat = obs_r - hankel @ (h.T @ minv_obs)

    def feasible(phi):
        # Ω_{φI} = Ω_N + Jᵀ S_φ⁻¹ J with S_φ = G − I/φ ≺ 0 for 0 < φ < φ̃: solve with −S_φ ≻ 0.
        neg_s = jnp.eye(N * n, dtype=dtype) / phi - gram
        omega_phi = linalg.symmetrize(omega - jmat.T @ linalg.psd_solve(neg_s, jmat))
        # NaN (−S_φ not numerically positive definite) compares false: infeasible.
        return jnp.linalg.eigvalsh(omega_phi)[0] > eig_tol

    def cond(carry):
        lo, hi, it = carry
        return (hi - lo > tol) & (it < max_iter)

    def body(carry):
        lo, hi, it = carry
        mid = 0.5 * (lo + hi)
        ok = feasible(mid)
        return jnp.where(ok, mid, lo), jnp.where(ok, hi, mid), it + 1

    hi0 = jnp.where(jnp.isfinite(phi_tilde) & (phi_tilde > 0), phi_tilde, jnp.zeros((), dtype))
    phi, _, _ = lax.while_loop(cond, body, (jnp.zeros((), dtype), hi0, jnp.zeros((), jnp.int32)))

    # Theorem 2: q nominal Riccati prior steps from Σ̄⁻_{x,0} = Σ_w (Joseph form).
    eye_n = jnp.eye(n, dtype=dtype)

    def riccati(_, p):
        s = linalg.symmetrize(C @ p @ C.T + Sigma_v)
        gain = linalg.psd_solve(s, C @ p).T
        a = eye_n - gain @ C
        post = a @ p @ a.T + gain @ Sigma_v @ gain.T
        return linalg.symmetrize(A @ post @ A.T + Sigma_w)

    prior = lax.fori_loop(0, q, riccati, linalg.symmetrize(Sigma_w))
    trace = jnp.trace(prior)
    lam_max = jnp.linalg.eigvalsh(prior)[-1]

    # Eq. 20, as √tr · x / (√(1−x) (1 + √(1−x))) with x = φ λ_max (no cancellation).
    x = phi * lam_max
    valid = (phi > 0) & (x < 1) & jnp.isfinite(trace) & jnp.isfinite(lam_max)
    root = jnp.sqrt(jnp.where(valid, 1.0 - x, jnp.ones((), dtype)))
    theta = jnp.sqrt(trace) * x / (root * (1.0 + root))
    theta = jnp.where(valid, theta, jnp.full((), jnp.nan, dtype))
    return ThetaMax(theta_max=theta, phi_tilde=phi_tilde, phi=phi, nominal_prior_cov=prior, valid=valid)


def _static_int(name: str, value, minimum: int) -> int:
    try:
        out = operator.index(value)
    except TypeError as e:
        raise ValueError(f"{name} must be a Python integer (it fixes array shapes / loop lengths), got {type(value).__name__}") from e
    if out < minimum:
        raise ValueError(f"{name} must be >= {minimum}, got {out}")
    return out


def theta_max(
    A: Float[ArrayLike, "n n"],
    C: Float[ArrayLike, "m n"],
    Sigma_w: Float[ArrayLike, "n n"],
    Sigma_v: Float[ArrayLike, "m m"],
    N: int = 8,
    q: int = 20,
    *,
    tol: float = 1e-10,
    eig_tol: float = 1e-10,
    max_iter: int = 1000,
) -> ThetaMax:
    """The radius θ_max of Theorem 2 (eq. 20) for the model `x⁺ = A x + w`, `y = C x + v`
    with nominal `w ~ N(0, Σ_w)`, `v ~ N(0, Σ_v)` (Jang, Hakobyan & Yang 2025).

    Steps (as in the authors' `convergence_check.py`):

    1. Block matrices of the N-step downsampled model (Section 4.2): O_N (blocks
       `C A^{N−1}, …, C A, C`, newest first), O_N^R (`A^{N−1}, …, A, I`),
       `D_N = I_N ⊗ chol(Σ_v)`, the block-Hankel `[L_N]_ij = A^{j−i−1} Σ_w^{1/2}`
       (j > i) and `H_N = (I_N ⊗ C) L_N`, with `Σ_w^{1/2} = chol(Σ_w)` as in the
       authors' code (all quantities below are invariant to that choice).
    2. `φ̃_N = 1 / λ_max(L (I + Hᵀ(DDᵀ)⁻¹H)⁻¹ Lᵀ)` (eq. 18).
    3. φ_N: bisection on `[0, φ̃_N]` to width `tol` for the largest φ with
       `λ_min(Ω_N + J_Nᵀ S_φ⁻¹ J_N) > eig_tol`, `S_φ = L(I + Hᵀ(DDᵀ)⁻¹H)⁻¹Lᵀ − I/φ`
       (eq. 17 definitions at `Φ̄_{N,t} = φ I`; the sign conventions of the paper and
       the code agree). This replaces the paper's "decrease φ until Ω becomes
       singular" (Section 5.1) by the code's bisection; `max_iter` caps it.
    4. Σ̄⁻_{x,q}: `q` nominal Riccati steps `Σ̄ ← A(Σ̄⁻¹ + CᵀΣ_v⁻¹C)⁻¹Aᵀ + Σ_w` from
       `Σ̄ = Σ_w` (computed in Joseph form).
    5. `θ_max = √(Tr Σ̄ / (1 − φ_N λ_max(Σ̄))) − √(Tr Σ̄)` (eq. 20); NaN and
       `valid = False` when `φ_N λ_max(Σ̄) ≥ 1` or when no `φ_N > 0` was found
       (e.g. (A, C) not observable over N steps, so that Ω_N is singular).

    θ_max is a *sufficient*, conservative condition and only for `θ_v = 0`: for
    `θ_x ∈ [0, θ_max]` the time-varying DR Riccati recursion (16) converges to the
    steady state of the SDP (14) (Theorem 2, Corollary 1). It says nothing about
    `θ_v > 0` nor about larger radii. It is a diagnostic: φ_N comes from a bisection,
    so it is not differentiable (its gradient is zero). Use float64.

    **Arguments:**

    - `A` (n, n), `C` (m, n), `Sigma_w` (n, n) and `Sigma_v` (m, m) positive definite.
    - `N`: block length, a Python int with `N ≥ max(n, 2)` (Proposition 1 needs
      `N ≥ n`; at N = 1, L_N = 0 and φ̃_N is infinite). The paper's example uses 8.
    - `q`: number of nominal Riccati steps, Python int ≥ 1 (paper: 20).
    - `tol`: bisection width on φ; `eig_tol`: the λ_min threshold (both 1e-10 in the
      authors' code); `max_iter`: bisection cap.

    **Example:** `theta_max(A, C, I₂, [[1]], N=8, q=20).theta_max ≈ 3.356` for
    `A = [[0.1, 1], [0, 1.2]]`, `C = [[1, −1]]` (Section 5.1).
    """
    A = as_float_array("A", A, (2,))
    C = as_float_array("C", C, (2,))
    Sigma_w = as_float_array("Sigma_w", Sigma_w, (2,))
    Sigma_v = as_float_array("Sigma_v", Sigma_v, (2,))
    n = A.shape[0]
    if A.shape != (n, n):
        raise ValueError(f"A must be square (n, n), got shape {A.shape}")
    if C.shape[1] != n:
        raise ValueError(f"C must have shape (m, {n}) to match A, got {C.shape}")
    m = C.shape[0]
    if Sigma_w.shape != (n, n):
        raise ValueError(f"Sigma_w must have shape ({n}, {n}) to match A, got {Sigma_w.shape}")
    if Sigma_v.shape != (m, m):
        raise ValueError(f"Sigma_v must have shape ({m}, {m}) to match C, got {Sigma_v.shape}")
    check_covariance("Sigma_w", Sigma_w)
    check_covariance("Sigma_v", Sigma_v)
    N = _static_int("N", N, 1)
    if N < max(n, 2):
        raise ValueError(f"N must be >= max(n_x, 2) = {max(n, 2)} (Proposition 1 needs N >= n_x = {n}), got N = {N}")
    q = _static_int("q", q, 1)
    max_iter = _static_int("max_iter", max_iter, 1)
    if not (isinstance(tol, jax.core.Tracer) or float(tol) > 0):
        raise ValueError(f"tol must be > 0, got {tol}")
    if not (isinstance(eig_tol, jax.core.Tracer) or float(eig_tol) >= 0):
        raise ValueError(f"eig_tol must be >= 0, got {eig_tol}")
    dtype = jnp.result_type(A, C, Sigma_w, Sigma_v)
    A, C, Sigma_w, Sigma_v = (x.astype(dtype) for x in (A, C, Sigma_w, Sigma_v))
    # q only sets a loop length: passed traced, so that changing it does not recompile.
    return _theta_max(
        A, C, Sigma_w, Sigma_v, jnp.asarray(q, jnp.int32), jnp.asarray(tol, dtype), jnp.asarray(eig_tol, dtype),
        N=N, max_iter=max_iter,
    )
