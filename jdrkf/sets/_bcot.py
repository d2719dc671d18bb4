"""Bicausal optimal-transport (BCOT) distributionally robust Kalman filter (Han 2023,
"Distributionally robust Kalman filtering with volatility uncertainty", arXiv
2302.05993), the baseline of Jang, Hakobyan & Yang (2025): its worst-case problem and ambiguity set; the
filter is `jdrkf.BCOTKF`. See `docs/math/steady_state.md`.

Per step, with the previous posterior `N(x̂, Σ_p)` and nominal `Q_p = G Q Gᵀ`, `R_p`:

    max_{Σ, Q, R}  f = Tr(P⁻ − P⁻Cᵀ(CP⁻Cᵀ + R)⁻¹CP⁻),   P⁻ = AΣAᵀ + Q,
    s.t.  B²(N(Q, R), N(Q_p, R_p)) + B²(H^½ΣH^½, H^½Σ_pH^½) ≤ r,

`N(Q, R) = M blkdiag(Q, R) Mᵀ` with `M = [[I, 0], [C, I]]` (the law of `(w, Cw + v)`),
`H = I + AᵀA + AᵀCᵀCA`, `B²` the squared Bures (Gelbrich) distance.

**Reduction to a smooth convex problem in `2nm + 1` variables** (derived here, checked
against an SDP in `tests/test_bcot.py`). Write `E = I − KC`. Danskin (§0):
`f = min_K Tr(E P⁻ Eᵀ + K R Kᵀ) = min_K ⟨D_Σ, Σ⟩ + ⟨D_Q, Q⟩ + ⟨D_R, R⟩` with
`D_Q = EᵀE`, `D_Σ = AᵀD_QA`, `D_R = KᵀK`, linear in `(Σ, Q, R)`. The feasible set is
convex and compact, so Sion's theorem swaps max and min, and the inner maximum of a
linear function over the budget set is dualized with one multiplier `γ = 1/t` for the
budget and one `n × m` multiplier `Z` for the constraint that `blkdiag(Q, R)` has zero
off-diagonal block (without it the Gelbrich oracle would correlate `w` and `v`).
Both Gelbrich conjugates are closed form (§A.1 with the congruences `H`, `Ĥ = MᵀM`):

    f* = min_{K, t > 0, Z}  G = r/t + ⟨H(H − tD_Σ)⁻¹D_Σ, Σ_p⟩ + ⟨Ĥ(Ĥ − tΔ)⁻¹Δ, W_p⟩,

`Δ = blkdiag(D_Q, D_R) + [[0, Z], [Zᵀ, 0]]`, `W_p = blkdiag(Q_p, R_p)`, on the open
convex domain `H − tD_Σ ≻ 0`, `Ĥ − tΔ ≻ 0`. `G` is jointly convex (a supremum of
functions convex in `(K, 1/t, Z)`), and its minimizer gives the worst case in closed form:

    Σ* = (H − tD_Σ)⁻¹ H Σ_p H (H − tD_Σ)⁻¹,   blkdiag(Q*, R*) = (Ĥ − tΔ)⁻¹ Ĥ W_p Ĥ (Ĥ − tΔ)⁻¹,

`K` is the Kalman gain of `(Σ*, Q*, R*)`, `∂G/∂Z = 0` makes the noise blocks
independent, `∂G/∂t = 0` makes the budget active, and `df*/dr = γ* = 1/t*` (envelope).
With `θ = √r` and `t = θ s`, `G = f₀(K) + θ Γ(K, s, Z)`, where `f₀` is the nominal MSE of
gain `K` and `Γ = 1/s + s[⟨D_Σ(H − tD_Σ)⁻¹D_Σ, Σ_p⟩ + ⟨Δ(Ĥ − tΔ)⁻¹Δ, W_p⟩]`; the system
`(∇_K G, ∂_s Γ, ∇_Z Γ) = 0` is smooth and nonsingular down to `r = 0`.

**Solver.** Damped Newton on that `(2nm + 1)`-variable system (dense Jacobian by
`jacfwd`, Armijo backtracking on `G` that also keeps the iterate in the domain), from
the nominal Kalman gain and the small-radius multiplier. This is a deliberate departure
from the first-order schemes suggested in §D.2: the primal has `n(n+1) + m(m+1)/2`
unknowns and a budget set without a closed-form oracle (Frank–Wolfe would need an
iterative oracle inside every iteration, augmented Lagrangian a nested loop), while the
reduced problem is tiny, smooth and convex, so Newton reaches round-off in 5–15
iterations (36 at `r = 10⁶`), using Cholesky solves only (one `eigvalsh`, forward only,
places the starting point inside the domain). Cost per iteration: a `(2nm+1)`-column
Jacobian of `O((n+m)³)` work, so this suits the small state dimensions of the DR-KF
literature; for `nm` in the hundreds a matrix-free (Newton–CG) variant would be needed.
Stopping: a full Newton step of
max-norm `≤ √eps (1 + ‖x‖∞)` (quadratic convergence puts the next error at round-off).
Derivatives with respect to `radius`, the nominal covariances, `A` and `C` come from the
implicit function theorem on the same system (`lax.custom_root`), never from the loop.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jax import lax
from jax.flatten_util import ravel_pytree
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from .. import linalg
from .._root import implicit_root, newton
from .._validation import as_float_array, check_covariance, check_positive_int, check_scalar, in_range

_LINE_SEARCH_MAX = 60


class BCOTWorstCase(eqx.Module):
    """Solution of one BCOT step (`bcot_worst_case`).

    - `prior_cov`, `process_cov`, `noise_cov`: the worst-case `Σ*`, `Q*`, `R*`.
    - `gain`: the Kalman gain `K*` of the worst case (the dual variable `K`).
    - `value`: `f(Σ*, Q*, R*)`, the trace of the worst-case posterior covariance.
    - `multiplier`: `γ* = df*/d radius` (`inf` at `radius = 0`, where `f* − f₀ ~ √radius`).
    - `iterations`: Newton iterations; `residual`: max-norm of the optimality system at
      the returned point; `gap`: dual bound `G` minus `value` (≈ 0 at the optimum);
      `converged`: the stopping test was met within `max_iter` with finite output, the
      duality gap is closed (`|gap| ≤ √eps · value`), and the radius, if traced, is a
      finite number `≥ 0`.
    """

    prior_cov: Float[Array, "n n"]
    process_cov: Float[Array, "n n"]
    noise_cov: Float[Array, "m m"]
    gain: Float[Array, "n m"]
    value: Float[Array, ""]
    multiplier: Float[Array, ""]
    iterations: Int[Array, ""]
    residual: Float[Array, ""]
    gap: Float[Array, ""]
    converged: Bool[Array, ""]


# The solver factorizes with LAPACK (`jnp.linalg.cholesky`) rather than `linalg.cholesky`,
# whose unrolled code for n ≤ 6 made the Newton loop (Jacobians of solves, nested
# while loops) take minutes to compile; `jnp.linalg.solve` (LU) is avoided for the same
# reason except for the one non-symmetric Newton system.
def _chol(a):
    return jnp.linalg.cholesky(linalg.symmetrize(a))


def _cho_solve(chol, b):
    return jax.scipy.linalg.cho_solve((chol, True), b)


def _blkdiag(a, b):
    za = jnp.zeros((a.shape[0], b.shape[1]), a.dtype)
    return jnp.block([[a, za], [za.T, b]])


def _offdiag(z):
    n, m = z.shape
    return jnp.block([[jnp.zeros((n, n), z.dtype), z], [z.T, jnp.zeros((m, m), z.dtype)]])


def _weights(a, c):
    """`H = I + AᵀA + AᵀCᵀCA` and `Ĥ = MᵀM = [[I + CᵀC, Cᵀ], [C, I]]`."""
    n, m = a.shape[0], c.shape[0]
    eye_n, eye_m = jnp.eye(n, dtype=a.dtype), jnp.eye(m, dtype=a.dtype)
    ca = c @ a
    h = linalg.symmetrize(eye_n + a.T @ a + ca.T @ ca)
    hh = linalg.symmetrize(jnp.block([[eye_n + c.T @ c, c.T], [c, eye_m]]))
    return h, hh


def _directions(k, a, c):
    """Gradients of `f` at gain `K` (§D.2): `D_Σ = AᵀD_QA`, `D_Q = (I − KC)ᵀ(I − KC)`, `D_R = KᵀK`."""
    e = jnp.eye(a.shape[0], dtype=a.dtype) - k @ c
    dq = linalg.symmetrize(e.T @ e)
    return linalg.symmetrize(a.T @ dq @ a), dq, linalg.symmetrize(k.T @ k)


def _transport(d, h, nominal, t):
    """For `D` and the weight `h` of one Gelbrich term: `Y = (h − tD)⁻¹D` and
    `∇_D ⟨D(h − tD)⁻¹D, nominal⟩ = YΣ̂ + Σ̂Yᵀ + tYΣ̂Yᵀ`, so that the worst case is
    `(h − tD)⁻¹hΣ̂h(h − tD)⁻¹ = Σ̂ + t·∇` (exactly, also at `t = 0`)."""
    with linalg.lapack_only():  # see `_chol`; tangents of the Newton Jacobian: batched products
        y = linalg.psd_solve_fwd(h - t * d, d)
    ys = y @ nominal
    return y, linalg.symmetrize(ys + ys.T + t * ys @ y.T)


def _dual_terms(x, params):
    """`(f₀(K), Γ(K, s, Z), in_domain)` with `G = f₀ + θ Γ` (module docstring)."""
    k, s, z = x
    theta, sp, qp, rp, a, c = params
    h, hh = _weights(a, c)
    ds, dq, dr = _directions(k, a, c)
    wp = _blkdiag(qp, rp)
    delta = _blkdiag(dq, dr) + _offdiag(z)
    t = theta * s
    f0 = jnp.vdot(ds, sp) + jnp.vdot(dq, qp) + jnp.vdot(dr, rp)
    ls, lw = _chol(h - t * ds), _chol(hh - t * delta)
    gs = jnp.vdot(ds @ _cho_solve(ls, ds), sp)
    gw = jnp.vdot(delta @ _cho_solve(lw, delta), wp)
    gam = 1.0 / s + s * (gs + gw)
    ok = jnp.all(jnp.isfinite(ls)) & jnp.all(jnp.isfinite(lw)) & (s > 0) & jnp.isfinite(gam)
    return f0, gam, ok


def _stationarity(x, params):
    """Optimality system `(∇_K G, ∂_s Γ, ∇_Z Γ)` in closed form (smooth in `θ`, also at
    `θ = 0`), and the primal point `(Σ(x), blkdiag-part of W(x))` it implies.

    `∇_K G = 2(K(CPCᵀ + R) − PCᵀ)` with `P = AΣAᵀ + Q` at the primal point (the gain
    equation), `∂_s Γ = −1/s² + Σ_i [⟨D_iY_i, Σ̂_i⟩ + t⟨D_i, Y_iΣ̂_iY_iᵀ⟩]`,
    `∇_Z Γ = 2s ∇_Δ[...]₁₂` (the off-diagonal block of `(W(x) − W_p)/t`)."""
    k, s, z = x
    theta, sp, qp, rp, a, c = params
    n = a.shape[0]
    h, hh = _weights(a, c)
    ds, dq, dr = _directions(k, a, c)
    wp = _blkdiag(qp, rp)
    delta = _blkdiag(dq, dr) + _offdiag(z)
    t = theta * s
    ys, grad_s = _transport(ds, h, sp, t)
    yw, grad_w = _transport(delta, hh, wp, t)
    sig = sp + t * grad_s
    w = wp + t * grad_w
    q, r = w[:n, :n], w[n:, n:]
    p = linalg.symmetrize(a @ sig @ a.T + q)
    pc = p @ c.T
    res_k = 2.0 * (k @ (c @ pc + r) - pc)
    g = jnp.vdot(ds @ ys, sp) + jnp.vdot(delta @ yw, wp)
    dg = jnp.vdot(ds, ys @ sp @ ys.T) + jnp.vdot(delta, yw @ wp @ yw.T)
    res_s = -1.0 / (s * s) + g + t * dg
    res_z = 2.0 * s * grad_w[:n, n:]
    return (res_k, res_s, res_z), (sig, q, r)


def _residual(params):
    return lambda x: _stationarity(x, params)[0]


def _lambda_max(chol, d):
    """Largest eigenvalue of `L⁻¹DL⁻ᵀ` (`h = LLᵀ`), i.e. of the pencil `(D, h)`; forward only."""
    solve = jax.scipy.linalg.solve_triangular
    m = solve(chol, solve(chol, d, lower=True).T, lower=True)
    return jnp.linalg.eigvalsh(linalg.symmetrize(m))[-1]


def _initial(params):
    """Nominal Kalman gain, `Z = 0`, and `s = 1/√q`, the `θ → 0` limit of `∂_s Γ = 0`,
    capped at half the distance to the domain boundary `t λ_max = 1`."""
    theta, sp, qp, rp, a, c = params
    n, m = a.shape[0], c.shape[0]
    p = linalg.symmetrize(a @ sp @ a.T + qp)
    k = _cho_solve(_chol(c @ p @ c.T + rp), c @ p).T
    z = jnp.zeros((n, m), a.dtype)
    h, hh = _weights(a, c)
    ds, dq, dr = _directions(k, a, c)
    dw = _blkdiag(dq, dr)
    lh, lhh = _chol(h), _chol(hh)
    q = jnp.vdot(ds @ _cho_solve(lh, ds), sp) + jnp.vdot(dw @ _cho_solve(lhh, dw), _blkdiag(qp, rp))
    tiny = jnp.finfo(a.dtype).tiny
    s0 = 1.0 / jnp.sqrt(jnp.maximum(q, tiny))
    lam = jnp.maximum(_lambda_max(lh, ds), _lambda_max(lhh, dw))
    s0 = jnp.minimum(s0, 0.5 / jnp.maximum(theta * lam, tiny))
    return k, s0, z


def _newton(params, x0, max_iter):
    """Damped Newton on the optimality system with Armijo backtracking on `G` (infinite
    off the domain, so iterates stay in it); stops after a full step of max-norm
    `≤ √eps (1 + ‖x‖∞)`."""

    def objective(x):
        f0, gam, ok = _dual_terms(x, params)
        return jnp.where(ok, f0 + params[0] * gam, jnp.inf)

    # ∇G = scale · residual: the s and Z rows of the residual are ∇Γ = ∇G / θ.
    theta = params[0]
    scale = (jnp.ones_like(x0[0]), theta * jnp.ones_like(x0[1]), theta * jnp.ones_like(x0[2]))
    xtol = float(jnp.finfo(theta.dtype).eps) ** 0.5
    return newton(_residual(params), x0, max_iter, objective=objective, gradient_scale=scale, xtol=xtol,
                  max_backtracks=_LINE_SEARCH_MAX)


def _primal(x, params):
    """Worst-case `(Σ*, Q*, R*)` from the dual point (nominal exactly at `θ = 0`)."""
    theta, sp, qp, rp = params[:4]
    sig, q, r = _stationarity(x, params)[1]
    nominal = theta == 0
    # `0 · θ` is 0 in value; at r = 0 its derivative in r is 0 · ∞ = NaN in forward and
    # reverse mode, so derivatives in `radius` there are NaN rather than a silent 0 (the
    # `where` alone would give 0). Derivatives in the other arguments are unaffected.
    poison = 0.0 * theta
    return (jnp.where(nominal, sp, sig) + poison, jnp.where(nominal, qp, q) + poison, jnp.where(nominal, rp, r) + poison)


def _posterior_trace(sig, q, r, a, c):
    p = linalg.symmetrize(a @ sig @ a.T + q)
    k = _cho_solve(_chol(c @ p @ c.T + r), c @ p).T
    return jnp.trace(p) - jnp.trace(k @ c @ p)


def _solve(prior_cov, process_cov, noise_cov, a, c, radius, max_iter) -> BCOTWorstCase:
    dtype = prior_cov.dtype
    # θ = √r. At r = 0 the true derivative of the value is +inf (f* − f₀ ~ √r); see `_primal`.
    pos = radius > 0
    theta = jnp.sqrt(radius).astype(dtype)
    params = (theta, prior_cov, process_cov, noise_cov, a, c)

    def solve(guess):
        del guess
        p_ = jax.tree.map(lax.stop_gradient, params)
        x, iters, _, done = _newton(p_, _initial(p_), max_iter)
        return x, (iters, jnp.max(jnp.abs(ravel_pytree(_residual(p_)(x))[0])), done)

    n, m = a.shape[0], c.shape[0]
    guess = (jnp.zeros((n, m), dtype), jnp.ones((), dtype), jnp.zeros((n, m), dtype))
    x, (iters, resid, done) = implicit_root(_residual(params), solve, guess)
    sig, q, r = _primal(x, params)
    value = _posterior_trace(sig, q, r, a, c)
    f0, gam, _ = _dual_terms(x, params)
    gap = f0 + theta * gam - value
    multiplier = jnp.where(pos, 1.0 / (theta * x[1]), jnp.inf)
    finite = jnp.isfinite(value) & jnp.all(jnp.isfinite(sig)) & jnp.all(jnp.isfinite(q)) & jnp.all(jnp.isfinite(r))
    # Certificate: the dual bound meets the primal value (|gap| ~ eps at the optimum; a stopped
    # or wrong point leaves a gap of either sign, e.g. 4% after one Newton step).
    certified = jnp.abs(gap) <= jnp.sqrt(jnp.finfo(dtype).eps) * jnp.abs(value)
    return BCOTWorstCase(
        prior_cov=sig,
        process_cov=q,
        noise_cov=r,
        gain=x[0],
        value=value,
        multiplier=multiplier,
        iterations=iters,
        residual=resid,
        gap=gap,
        converged=done & certified & finite & in_range(radius, 0.0),
    )


def bcot_worst_case(
    prior_cov: Float[ArrayLike, "n n"],
    process_cov: Float[ArrayLike, "n n"],
    noise_cov: Float[ArrayLike, "m m"],
    A: Float[ArrayLike, "n n"],
    C: Float[ArrayLike, "m n"],
    radius: Float[ArrayLike, ""],
    *,
    max_iter: int = 100,
) -> BCOTWorstCase:
    """Worst-case `(Σ, Q, R)` of one BCOT step (Han 2023; `docs/math/steady_state.md`).

    Maximizes the posterior MSE `Tr(P⁻ − P⁻Cᵀ(CP⁻Cᵀ + R)⁻¹CP⁻)`, `P⁻ = AΣAᵀ + Q`, subject
    to `B²(N(Q, R), N(Q_p, R_p)) + B²(H^½ΣH^½, H^½Σ_pH^½) ≤ radius`, where
    `Σ_p = prior_cov` (previous posterior), `Q_p = process_cov` (`G Q Gᵀ`, state
    coordinates), `R_p = noise_cov`, `N(Q, R) = [[Q, QCᵀ], [CQ, CQCᵀ + R]]` and
    `H = I + AᵀA + AᵀCᵀCA`. **`radius` bounds the squared transport cost** (as in the
    authors' code), not a distance. The nominal covariances must be positive definite.

    Solved through an exact convex reformulation in `2nm + 1` variables by damped Newton
    (see the module docstring); differentiable in all arguments by the implicit function
    theorem, except in `radius` at `radius = 0` (the value grows like `√radius`; the
    derivative there is NaN). `radius = 0` returns the nominal covariances exactly.
    """
    prior_cov = as_float_array("prior_cov", prior_cov, (2,))
    process_cov = as_float_array("process_cov", process_cov, (2,))
    noise_cov = as_float_array("noise_cov", noise_cov, (2,))
    A = as_float_array("A", A, (2,))
    C = as_float_array("C", C, (2,))
    for name, x in (("prior_cov", prior_cov), ("process_cov", process_cov), ("noise_cov", noise_cov)):
        check_covariance(name, x)
    n, m = prior_cov.shape[0], noise_cov.shape[0]
    if process_cov.shape != (n, n):
        raise ValueError(f"process_cov has shape {tuple(process_cov.shape)} but expected ({n}, {n}) (prior_cov is {n}×{n})")
    if A.shape != (n, n):
        raise ValueError(f"A has shape {tuple(A.shape)} but expected ({n}, {n}) (prior_cov is {n}×{n})")
    if C.shape != (m, n):
        raise ValueError(f"C has shape {tuple(C.shape)} but expected ({m}, {n}) (noise_cov is {m}×{m}, prior_cov {n}×{n})")
    max_iter = check_positive_int("max_iter", max_iter)
    radius = check_scalar("radius", radius)
    dtype = jnp.result_type(prior_cov, process_cov, noise_cov, A, C)
    args = (x.astype(dtype) for x in (prior_cov, process_cov, noise_cov, A, C, radius))
    # `max_iter` is passed as an array so that changing it does not recompile.
    return _solve_jit(*args, jnp.asarray(max_iter))


_solve_jit = eqx.filter_jit(_solve)


class BCOT(eqx.Module):
    """The BCOT ambiguity set of one filter step (Han 2023): laws of the prior state and
    the noises whose squared bicausal transport cost from the nominal ones is at most
    `radius`, `B²(N(Q, R), N(Q_p, R_p)) + B²(H^½ΣH^½, H^½Σ_pH^½) ≤ radius` (module
    docstring). **`radius` bounds the squared cost** (the authors' convention), `≥ 0`;
    `radius = 0` is the nominal model. Array field: differentiable for `radius > 0`."""

    radius: Float[Array, ""]

    def __init__(self, radius: Float[ArrayLike, ""]):
        self.radius = check_scalar("radius", radius)

    def valid(self) -> Bool[Array, ""]:
        """Traced range check (`0 ≤ radius < ∞`); concrete values are checked when built."""
        return in_range(self.radius, 0.0)

    def worst_case(self, prior_cov, process_cov, noise_cov, A, C, max_iter: int) -> BCOTWorstCase:
        """`bcot_worst_case` without its eager argument checks (for use inside a filter
        step, where the arguments are traced and shapes are known to agree)."""
        return _solve(prior_cov, process_cov, noise_cov, A, C, self.radius.astype(prior_cov.dtype), max_iter)
