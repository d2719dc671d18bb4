"""Marginal DR-MMSE problem of multi-sensor fusion (Chen, Li, Liu, He, "A Marginal
Distributionally Robust Kalman Filter for Sensor Fusion", IEEE SPL 2025; problem (16)).

The adversary picks the joint covariance `S` of `(x, y¹, …, yᵖ)`; only the marginal
blocks `S_{B_i}` of `(x, yⁱ)` are constrained, to a moment set or a KL ball around the
nominal `Σ_i`. The cross-sensor blocks are free: the adversary chooses how sensor
errors correlate. Method (`docs/math/marginal.md`):

1. Whitening `S = G Z Gᵀ`, with `G` lower block-triangular and `G_i G_iᵀ = Σ_i` for
   the rows/columns of block `B_i`: the constraints become `γ₁ I ⪯ Z_{B_i} ⪯ γ₂ I`, or
   `Tr Z_{B_i} − log det Z_{B_i} − d_i ≤ 2c`, plus `Z ⪰ 0`.
2. Projected gradient ascent with monotone backtracking on `f(Z) = Tr(S/S_yy)`, the
   projection onto the intersection by Dykstra's algorithm (each set is a spectral
   map of one block: an eigenvalue clip, or for KL a map with one scalar multiplier
   found by bisection). Used for sets without interior (below).
3. Log-barrier path following: damped Newton on
   `max f(Z)/f₀ + μ[Σ_i barrier_i(Z_{B_i}) + log det Z]` (`f₀` = nominal value) from
   the centre of the set, `μ = 10⁻¹ … 10⁻⁸` (float32: `10⁻³`). The barrier problem is
   strictly concave, so its solution is unique and smooth in the data; its value is
   within `ν μ f₀` of the SDP optimum (`ν` = total size of the barriers; ~1e-8 relative
   in practice, a slight underestimate), and it is strictly feasible. Derivatives
   (w.r.t. the radii and the nominal covariance, forward and reverse mode) are the
   implicit-function derivatives of this barrier solution (`custom_jvp`), i.e. the exact
   derivatives of the returned map.

When the feasible set has no interior (some `γ₁ᵢ = γ₂ᵢ`, or `max γ₁ = min γ₂`, or some
`cᵢ = 0`), the projected-gradient solution is returned, and its derivatives are those of
the barrier problem with all radii shifted outwards by `1e-6` (γ₁ − δ, γ₂ + δ, c + δ):
approximate one-sided derivatives (for `c = 0` the exact one is infinite, the set grows
like `√c`; this returns a large finite number).

The worst-case `S*` need not be unique (e.g. for one sensor every `S` with
`S/S_yy = γ₂ Σ/Σ_yy` is optimal); the barrier solution is the analytic centre of the
optimal face, so gain, posterior covariance and value are the meaningful outputs.
"""

from __future__ import annotations

import abc
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jax.scipy.linalg import solve_triangular
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from .. import linalg
from .._root import default_rtol, implicit_root, newton
from .._validation import as_float_array, check_covariance, check_positive_int, in_range, is_concrete, renamed, renamed_attribute

_DYKSTRA_MAX_ITER = 200
_BISECT_ITER = 80
_BACKTRACK_MAX = 40
_NEWTON_PER_STAGE = 8
_NEWTON_FINAL = 12
_MU0 = 1e-1
_WIDEN = 1e-6


# ------------------------------------------------------------------------------ sets


def _per_sensor(name: str, x, *, lower: float, upper: float, lower_open: bool = False):
    x = as_float_array(name, x, (0, 1))
    if is_concrete(x):
        v = np.asarray(x, dtype=np.float64)
        bad = ~np.isfinite(v) | (v < lower) | (v > upper) | ((v == lower) if lower_open else False)
        if np.any(bad):
            lo = "(" if lower_open else "["
            raise ValueError(f"{name} must lie in {lo}{lower:g}, {upper:g}] (per sensor), got {v}")
    return x


