"""Steady-state Wasserstein DR worst case (Jang, Hakobyan & Yang, "On the steady-state
distributionally robust Kalman filter", 2025, problems (13)/(14); see
`docs/math/steady_state.md`): the least-favourable stationary prior and noise covariances
and the constant gain of `jdrkf.SteadyStateDRKF`, by Newton's method on the KKT system with
implicit derivatives."""

from __future__ import annotations

import functools

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from .. import linalg
from .._root import default_rtol, implicit_root, newton
from .._validation import as_float_array, check_positive_int, check_scalar, in_range
from ._wasserstein import Wasserstein, oracle_residual


def posterior_and_gain(prior_cov, noise_cov, h):
    """Posterior covariance `Σ⁻ − Σ⁻Cᵀ(CΣ⁻Cᵀ + Σv)⁻¹CΣ⁻` (eq. 8) and the gain (eq. 9)."""
    gain = linalg.psd_solve(linalg.symmetrize(h @ prior_cov @ h.T + noise_cov), h @ prior_cov).T
    a = jnp.eye(prior_cov.shape[0], dtype=prior_cov.dtype) - gain @ h
    return linalg.symmetrize(a @ prior_cov @ a.T + gain @ noise_cov @ gain.T), gain


def _positive_definite(a: Float[Array, "n n"]) -> Bool[Array, ""]:
    """Whether the symmetric `a` is numerically positive definite (its Cholesky factor is finite)."""
    return jnp.all(jnp.isfinite(jnp.diagonal(jnp.linalg.cholesky(a))))


class SteadyStateDR(eqx.Module):
    """Solution of the steady-state DR problem (13)/(14).

    - `gain`: `K_ss = Σ⁻*Cᵀ(CΣ⁻*Cᵀ + Σv*)⁻¹` (Algorithm 1, line 3).
    - `prior_cov` (`Σ⁻*_ss`), `noise_cov` (`Σv*_ss`), `posterior_cov` (`Σ*_ss`), and the
      stationary pseudo-nominal prior `nominal_prior_cov = A Σ*_ss Aᵀ + Σ̂w`.
    - `value`: `Tr Σ*_ss`, the optimal value of (14).
    - `adjoint`: the multiplier `Λ` of the stationarity constraint (see `SteadyStateDRKF`).
    - `iterations`: Newton iterations (chord steps for a pair solved from an anchor under
      `vmap` over radii); `residual`: the norm of the optimality system at the solution;
      `converged`: `residual` small relative to the solution, at a point of the domain.
    """

    gain: Float[Array, "n m"]
    prior_cov: Float[Array, "n n"]
    noise_cov: Float[Array, "m m"]
    posterior_cov: Float[Array, "n n"]
    nominal_prior_cov: Float[Array, "n n"]
    value: Float[Array, ""]
    adjoint: Float[Array, "n n"]
    iterations: Int[Array, ""]
    residual: Float[Array, ""]
    converged: Bool[Array, ""]


def _layout(n: int, m: int):
    """`pack`/`unpack` between `(Σ⁻, Σv, s_x, s_v, Λ)` and one vector holding the upper
    triangles of the three symmetric matrices (row-major) and the two scalars."""
    (rn, cn), (rm, cm) = np.triu_indices(n), np.triu_indices(m)
    full_n, full_m = np.empty((n, n), np.int32), np.empty((m, m), np.int32)
    full_n[rn, cn] = full_n[cn, rn] = np.arange(rn.size)
    full_m[rm, cm] = full_m[cm, rm] = np.arange(rm.size)
    kn, km = rn.size, rm.size

    def pack(prior, noise, mx, mv, lam):
        return jnp.concatenate([prior[rn, cn], noise[rm, cm], jnp.stack([mx, mv]), lam[rn, cn]])

    def unpack(x):
        prior, noise = x[:kn][full_n], x[kn:kn + km][full_m]
        return prior, noise, x[kn + km], x[kn + km + 1], x[kn + km + 2:][full_n]

    return pack, unpack


