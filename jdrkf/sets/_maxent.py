"""Maximum-entropy distributions near a discrete reference `q` (Wang 2022, "Distributionally
Robust State Estimation for Nonlinear Systems", IEEE TSP, §III-B/C and Algorithm 1).

Three problems, all used to build worst-case prior particle weights (Methods 1–2):

* `maxent_kl` — Theorem 6, eq. (34): `max H(p)` s.t. `KL(p‖q) ≤ θ`, `Σp = 1`. Stationarity
  (35) gives `p ∝ q^β` with `β = λ₀/(1 + λ₀) ∈ [0, 1]` (tempering towards uniform), and
  `KL(p_β‖q)` decreases in `β`, so `β*` is the root of `KL(p_β‖q) = θ` (uniform `p` once
  `θ ≥ KL(u‖q)`). Zero entries of `q` are handled exactly by masking (`p_i = 0` there; the
  reference code instead adds `1e-6` to `q`).
* `maxent_wasserstein` / `maxent_transport` — Theorem 5, eqs. (27)–(29) (coupling-entropy
  relaxation): `P_ij = q_i softmax_j(−v₀ c_ij)`, `p_j = Σ_i P_ij`, with `v₀ = 0` when
  `C(0) = Σ c_ij q_i / M ≤ θ` and otherwise the root of `C(v₀) = Σ c_ij P_ij(v₀) = θ`
  (`C` decreases). Feasible iff `θ ≥ Σ_i q_i min_j c_ij`. Note (`docs/math/particle.md`) that the
  coupling entropy is a *surrogate*: `p` does not maximize `H(p)` of the marginal itself.
* `maxent_wasserstein_continuous` — Theorem 3, eqs. (15)–(18): density
  `p(x) = exp(−v₀ min_i(‖x − x_i‖ − λ_i) − v₁ − 1)` on a bounded domain, discretized on
  Monte Carlo (or quadrature) points; see its docstring for the (small, documented)
  entropic smoothing that makes the discretized dual smooth and the solution unique.

"Exact" solves reduce each discrete problem to one scalar equation, solved by bracketed
(safeguarded) Newton in a capped `lax.while_loop`; derivatives come from the implicit
function theorem at the root (`lax.custom_root`), never from the iterations, so `p` is
differentiable in `θ`, `q` and the supports. `method="pgd"` reproduces the authors'
projected gradient descent on the dual (Algorithm 1 / the reference MATLAB code), whose
early-stopped iterates are what the supplement's Tables V and VI print.

Everything is `jit`/`vmap`-able (fixed shapes, capped loops). Detailed results
(`*_solve`) are `MaxEntResult`s; the short forms return `p` only.
"""

from __future__ import annotations

from functools import partial

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jax.nn import log_softmax, logsumexp
from jaxtyping import Array, ArrayLike, Bool, Float, Int, PRNGKeyArray

from .._root import bracketed_newton, implicit_root
from .._validation import as_float_array, check_scalar, in_range, is_concrete, renamed

__all__ = [
    "MaxEntContinuous",
    "MaxEntResult",
    "maxent_kl",
    "maxent_kl_solve",
    "maxent_transport",
    "maxent_transport_solve",
    "maxent_wasserstein",
    "maxent_wasserstein_continuous",
    "maxent_wasserstein_solve",
]


class MaxEntResult(eqx.Module):
    """Detailed result of a discrete max-entropy solve.

    - `p`: the distribution (sums to 1).
    - `dual`: the scalar dual variable: `β = λ₀/(1+λ₀) ∈ [0, 1]` (KL, `p ∝ q^β`) or `v₀ ≥ 0`
      (Wasserstein; `0` when the budget is inactive). For `method="pgd"` it is the final
      iterate `λ₀` resp. `v₀` of the authors' dual variables.
    - `constraint`: `KL(p‖q)` resp. the transport cost `Σ c_ij P_ij` at the output.
    - `iterations`, `converged`: of the scalar Newton solve (or of the PGD loop);
      `converged` is `False` for a traced `theta` that is not a finite number `≥ 0`, and
      for an infeasible Wasserstein budget (`feasible` is `False`).
    - `feasible`: `False` only for a Wasserstein budget below the minimal cost
      `Σ_i q_i min_j c_ij` (then `p` is the `v₀ → ∞` limit, NaN-free).
    - `coupling`: the joint `P` (Wasserstein) or `None` (KL).
    """

    p: Float[Array, " M"]
    dual: Float[Array, ""]
    constraint: Float[Array, ""]
    iterations: Int[Array, ""]
    converged: Bool[Array, ""]
    feasible: Bool[Array, ""]
    coupling: Float[Array, "N M"] | None = None


# ---------------------------------------------------------------------- scalar roots


def _implicit(residual, x, active, params):
    """`x`, a root of `residual(·, params)` where `active` (held at a bound elsewhere) from
    a non-differentiated solve, with the derivatives of the implicit function theorem
    (`dx = −(∂_x r)⁻¹ ∂_p r dp`) on the `active` coordinates and `0` on the others. `x` is
    a scalar (then also `0` where `∂_x r` is zero or not finite) or a vector (`residual`
    a gradient, `∂_x r` its Hessian, nonsingular on the active coordinates)."""
    x = lax.stop_gradient(x)  # the solve is never differentiated
    if x.ndim == 0:
        dr_dx = jax.jvp(lambda y: residual(y, params), (x,), (jnp.ones_like(x),))[1]
        active = active & (dr_dx != 0) & jnp.isfinite(dr_dx)
    return implicit_root(lambda y: jnp.where(active, residual(y, params), y - x), lambda _: (x, ()), x)[0]