class AbstractMarginalSet(eqx.Module):
    """Per-sensor ambiguity sets on the marginal blocks `S_{B_i}` of `(x, yⁱ)`, in the
    whitened coordinates `Z_{B_i}` (`S = G Z Gᵀ`, nominal `Z = I`). One interface for the
    solver (`marginal_mmse`): the projection onto one block's set (projected gradient),
    its log-barrier and the barrier's gradient (barrier path), the interior test, the
    outward widening and the centre. Subclasses hold one value per sensor after
    `broadcast(p, dtype)`."""

    @abc.abstractmethod
    def valid(self) -> Bool[Array, ""]:
        """Traced range check; concrete values are checked when the set is built."""

    @abc.abstractmethod
    def broadcast(self, p: int, dtype) -> AbstractMarginalSet:
        """The set with one value per sensor (`p` sensors) in `dtype`."""

    @abc.abstractmethod
    def project(self, block: Float[Array, "b b"], i: int) -> Float[Array, "b b"]:
        """Euclidean projection of the symmetric `block` onto sensor `i`'s set (a spectral map)."""

    @abc.abstractmethod
    def barrier(self, block: Float[Array, "b b"], i: int) -> Float[Array, ""]:
        """Log-barrier of sensor `i`'s set at `block` (`−∞` outside)."""

    @abc.abstractmethod
    def barrier_grad(self, block: Float[Array, "b b"], i: int) -> Float[Array, "b b"]:
        """Gradient of `barrier` with respect to the (symmetric) `block`."""

    @abc.abstractmethod
    def barrier_size(self, n: int, dims: tuple[int, ...]) -> float:
        """Self-concordance parameter `ν` of the sum of the blocks' barriers."""

    @abc.abstractmethod
    def interior(self) -> Bool[Array, ""]:
        """Whether the intersection of the sets has a nonempty interior."""

    @abc.abstractmethod
    def widen(self) -> AbstractMarginalSet:
        """The set with its radii shifted outwards by `_WIDEN` (derivatives for sets
        without interior)."""

    @abc.abstractmethod
    def centre(self, dim: int, dtype) -> Float[Array, "dim dim"]:
        """A point of the intersection, strictly inside when it has an interior."""


class MarginalMoment(AbstractMarginalSet):
    """Per-sensor moment sets `γ₁ᵢ Σ_i ⪯ S_{B_i} ⪯ γ₂ᵢ Σ_i` (Chen et al. 2025, eq. 2 with
    zero mean ambiguity), `0 < γ₁ ≤ 1 ≤ γ₂`. Scalars or one value per sensor.
    The authors' code (`MDRO.m`) uses `γ₁ = 1 − g`, `γ₂ = 1 + g`.

    Whitened, `γ₁ᵢ I ⪯ Z_{B_i} ⪯ γ₂ᵢ I`: projection clips the eigenvalues to
    `[γ₁ᵢ, γ₂ᵢ]`; barrier `log det(Z_B − γ₁ᵢ I) + log det(γ₂ᵢ I − Z_B)`."""

    gamma1: Float[Array, "*p"]
    gamma2: Float[Array, "*p"]

    def __init__(self, gamma1: Float[ArrayLike, "*p"], gamma2: Float[ArrayLike, "*p"]):
        self.gamma1 = _per_sensor("gamma1", gamma1, lower=0.0, upper=1.0, lower_open=True)
        self.gamma2 = _per_sensor("gamma2", gamma2, lower=1.0, upper=np.inf)

    def valid(self) -> Bool[Array, ""]:
        """Traced range check (`0 < γ₁ ≤ 1 ≤ γ₂ < ∞`); concrete values are checked eagerly."""
        return in_range(self.gamma1, 0.0, 1.0, lower_open=True) & in_range(self.gamma2, 1.0)

    def broadcast(self, p, dtype):
        return _replace(self, gamma1=_broadcast("gamma1", self.gamma1, p, dtype), gamma2=_broadcast("gamma2", self.gamma2, p, dtype))

    def project(self, block, i):
        return _spectral(block, lambda lam: jnp.clip(lam, self.gamma1[i], self.gamma2[i]))

    def barrier(self, block, i):
        eye = jnp.eye(block.shape[-1], dtype=block.dtype)
        return linalg.psd_logdet(block - self.gamma1[i] * eye) + linalg.psd_logdet(self.gamma2[i] * eye - block)

    def barrier_grad(self, block, i):
        eye = jnp.eye(block.shape[-1], dtype=block.dtype)
        return linalg.psd_inv(block - self.gamma1[i] * eye) - linalg.psd_inv(self.gamma2[i] * eye - block)

    def barrier_size(self, n, dims):
        return 2.0 * sum(n + d for d in dims)

    def interior(self):
        return jnp.all(self.gamma1 < self.gamma2) & (jnp.max(self.gamma1) < jnp.min(self.gamma2))

    def widen(self):
        return _replace(self, gamma1=jnp.maximum(self.gamma1 - _WIDEN, 0.5 * self.gamma1), gamma2=self.gamma2 + _WIDEN)

    def centre(self, dim, dtype):
        return 0.5 * (jnp.max(self.gamma1) + jnp.min(self.gamma2)) * jnp.eye(dim, dtype=dtype)