def _stationary_residual(a, h, w, v, theta_x, theta_v):
    """Optimality system of (13) in `z = (Σ⁻, Σv, s_x, s_v, Λ)` (packed by `_layout`).

    With `Σ = post(Σ⁻, Σv)`, `Σ̂⁻ = A Σ Aᵀ + Σ̂w`, weight `Ŵ = I + AᵀΛA` and the gradients
    `D_x = (I − KC)ᵀŴ(I − KC)`, `D_v = KᵀŴK` of `Tr(Ŵ post)`:
    `Σ⁻ = T_x Σ̂⁻ T_x`, `Σv = T_v Σ̂v T_v` with `T = (I − θ s D)⁻¹` and
    `s² Tr(Σ̂ (D T)²) = 1` (the Gelbrich oracles of `jdrkf.sets.Wasserstein`, each with its
    scalar multiplier; `s = 1` for an inactive set, `Tr D = 0`) and
    `Λ = D_x T_x` (the sensitivity of the weighted value to the pseudo-nominal, i.e. the
    multiplier of `Σ̂⁻ = A Σ Aᵀ + Σ̂w`). Inverses are `linalg.psd_inv`, whose
    derivative is two products: the dense Jacobian by `jacfwd` is then a few batched
    products. Products are `linalg.matmul`: LAPACK-sized calls under `lapack_only` (the
    Newton solves), elementwise for small matrices otherwise (the chord steps of
    `_many_radii`, one residual per radius pair). `T_x` is shared by the oracle's residual and `Λ`.
    """
    n, m = a.shape[0], h.shape[0]
    pack, unpack = _layout(n, m)
    eye_n = jnp.eye(n, dtype=a.dtype)

    mm = linalg.matmul

    def residual(x):
        prior, noise, mx, mv, lam = unpack(x)
        ph = mm(prior, h.T)
        gain = mm(ph, linalg.psd_inv(mm(h, ph) + noise))
        e = eye_n - mm(gain, h)
        nominal = linalg.symmetrize(mm(mm(a, mm(e, prior)), a.T)) + w
        weight = eye_n + mm(mm(a.T, lam), a)
        dx = mm(mm(e.T, weight), e)
        dv = mm(mm(gain.T, weight), gain)
        r_prior, qx, tx = oracle_residual(theta_x, prior, mx, dx, nominal)
        r_noise, qv, _ = oracle_residual(theta_v, noise, mv, dv, v)
        return pack(r_prior, r_noise, qx, qv, lam - mm(dx, tx))

    return residual


def _weighted_gradients(prior, noise, lam, a, h):
    """Posterior `post(Σ⁻, Σv)` and the gradients `D_x = (I − KC)ᵀŴ(I − KC)`, `D_v = KᵀŴK`
    of `Tr(Ŵ post(Σ⁻, Σv))`, `Ŵ = I + AᵀΛA`."""
    eye = jnp.eye(a.shape[0], dtype=a.dtype)
    post, gain = posterior_and_gain(prior, noise, h)
    e = eye - gain @ h
    weight = eye + a.T @ lam @ a
    return post, linalg.symmetrize(e.T @ weight @ e), linalg.symmetrize(gain.T @ weight @ gain)


def _initial_guess(a, h, w, v):
    """The exact solution at zero radii: the nominal steady state (filtering DARE), its
    adjoint (the discrete Lyapunov equation `Λ = EᵀE + EᵀAᵀΛAE`, `E = I − KC`), and the
    oracles' multipliers `s = 1/√Tr(Σ̂ D²)` there (packed by `_layout`)."""
    n = a.shape[0]
    eye = jnp.eye(n, dtype=a.dtype)
    nominal = linalg.solve_dare(a, h, w, v)
    _, gain = posterior_and_gain(nominal, v, h)
    e = eye - gain @ h
    mt = (a @ e).T
    lam = jnp.linalg.solve(jnp.eye(n * n, dtype=a.dtype) - jnp.kron(mt, mt), (e.T @ e).reshape(-1)).reshape(n, n)
    lam = linalg.symmetrize(lam)
    _, dx, dv = _weighted_gradients(nominal, v, lam, a, h)

    def multiplier(d, nominal):
        q = jnp.sum(nominal * (d @ d))
        return jnp.where(jnp.trace(d) > 0, lax.rsqrt(jnp.where(q > 0, q, 1.0)), 1.0)

    pack, _ = _layout(n, h.shape[0])
    return pack(nominal, v, multiplier(dx, nominal), multiplier(dv, v), lam)