# ------------------------------------------------------------------------- checks


def _check_prob(name, q):
    q = as_float_array(name, q, (1,))
    if q.shape[0] < 1:
        raise ValueError(f"{name} must have at least one entry, got shape {q.shape}")
    if is_concrete(q):
        a = np.asarray(q, dtype=np.float64)
        if not np.all(np.isfinite(a)) or np.any(a < 0) or a.sum() <= 0:
            raise ValueError(f"{name} must be finite, nonnegative and not all zero")
        if abs(a.sum() - 1.0) > 1e-4:
            raise ValueError(f"{name} must sum to 1 (got sum {a.sum():.6g})")
    return q / jnp.sum(q)


def _theta_checked(res: MaxEntResult, theta) -> MaxEntResult:
    """`res` with `converged = False` when a traced `theta` is out of range (NaN, negative
    or infinite; concrete values raise in `check_scalar`)."""
    return eqx.tree_at(lambda r: r.converged, res, res.converged & in_range(theta, 0.0))


def _check_method(method):
    if method not in ("exact", "pgd"):
        raise ValueError(f"method must be 'exact' or 'pgd', got {method!r}")


# ----------------------------------------------------------------------------- KL


def _masked_log(q):
    pos = q > 0
    return pos, jnp.where(pos, jnp.log(jnp.where(pos, q, 1.0)), 0.0)


def _tempered(beta, lq, pos):
    """`log p_β` with `p_β ∝ q^β` on the support of `q` (`−∞` off it)."""
    z = jnp.where(pos, beta * lq, -jnp.inf)
    return z - logsumexp(z)


def _kl_to_q(logp, lq, pos):
    """`KL(p‖q)` with `p = exp(logp)` supported on `pos`."""
    return jnp.sum(jnp.where(pos, jnp.exp(logp) * (logp - lq), 0.0))


def _kl_residual(s, params):
    """`√KL(p_{1−s}‖q) − √θ`, increasing in `s = 1 − β ∈ [0, 1]` and nearly linear near
    `s = 0` (where `KL ≈ s² Var_q(ln q)/2`), which keeps Newton quadratic for small `θ`."""
    lq, pos, theta = params
    kl = _kl_to_q(_tempered(1.0 - s, lq, pos), lq, pos)
    return jnp.sqrt(jnp.maximum(kl, jnp.finfo(s.dtype).tiny)) - jnp.sqrt(theta)


def _kl_exact(q, theta, max_iter):
    pos, lq = _masked_log(q)
    lq_ng, theta_ng = lax.stop_gradient(lq), lax.stop_gradient(theta)
    kl_uniform = _kl_to_q(_tempered(jnp.zeros_like(theta), lq_ng, pos), lq_ng, pos)
    active = (theta_ng > 0) & (theta_ng < kl_uniform)
    # Guess from the quadratic expansion KL ≈ s² Var_q(ln q) / 2.
    mean = jnp.sum(jnp.where(pos, q * lq_ng, 0.0))
    var = jnp.sum(jnp.where(pos, q * (lq_ng - mean) ** 2, 0.0))
    s0 = jnp.sqrt(2.0 * theta_ng / jnp.maximum(var, jnp.finfo(q.dtype).tiny))
    s, fs, k, _ = bracketed_newton(lambda s: _kl_residual(s, (lq_ng, pos, theta_ng)), s0, 0.0, 1.0, max_iter, x_scale=1.0)
    s = jnp.where(theta_ng <= 0, 0.0, jnp.where(active, s, 1.0))
    s = _implicit(_kl_residual, s, active, (lq, pos, theta))
    beta = 1.0 - s
    logp = _tempered(beta, lq, pos)
    p = jnp.exp(logp)
    tol = 1e3 * jnp.finfo(q.dtype).eps
    converged = ~active | (jnp.abs(fs) <= tol * jnp.maximum(jnp.sqrt(theta_ng), 1.0))
    return MaxEntResult(p, beta, _kl_to_q(logp, lq, pos), k, converged, jnp.asarray(True))


def _kl_pgd(q, theta, step, max_iter, tol, init):
    """The reference `main.m` of Table V verbatim: `p` from the current `(λ₀, λ₁)` by (35),
    gradients (37)–(38), a projected step, stop when `|Σp − 1| < tol` (checked on the `p`
    of the previous pass, starting from `p = 0`) or after `max_iter` passes; renormalize."""
    pos, lq = _masked_log(q)
    dtype = q.dtype

    def p_of(l0, l1):
        return jnp.where(pos, jnp.exp((l0 * lq - l1) / (l0 + 1.0) - 1.0), 0.0)

    def cond(c):
        _, _, p, k = c
        return (k < max_iter) & (jnp.abs(jnp.sum(p) - 1.0) >= tol)

    def body(c):
        l0, l1, _, k = c
        p = p_of(l0, l1)
        g0 = theta + jnp.sum(jnp.where(pos, p * (1.0 + (lq + l1) / (l0 + 1.0)), 0.0))
        g1 = 1.0 - jnp.sum(p)
        return jnp.maximum(l0 - step * g0, 0.0), l1 - step * g1, p, k + 1

    init = (jnp.asarray(init[0], dtype), jnp.asarray(init[1], dtype), jnp.zeros_like(q), jnp.asarray(0))
    l0, _, p, k = lax.while_loop(cond, body, init)
    converged = jnp.abs(jnp.sum(p) - 1.0) < tol
    p = p / jnp.sum(p)
    logp = jnp.where(pos, jnp.log(jnp.where(pos, p, 1.0)), -jnp.inf)
    return MaxEntResult(p, l0, _kl_to_q(logp, lq, pos), k, converged, jnp.asarray(True))