class MarginalKL(AbstractMarginalSet):
    """Per-sensor KL balls `KL(N(0, S_{B_i}) ‖ N(0, Σ_i)) =
    ½[Tr(Σ_i⁻¹S_{B_i}) − log det(Σ_i⁻¹S_{B_i}) − d_i] ≤ cᵢ` of radii `radius = c ≥ 0`
    (scalar or per sensor; `c=` is a deprecated alias of `radius`).
    Note: the authors' code (`MDRO.m`) bounds twice this quantity (no ½) by its `c`,
    so their `c` is `2 · radius` here.

    Whitened, `Tr Z_B − log det Z_B − d_i ≤ 2cᵢ`: projection maps the spectrum with one
    multiplier found by bisection (`_kl_map`); barrier `log(2cᵢ − Tr Z_B + log det Z_B + d_i)`."""

    radius: Float[Array, "*p"]

    def __init__(self, radius: Float[ArrayLike, "*p"] = None, *, c: Float[ArrayLike, "*p"] = None):
        radius = renamed("c", c, "radius", radius, "MarginalKL")
        self.radius = _per_sensor("radius", radius, lower=0.0, upper=np.inf)

    c = renamed_attribute("c", "radius")

    def valid(self) -> Bool[Array, ""]:
        """Traced range check (`0 ≤ radius < ∞`); concrete values are checked eagerly."""
        return in_range(self.radius, 0.0)

    def broadcast(self, p, dtype):
        return _replace(self, radius=_broadcast("radius", self.radius, p, dtype))

    def project(self, block, i):
        return _spectral(block, lambda lam: _kl_map(lam, 2.0 * self.radius[i]))

    def _slack(self, block, i):
        return 2.0 * self.radius[i] - (jnp.trace(block) - linalg.psd_logdet(block) - block.shape[-1])

    def barrier(self, block, i):
        return jnp.log(self._slack(block, i))

    def barrier_grad(self, block, i):
        eye = jnp.eye(block.shape[-1], dtype=block.dtype)
        return (linalg.psd_inv(block) - eye) / self._slack(block, i)

    def barrier_size(self, n, dims):
        return float(len(dims))

    def interior(self):
        return jnp.all(self.radius > 0)

    def widen(self):
        return _replace(self, radius=self.radius + _WIDEN)

    def centre(self, dim, dtype):
        return jnp.eye(dim, dtype=dtype)


def _replace(module: eqx.Module, **fields) -> eqx.Module:
    """`module` with `fields` replaced, without running `__init__` (its eager checks would
    see tracers or intermediate values)."""
    names = tuple(fields)
    return eqx.tree_at(lambda m: tuple(getattr(m, k) for k in names), module, tuple(fields.values()))


