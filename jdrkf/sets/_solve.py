"""Worst-case (least-favourable) covariances of DR-MMSE problems: Frank–Wolfe with
backtracking, a Newton polish on the optimality system, implicit derivatives."""

from __future__ import annotations

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
from jax import lax
from jax.flatten_util import ravel_pytree
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from .. import linalg
from .._validation import as_float_array, check_covariance
from ._base import AbstractAmbiguitySet, radius
from ._moment import Moment
from ._wasserstein import Wasserstein

class WorstCase(eqx.Module):
    """Solution of the decoupled problem (Wang & Ye 2022, eqs. 32–35 and 36–37).

    - `state_cov`, `noise_cov`: the worst-case prior `Σx*` and noise `Σv*` covariances.
    - `value`: `Tr(Σx* − i_min Σx*Hᵀ(HΣx*Hᵀ + Σv*)⁻¹HΣx*)`, the trace of the worst-case
      posterior covariance (eq. 41).
    - `iterations`: Frank–Wolfe iterations; `gap`: the Frank–Wolfe duality gap where it
      stopped (an upper bound on the optimal value minus the value there; the Newton
      polish that follows only moves closer to the optimum); `converged`: `gap ≤ rtol · value`.
    """

    state_cov: Float[Array, "n n"]
    noise_cov: Float[Array, "m m"]
    value: Float[Array, ""]
    iterations: Int[Array, ""]
    gap: Float[Array, ""]
    converged: Bool[Array, ""]


class JointWorstCase(eqx.Module):
    """Solution of the joint problem (Theorem 8; the Wasserstein KF of
    Shafieezadeh-Abadeh et al. 2018): `cov` is the worst-case covariance of `(x, y)`,
    `value` the trace of its Schur complement `S_xx − S_xy S_yy⁻¹ S_yx`; other fields as
    in `WorstCase`."""

    cov: Float[Array, "d d"]
    value: Float[Array, ""]
    iterations: Int[Array, ""]
    gap: Float[Array, ""]
    converged: Bool[Array, ""]


def _decoupled_objective(h, i_min):
    """`f(Σx, Σv) = Tr Σx − i Tr(K H Σx)`, `K = ΣxHᵀ(HΣxHᵀ + Σv)⁻¹`, and its gradient
    `((1 − i)I + i(I − KH)ᵀ(I − KH), i KᵀK)` (algorithms.md §A.0, scaled by `i_min`)."""

    def fg(blocks):
        sx, sv = blocks
        s = linalg.symmetrize(h @ sx @ h.T + sv)
        k = linalg.psd_solve(s, h @ sx).T
        eye = jnp.eye(sx.shape[-1], dtype=sx.dtype)
        a = eye - k @ h
        value = jnp.trace(sx) - i_min * jnp.trace(k @ h @ sx)
        dx = (1.0 - i_min) * eye + i_min * (a.T @ a)
        dv = i_min * (k.T @ k)
        return value, (linalg.symmetrize(dx), linalg.symmetrize(dv))

    return fg


def _joint_objective(n):
    """`f(S) = Tr(S/S_yy)` and its gradient `[I, −K]ᵀ[I, −K]`, `K = S_xy S_yy⁻¹` (§0)."""

    def fg(blocks):
        (s,) = blocks
        sxx, sxy, syy = s[:n, :n], s[:n, n:], s[n:, n:]
        k = linalg.psd_solve(syy, sxy.T).T
        value = jnp.trace(sxx) - jnp.trace(k @ sxy.T)
        e = jnp.concatenate([jnp.eye(n, dtype=s.dtype), -k], axis=1)
        return value, (linalg.symmetrize(e.T @ e),)

    return fg


