"""Worst-case (least-favourable) covariances of DR-MMSE problems: Frank–Wolfe with
backtracking to a loose start, chord (simplified Newton) steps on the optimality system
written in the gain and the sets' multipliers, implicit derivatives."""

from __future__ import annotations

from collections.abc import Callable
from typing import NamedTuple

import equinox as eqx
import jax
import jax.numpy as jnp
from jax import lax
from jax.flatten_util import ravel_pytree
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from .. import linalg
from .._root import chord, default_rtol, implicit_root, newton
from .._validation import as_float_array, check_covariance, check_scalar, renamed
from ._base import AbstractAmbiguitySet
from ._moment import Moment
from ._wasserstein import Wasserstein

# Frank–Wolfe stops at this relative gap (or `rtol` if looser); the chord iterations take over.
_START_RTOL = 1e-5
_CHORD_MAX_STEPS = 30
# The chord steps stop once the residual's 2-norm is below this fraction of `rtol`
# (absolute, so that every multiplier equation is then within `rtol / 100` of zero, as the
# certificate requires), or at round-off.
_CHORD_FTOL_FRACTION = 1e-2
_NEWTON_MAX_STEPS = 30


class WorstCase(eqx.Module):
    """Solution of the decoupled problem (Wang & Ye 2022, eqs. 32–35 and 36–37).

    - `state_cov`, `noise_cov`: the worst-case prior `Σx*` and noise `Σv*` covariances.
    - `value`: `Tr(Σx* − i_min Σx*Hᵀ(HΣx*Hᵀ + Σv*)⁻¹HΣx*)`, the trace of the worst-case
      posterior covariance (eq. 41).
    - `iterations`: Frank–Wolfe iterations plus chord (and any damped Newton) steps; `gap`: a duality gap at the
      solution (an upper bound on the optimal value minus `value`, see `_solve`);
      `converged`: `gap ≤ rtol · value` with the sets' multiplier equations solved to `rtol`.
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


class _Objective(NamedTuple):
    """An MMSE objective `f` whose gradient depends on the blocks `Σ` only through a gain
    `K` (`n × m`): `∇f(Σ) = directions(gain(Σ))`. The optimality system of `max f` can
    then be written in `K` and the sets' multipliers (`_reduced_residual`).

    - `fg(Σ) -> (f, ∇f)`: for Frank–Wolfe.
    - `gain(Σ) -> K`; `directions(K) -> ∇f`.
    - `factors`: one thin matrix `Y` per block; `gain_residual(K, (Σ Y, …))` vanishes exactly
      at `K = gain(Σ)` and needs the blocks only through the products `Σ Y`.
    """

    fg: Callable
    gain: Callable
    directions: Callable
    factors: tuple
    gain_residual: Callable


def _decoupled_objective(h, i_min) -> _Objective:
    """`f(Σx, Σv) = Tr Σx − i Tr(K H Σx)`, `K = ΣxHᵀ(HΣxHᵀ + Σv)⁻¹`, with the gradient
    `((1 − i)I + i(I − KH)ᵀ(I − KH), i KᵀK)` (the gradient of Wang & Ye's eq. 41, scaled by `i = i_min`);
    gain residual `K(HΣxHᵀ + Σv) − ΣxHᵀ` (factors `Hᵀ`, `I`)."""
    n, m = h.shape[1], h.shape[0]

    def gain(blocks):
        sx, sv = blocks
        return linalg.gauss_jordan_solve(h @ sx @ h.T + sv, h @ sx).T

    def directions(k):
        # (I − KH)ᵀ(I − KH) = I − KH − (KH)ᵀ + Hᵀ(KᵀK)H: each tangent of K costs O(n²m)
        kk = linalg.symmetrize(k.T @ k)
        kh = k @ h
        dx = jnp.eye(n, dtype=k.dtype) - i_min * (kh + kh.T) + i_min * (h.T @ kk @ h)
        return linalg.symmetrize(dx), i_min * kk

    def fg(blocks):
        sx, _ = blocks
        k = gain(blocks)
        return jnp.trace(sx) - i_min * jnp.trace(k @ h @ sx), directions(k)

    def gain_residual(k, thin):
        sxh, sv = thin
        return k @ linalg.symmetrize(h @ sxh + sv) - sxh

    return _Objective(fg, gain, directions, (h.T, jnp.eye(m, dtype=h.dtype)), gain_residual)


def _joint_objective(n, d, dtype) -> _Objective:
    """`f(S) = Tr(S/S_yy)` and its gradient `[I, −K]ᵀ[I, −K]`, `K = S_xy S_yy⁻¹`; gain
    residual `K S_yy − S_xy` (factor `[0, I]ᵀ`, the `y` columns)."""

    def gain(blocks):
        (s,) = blocks
        return linalg.gauss_jordan_solve(s[n:, n:], s[:n, n:].T).T

    def directions(k):
        e = jnp.concatenate([jnp.eye(n, dtype=k.dtype), -k], axis=1)
        return (linalg.symmetrize(e.T @ e),)

    def fg(blocks):
        (s,) = blocks
        k = gain(blocks)
        return jnp.trace(s[:n, :n]) - jnp.trace(k @ s[:n, n:].T), directions(k)

    def gain_residual(k, thin):
        (sy,) = thin
        return k @ linalg.symmetrize(sy[n:]) - sy[:n]

    return _Objective(fg, gain, directions, (jnp.eye(d, dtype=dtype)[:, n:],), gain_residual)


def _frank_wolfe(fg, sets, nominals, rtol, max_iter):
    """Frank–Wolfe with backtracking step sizes (Armijo-type line search), from the nominals.

    Returns the last iterate, the iteration count and the oracles' multipliers at that
    iterate (each oracle is traced once, inside the loop).
    """
    dtype = nominals[0].dtype

    def cond(c):
        return (~c[3]) & (c[1] < max_iter)

    def body(c):
        s, k, beta, _, mults = c
        value, grads = fg(s)
        # Each oracle's scalar search starts from the previous iterate's multiplier (0 at first: its default start).
        lmos, mults = zip(*(st.oracle(g, nom, guess=mu) for st, g, nom, mu in zip(sets, grads, nominals, mults, strict=True)),
                          strict=True)
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

        beta, ascent, _ = lax.while_loop(bt_cond, bt_body, (beta, done, 0))
        # No step of the line search ascends: Frank–Wolfe has reached its rounding floor
        # (float32 far from the tolerance). Stop here; the chord steps and the final
        # certificate decide convergence (without this, each remaining iteration would
        # spend 60 backtracking evaluations).
        stalled = ~ascent
        eta = jnp.where(done | stalled, 0.0, jnp.minimum(gap / (beta * pn_safe), 1.0))
        s = tuple(linalg.symmetrize(si + eta * pi) for si, pi in zip(s, p, strict=True))
        return s, k + jnp.where(done | stalled, 0, 1), beta, done | stalled, tuple(mults)

    beta0 = jnp.ones((), dtype) / sum(jnp.trace(nom) for nom in nominals)
    zero = jnp.zeros((), dtype)
    init = (tuple(nominals), jnp.zeros((), int), beta0, jnp.zeros((), bool), tuple(zero for _ in nominals))
    s, k, _, _, mults = lax.while_loop(cond, body, init)
    return s, k, mults


def _oracle(st, multiplier, direction, nominal):
    """The set's oracle `Σ(s, D)` as a smooth function of its multiplier `s` and the
    direction `D`, and the multiplier's equation: every set's `residual` is
    `(Σ − Σ(s, D), equation)` with an equation independent of `Σ`."""
    r, q = st.residual(jnp.zeros_like(nominal), multiplier, direction, nominal)
    return -r, q


def _reduced_residual(obj: _Objective, sets, nominals):
    """Optimality system of `max f` in `x = (K, s₁, s₂, …)`: `Σⱼ = Σⱼ(sⱼ, Dⱼ(K))` are the
    oracles at the directions `D(K) = obj.directions(K)`, and at the optimum
    `K = gain(Σ)` and each multiplier solves its set's equation. It has `n·m + #sets`
    unknowns (the system in the blocks has `n² + m² + 2`)."""

    def residual(x):
        k, mults = x
        oracles = [_oracle(*a) for a in zip(sets, mults, obj.directions(k), nominals, strict=True)]
        thin = tuple(sig @ y for (sig, _), y in zip(oracles, obj.factors, strict=True))
        return obj.gain_residual(k, thin), tuple(q for _, q in oracles)

    return residual


def _blocks(obj: _Objective, sets, nominals, x):
    """The worst-case blocks `Σⱼ(sⱼ, Dⱼ(K))` at `x = (K, s)`. Zero-radius blocks are the
    nominals exactly, with the derivatives of `Σⱼ(sⱼ, Dⱼ(K))` (e.g. in the radius)."""
    k, mults = x
    blocks = []
    for st, mu, d, nom in zip(sets, mults, obj.directions(k), nominals, strict=True):
        sig = linalg.symmetrize(_oracle(st, mu, d, nom)[0])
        blocks.append(jnp.where(st.is_nominal(), lax.stop_gradient(nom) + (sig - lax.stop_gradient(sig)), sig))
    return tuple(blocks)


def _wasserstein_jacobian(h, i_min, sets, nominals):
    """Closed-form Jacobian of `_reduced_residual` for the decoupled objective with two
    Wasserstein balls (`jax.jacfwd` pushes `n·m` tangents through `O(n²m)` products each;
    this is `O(n²m²)`), flattened as `ravel_pytree` orders `(K, (s_x, s_v))`.

    With `A = I − KH`, `dD_x = −i(HᵀdKᵀA + AᵀdKH)`, `dD_v = i(dKᵀK + KᵀdK)` and, per ball,
    `dΣ = θ s (T dD Σ + Σ dD T) + θ ds (TDΣ + ΣDT)` (`Σ = TΣ̂T`, `dT = θT(ds D + s dD)T`),
    the gain residual `r = KS − ΣxHᵀ` (`S = HΣxHᵀ + Σv`) has
    `dr = dK S − A dΣx Hᵀ + K dΣv`, a sum of terms `X dK Y` (entry `X_ak Y_lb` of column
    `dK = e_k e_lᵀ`) and `X dKᵀ Y` (`X_al Y_kb`). The radius equation
    `q = s² Tr(Σ̂P²) − 1` (`P = DT`; `T = I + θsP`, so `dP = T dD T + θ ds P²`) has
    `dq = s²⟨TQT, dD⟩ + (2s Tr(Σ̂P²) + 2θs² Tr(Σ̂P³)) ds`, `Q = PΣ̂ + Σ̂P`; an inactive
    ball's equation is `s − 1`.
    """

    def jacobian(x):
        k, mults = x
        n, m = k.shape
        a = jnp.eye(n, dtype=k.dtype) - k @ h
        ds = _decoupled_objective(h, i_min).directions(k)
        parts = []
        for st, s, d, nom in zip(sets, mults, ds, nominals, strict=True):
            rho = st.radius.astype(nom.dtype)
            t = linalg.psd_inv(jnp.eye(d.shape[-1], dtype=d.dtype) - rho * s * d)
            sig = linalg.symmetrize(t @ nom @ t)
            p = linalg.symmetrize(t @ d)
            p2 = p @ p
            q_mat = p @ nom
            slope = 2.0 * s * jnp.sum(nom * p2) + 2.0 * rho * s * s * jnp.sum((nom @ p) * p2)
            active = jnp.trace(d) > 0
            tds = t @ d @ sig
            parts.append((rho * s, t, sig, s * s * (t @ (q_mat + q_mat.T) @ t), rho * (tds + tds.T), slope, active))
        (cx, tx, sx, gx, dsx, slope_x, act_x), (cv, tv, sv, gv, dsv, slope_v, act_v) = parts

        def dk(x_, y_):  # X dK Y
            return jnp.einsum("ak,lb->abkl", x_, y_)

        def dkt(x_, y_):  # X dKᵀ Y
            return jnp.einsum("al,kb->abkl", x_, y_)

        u, w = a @ tx @ h.T, a @ sx @ h.T
        kt, ks = k @ tv, k @ sv
        s_mat = linalg.symmetrize(h @ sx @ h.T + sv)
        jkk = (
            dk(jnp.eye(n, dtype=k.dtype), s_mat)
            + i_min * cx * (dkt(u, w) + dkt(w, u) + dk(a @ tx @ a.T, h @ sx @ h.T) + dk(a @ sx @ a.T, h @ tx @ h.T))
            + i_min * cv * (dkt(kt, ks) + dkt(ks, kt) + dk(kt @ k.T, sv) + dk(ks @ k.T, tv))
        ).reshape(n * m, n * m)
        cols = jnp.stack([(-a @ dsx @ h.T).ravel(), (k @ dsv).ravel()], axis=1)
        rows = jnp.stack([jnp.where(act_x, -2.0 * i_min * (a @ gx @ h.T), 0.0).ravel(), jnp.where(act_v, 2.0 * i_min * (k @ gv), 0.0).ravel()])
        corner = jnp.diag(jnp.stack([jnp.where(act_x, slope_x, 1.0), jnp.where(act_v, slope_v, 1.0)]))
        return jnp.block([[jkk, cols], [rows, corner]])

    return jacobian


def _solve(make_objective: Callable, params, sets: tuple, nominals: tuple, rtol, max_iter, make_jacobian=None):
    """Worst-case blocks of `max f` over the product of `sets`, with implicit derivatives.

    The optimum is the fixed point `Σ = LMO(∇f(Σ))` of each block (first-order optimality of the concave maximization),
    written as the smooth system `_reduced_residual` in the gain `K` and the multipliers.
    Forward: Frank–Wolfe to a relative gap `max(rtol, _START_RTOL)`, then chord steps on
    that system to an absolute residual of `rtol / 100` or round-off (`chord`; the Jacobian in closed form for two
    Wasserstein balls, `make_jacobian`, else `jax.jacfwd`); if the chord steps stop short
    of `rtol` or leave a multiplier equation outside it, damped Newton (`newton`, a fresh
    Jacobian each step) to the same absolute residual. Derivatives: the implicit function theorem on the same system
    (`lax.custom_root`); the blocks are smooth functions of its solution.

    `gap` is the duality gap `Σⱼ⟨Dⱼ(K), Σⱼ⟩ − f(Σ) ≥ max f − f(Σ)` at the solution: `Σ(K)`
    maximizes `⟨D(K), ·⟩` over the sets, and `f(Σ') ≤ ⟨D(K), Σ'⟩` for every `Σ'` (`f` is the
    minimum over gains of that linear function). `converged`: `gap ≤ rtol · f` and the
    multipliers' equations solved to `rtol` (so that `Σ(K)` is that maximizer).
    """
    dtype = nominals[0].dtype

    def solve(guess):
        del guess
        p_, sets_, noms_ = jax.tree.map(lax.stop_gradient, (params, sets, nominals))
        obj = make_objective(*p_)
        s, iters, mults = _frank_wolfe(obj.fg, sets_, noms_, max(rtol, _START_RTOL), max_iter)
        jacobian = None if make_jacobian is None else make_jacobian(*p_, sets_, noms_)
        residual = _reduced_residual(obj, sets_, noms_)
        x, r, steps = chord(residual, (obj.gain(s), mults), jacobian, _CHORD_MAX_STEPS, ftol=_CHORD_FTOL_FRACTION * rtol)

        def damped(x):
            # The chord steps failed to reach the tolerance: the start lies outside their
            # contraction region (seen on ill-conditioned H, R where Frank–Wolfe stalls at a
            # gap ~1e-6). Damped Newton with a fresh Jacobian each step takes over, to the
            # chord's absolute residual (newton's test is relative to ‖x‖, which a large
            # multiplier inflates past what the certificate's equations allow) or round-off.
            ftol = _CHORD_FTOL_FRACTION * rtol / (1.0 + jnp.linalg.norm(ravel_pytree(x)[0]))
            result = newton(residual, x, _NEWTON_MAX_STEPS, ftol=ftol)
            return result.x, result.iterations

        far = (jnp.linalg.norm(ravel_pytree(r)[0]) > rtol * (1.0 + jnp.linalg.norm(ravel_pytree(x)[0]))) | (
            jnp.max(jnp.abs(jnp.stack(r[1]))) > rtol)  # newton's own test, or a multiplier equation outside the certificate
        x, more = lax.cond(far, damped, lambda x: (x, jnp.zeros((), steps.dtype)), x)
        _, equations = residual(x)
        return x, (iters + steps + more, jnp.max(jnp.abs(jnp.stack(equations))))

    obj = make_objective(*params)
    k0 = jax.eval_shape(obj.gain, nominals)
    guess = (jnp.zeros(k0.shape, dtype), tuple(jnp.zeros((), dtype) for _ in nominals))
    x, (iters, worst) = implicit_root(_reduced_residual(obj, sets, nominals), solve, guess)
    blocks = _blocks(obj, sets, nominals, x)
    value, _ = obj.fg(blocks)
    bound = sum(jnp.vdot(d, b) for d, b in zip(obj.directions(x[0]), blocks, strict=True))
    gap = lax.stop_gradient(jnp.maximum(bound - value, 0.0))
    tol = rtol * jnp.maximum(jnp.abs(value), jnp.finfo(dtype).tiny)
    converged = (worst <= rtol) & (gap <= tol)
    return blocks, value, iters, gap, converged


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
    each set in closed form (Wang & Ye, eqs. 34–36; the KL ball's dual), to a loose start, then chord
    steps on the optimality system in the gain and the multipliers, which also gives the
    derivatives (implicit function theorem) with respect to radii, `prior_cov`, `H`,
    `noise_cov` and `i_min`.
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
    valid = state_set.valid() & noise_set.valid()  # radii in range (traced radii are not checked eagerly)
    if all(isinstance(st, Moment) for st in sets):
        s = tuple(st.worst_case(nom) for st, nom in zip(sets, noms, strict=True))
        value, _ = _decoupled_objective(H, i_min).fg(s)
        zero = jnp.zeros((), prior_cov.dtype)
        return WorstCase(s[0], s[1], value, jnp.zeros((), int), zero, valid)
    both_wasserstein = all(isinstance(st, Wasserstein) for st in sets)
    make_jacobian = _wasserstein_jacobian if both_wasserstein else None
    s, value, iters, gap, conv = _solve(_decoupled_objective, (H, i_min), sets, noms, rtol, max_iter, make_jacobian)
    return WorstCase(s[0], s[1], value, iters, gap, conv & valid)


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
        value, _ = _joint_objective(n, cov.shape[0], cov.dtype).fg((s,))
        return JointWorstCase(s, value, jnp.zeros((), int), jnp.zeros((), cov.dtype), joint_set.valid())
    s, value, iters, gap, conv = _solve(lambda: _joint_objective(n, cov.shape[0], cov.dtype), (), (joint_set,), (cov,), rtol, max_iter)
    return JointWorstCase(s[0], value, iters, gap, conv & joint_set.valid())


def wasserstein_mmse(
    prior_cov: Float[ArrayLike, "n n"],
    H: Float[ArrayLike, "m n"],
    noise_cov: Float[ArrayLike, "m m"],
    radius_x: Float[ArrayLike, ""] = None,
    radius_v: Float[ArrayLike, ""] = None,
    *,
    i_min: Float[ArrayLike, ""] = 1.0,
    rtol: float | None = None,
    max_iter: int = 500,
    theta_x: Float[ArrayLike, ""] = None,
    theta_v: Float[ArrayLike, ""] = None,
) -> WorstCase:
    """Decoupled Wasserstein DR-MMSE problem (Wang & Ye 2022, eqs. 32–35; Jang et al.
    2025, eq. 5): separate `W₂` balls of radii `radius_x` around `prior_cov` and
    `radius_v` around `noise_cov` (`theta_x=`, `theta_v=`: deprecated aliases). See `worst_case`."""
    radius_x = renamed("theta_x", theta_x, "radius_x", radius_x, "wasserstein_mmse", stacklevel=3)
    radius_v = renamed("theta_v", theta_v, "radius_v", radius_v, "wasserstein_mmse", stacklevel=3)
    sets = Wasserstein(check_scalar("radius_x", radius_x)), Wasserstein(check_scalar("radius_v", radius_v))
    return worst_case(*sets, prior_cov, H, noise_cov, i_min=i_min, rtol=rtol, max_iter=max_iter)


def wasserstein_mmse_joint(
    cov: Float[ArrayLike, "d d"], n: int, radius: Float[ArrayLike, ""] = None, *, rtol: float | None = None,
    max_iter: int = 500, rho: Float[ArrayLike, ""] = None,
) -> JointWorstCase:
    """Joint Wasserstein DR-MMSE problem: one `W₂` ball of radius `radius` around the
    covariance `cov` of `(x, y)` (Shafieezadeh-Abadeh et al. 2018; Theorem 8 of
    Wang & Ye 2022; `rho=`: deprecated alias). See `worst_case_joint`."""
    radius = renamed("rho", rho, "radius", radius, "wasserstein_mmse_joint", stacklevel=3)
    return worst_case_joint(Wasserstein(check_scalar("radius", radius)), cov, n, rtol=rtol, max_iter=max_iter)