def maxent_kl_solve(
    q: Float[ArrayLike, " N"],
    radius: Float[ArrayLike, ""] = None,
    *,
    theta: Float[ArrayLike, ""] | None = None,
    method: str = "exact",
    step: float = 0.05,
    max_iter: int | None = None,
    tol: float = 1e-8,
    init: tuple[float, float] = (2.0, 0.0),
) -> MaxEntResult:
    """`max H(p)` s.t. `KL(p‖q) ≤ θ`, `Σp = 1` (Theorem 6, eq. 34), with diagnostics;
    `θ = radius` (`theta=`: deprecated alias).

    `method="exact"`: `p ∝ q^β`, `β ∈ [0, 1]` the root of `KL(p_β‖q) = θ` (bracketed
    Newton, at most `max_iter` (default 60) steps; `θ = 0 ⇒ p = q`, `θ ≥ KL(u‖q) ⇒ p`
    uniform on the support of `q`); differentiable in `q` and `θ` (implicit function
    theorem; the derivative in `θ` is infinite at `θ = 0` and reported as 0 there).

    `method="pgd"`: Algorithm 1 as in the authors' code (step `step`, init `(λ₀, λ₁) = init`,
    stop when `|Σp − 1| < tol` or after `max_iter` (default 50 000) passes, renormalize).
    Its output is an unconverged iterate in general: with the Table V settings it reproduces
    the printed `p` to ≈1e-4 while `KL(p‖q)` misses `θ` by ≈1e-4 (tests/test_maxent.py).
    Not differentiable in a useful sense.
    """
    _check_method(method)
    q = _check_prob("q", q)
    theta = check_scalar("radius", renamed("theta", theta, "radius", radius, "maxent_kl_solve", stacklevel=3)).astype(q.dtype)
    if method == "exact":
        return _theta_checked(_kl_exact(q, theta, 60 if max_iter is None else max_iter), theta)
    return _theta_checked(_kl_pgd(q, theta, step, 50_000 if max_iter is None else max_iter, tol, init), theta)


def maxent_kl(q: Float[ArrayLike, " N"], radius: Float[ArrayLike, ""] = None, **kwargs) -> Float[Array, " N"]:
    """`p` of `maxent_kl_solve` (same arguments): Theorem 6, `p ∝ q^β`."""
    return maxent_kl_solve(q, radius, **kwargs).p


# --------------------------------------------------------------- Wasserstein, discrete


def _pairwise_distance(a, b):
    """Euclidean `‖a_i − b_j‖` with a zero (sub)gradient at coincident points."""
    d2 = jnp.sum((a[:, None, :] - b[None, :, :]) ** 2, axis=-1)
    pos = d2 > 0
    return jnp.where(pos, jnp.sqrt(jnp.where(pos, d2, 1.0)), 0.0)


def _log_excess(v0, c, lq, qpos):
    """`ln(C(v₀) − C_min)` with `C_min = Σ_i q_i min_j c_ij`, summed without cancellation
    (every term `q_i P_{j|i} (c_ij − min_j c_ij)` is nonnegative)."""
    gap = c - jnp.min(c, axis=1, keepdims=True)
    gpos = gap > 0
    log_gap = jnp.where(gpos, jnp.log(jnp.where(gpos, gap, 1.0)), -jnp.inf)
    terms = jnp.where(qpos[:, None] & gpos, lq[:, None] + log_softmax(-v0 * c, axis=1) + log_gap, -jnp.inf)
    return logsumexp(terms)


def _transport_residual(u, params):
    """`ln(θ − C_min) − ln(C(e^u) − C_min)`, increasing in `u = ln v₀`."""
    c, lq, qpos, log_slack = params
    return log_slack - _log_excess(jnp.exp(u), c, lq, qpos)


