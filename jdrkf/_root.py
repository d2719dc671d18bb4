"""Root finding shared by every solver of the package.

- `newton`: damped Newton on a smooth system `F(x) = 0` (a pytree `x`, dense Jacobian),
  with backtracking on `‖F‖` or on an objective whose stationary points are the roots,
  and a domain predicate that rejects infeasible trial points.
- `chord`: simplified Newton steps with one factorized Jacobian, for a start already
  close to the root.
- `bracketed_newton`: safeguarded Newton (bisection fallback) on an increasing scalar
  equation with a sign-changing bracket.
- `implicit_root`: derivatives of a root by the implicit function theorem
  (`lax.custom_root` with `dense_solve`): `dx = −(∂F/∂x)⁻¹ (∂F/∂p) dp` for every
  parameter `p` that `F` closes over. The iterations are never differentiated, so
  `grad`, `jvp`, `vmap` and higher derivatives see only the root.
- `default_rtol`: the default relative tolerance of the solvers for a dtype.

All loops are `lax.while_loop`s capped by `max_iter`, so they run under `jit` and `vmap`
(under `vmap` every member iterates until the slowest one stops).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
from jax import lax
from jax.flatten_util import ravel_pytree
from jaxtyping import Array, Bool, Float, Int

# Armijo's sufficient-decrease constant of the line searches.
_ARMIJO = 1e-4


def default_rtol(dtype) -> float:
    """Default relative tolerance of the solvers: `eps^(2/3)` (≈4e-11 in float64, 2e-5 in
    float32); Newton and chord steps usually reach machine precision."""
    return float(jnp.finfo(dtype).eps) ** (2.0 / 3.0)


def dense_solve(g: Callable, y: Any) -> Any:
    """Solve the linear system `g(x) = y` (`g` linear, pytrees `x`, `y` of one structure)
    by forming its dense matrix with `jax.jacfwd` and an LU solve. This is the
    `tangent_solve` of `lax.custom_root` for the small systems of this package."""
    flat_y, unravel = ravel_pytree(y)
    jac = jax.jacfwd(lambda v: ravel_pytree(g(unravel(v)))[0])(jnp.zeros_like(flat_y))
    return unravel(jnp.linalg.solve(jac, flat_y))


def implicit_root(residual: Callable, solve: Callable, guess: Any):
    """The root `x*` of `residual(x) = 0` computed by `solve(guess) -> (x*, aux)`, with the
    derivatives of the implicit function theorem: for every parameter `p` that
    `residual` closes over, `dx* = −(∂F/∂x)⁻¹ (∂F/∂p) dp` at `x*` (dense solve,
    `dense_solve`). `solve` is never differentiated; `aux` (iteration counts, flags,
    residual norms) is returned as computed, with zero derivatives. Returns `(x*, aux)`."""
    float_dtype = jnp.result_type(*jax.tree.leaves(guess))
    dtypes = []

    def solve_(_, g):
        x, aux = solve(g)
        leaves, treedef = jax.tree.flatten(aux)
        dtypes.append((treedef, [leaf.dtype for leaf in leaves]))
        # `lax.custom_root` differentiates its auxiliary outputs: integer ones are rejected.
        return x, [jnp.asarray(leaf).astype(float_dtype) for leaf in leaves]

    x, aux = lax.custom_root(residual, guess, solve_, dense_solve, has_aux=True)
    treedef, leaf_dtypes = dtypes[0]
    aux = [lax.stop_gradient(a).astype(d) for a, d in zip(aux, leaf_dtypes, strict=True)]
    return x, jax.tree.unflatten(treedef, aux)


class NewtonResult(NamedTuple):
    """`x`: the last accepted iterate; `iterations`: Newton steps taken; `residual`:
    `‖F(x)‖₂`; `stopped`: a stopping test was met (`‖F‖` at `ftol` or a small full step),
    as opposed to reaching `max_iter` or a line search that found no decrease."""

    x: Any
    iterations: Int[Array, ""]
    residual: Float[Array, ""]
    stopped: Bool[Array, ""]


def newton(
    residual: Callable,
    x0: Any,
    max_iter,
    *,
    in_domain: Callable | None = None,
    objective: Callable | None = None,
    gradient_scale: Any = None,
    ftol: float | None = None,
    xtol: float | None = None,
    max_backtracks: int = 40,
) -> NewtonResult:
    """Damped Newton's method for `F(x) = 0` (`residual`), `x` any pytree of arrays.

    Each step solves `J(x) p = −F(x)` with the dense Jacobian (`jax.jacfwd` of the
    flattened residual) and backtracks `α = 1, ½, ¼, …` (at most `max_backtracks`
    trials) on a merit function `φ`:

    - `objective=None`: `φ = ‖F‖₂`, accepting the first `φ(x + αp) < (1 − 10⁻⁴α) φ(x)`
      (or, after the last trial, any decrease); trial points where `F` is not finite or
      `in_domain(x)` is false are rejected;
    - otherwise `φ = objective`, a function with gradient `∇φ = gradient_scale ⊙ F`
      (`gradient_scale ≥ 0`, a pytree like `x`; default 1: `F` is the gradient) that is
      not finite outside the domain, e.g. a convex function whose minimizer is the root;
      the first Armijo point `φ(x + αp) ≤ φ(x) + 10⁻⁴α ⟨∇φ, p⟩ + 10 eps |φ(x)|` is
      accepted (the last term absorbs rounding at the optimum). If `p` is not a descent
      direction (or not finite), `p = −F(x)`.

    Every iterate stays in the domain when `x0` is in it. The loop stops when
    `‖F‖ ≤ ftol (1 + ‖x‖₂)` (norm merit only), after a full step (`α = 1`) with
    `‖p‖∞ ≤ xtol (1 + ‖x‖∞)` (if `xtol` is given; quadratic convergence then puts the
    error at round-off), when no trial point is accepted, or after `max_iter` steps.
    """
    if objective is not None and (ftol is not None or in_domain is not None):
        raise ValueError("with an objective, the domain is where it is finite and the stopping test is xtol")
    flat0, unravel = ravel_pytree(x0)
    dtype = flat0.dtype
    eps = jnp.finfo(dtype).eps
    scale = 1.0 if gradient_scale is None else ravel_pytree(gradient_scale)[0]

    def flat_res(v):
        return ravel_pytree(residual(unravel(v)))[0]

    def merit(v):
        if objective is not None:
            phi = objective(unravel(v))
            return jnp.where(jnp.isfinite(phi), phi, jnp.inf)
        r = flat_res(v)
        ok = jnp.all(jnp.isfinite(r))
        if in_domain is not None:
            ok = ok & in_domain(unravel(v))
        return jnp.where(ok, jnp.linalg.norm(r), jnp.inf)

    def small_residual(v, nr):
        return jnp.zeros((), bool) if ftol is None else nr <= ftol * (1.0 + jnp.linalg.norm(v))

    def cond(c):
        _, k, _, _, stop = c
        return (k < max_iter) & ~stop

    def body(c):
        v, k, phi, _, _ = c
        jac, r = jax.jacfwd(lambda u: (flat_res(u), flat_res(u)), has_aux=True)(v)
        p = -jnp.linalg.solve(jac, r)
        if objective is None:
            slope, fallback, slack = -phi, jnp.zeros((), bool), jnp.zeros((), dtype)
        else:
            grad = scale * r
            slope = jnp.vdot(grad, p)
            fallback = ~jnp.all(jnp.isfinite(p)) | (slope > 0)
            p = jnp.where(fallback, -r, p)
            slope = jnp.where(fallback, -jnp.vdot(grad, r), slope)
            slack = 10 * eps * jnp.abs(phi)

        def ls_cond(b):
            _, ok, j, _ = b
            return ~ok & (j < max_backtracks)

        def ls_body(b):
            alpha, _, j, _ = b
            alpha = jnp.where(j == 0, alpha, 0.5 * alpha)
            trial = merit(v + alpha * p)
            if objective is None:
                ok = trial < (1.0 - _ARMIJO * alpha) * phi
            else:
                ok = trial <= phi + _ARMIJO * alpha * slope + slack
            return alpha, ok, j + 1, trial

        init = (jnp.ones((), dtype), jnp.zeros((), bool), 0, phi)
        alpha, ok, _, trial = lax.while_loop(ls_cond, ls_body, init)
        if objective is None:
            ok = trial < phi
        v_new = jnp.where(ok, v + alpha * p, v)
        phi = jnp.where(ok, trial, phi)
        met = small_residual(v_new, phi) if objective is None else jnp.zeros((), bool)
        if xtol is not None:
            met = met | (ok & (alpha == 1) & ~fallback & (jnp.max(jnp.abs(p)) <= xtol * (1 + jnp.max(jnp.abs(v)))))
        return v_new, k + 1, phi, met, met | ~ok

    phi0 = merit(flat0)
    met0 = small_residual(flat0, phi0) if objective is None else jnp.zeros((), bool)
    v, k, phi, met, _ = lax.while_loop(cond, body, (flat0, jnp.zeros((), int), phi0, met0, met0))
    nr = phi if objective is None else jnp.linalg.norm(flat_res(v))
    return NewtonResult(unravel(v), k, nr, met)


def chord(residual: Callable, x0: Any, jacobian: Callable | None, max_steps: int, ftol: float = 0.0):
    """Chord (simplified Newton) iterations `x ← x − J(x₀)⁻¹ F(x)` with one dense Jacobian
    (`jacobian(x₀)`, or `jax.jacfwd` of the flattened residual when `None`), LU-factorized
    once. Near a regular root the contraction factor is about the start's error, so a
    few steps reach round-off. A step is taken only if it decreases `‖F‖`, and the loop
    stops once a step decreases it by less than half, once `‖F‖₂ ≤ ftol` (absolute;
    default 0: round-off), or after `max_steps`. Returns the last accepted iterate, its
    residual and the number of steps taken."""
    flat0, unravel = ravel_pytree(x0)

    def res(v):
        return ravel_pytree(residual(unravel(v)))[0]

    jac = jax.jacfwd(res)(flat0) if jacobian is None else jacobian(x0)
    lu = jax.scipy.linalg.lu_factor(jac)

    def cond(c):
        return c[3] & (c[2] < max_steps)

    def body(c):
        v, r, k, _ = c
        v_new = v - jax.scipy.linalg.lu_solve(lu, r)
        r_new = res(v_new)
        norm, norm_new = jnp.linalg.norm(r), jnp.linalg.norm(r_new)
        better = jnp.all(jnp.isfinite(r_new)) & (norm_new < norm)
        keep = lambda a, b: jnp.where(better, a, b)  # noqa: E731
        go_on = better & (norm_new < 0.5 * norm) & (norm_new > ftol)
        return keep(v_new, v), keep(r_new, r), k + better.astype(k.dtype), go_on

    v, r, k, _ = lax.while_loop(cond, body, (flat0, res(flat0), jnp.zeros((), int), jnp.ones((), bool)))
    return unravel(v), unravel(r), k


class ScalarRoot(NamedTuple):
    """`x`: the last iterate; `fx`: `f(x)`; `iterations`: steps taken; `stopped`: a
    stopping test was met (`f(x) = 0`, a step or a bracket below the tolerance) before
    `max_iter`."""

    x: Float[Array, ""]
    fx: Float[Array, ""]
    iterations: Int[Array, ""]
    stopped: Bool[Array, ""]


def bracketed_newton(f: Callable, x0, lo, hi, max_iter, *, x_scale: float = 0.0, has_slope: bool = False) -> ScalarRoot:
    """Safeguarded Newton on an increasing scalar `f` with `f(lo) ≤ 0 ≤ f(hi)`.

    Each step shrinks the bracket with the sign of `f(x)` (`lo = x` where `f(x) < 0`, else
    `hi = x`) and takes the Newton step `x − f(x)/f'(x)` if it lands in the bracket
    (steps leaving it by a few ulps are clipped into it, since `f` may be evaluated twice
    with different rounding), else bisects. A Newton step (above the step tolerance) back onto an end of the bracket
    that was already evaluated bisects too: at the noise floor of `f` Newton may
    alternate between two points whose distance exceeds the step tolerance, and under
    `vmap` one such member would keep every member iterating to `max_iter`. From a
    start where `f ≥ 0` and `f` convex (or `f ≤ 0` and `f` concave) the Newton steps are
    monotone and never bisect.
    With `has_slope`, `f(x)` returns `(f(x), f'(x))`; otherwise `f'` is `jax.jvp` of `f`. Stops when `f(x) = 0`, when a
    step or the bracket is below `4 eps max(|x|, x_scale)`, or after `max_iter` steps.
    """
    x0 = jnp.asarray(x0)
    eps = jnp.finfo(x0.dtype).eps
    lo, hi = jnp.full_like(x0, lo), jnp.full_like(x0, hi)
    lo0, hi0 = lo, hi

    def evaluate(x):
        return f(x) if has_slope else jax.jvp(f, (x,), (jnp.ones_like(x),))

    def tol(x):
        return 4 * eps * jnp.maximum(jnp.abs(x), x_scale)

    def cond(c):
        x, fx, _, lo, hi, step, k = c
        return (k < max_iter) & (fx != 0) & (jnp.abs(step) > tol(x)) & (hi - lo > tol(x))

    def body(c):
        x, fx, dfx, lo, hi, _, k = c
        below = fx < 0
        lo, hi = jnp.where(below, x, lo), jnp.where(below, hi, x)
        step = fx / dfx
        newton = x - step
        slack = 4 * tol(x)
        inside = jnp.isfinite(newton) & (newton >= lo - slack) & (newton <= hi + slack)
        trial = jnp.clip(newton, lo, hi)
        revisit = ((trial == lo) & (lo != lo0)) | ((trial == hi) & (hi != hi0))  # f known there: no progress
        # A step below the tolerance has converged (it may round onto the end just set to x): take it and stop.
        x_new = jnp.where(inside & (~revisit | (jnp.abs(step) <= tol(x))), trial, 0.5 * (lo + hi))
        fx_new, dfx_new = evaluate(x_new)
        return x_new, fx_new, dfx_new, lo, hi, x_new - x, k + 1

    x0 = jnp.clip(x0, lo, hi)
    fx0, dfx0 = evaluate(x0)
    init = (x0, fx0, dfx0, lo, hi, jnp.full_like(x0, jnp.inf), jnp.zeros((), int))
    x, fx, _, lo, hi, step, k = lax.while_loop(cond, body, init)
    stopped = (fx == 0) | (jnp.abs(step) <= tol(x)) | (hi - lo <= tol(x))
    return ScalarRoot(x, fx, k, stopped)