# Fixed-point sweeps (`_oracle_step`) before each Newton solve; the best one (least
# residual) is Newton's start. On random systems 8 sweeps cut the median number of
# Newton iterations from 13 to 4 at n = 2 and from 10 to 5 at n = 4 (iterated on, the
# sweeps diverge or cycle on about half of the systems).
_SWEEPS = 8


def _oracle_step(a, h, w, v, theta_x, theta_v, x):
    """One fixed-point sweep of the optimality system at radii `(θx, θv)`: the Gelbrich
    oracles for the gradients at `x`, then `Λ = D_x T_x` (a start inside the domain)."""
    pack, unpack = _layout(a.shape[0], h.shape[0])
    prior, noise, _, _, lam = unpack(x)
    post, dx, dv = _weighted_gradients(prior, noise, lam, a, h)
    prior, mx = Wasserstein(theta_x).oracle(dx, linalg.symmetrize(a @ post @ a.T + w))
    noise, mv = Wasserstein(theta_v).oracle(dv, v)
    # The gradients at the new covariances differ: keep `I − θ s D ≻ 0` there.
    _, dx, dv = _weighted_gradients(prior, noise, lam, a, h)
    lx, lv = jnp.linalg.eigvalsh(dx)[-1], jnp.linalg.eigvalsh(dv)[-1]
    mx = jnp.where(theta_x * mx * lx < 0.9, mx, 0.9 / (theta_x * lx))
    mv = jnp.where(theta_v * mv * lv < 0.9, mv, 0.9 / (theta_v * lv))
    lam = linalg.symmetrize(dx @ linalg.psd_inv(jnp.eye(a.shape[0], dtype=a.dtype) - theta_x * mx * dx))
    return pack(prior, noise, mx, mv, lam)


def _in_domain(a, h, x) -> Bool[Array, ""]:
    """Whether `x` lies on the branch of the convex problem's KKT point: the ball
    multipliers are positive (negative roots of the sets' scalar equations belong to the
    minimizing oracle), `I + AᵀΛA`, the multiplier of the Schur inequality of (14), is
    positive definite, and so are `Σ⁻` and `Σv`. The system has other roots: with an
    indefinite weight (and a lower value), and — when `Σ̂w` is nearly singular — with an
    indefinite `Σ⁻` that is self-consistent because `Σ̂⁻ = AΣAᵀ + Σ̂w` inherits the
    negative eigenvalue of `Σ` (infeasible for (14), with a *higher* "value"). Trial
    points off this domain are rejected, so a converged solve is a feasible KKT point of
    the convex problem."""
    prior, noise, mx, mv, lam = _layout(a.shape[0], h.shape[0])[1](x)
    weight = jnp.eye(a.shape[0], dtype=a.dtype) + a.T @ lam @ a
    return (mx > 0) & (mv > 0) & _positive_definite(weight) & _positive_definite(prior) & _positive_definite(noise)