def _transport_exact(q, c, theta, max_iter):
    qpos, lq = _masked_log(q)
    dtype = q.dtype
    c_ng, lq_ng, theta_ng = lax.stop_gradient(c), lax.stop_gradient(lq), lax.stop_gradient(theta)
    m = c_ng.shape[1]
    c_min = jnp.sum(q * jnp.min(c_ng, axis=1))
    c_zero = jnp.sum(q[:, None] * c_ng) / m
    feasible = theta_ng >= c_min
    active = theta_ng < c_zero
    slack = theta - jnp.min(c, axis=1) @ q
    tiny = jnp.finfo(dtype).tiny
    log_slack = jnp.log(jnp.maximum(slack, tiny))
    log_slack_ng = lax.stop_gradient(log_slack)
    # Bracket for u = ln v₀: C(v₀) is within ~1e-12 of C(0) at the bottom and equals C_min
    # to working precision (e^{-800}) at the top.
    scale = jnp.maximum(jnp.max(c_ng), tiny)
    gap = c_ng - jnp.min(c_ng, axis=1, keepdims=True)
    gap_min = jnp.min(jnp.where(gap > 0, gap, jnp.inf))
    gap_min = jnp.where(jnp.isfinite(gap_min), gap_min, scale)
    lo, hi = jnp.log(1e-12 / scale), jnp.log(800.0 / gap_min)
    # Guess: first-order expansion C(v₀) ≈ C(0) − v₀ Σ_i q_i Var_j(c_ij).
    var0 = jnp.sum(q * jnp.var(c_ng, axis=1))
    u0 = jnp.log(jnp.maximum((c_zero - theta_ng) / jnp.maximum(var0, tiny), tiny))
    params_ng = (c_ng, lq_ng, qpos, log_slack_ng)
    u, fu, k, _ = bracketed_newton(lambda u: _transport_residual(u, params_ng), u0, lo, hi, max_iter, x_scale=1.0)
    u = _implicit(_transport_residual, u, active & feasible & (slack > 0), (c, lq, qpos, log_slack))
    v0 = jnp.where(active, jnp.exp(u), 0.0)
    coupling = q[:, None] * jax.nn.softmax(-v0 * c, axis=1)
    # An infeasible budget has no solution: never converged (`p` is the `v₀ → ∞` limit).
    converged = feasible & (~active | (jnp.abs(fu) <= 1e3 * jnp.finfo(dtype).eps))
    return MaxEntResult(
        jnp.sum(coupling, axis=0), v0, jnp.sum(c * coupling), k, converged, feasible, coupling
    )


def _transport_pgd(q, c, theta, step, max_iter, tol, init):
    """The reference `main_Table_6.m` verbatim: `P_ij = exp(−v₀ c_ij − λ_i − 1)` (28),
    gradients (30)–(31), projected step; stop when `|ΣP − 1| < tol` (on the previous pass,
    starting from `P = 0`) or after `max_iter` passes; renormalize `P`."""
    n = c.shape[0]
    dtype = q.dtype

    def p_of(v0, lam):
        return jnp.exp(-v0 * c - lam[:, None] - 1.0)

    def cond(carry):
        _, _, p, k = carry
        return (k < max_iter) & (jnp.abs(jnp.sum(p) - 1.0) >= tol)

    def body(carry):
        v0, lam, _, k = carry
        p = p_of(v0, lam)
        g0 = theta - jnp.sum(c * p)
        glam = q - jnp.sum(p, axis=1)
        return jnp.maximum(v0 - step * g0, 0.0), lam - step * glam, p, k + 1

    init = (jnp.asarray(init[0], dtype), jnp.full((n,), init[1], dtype), jnp.zeros_like(c), jnp.asarray(0))
    v0, _, coupling, k = lax.while_loop(cond, body, init)
    converged = jnp.abs(jnp.sum(coupling) - 1.0) < tol
    coupling = coupling / jnp.sum(coupling)
    return MaxEntResult(
        jnp.sum(coupling, axis=0), v0, jnp.sum(c * coupling), k, converged, jnp.asarray(True), coupling
    )


def maxent_transport_solve(
    q: Float[ArrayLike, " N"],
    cost: Float[ArrayLike, "N M"],
    radius: Float[ArrayLike, ""] = None,
    *,
    theta: Float[ArrayLike, ""] | None = None,
    method: str = "exact",
    step: float = 0.9,
    max_iter: int | None = None,
    tol: float = 1e-4,
    init: tuple[float, float] = (2.0, 0.0),
) -> MaxEntResult:
    """Theorem 5 (eqs. 27–29) for a generic nonnegative cost matrix `cost[i, j]`.

    `max −Σ P_ij ln P_ij` s.t. `Σ_j P_ij = q_i`, `Σ c_ij P_ij ≤ θ`; `p_j = Σ_i P_ij`;
    `θ = radius` (`theta=`: deprecated alias).

    `method="exact"`: `P_ij = q_i softmax_j(−v₀ c_ij)`; `v₀ = 0` (rows uniform) when
    `θ ≥ C(0)`, else the root of `C(v₀) = θ`, found by bracketed Newton on
    `ln(C(v₀) − C_min) = ln(θ − C_min)` in `ln v₀` (at most `max_iter`, default 100,
    steps). A budget below `C_min = Σ_i q_i min_j c_ij` is infeasible: a `ValueError` when
    concrete, otherwise `feasible=False` and the `v₀ → ∞` limit. Differentiable in `q`,
    `cost` and `θ` (implicit function theorem).

    `method="pgd"`: the authors' projected gradient on `(v₀, λ)` (`main_Table_6.m`: step
    `step`, init `v₀, λ_i = init`, stop when `|ΣP − 1| < tol` or after `max_iter` (default
    5 000 000) passes, renormalize).
    """
    _check_method(method)
    q = _check_prob("q", q)
    cost = as_float_array("cost", cost, (2,)).astype(q.dtype)
    if cost.shape[0] != q.shape[0]:
        raise ValueError(f"cost must have shape (N, M) with N = len(q) = {q.shape[0]}, got {cost.shape}")
    theta = check_scalar("radius", renamed("theta", theta, "radius", radius, "maxent_transport_solve", stacklevel=3)).astype(q.dtype)
    if is_concrete(cost) and is_concrete(theta) and is_concrete(q):
        c_np, q_np = np.asarray(cost, np.float64), np.asarray(q, np.float64)
        if np.any(c_np < 0) or not np.all(np.isfinite(c_np)):
            raise ValueError("cost must be finite and nonnegative")
        c_min = float(q_np @ c_np.min(axis=1))
        if method == "exact" and float(theta) < c_min * (1 - 1e-12):
            raise ValueError(
                f"radius = {float(theta):.6g} is infeasible: it must be >= the minimal transport cost "
                f"sum_i q_i min_j c_ij = {c_min:.6g}"
            )
    if method == "exact":
        return _theta_checked(_transport_exact(q, cost, theta, 100 if max_iter is None else max_iter), theta)
    return _theta_checked(_transport_pgd(q, cost, theta, step, 5_000_000 if max_iter is None else max_iter, tol, init), theta)