def _frank_wolfe(fg, sets, nominals, rtol, max_iter):
    """Frank–Wolfe with backtracking step sizes (algorithms.md §A.2), from the nominals.

    Returns the last iterate, the iteration count, the oracles' multipliers at that
    iterate and its duality gap (each oracle is traced once, inside the loop).
    """
    dtype = nominals[0].dtype

    def cond(c):
        return (~c[3]) & (c[1] < max_iter)

    def body(c):
        s, k, beta, _, _, _ = c
        value, grads = fg(s)
        lmos, mults = zip(*(st.oracle(g, nom) for st, g, nom in zip(sets, grads, nominals, strict=True)), strict=True)
        p = tuple(lm - si for lm, si in zip(lmos, s, strict=True))
        gap = sum(jnp.vdot(pi, gi) for pi, gi in zip(p, grads, strict=True))
        pn = sum(jnp.vdot(pi, pi) for pi in p)
        done = (gap <= rtol * jnp.abs(value)) | (pn == 0)
        beta = 0.5 * beta
        pn_safe = jnp.where(pn > 0, pn, 1.0)

        def bt_cond(b):
            _, ok, j = b
            return (~ok) & (j < 60)

        def bt_body(b):
            beta, _, j = b
            eta = jnp.minimum(gap / (beta * pn_safe), 1.0)
            trial = tuple(si + eta * pi for si, pi in zip(s, p, strict=True))
            ok = fg(trial)[0] >= value + eta * gap - 0.5 * eta * eta * beta * pn
            return jnp.where(ok, beta, 2.0 * beta), ok, j + 1

        beta, _, _ = lax.while_loop(bt_cond, bt_body, (beta, done, 0))
        eta = jnp.where(done, 0.0, jnp.minimum(gap / (beta * pn_safe), 1.0))
        s = tuple(linalg.symmetrize(si + eta * pi) for si, pi in zip(s, p, strict=True))
        return s, k + jnp.where(done, 0, 1), beta, done, tuple(mults), jnp.maximum(gap, 0.0)

    beta0 = jnp.ones((), dtype) / sum(jnp.trace(nom) for nom in nominals)
    zero = jnp.zeros((), dtype)
    init = (tuple(nominals), jnp.zeros((), int), beta0, jnp.zeros((), bool), tuple(zero for _ in nominals), zero)
    s, k, _, _, mults, gap = lax.while_loop(cond, body, init)
    return s, k, mults, gap


def _dense_solve(g, y):
    flat_y, unravel = ravel_pytree(y)
    jac = jax.jacfwd(lambda v: ravel_pytree(g(unravel(v)))[0])(jnp.zeros_like(flat_y))
    return unravel(jnp.linalg.solve(jac, flat_y))


def _solve(make_fg: Callable, params, sets: tuple, nominals: tuple, rtol, max_iter):
    """Worst-case blocks of `max f` over the product of `sets`, with implicit derivatives.

    The optimum is the fixed point `Σ = LMO(∇f(Σ))` of each block (algorithms.md §A.3),
    written as the smooth system `set.residual(Σ, multiplier, ∇f(Σ), nominal) = 0`.
    Forward: Frank–Wolfe to a relative gap `rtol`, then a Newton step on that system
    (quadratic convergence, so derivatives see a tight solution). Derivatives: the
    implicit function theorem on the same system (`lax.custom_root`).
    """

    def residual_of(fg, sets_, nominals_):
        def residual(x):
            s, mult = x
            _, grads = fg(s)
            out = [st.residual(si, mi, g, nom) for st, si, mi, g, nom in zip(sets_, s, mult, grads, nominals_, strict=True)]
            return tuple(o[0] for o in out), tuple(o[1] for o in out)

        return residual

    def solve(_, guess):
        del guess
        p_, sets_, noms_ = jax.tree.map(lax.stop_gradient, (params, sets, nominals))
        fg = make_fg(*p_)
        s, iters, mult, gap = _frank_wolfe(fg, sets_, noms_, rtol, max_iter)
        res_fn = residual_of(fg, sets_, noms_)
        x = (s, mult)

        def newton(x):
            r = res_fn(x)
            dx = _dense_solve(lambda v: jax.jvp(res_fn, (x,), (v,))[1], r)
            x_new = jax.tree.map(lambda a, b: a - b, x, dx)
            better = ravel_pytree(res_fn(x_new))[0]
            better = jnp.all(jnp.isfinite(better)) & (jnp.linalg.norm(better) < jnp.linalg.norm(ravel_pytree(r)[0]))
            return jax.tree.map(lambda a, b: jnp.where(better, a, b), x_new, x)

        s, mult = newton(x)  # from a gap of rtol = eps^(2/3), one step reaches round-off
        # Zero-radius blocks are returned exactly (the polish may leave round-off there).
        s = tuple(jnp.where(st.is_nominal(), nom, linalg.symmetrize(si)) for st, si, nom in zip(sets_, s, noms_, strict=True))
        value, _ = fg(s)
        converged = gap <= rtol * jnp.maximum(jnp.abs(value), jnp.finfo(value.dtype).tiny)
        # custom_root needs float auxiliary outputs (integer tangents are rejected).
        return (s, mult), (iters.astype(gap.dtype), gap, converged.astype(gap.dtype))

    guess = (tuple(nominals), tuple(jnp.zeros((), nominals[0].dtype) for _ in nominals))
    (s, _), (iters, gap, converged) = lax.custom_root(
        residual_of(make_fg(*params), sets, nominals), guess, solve, _dense_solve, has_aux=True
    )
    value, _ = make_fg(*params)(s)
    return s, value, iters.astype(int), gap, converged > 0