def _broadcast(name, x, p, dtype):
    x = jnp.asarray(x).astype(dtype)
    if x.ndim == 1 and x.shape[0] != p:
        raise ValueError(f"{name} has {x.shape[0]} values but there are {p} sensors (dims has length {p})")
    return jnp.broadcast_to(x, (p,))


class MarginalWorstCase(eqx.Module):
    """Solution of the marginal DR-MMSE problem (Chen et al. 2025, eq. 16 and eq. 32).

    - `cov`: worst-case joint covariance `S*` of `(x, y¹, …, yᵖ)`;
    - `gain`: `K* = S*_xy S*_yy⁻¹`; `posterior_cov`: `S*/S*_yy = S*_xx − K* S*_yx`;
    - `value`: `Tr(S*/S*_yy)`;
    - `polished`: the barrier path was used and is certified: its point is strictly
      feasible and its optimality gap bound (from the Newton decrement of the linearized
      barrier problem, `_barrier_gap`) is at most `2νμf₀`, twice the barrier's own
      accuracy (`ν` the barrier size, `μ` its final weight, `f₀ ≤ value` the nominal
      value; ~1e-7 relative in float64);
    - `iterations`, `residual`: projected-gradient iterations and relative size of its
      last step (`inf` if its line search failed; 0 and 0 when the set has an interior
      and the barrier path is used);
    - `converged`: `polished` when the set has an interior, else the projected gradient
      reached `rtol`; `False` when a traced radius is out of range (`set.valid()`).
    """

    cov: Float[Array, "d d"]
    gain: Float[Array, "n m"]
    value: Float[Array, ""]
    posterior_cov: Float[Array, "n n"]
    iterations: Int[Array, ""]
    converged: Bool[Array, ""]
    residual: Float[Array, ""]
    polished: Bool[Array, ""]


# ------------------------------------------------------------------------- helpers


def _blocks(n: int, dims: tuple[int, ...]) -> list[np.ndarray]:
    out, start = [], n
    for d in dims:
        out.append(np.concatenate([np.arange(n), np.arange(start, start + d)]))
        start += d
    return out


def _whitening(cov, n, dims):
    """Lower block-triangular `G` with `G_B G_Bᵀ = Σ_B` on each block `B = (x, yⁱ)`."""
    cov = linalg.symmetrize(cov)
    lp = linalg.cholesky(cov[:n, :n])
    rows = [jnp.concatenate([lp, jnp.zeros((n, sum(dims)), cov.dtype)], axis=1)]
    start = n
    for d in dims:
        sl = slice(start, start + d)
        a = solve_triangular(lp, cov[:n, sl], lower=True).T  # Σ_{yx} L_P⁻ᵀ
        schur = linalg.symmetrize(cov[sl, sl] - a @ a.T)
        before = jnp.zeros((d, start - n), cov.dtype)
        after = jnp.zeros((d, n + sum(dims) - start - d), cov.dtype)
        rows.append(jnp.concatenate([a, before, linalg.cholesky(schur), after], axis=1))
        start += d
    return jnp.concatenate(rows, axis=0)


def _objective(g, n):
    """`f(Z) = Tr(S/S_yy)`, `S = G Z Gᵀ`, and `∇f = Gᵀ[I, −K]ᵀ[I, −K]G` (Danskin)."""

    def fg(z):
        s = linalg.symmetrize(g @ z @ g.T)
        k = linalg.psd_solve_fwd(s[n:, n:], s[n:, :n]).T
        value = jnp.trace(s[:n, :n]) - jnp.sum(k * s[:n, n:])
        e = jnp.concatenate([jnp.eye(n, dtype=z.dtype), -k], axis=1) @ g
        return value, linalg.symmetrize(e.T @ e)

    return fg


def _spectral(block, fn):
    lam, vec = jnp.linalg.eigh(linalg.symmetrize(block))
    return linalg.symmetrize((vec * fn(lam)) @ vec.T)