def _continuation(a, h, w, v, theta_x, theta_v, max_iter):
    """Solve the optimality system for radii `τ(θx, θv)`, `τ: 0 → 1`. At `τ = 0` the
    initial guess is exact (the nominal steady state and its adjoint); each stage is
    a Newton solve started at the best of `_SWEEPS` fixed-point sweeps from the
    previous stage's solution; the step in `τ` doubles after a success and halves after
    a failure (first try: `τ = 1` directly)."""
    dtype = a.dtype
    zero = jnp.zeros((), dtype)

    in_domain = functools.partial(_in_domain, a, h)

    def cond(c):
        _, tau, dtau, _, _, _ = c
        return (tau < 1) & (dtau >= 2.0**-10)

    def body(c):
        x, tau, dtau, iters, nr, ok = c
        t = jnp.minimum(tau + dtau, 1.0)
        residual = _stationary_residual(a, h, w, v, t * theta_x, t * theta_v)

        def merit(y):
            r = residual(y)
            return jnp.where(jnp.all(jnp.isfinite(r)) & in_domain(y), jnp.linalg.norm(r), jnp.inf)

        def sweep(i, c):
            y, best, nb = c
            y = _oracle_step(a, h, w, v, t * theta_x, t * theta_v, y)
            ny = merit(y)
            better = ny < nb
            return y, jnp.where(better, y, best), jnp.where(better, ny, nb)

        _, xp, _ = lax.fori_loop(0, _SWEEPS, sweep, (x, x, merit(x)))
        eps = jnp.finfo(dtype).eps
        xt, k, nrt, _ = newton(residual, xp, max_iter, in_domain=in_domain, ftol=10 * eps)
        okt = nrt <= default_rtol(dtype) * (1.0 + jnp.linalg.norm(xt))
        return (jnp.where(okt, xt, x), jnp.where(okt, t, tau), jnp.where(okt, 2.0 * dtau, 0.5 * dtau), iters + k,
                jnp.where(okt, nrt, nr), okt)

    init = (_initial_guess(a, h, w, v), zero, jnp.ones((), dtype), jnp.zeros((), int), zero, jnp.zeros((), bool))
    x, tau, _, iters, nr, _ = lax.while_loop(cond, body, init)
    converged = tau >= 1
    return x, iters, jnp.where(converged, nr, jnp.inf), converged


# Many radius pairs on one system (`vmap` over the radii only): the anchors per radius
# axis, at most `_ANCHOR_COLUMNS` stacked rows of anchor inverses (their product with the
# residuals is one matrix product), the chord steps allowed before a pair falls back to
# the continuation, and the pairs per anchor below which plain `vmap` of it is used.
_MAX_ANCHORS_PER_AXIS = 4
_ANCHOR_COLUMNS = 512
_CHORD_STEPS = 60
_PAIRS_PER_ANCHOR = 4


def _anchors_per_axis(n: int, m: int) -> int:
    unknowns = n * (n + 1) + m * (m + 1) // 2 + 2  # the length of `_layout`'s vector
    return max(1, min(_MAX_ANCHORS_PER_AXIS, int((_ANCHOR_COLUMNS / unknowns) ** 0.5)))


def _cells(t, valid, g):
    """Centres of `g` equal cells over the range of the valid radii `t`, and each radius's cell."""
    lo = jnp.min(jnp.where(valid, t, jnp.inf))
    hi = jnp.max(jnp.where(valid, t, -jnp.inf))
    lo = jnp.where(jnp.isfinite(lo), lo, 0.0)
    width = (jnp.maximum(jnp.where(jnp.isfinite(hi), hi, 0.0), lo) - lo) / g
    centres = lo + width * (jnp.arange(g, dtype=t.dtype) + 0.5)
    cell = jnp.floor((t - lo) / jnp.where(width > 0, width, 1.0))
    return centres, jnp.clip(jnp.where(jnp.isfinite(cell), cell, 0), 0, g - 1).astype(jnp.int32)