def maxent_transport(q, cost, radius=None, **kwargs) -> Float[Array, " M"]:
    """`p` of `maxent_transport_solve` (same arguments)."""
    return maxent_transport_solve(q, cost, radius, **kwargs).p


def _check_support(name, x, n=None):
    x = as_float_array(name, x, (2,))
    if n is not None and x.shape[0] != n:
        raise ValueError(f"{name} must have shape ({n}, d) (one row per weight), got {x.shape}")
    return x


def maxent_wasserstein_solve(
    q: Float[ArrayLike, " N"],
    support_q: Float[ArrayLike, "N d"],
    support_p: Float[ArrayLike, "M d"],
    radius: Float[ArrayLike, ""] = None,
    **kwargs,
) -> MaxEntResult:
    """Theorem 5 with the paper's cost `c_ij = ‖x_i − y_j‖₂` between `support_q[i]` and
    `support_p[j]`; keyword arguments as in `maxent_transport_solve`."""
    q = _check_prob("q", q)
    xq = _check_support("support_q", support_q, q.shape[0]).astype(q.dtype)
    xp = _check_support("support_p", support_p).astype(q.dtype)
    if xp.shape[1] != xq.shape[1]:
        raise ValueError(f"support_p must have {xq.shape[1]} columns like support_q, got shape {xp.shape}")
    return maxent_transport_solve(q, _pairwise_distance(xq, xp), radius, **kwargs)


def maxent_wasserstein(q, support_q, support_p, radius=None, **kwargs) -> Float[Array, " M"]:
    """`p_j = Σ_i P_ij` of `maxent_wasserstein_solve` (Theorem 5, eq. 28)."""
    return maxent_wasserstein_solve(q, support_q, support_p, radius, **kwargs).p


# ------------------------------------------------------------- Wasserstein, continuous


def _soft_min(v0, mu, c, eps):
    """`G = −ε LSE_i(−(v₀ c_i − μ_i)/ε)` (→ `min_i (v₀ c_i − μ_i)` as `ε → 0`) and the
    soft cell assignment `r_i = softmax_i(−(v₀ c_i − μ_i)/ε)`."""
    z = -(v0 * c - mu) / eps
    return -eps * logsumexp(z, axis=-1), jax.nn.softmax(z, axis=-1)


def _cell_min(v0, lam, c, eps):
    """`_soft_min(v₀, v₀λ, c, ε)` in the paper's `λ`, and for `ε = 0` the hard `min` of
    eq. (16) with the cells `C_i = argmin_i (c_i − λ_i)` of eq. (18) (one-hot `r`)."""
    pos = eps > 0
    g_soft, r_soft = _soft_min(v0, v0 * lam, c, jnp.where(pos, eps, jnp.ones_like(eps)))
    gap = c - lam
    r_hard = jax.nn.one_hot(jnp.argmin(gap, axis=-1), c.shape[-1], dtype=c.dtype)
    g_hard = v0 * jnp.min(gap, axis=-1)
    return jnp.where(pos, g_soft, g_hard), jnp.where(pos, r_soft, r_hard)


def _continuous_dual(z, c, logw, q, theta, eps):
    """Reduced dual (`v₁` eliminated) of the smoothed problem, in `z = (v₀, μ)`, plus the
    gauge term `½(Σμ)²` (the dual is invariant under `μ → μ + t`)."""
    v0, mu = z[0], z[1:]
    g, _ = _soft_min(v0, mu, c, eps)
    return v0 * theta - mu @ q + logsumexp(logw - g) + 0.5 * jnp.sum(mu) ** 2


def _continuous_dual_z(z, params):
    return _continuous_dual(z, *params)