def _kl_map(lam, two_c):
    """Projection of the spectrum `lam` onto `Σ(λ − 1 − log λ) ≤ two_c` (§B.3):
    `λ(ν) = ½((μ − ν) + √((μ − ν)² + 4ν))`, `ν ≥ 0` by bisection."""
    dtype = lam.dtype
    pos = jnp.all(lam > 0)
    g0 = jnp.sum(jnp.where(lam > 0, lam - 1.0 - jnp.log(jnp.where(lam > 0, lam, 1.0)), jnp.inf))
    feasible = pos & (g0 <= two_c)

    def lam_of(nu):
        a = lam - nu
        return 0.5 * (a + jnp.sqrt(a * a + 4.0 * nu))

    def g_of(nu):
        x = lam_of(nu)
        return jnp.sum(x - 1.0 - jnp.log(x))

    hi0 = jnp.maximum(jnp.max(jnp.abs(lam)), jnp.asarray(1.0, dtype))

    def grow_cond(c):
        hi, k = c
        return (g_of(hi) > two_c) & (k < 200)

    hi, _ = lax.while_loop(grow_cond, lambda c: (4.0 * c[0], c[1] + 1), (hi0, 0))

    def bisect(_, c):
        lo, hi = c
        mid = 0.5 * (lo + hi)
        above = g_of(mid) > two_c
        return jnp.where(above, mid, lo), jnp.where(above, hi, mid)

    _, hi = lax.fori_loop(0, _BISECT_ITER, bisect, (jnp.zeros((), dtype), hi))
    out = lam_of(hi)
    out = jnp.where(two_c > 0, out, jnp.ones_like(lam))
    return jnp.where(feasible, lam, out)


def _projection(set_, blocks, eps):
    """Dykstra projection onto `{Z ⪰ εI} ∩ ⋂ᵢ Cᵢ` (`Cᵢ`: sensor `i`'s set on its block)."""
    n_sets = len(blocks) + 1

    def project_j(j, y):
        if j == 0:
            return _spectral(y, lambda lam: jnp.maximum(lam, eps))
        idx = blocks[j - 1]
        return y.at[np.ix_(idx, idx)].set(set_.project(y[np.ix_(idx, idx)], j - 1))

    def proj(y0):
        def cond(c):
            _, _, k, done = c
            return (~done) & (k < _DYKSTRA_MAX_ITER)

        def body(c):
            x, incs, k, _ = c
            x_old = x
            new_incs = []
            for j in range(n_sets):
                y = x + incs[j]
                x = project_j(j, y)
                new_incs.append(y - x)
            change = jnp.sqrt(jnp.sum((x - x_old) ** 2))
            done = change <= 1e-14 * (1.0 + jnp.sqrt(jnp.sum(x * x)))
            return x, tuple(new_incs), k + 1, done

        incs = tuple(jnp.zeros_like(y0) for _ in range(n_sets))
        x, _, _, _ = lax.while_loop(cond, body, (y0, incs, 0, jnp.zeros((), bool)))
        return linalg.symmetrize(x)

    return proj


def _projected_gradient(fg, proj, z0, rtol, max_iter):
    """Monotone projected gradient ascent with backtracking (§B.2 step 3) from the
    feasible `z0`."""
    dtype = z0.dtype

    def cond(c):
        return (~c[3]) & (c[2] < max_iter)

    def body(c):
        z, eta, k, _, _ = c
        value, grad = fg(z)

        def bt_cond(b):
            _, _, ok, j = b
            return (~ok) & (j < _BACKTRACK_MAX)

        def bt_body(b):
            eta, _, _, j = b
            zt = proj(z + eta * grad)
            dz = zt - z
            ok = fg(zt)[0] >= value + jnp.sum(grad * dz) - jnp.sum(dz * dz) / (2.0 * eta)
            return jnp.where(ok, eta, 0.5 * eta), zt, ok, j + 1

        eta, zt, ok, _ = lax.while_loop(bt_cond, bt_body, (eta, z, jnp.zeros((), bool), 0))
        zt = jnp.where(ok, zt, z)
        # A line search that finds no ascent ends the loop unconverged (residual `inf`).
        res = jnp.where(ok, jnp.sqrt(jnp.sum((zt - z) ** 2)) / jnp.sqrt(jnp.sum(zt * zt)), jnp.inf)
        done = (res <= rtol) | ~ok
        return zt, 1.5 * eta, k + 1, done, res

    grad_scale = jnp.sqrt(jnp.sum(fg(z0)[1] ** 2))
    eta0 = 1.0 / jnp.maximum(grad_scale, jnp.finfo(dtype).tiny)
    init = (z0, eta0, jnp.zeros((), int), jnp.zeros((), bool), jnp.ones((), dtype))
    z, _, k, _, res = lax.while_loop(cond, body, init)
    return z, k, res