def default_rtol(dtype) -> float:
    """Default relative duality-gap tolerance of Frank–Wolfe: `eps^(2/3)` (≈4e-11 in
    float64, 2e-5 in float32); the Newton polish then reaches machine precision."""
    return float(jnp.finfo(dtype).eps) ** (2.0 / 3.0)


def _as_set(name: str, s) -> AbstractAmbiguitySet:
    if s is None:
        return Moment(1.0)
    if not isinstance(s, AbstractAmbiguitySet):
        raise ValueError(f"{name} must be a jdrkf.sets ambiguity set (Wasserstein, KL, Moment) or None, got {type(s).__name__}")
    return s


def worst_case(
    state_set: AbstractAmbiguitySet | None,
    noise_set: AbstractAmbiguitySet | None,
    prior_cov: Float[ArrayLike, "n n"],
    H: Float[ArrayLike, "m n"],
    noise_cov: Float[ArrayLike, "m m"],
    *,
    i_min: Float[ArrayLike, ""] = 1.0,
    rtol: float | None = None,
    max_iter: int = 500,
) -> WorstCase:
    """Least-favourable prior and noise covariances of the decoupled DR-MMSE problem

    `max Tr(Σx − i_min ΣxHᵀ(HΣxHᵀ + Σv)⁻¹HΣx)` over `Σx ∈ state_set(prior_cov)`,
    `Σv ∈ noise_set(noise_cov)` (Wang & Ye 2022, eq. 32 with eq. 33, 37 or the KL balls
    18/21; `None` = the nominal only). Moment sets are closed form (Theorem 5); otherwise
    Frank–Wolfe with backtracking on the product of the sets, with the linear oracle of
    each set in closed form (algorithms.md §A.1–A.2, §B.3), polished by a Newton step on
    the optimality system, which also gives the derivatives (implicit function theorem)
    with respect to radii, `prior_cov`, `H`, `noise_cov` and `i_min`.
    """
    state_set, noise_set = _as_set("state_set", state_set), _as_set("noise_set", noise_set)
    prior_cov = as_float_array("prior_cov", prior_cov, (2,))
    H = as_float_array("H", H, (2,))
    noise_cov = as_float_array("noise_cov", noise_cov, (2,))
    check_covariance("prior_cov", prior_cov)
    check_covariance("noise_cov", noise_cov)
    n, m = prior_cov.shape[0], noise_cov.shape[0]
    if H.shape != (m, n):
        raise ValueError(f"H has shape {tuple(H.shape)} but expected ({m}, {n}) (noise_cov is {m}×{m}, prior_cov {n}×{n})")
    dtype = jnp.result_type(prior_cov, H, noise_cov)
    prior_cov, H, noise_cov = prior_cov.astype(dtype), H.astype(dtype), noise_cov.astype(dtype)
    i_min = as_float_array("i_min", i_min, (0,)).astype(dtype)
    rtol = default_rtol(dtype) if rtol is None else float(rtol)
    return _worst_case(state_set, noise_set, prior_cov, H, noise_cov, i_min, rtol, int(max_iter))