class MaxEntContinuous(eqx.Module):
    """Theorem 3 solution on a bounded domain, discretized on points `y_k` with weights
    `w_k` (Monte Carlo: `w_k = vol/K`).

    - `v0`, `v1`, `mu` (`μ_i = v₀ λ_i`; `lam` gives the paper's `λ_i = μ_i / v₀`),
      `temperature` (`ε`): `p(x) = exp(−G(x) − v₁ − 1)` with
      `G(x) = −ε LSE_i(−(v₀‖x − x_i‖ − μ_i)/ε)`, i.e. eq. (16) with the `min` smoothed
      (`ε = 0`, PGD only: the hard `min`).
    - `mass[k] = w_k p(y_k)` (sums to 1), `assignment[k, i]` = share of `y_k` transported
      to `x_i` (soft cell membership; rows sum to 1).
    - `constraint` = transport cost `Σ_k mass_k Σ_i assignment_ki ‖y_k − x_i‖`; `cell_mass`
      = `Σ_k mass_k assignment_ki` (= `q` at the solution, eq. 21).
    - `iterations`, `converged`: Newton steps and `‖∇dual‖_∞ ≤ tol` (`method="exact"`), or
      PGD passes and "the projected gradient (19)–(21) is below `tol`" (`method="pgd"`);
      `False` for a traced `theta` that is not a finite number `≥ 0`.
    """

    support: Float[Array, "N d"]
    q: Float[Array, " N"]
    v0: Float[Array, ""]
    v1: Float[Array, ""]
    mu: Float[Array, " N"]
    temperature: Float[Array, ""]
    points: Float[Array, "K d"]
    weights: Float[Array, " K"]
    mass: Float[Array, " K"]
    assignment: Float[Array, "K N"]
    constraint: Float[Array, ""]
    cell_mass: Float[Array, " N"]
    iterations: Int[Array, ""]
    converged: Bool[Array, ""]

    @property
    def lam(self) -> Float[Array, " N"]:
        """The paper's `λ_i = μ_i / v₀` (`0` when `v₀ = 0`)."""
        pos = self.v0 > 0
        return jnp.where(pos, self.mu / jnp.where(pos, self.v0, 1.0), 0.0)

    def _g(self, x):
        x = jnp.asarray(x, self.points.dtype)
        d2 = jnp.sum((x[..., None, :] - self.support) ** 2, axis=-1)
        pos = d2 > 0  # zero (sub)gradient at the atoms, as in `_pairwise_distance`
        c = jnp.where(pos, jnp.sqrt(jnp.where(pos, d2, 1.0)), 0.0)
        eps = self.temperature
        soft = eps > 0
        g_soft, _ = _soft_min(self.v0, self.mu, c, jnp.where(soft, eps, jnp.ones_like(eps)))
        return c, jnp.where(soft, g_soft, jnp.min(self.v0 * c - self.mu, axis=-1))

    def log_density(self, x: Float[ArrayLike, "... d"]) -> Float[Array, "..."]:
        """`ln p(x)` (eq. 16 with the smoothed min); `x` anywhere in the domain."""
        _, g = self._g(x)
        return -g - self.v1 - 1.0

    def cell(self, x: Float[ArrayLike, "... d"]) -> Int[Array, "..."]:
        """Index `i` of the cell `C_i` (eq. 18: argmin of `‖x − x_i‖ − λ_i`) containing `x`."""
        c, _ = self._g(x)
        return jnp.argmin(self.v0 * c - self.mu, axis=-1)

    def sample(self, key: PRNGKeyArray, num: int) -> tuple[Float[Array, "num d"], Int[Array, " num"]]:
        """Method 2: draw a cell `j ~ q`, then a point of `C_j` from `p` restricted to it.

        The second draw resamples the discretization points `y_k` with probabilities
        `mass_k · assignment_kj / q_j` (importance resampling of uniform Monte Carlo points
        with weights `∝ p`; inverse CDF per cell). Returns the points and their cells `j`;
        all samples carry weight `1/num`."""
        k_cell, k_point = jax.random.split(key)
        cells = jax.random.categorical(k_cell, jnp.log(self.q), shape=(num,))
        joint = self.mass[:, None] * self.assignment  # K × N
        cdf = jnp.cumsum(joint, axis=0).T  # N × K
        cdf = cdf / cdf[:, -1:]
        u = jax.random.uniform(k_point, (num,), dtype=self.points.dtype)
        idx = jax.vmap(lambda j, u_: jnp.searchsorted(cdf[j], u_))(cells, u)
        idx = jnp.minimum(idx, self.points.shape[0] - 1)
        return self.points[idx], cells


def _continuous_exact(c, logw, q, theta, eps, max_iter, tol):
    """Projected Newton with backtracking on `_continuous_dual` (under `stop_gradient`),
    then the implicit function theorem at the minimizer (`_implicit` on the gradient)."""
    dtype = q.dtype
    n = q.shape[0]
    params = (c, logw, q, theta, eps)
    params_ng = lax.stop_gradient(params)
    dual = partial(_continuous_dual_z, params=params_ng)
    grad_f, hess_f = jax.grad(dual), jax.hessian(dual)
    steps = 0.5 ** jnp.arange(30, dtype=dtype)

    def newton_dir(z):
        g, h = grad_f(z), hess_f(z)
        fixed = (z[0] <= 0) & (g[0] > 0)  # v₀ = 0 with the bound active: drop it
        keep = jnp.ones_like(z).at[0].set(jnp.where(fixed, 0.0, 1.0))
        h = h * keep[:, None] * keep[None, :] + jnp.diag(1.0 - keep)
        g_red = g * keep
        return g_red, -jnp.linalg.solve(h, g_red)

    def cond(carry):
        _, g_red, k = carry
        return (k < max_iter) & (jnp.max(jnp.abs(g_red)) > tol)

    def body(carry):
        z, _, k = carry
        g_red, dz = newton_dir(z)
        f0 = dual(z)

        def trial(t):
            zt = z + t * dz
            return zt.at[0].set(jnp.maximum(zt[0], 0.0))

        cand = jax.vmap(trial)(steps)
        vals = jax.vmap(dual)(cand)
        ok = vals <= f0 + 1e-4 * jnp.sum(g_red * (cand - z), axis=1)
        idx = jnp.argmax(ok)
        z_new = jnp.where(jnp.any(ok), cand[idx], z)
        g_new, _ = newton_dir(z_new)
        return z_new, g_new, k + 1

    z0 = jnp.concatenate([jnp.ones((1,), dtype), jnp.zeros((n,), dtype)])
    g0, _ = newton_dir(z0)
    z, g_red, k = lax.while_loop(cond, body, (z0, g0, jnp.asarray(0)))
    # v₀ > 0: full IFT system; v₀ = 0 (budget slack): v₀ stays 0, IFT in μ only.
    keep = jnp.ones((n + 1,), bool).at[0].set(z[0] > 0)
    z = _implicit(jax.grad(_continuous_dual_z), z, keep, params)
    v0, mu = z[0], z[1:]
    g, r = _soft_min(v0, mu, c, eps)
    log_norm = logsumexp(logw - g)
    return v0, log_norm - 1.0, mu, jnp.exp(logw - g - log_norm), r, k, jnp.max(jnp.abs(g_red)) <= tol