# ----------------------------------------------------------------- barrier polish


def _barrier_fn(n, dims, blocks, tri):
    dim = n + sum(dims)

    pos = np.zeros((dim, dim), dtype=np.int32)
    pos[tri] = np.arange(len(tri[0]))
    pos = np.maximum(pos, pos.T)  # position of (i, j) in the upper-triangle vector

    def unvec(v):
        return v[pos]  # a gather: transposes (reverse mode) without unique-index scatters

    def F(v, g, set_, mu):
        z = unvec(v)
        fg = _objective(g, n)
        f0 = fg(jnp.eye(dim, dtype=v.dtype))[0]
        bar = linalg.psd_logdet(z)
        for i, idx in enumerate(blocks):
            bar = bar + set_.barrier(z[np.ix_(idx, idx)], i)
        return fg(z)[0] / f0 + mu * bar

    weights = np.where(tri[0] == tri[1], 1.0, 2.0)

    def dF(v, g, set_, mu):
        """Closed-form gradient of `F` in the upper-triangle coordinates `v` (inverses by
        `linalg.psd_inv`, whose derivative −X dA X makes the Hessian by jacfwd batched products)."""
        z = unvec(v)
        fg = _objective(g, n)
        f0 = fg(jnp.eye(dim, dtype=v.dtype))[0]
        gz = fg(z)[1] / f0 + mu * linalg.psd_inv(z)
        for i, idx in enumerate(blocks):
            gz = gz.at[np.ix_(idx, idx)].add(mu * set_.barrier_grad(z[np.ix_(idx, idx)], i))
        return linalg.symmetrize(gz)[tri] * jnp.asarray(weights, v.dtype)

    return F, dF, unvec


def _barrier_path(F, dF, v, args, mu_final, stages):
    """Path following: damped Newton ascent (`newton` on `−F`, whose gradient is `−dF`)
    on `F(·, *args, μ)` for `μ = _MU0 · 10⁻ⁱ`, `i = 0, …, stages − 1`
    (`_NEWTON_PER_STAGE` steps each), then `_NEWTON_FINAL` steps at `μ = mu_final`. There
    is no step-size stopping test: near the boundary the barrier Hessian is large
    (`~μ/slack²`), so a small step does not mean a small gradient; a stage ends early only
    when its line search finds no ascent (at round-off)."""

    def stage(i, v):
        mu = jnp.maximum(_MU0 * jnp.asarray(10.0, v.dtype) ** (-i.astype(v.dtype)), mu_final)
        max_iter = jnp.where(i < stages, _NEWTON_PER_STAGE, _NEWTON_FINAL)
        return newton(lambda u: -dF(u, *args, mu), v, max_iter, objective=lambda u: -F(u, *args, mu)).x

    return lax.fori_loop(0, stages + 1, stage, v)