def _many_radii(a, h, w, v, theta_x, theta_v, max_iter):
    """`_continuation` for a batch of radius pairs `(θx_b, θv_b)` on one system.

    The valid radii's range is cut into `g × g` cells; the continuation solves the system
    at the cell centres (the anchors `z_k`), whose Jacobians `J_k` give each pair a start
    on the tangent, `z_k − J_k⁻¹ ∂F/∂θ (θ_b − θ_k)`, and chord steps
    `z ← z − J_k⁻¹ F(z; θ_b)` — one residual per step and pair and one matrix product for
    the batch, where Newton under `vmap` forms and factorizes a Jacobian per pair and
    runs the slowest pair's continuation, sweeps and line search for every pair. A pair
    counts as solved under the continuation's own test (residual at tolerance at a point of
    the domain); pairs that are not (a chord that stalls or leaves the domain) are solved
    by the continuation, under `vmap`, in a branch taken only when there are such pairs.
    Returns the continuation's outputs, with the chord steps as the iteration count."""
    dtype = a.dtype
    g = _anchors_per_axis(a.shape[0], h.shape[0])
    size = theta_x.shape[0]
    continuation = jax.vmap(lambda tx, tv: _continuation(a, h, w, v, tx, tv, max_iter))
    valid = (theta_x >= 0) & (theta_v >= 0) & jnp.isfinite(theta_x) & jnp.isfinite(theta_v)
    (cx, kx), (cv, kv) = _cells(theta_x, valid, g), _cells(theta_v, valid, g)
    ax, av = jnp.repeat(cx, g), jnp.tile(cv, g)
    cell = kx * g + kv
    z, *_ = continuation(ax, av)  # unrolled small-matrix code outside `lapack_only`: faster for n ≤ 6

    def derivatives(z, tx, tv):
        return jax.jacfwd(lambda z, tx, tv: _stationary_residual(a, h, w, v, tx, tv)(z), argnums=(0, 1, 2))(z, tx, tv)

    with linalg.lapack_only():
        jac, dfx, dfv = jax.vmap(derivatives)(z, ax, av)
    inverse = jnp.linalg.inv(jac)
    tangent_x, tangent_v = jnp.einsum("kij,kj->ki", inverse, dfx), jnp.einsum("kij,kj->ki", inverse, dfv)
    x = z[cell] - tangent_x[cell] * (theta_x - ax[cell])[:, None] - tangent_v[cell] * (theta_v - av[cell])[:, None]
    unknowns = z.shape[1]
    stacked = inverse.reshape(g * g * unknowns, unknowns)
    residual = jax.vmap(lambda z, tx, tv: _stationary_residual(a, h, w, v, tx, tv)(z))
    rtol = default_rtol(dtype)

    def status(x, r):
        nr = jnp.linalg.norm(r, axis=1)
        return nr, nr <= rtol * (1.0 + jnp.linalg.norm(x, axis=1))

    def moving(x, r):
        nr, done = status(x, r)
        return valid & ~done & jnp.isfinite(nr)

    def cond(c):
        x, r, k, _ = c
        return (k < _CHORD_STEPS) & jnp.any(moving(x, r))

    def body(c):
        x, r, k, steps = c
        move = moving(x, r)
        step = jnp.take_along_axis((r @ stacked.T).reshape(size, g * g, unknowns), cell[:, None, None], axis=1)[:, 0]
        x = jnp.where(move[:, None], x - step, x)
        return x, residual(x, theta_x, theta_v), k + 1, steps + move.astype(jnp.int32)

    x, r, _, steps = lax.while_loop(cond, body, (x, residual(x, theta_x, theta_v), jnp.zeros((), jnp.int32),
                                                 jnp.zeros(size, jnp.int32)))
    nr, done = status(x, r)
    ok = valid & done & jax.vmap(functools.partial(_in_domain, a, h))(x)
    chorded = (x, steps, jnp.where(ok, nr, jnp.inf), ok)
    need = valid & ~ok

    def rescue(_):
        with linalg.lapack_only():
            xs, ks, nrs, oks = continuation(theta_x, theta_v)
        pick = lambda fallback, mine: jnp.where(need.reshape(need.shape + (1,) * (mine.ndim - 1)), fallback, mine)  # noqa: E731
        return pick(xs, x), pick(ks.astype(jnp.int32), steps), pick(nrs, chorded[2]), pick(oks, ok)

    return lax.cond(jnp.any(need), rescue, lambda _: chorded, None)


def _radii_solver(max_iter: int):
    """`_continuation` at fixed `max_iter`, batched by `_many_radii` under `vmap` over the
    radii alone (at least `_PAIRS_PER_ANCHOR` pairs per anchor); any other batching maps the
    continuation."""

    @jax.custom_batching.custom_vmap
    def solve(a, h, w, v, theta_x, theta_v):
        x, k, nr, ok = _continuation(a, h, w, v, theta_x, theta_v, max_iter)
        return x, k.astype(jnp.int32), nr, ok

    @solve.def_vmap
    def _(size, batched, a, h, w, v, theta_x, theta_v):
        if any(batched[:4]) or size < _PAIRS_PER_ANCHOR * _anchors_per_axis(a.shape[-1], h.shape[-2]) ** 2:
            with linalg.lapack_only():
                out = jax.vmap(solve.fun, in_axes=tuple(0 if b else None for b in batched))(a, h, w, v, theta_x, theta_v)
        else:
            tx, tv = (t if b else jnp.broadcast_to(t, (size,)) for t, b in zip((theta_x, theta_v), batched[4:], strict=True))
            out = _many_radii(a, h, w, v, tx, tv, max_iter)
        return out, (True,) * 4

    return solve