def _continuous_pgd(c, logw, q, theta, eps, step, max_iter, tol, init):
    """The reference `main.m` of Fig. 7 / Table IV (Algorithm 1 with eqs. 19–21): from
    `(v₀, v₁, λ) = (init[0], init[1], 0)`, plain projected gradient steps of size `step` on
    the dual (17) in the paper's variables; stop when the projected gradient (19)–(21) is
    below `tol` (max-norm) at the current iterate, or after `max_iter` steps. (`main.m`
    tests `|∫p − 1| = |(20)|` alone; on Table IV that fires after 64 steps with the
    transport cost 8× over budget.) `ε = eps > 0` smooths the `min` as in the exact
    solver; `ε = 0` is the paper's hard `min` / hard cells."""
    dtype = q.dtype
    w = jnp.exp(logw)

    def stats(v0, v1, lam):
        g, r = _cell_min(v0, lam, c, eps)
        p = w * jnp.exp(-g - v1 - 1.0)  # w_k p(y_k), unnormalized
        gap = jnp.sum(r * (c - lam), axis=1)  # ∂G/∂v₀ = g(x, λ) of (19)
        return jnp.sum(p), p @ gap, p @ r

    def grads(v0, lam, s):
        p_int, gp_int, part_int = s
        return theta - lam @ q - gp_int, 1.0 - p_int, v0 * (part_int - q)  # (19), (20), (21)

    def residual(v0, lam, s):
        g0, g1, glam = grads(v0, lam, s)
        g0 = jnp.where(v0 > 0, g0, jnp.minimum(g0, 0.0))  # projected gradient at the bound
        return jnp.maximum(jnp.maximum(jnp.abs(g0), jnp.abs(g1)), jnp.max(jnp.abs(glam)))

    def cond(carry):
        v0, _, lam, s, k = carry
        return (k < max_iter) & (residual(v0, lam, s) >= tol)

    def body(carry):
        v0, v1, lam, s, k = carry
        g0, g1, glam = grads(v0, lam, s)
        v0, v1, lam = jnp.maximum(v0 - step * g0, 0.0), v1 - step * g1, lam - step * glam
        return v0, v1, lam, stats(v0, v1, lam), k + 1

    v0, v1 = jnp.asarray(init[0], dtype), jnp.asarray(init[1], dtype)
    lam = jnp.zeros_like(q)
    v0, v1, lam, s, k = lax.while_loop(cond, body, (v0, v1, lam, stats(v0, v1, lam), jnp.asarray(0)))
    converged = residual(v0, lam, s) < tol
    # Algorithm 1's normalization step: p ← p/∫p, i.e. v₁ ← v₁ + ln ∫p.
    g, r = _cell_min(v0, lam, c, eps)
    log_norm = logsumexp(logw - g)
    return v0, log_norm - 1.0, v0 * lam, jnp.exp(logw - g - log_norm), r, k, converged