def _barrier_gap(dF, v, args, mu, n, dims):
    """Bound on `(max f − f(Z))/f₀` at a strictly feasible point `v` of the barrier path.

    By Danskin `f ≤ ⟨∇f(Z), ·⟩` on the set, so the optimum is at most that of the *linear*
    problem `max ⟨∇f(Z), ·⟩`, whose barrier problem `⟨∇f(Z), ·⟩/f₀ + μ b` has at `Z` the
    same gradient `g` as `F` and the Hessian `μ∇²b` of the barrier alone. With the Newton
    decrement `λ² = gᵀ(−μ∇²b)⁻¹g / μ` of that problem (a KKT residual in the barrier's
    local norm), the interior-point bound for a `ν`-self-concordant barrier (Nesterov,
    *Lectures on Convex Optimization*, Thm. 5.3.10) gives, for `λ < 1`,
    `max f − f(Z) ≤ μ f₀ (ν + (λ + √ν) λ / (1 − λ))`, `ν = d + 2Σ|Bᵢ|` (moment sets) or
    `d + p` (one term per KL ball). Returns that bound divided by `f₀` (`inf` if `λ ≥ 1`)
    and `νμ`, the part the barrier itself leaves."""
    dim = n + sum(dims)
    nu = dim + args[1].barrier_size(n, dims)
    grad = dF(v, *args, mu)
    hess_barrier = jax.jacfwd(dF)(v, *args, mu) - jax.jacfwd(dF)(v, *args, jnp.zeros_like(mu))
    lam = jnp.sqrt(jnp.maximum(-jnp.sum(grad * jnp.linalg.solve(hess_barrier, grad)) / mu, 0.0))
    bound = mu * (nu + (lam + np.sqrt(nu)) * lam / (1.0 - lam))
    return jnp.where(lam < 1, bound, jnp.inf), nu * mu


def _mu_schedule(dtype):
    # Final barrier weight: the value is within ν·μ (relative) of the SDP optimum, and the
    # barrier Hessian's condition number grows like 1/μ² (IFT accuracy).
    mu_final = 1e-8 if jnp.finfo(dtype).bits >= 64 else 1e-3
    stages = max(1, math.ceil(math.log10(_MU0 / mu_final)))
    return mu_final, stages


def _make_zstar(n, dims, rtol, max_iter):
    blocks = _blocks(n, dims)
    dim = n + sum(dims)
    tri = np.triu_indices(dim)
    F, dF, unvec = _barrier_fn(n, dims, blocks, tri)

    def forward(g, set_):
        dtype = g.dtype
        fg = _objective(g, n)
        eps = jnp.asarray(1e-9, dtype) if dtype == jnp.float64 else jnp.asarray(1e-5, dtype)
        proj = _projection(set_, blocks, eps)
        interior = set_.interior()
        centre = set_.centre(dim, dtype)
        # With an interior the barrier path (from its centre) is the solver: the projected
        # gradient runs only for sets without interior (lax.cond skips it otherwise;
        # under vmap both branches run).
        z_pg, iters, res = lax.cond(
            interior,
            lambda: (centre, jnp.zeros((), int), jnp.zeros((), dtype)),
            lambda: _projected_gradient(fg, proj, centre, rtol, max_iter),
        )
        bset = jax.tree.map(lambda p, w: jnp.where(interior, p, w), set_, set_.widen())
        mu_final, stages = _mu_schedule(dtype)
        alpha = jnp.asarray(1e-2, dtype)
        z0 = (1.0 - alpha) * z_pg + alpha * bset.centre(dim, dtype)  # = centre if interior
        v = z0[tri]
        mu = jnp.asarray(mu_final, dtype)
        v = _barrier_path(F, dF, v, (g, bset), mu, stages)
        # Certificate: a strictly feasible point whose gap bound is at most twice the
        # barrier's own `νμf₀` (relative to the nominal value `f₀ ≤ max f`).
        feasible = jnp.all(jnp.isfinite(v)) & jnp.isfinite(F(v, g, bset, mu))
        gap, barrier = _barrier_gap(dF, v, (g, bset), mu, n, dims)
        polished = interior & feasible & (gap <= 2.0 * barrier)
        z = jnp.where(polished, unvec(v), z_pg)
        converged = jnp.where(interior, polished, res <= rtol)
        return z, v, bset, mu, iters, res, polished, converged

    def zstar(g, set_):
        """Worst case `Z*` (the barrier solution when polished, else the projected-gradient
        point) with the derivatives of the barrier solution: the implicit function
        theorem on `∇F = 0` (`implicit_root`), the solve itself under `stop_gradient`."""
        with linalg.lapack_only():
            z, v, bset, mu, iters, res, polished, converged = forward(*jax.tree.map(lax.stop_gradient, (g, set_)))
            # The widening is a shift: the barrier's radii have the tangents of `set_`'s.
            bs = jax.tree.map(lambda p, b: p + lax.stop_gradient(b - p), set_, bset)
            v = implicit_root(lambda u: dF(u, g, bs, mu), lambda _: (v, ()), v)[0]
        z = jnp.where(polished, unvec(v), unvec(v) + lax.stop_gradient(z - unvec(v)))
        return z, (iters, res, polished, converged)

    return zstar