@eqx.filter_jit
def _steady_state(a, h, w, v, theta_x, theta_v, max_iter):
    with linalg.lapack_only():
        return _steady_state_impl(a, h, w, v, theta_x, theta_v, max_iter)


def _steady_state_impl(a, h, w, v, theta_x, theta_v, max_iter):
    params = (a, h, w, v, theta_x, theta_v)

    def solve(guess):
        del guess
        x, k, nr, ok = _radii_solver(max_iter)(*jax.tree.map(lax.stop_gradient, params))
        return x, (k, nr, ok)

    guess = _initial_guess(*jax.tree.map(lax.stop_gradient, (a, h, w, v)))
    x, (k, nr, ok) = implicit_root(_stationary_residual(*params), solve, guess)
    prior, noise, _, _, lam = _layout(a.shape[0], h.shape[0])[1](x)
    noise = jnp.where(theta_v == 0, v, noise)  # exact at zero radius
    post, gain = posterior_and_gain(prior, noise, h)
    converged = ok & in_range(theta_x, 0.0) & in_range(theta_v, 0.0)
    return SteadyStateDR(
        gain=gain,
        prior_cov=prior,
        noise_cov=noise,
        posterior_cov=post,
        nominal_prior_cov=linalg.symmetrize(a @ post @ a.T + w),
        value=jnp.trace(post),
        adjoint=lam,
        iterations=k,
        residual=nr,
        converged=converged,
    )


def steady_state_worst_case(
    A: Float[ArrayLike, "n n"],
    C: Float[ArrayLike, "m n"],
    process_cov: Float[ArrayLike, "n n"],
    noise_cov: Float[ArrayLike, "m m"],
    radius_x: Float[ArrayLike, ""],
    radius_v: Float[ArrayLike, ""],
    *,
    max_iter: int = 20,
) -> SteadyStateDR:
    """Least-favourable stationary covariances of the steady-state Wasserstein DR
    problem (Jang, Hakobyan & Yang 2025, problems (13)/(14)) for the time-invariant
    system `x⁺ = A x + w`, `y = C x + v` with nominal `Σ̂w = process_cov` (`G Q Gᵀ`),
    `Σ̂v = noise_cov` and radii `θx = radius_x`, `θv = radius_v` (`≥ 0`, differentiable):
    maximize `Tr Σ` subject to `Σ = post(Σ⁻, Σv)`, `Σ̂⁻ = AΣAᵀ + Σ̂w`, `𝓑(Σ⁻, Σ̂⁻) ≤ θx`,
    `𝓑(Σv, Σ̂v) ≤ θv`, without an SDP solver (the method is described in
    `jdrkf.SteadyStateDRKF`). `max_iter`: Newton iterations per continuation stage."""
    A, C, process_cov, noise_cov = (as_float_array(k, x, (2,)) for k, x in
                                    (("A", A), ("C", C), ("process_cov", process_cov), ("noise_cov", noise_cov)))
    radius_x, radius_v = check_scalar("radius_x", radius_x), check_scalar("radius_v", radius_v)
    return solve_steady_state(A, C, process_cov, noise_cov, radius_x, radius_v, check_positive_int("max_iter", max_iter))


def solve_steady_state(A, C, process_cov, noise_cov, radius_x, radius_v, max_iter: int) -> SteadyStateDR:
    """`steady_state_worst_case` without the eager argument checks (traced arguments
    inside a filter); the radii are cast to the system's dtype."""
    dtype = A.dtype
    return _steady_state(A, C, process_cov, noise_cov, jnp.asarray(radius_x).astype(dtype), jnp.asarray(radius_v).astype(dtype), int(max_iter))