def maxent_wasserstein_continuous(
    q: Float[ArrayLike, " N"],
    support_q: Float[ArrayLike, "N d"],
    radius: Float[ArrayLike, ""] = None,
    *,
    theta: Float[ArrayLike, ""] | None = None,
    key: PRNGKeyArray | None = None,
    num_points: int = 2000,
    bounds: tuple[float, float] | Float[ArrayLike, "d 2"] = (0.0, 1.0),
    points: Float[ArrayLike, "K d"] | None = None,
    weights: Float[ArrayLike, " K"] | None = None,
    temperature: float = 0.05,
    method: str = "exact",
    step: float = 0.05,
    max_iter: int | None = None,
    tol: float | None = None,
    init: tuple[float, float] = (2.0, 0.0),
) -> MaxEntContinuous:
    """Theorem 3: the max-entropy density within Wasserstein-1 distance `θ = radius` of the
    discrete `q` on `support_q`, over a box domain (`theta=`: deprecated alias).

    The domain integral is discretized on `points` (with quadrature `weights`; default
    `vol/K`), or on `num_points` uniform Monte Carlo points in `bounds` (a `(lo, hi)` pair
    for every axis, or one row per axis) drawn with `key` — the paper uses 2000 points on
    `[0, 1]²`. On a finite point set the cell masses of eq. (21) are step functions of `λ`,
    so the dual (17) is not smooth and its minimizer not unique; we therefore smooth the
    `min` in (16) with temperature `ε = temperature > 0` (in nats of `v₀ c`): this is the
    exact solution of `max H(p) + ε H(cell | x)` s.t. transport cost `≤ θ`, cell masses
    `= q`, `∫p = 1` on the discretization (converges to Theorem 3 as `ε → 0`).

    `method="exact"`: projected Newton with backtracking on the reduced convex dual in
    `(v₀, μ = v₀λ)` (`v₁` eliminated in closed form, so `∫p = 1` exactly; at most
    `max_iter`, default 200, steps; stop when the gradient is below `tol`, default 1e-10
    (float64) / 1e-5 (float32)). Differentiable (`jax.grad`/`jax.jvp`) in `radius`, `q`,
    `support_q`, `points`, `weights` and `temperature` by the implicit function theorem on
    the dual's stationarity (the Newton loop runs under `stop_gradient`); when the budget is
    slack (`θ` at least the cost of the unconstrained solution) `v₀ = 0` and its derivative
    is 0 (reduced system in `μ`).

    `method="pgd"`: the paper's projected gradient descent (Algorithm 1 with gradients
    (19)–(21), as in the authors' `main.m` for Fig. 7): variables `(v₀, v₁, λ)` from
    `(init[0], init[1], 0)`, step `step` (α), stop when the projected gradient (19)–(21)
    is below `tol` (max-norm; default 1e-3, the code's `numerical_eps`, which the code
    applies to (20) alone) or after `max_iter` (S, default 500) steps; `p` is then
    renormalized (`v1` is reported after normalization). It uses the same smoothed `min`,
    or with `temperature=0` the paper's hard `min` and hard cells verbatim. Its output is an
    early-stopped iterate in general (`converged`: the gradient test passed). The fixed
    step is stable only while `step · v₀²/ε` is moderate (on Table IV, α = 0.05 oscillates
    and 500 steps end with the transport cost ≈ 7× θ). Derivatives flow through the unrolled iterations in forward mode
    (`jax.jvp`/`jacfwd` give the derivative of the returned iterate); reverse mode is not
    available (`lax.while_loop`); there is no implicit differentiation.
    """
    _check_method(method)
    q = _check_prob("q", q)
    dtype = q.dtype
    xq = _check_support("support_q", support_q, q.shape[0]).astype(dtype)
    d = xq.shape[1]
    theta = check_scalar("radius", renamed("theta", theta, "radius", radius, "maxent_wasserstein_continuous", stacklevel=3)).astype(dtype)
    if is_concrete(temperature):
        t = float(np.asarray(temperature))
        if not np.isfinite(t) or t < 0 or (t == 0 and method == "exact"):
            raise ValueError(
                f"temperature must be a finite number > 0 (>= 0 with method='pgd'), got {t:g}"
            )
    if method == "pgd" and is_concrete(step):
        s = float(np.asarray(step))
        if not np.isfinite(s) or s <= 0:
            raise ValueError(f"step must be a finite number > 0, got {s:g}")
    if max_iter is not None and is_concrete(max_iter):
        m = np.asarray(max_iter)
        if m.ndim != 0 or not np.issubdtype(m.dtype, np.integer) or m < 0:
            raise ValueError(f"max_iter must be a nonnegative int, got {max_iter!r}")
    if points is None:
        if key is None:
            raise ValueError("pass either points (K, d) or a PRNG key to draw Monte Carlo points")
        b = jnp.asarray(bounds, dtype)
        b = jnp.broadcast_to(b, (d, 2))
        u = jax.random.uniform(key, (num_points, d), dtype=dtype)
        pts = b[:, 0] + u * (b[:, 1] - b[:, 0])
        vol = jnp.prod(b[:, 1] - b[:, 0])
        w = jnp.full((num_points,), vol / num_points, dtype)
    else:
        pts = _check_support("points", points).astype(dtype)
        if pts.shape[1] != d:
            raise ValueError(f"points must have {d} columns like support_q, got shape {pts.shape}")
        if weights is None:
            raise ValueError("pass quadrature weights (K,) together with points (w_k = volume / K for Monte Carlo)")
        w = as_float_array("weights", weights, (1,)).astype(dtype)
        if w.shape[0] != pts.shape[0]:
            raise ValueError(f"weights must have shape ({pts.shape[0]},), got {w.shape}")
    eps_t = jnp.asarray(temperature, dtype)
    c = _pairwise_distance(pts, xq)  # K × N
    logw = jnp.log(w)
    if method == "exact":
        tol = (1e-10 if dtype == jnp.float64 else 1e-5) if tol is None else tol
        out = _continuous_exact(c, logw, q, theta, eps_t, 200 if max_iter is None else max_iter, tol)
    else:
        tol = 1e-3 if tol is None else tol
        out = _continuous_pgd(c, logw, q, theta, eps_t, step, 500 if max_iter is None else max_iter, tol, init)
    v0, v1, mu, mass, r, k, converged = out
    return MaxEntContinuous(
        support=xq,
        q=q,
        v0=v0,
        v1=v1,
        mu=mu,
        temperature=eps_t,
        points=pts,
        weights=w,
        mass=mass,
        assignment=r,
        constraint=jnp.sum(mass[:, None] * r * c),
        cell_mass=mass @ r,
        iterations=k,
        converged=converged & in_range(theta, 0.0),
    )