# ------------------------------------------------------------------------- solver


def marginal_mmse(
    cov: Float[ArrayLike, "d d"],
    n: int,
    dims: tuple[int, ...],
    set: AbstractMarginalSet,  # noqa: A002  (name fixed by the API)
    *,
    rtol: float | None = None,
    max_iter: int = 500,
) -> MarginalWorstCase:
    """Worst-case covariance of the marginal DR-MMSE problem (Chen et al. 2025, eq. 16):

    `max Tr(S_xx − S_xy S_yy⁻¹ S_yx)` over `S ⪰ 0` with each marginal block `S_{B_i}`
    of `(x, yⁱ)` in `set` around the nominal block `Σ_i` of `cov`.

    `cov`: nominal joint covariance of `(x, y¹, …, yᵖ)` (`d = n + Σ dims`), positive
    definite on each block `B_i`; its cross-sensor blocks are ignored (free for the
    adversary). `n`: state dimension; `dims`: sensor dimensions (static). `rtol`:
    relative step tolerance of the projected-gradient phase (default `eps^(2/3)`);
    `max_iter`: its cap. The estimator is `x̂ = μ_x + K*(y − μ_y)`, `V = S*/S*_yy`
    (eq. 32). Differentiable (forward and reverse) w.r.t. `cov` and the radii; see the
    module docstring for the method and the degenerate cases.
    """
    if not isinstance(set, AbstractMarginalSet):
        raise ValueError(f"set must be a marginal set (jdrkf.sets.MarginalMoment, MarginalKL), got {type(set).__name__}")
    cov = as_float_array("cov", cov, (2,))
    check_covariance("cov", cov)
    if not isinstance(dims, (tuple, list)) or len(dims) == 0 or not all(isinstance(d, (int, np.integer)) and d >= 1 for d in dims):
        raise ValueError(f"dims must be a non-empty tuple of positive ints (one per sensor), got {dims!r}")
    dims = tuple(int(d) for d in dims)
    n = check_positive_int("n", n, " (the state dimension)")
    n = int(n)
    d = n + sum(dims)
    if cov.shape != (d, d):
        raise ValueError(f"cov has shape {tuple(cov.shape)} but expected ({d}, {d}) (n = {n}, dims = {dims})")
    rtol = default_rtol(cov.dtype) if rtol is None else float(rtol)
    sol = _marginal_mmse(cov, set.broadcast(len(dims), cov.dtype), n, dims, rtol, int(max_iter))
    return eqx.tree_at(lambda s: s.converged, sol, sol.converged & set.valid())


@eqx.filter_jit
def _marginal_mmse(cov, set_, n, dims, rtol, max_iter):
    g = _whitening(cov, n, dims)
    zstar = _make_zstar(n, dims, rtol, max_iter)
    z, (iters, res, polished, converged) = zstar(g, set_)
    s = linalg.symmetrize(g @ z @ g.T)
    k = linalg.psd_solve(s[n:, n:], s[n:, :n]).T
    post = linalg.symmetrize(s[:n, :n] - k @ s[n:, :n])
    value = jnp.trace(s[:n, :n]) - jnp.sum(k * s[:n, n:])
    return MarginalWorstCase(s, k, value, post, iters, converged, res, polished)