# Compiled once per set types, shapes and static options, so that eager calls (outside a
# user's jit) do not re-trace the solver's loops each time.
@eqx.filter_jit
def _worst_case(state_set, noise_set, prior_cov, H, noise_cov, i_min, rtol, max_iter):
    sets, noms = (state_set, noise_set), (prior_cov, noise_cov)
    if all(isinstance(st, Moment) for st in sets):
        s = tuple(st.worst_case(nom) for st, nom in zip(sets, noms, strict=True))
        value, _ = _decoupled_objective(H, i_min)(s)
        zero = jnp.zeros((), prior_cov.dtype)
        return WorstCase(s[0], s[1], value, jnp.zeros((), int), zero, jnp.ones((), bool))
    s, value, iters, gap, conv = _solve(_decoupled_objective, (H, i_min), sets, noms, rtol, max_iter)
    return WorstCase(s[0], s[1], value, iters, gap, conv)


def worst_case_joint(
    joint_set: AbstractAmbiguitySet,
    cov: Float[ArrayLike, "d d"],
    n: int,
    *,
    rtol: float | None = None,
    max_iter: int = 500,
) -> JointWorstCase:
    """Least-favourable covariance of `(x, y)` (first `n` coordinates `x`) for the joint
    problem `max Tr(S_xx − S_xy S_yy⁻¹ S_yx)` over `S ∈ joint_set(cov)` (Theorem 8).

    Same method and derivatives as `worst_case`; `Moment` is closed form (`θ₂ cov`).
    """
    joint_set = _as_set("joint_set", joint_set)
    cov = as_float_array("cov", cov, (2,))
    check_covariance("cov", cov)
    d = cov.shape[0]
    if not isinstance(n, int) or not 1 <= n < d:
        raise ValueError(f"n must be an int with 1 <= n < {d} (the state dimension within cov), got {n!r}")
    rtol = default_rtol(cov.dtype) if rtol is None else float(rtol)
    return _worst_case_joint(joint_set, cov, n, rtol, int(max_iter))


@eqx.filter_jit
def _worst_case_joint(joint_set, cov, n, rtol, max_iter):
    if isinstance(joint_set, Moment):
        s = joint_set.worst_case(cov)
        value, _ = _joint_objective(n)((s,))
        return JointWorstCase(s, value, jnp.zeros((), int), jnp.zeros((), cov.dtype), jnp.ones((), bool))
    s, value, iters, gap, conv = _solve(lambda: _joint_objective(n), (), (joint_set,), (cov,), rtol, max_iter)
    return JointWorstCase(s[0], value, iters, gap, conv)


def wasserstein_mmse(
    prior_cov: Float[ArrayLike, "n n"],
    H: Float[ArrayLike, "m n"],
    noise_cov: Float[ArrayLike, "m m"],
    theta_x: Float[ArrayLike, ""],
    theta_v: Float[ArrayLike, ""],
    *,
    i_min: Float[ArrayLike, ""] = 1.0,
    rtol: float | None = None,
    max_iter: int = 500,
) -> WorstCase:
    """Decoupled Wasserstein DR-MMSE problem (Wang & Ye 2022, eqs. 32–35; Jang et al.
    2025, eq. 5): separate `W₂` balls of radii `theta_x` around `prior_cov` and
    `theta_v` around `noise_cov`. See `worst_case`."""
    sets = Wasserstein(radius("theta_x", theta_x)), Wasserstein(radius("theta_v", theta_v))
    return worst_case(*sets, prior_cov, H, noise_cov, i_min=i_min, rtol=rtol, max_iter=max_iter)


def wasserstein_mmse_joint(
    cov: Float[ArrayLike, "d d"], n: int, rho: Float[ArrayLike, ""], *, rtol: float | None = None, max_iter: int = 500
) -> JointWorstCase:
    """Joint Wasserstein DR-MMSE problem: one `W₂` ball of radius `rho` around the
    covariance `cov` of `(x, y)` (Shafieezadeh-Abadeh et al. 2018; Theorem 8 of
    Wang & Ye 2022). See `worst_case_joint`."""
    return worst_case_joint(Wasserstein(radius("rho", rho)), cov, n, rtol=rtol, max_iter=max_iter)
