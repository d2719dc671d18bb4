"""Covariance intersection (Julier & Uhlmann 1997): fusing estimates with unknown
cross-correlations by the bound `(Σ ω_i P_i⁻¹)⁻¹`, consistent for every correlation (the
worst case over the unknown cross-covariances), with the weights `ω` minimizing its
`log det` or trace (`docs/math/marginal.md`). The CI baseline of Chen et al. (2025); the
filter is `jdrkf.CovarianceIntersection`."""

from __future__ import annotations

from typing import Literal

import equinox as eqx
import jax.numpy as jnp
from jax import lax
from jaxtyping import Array, Float

from .. import linalg
from .._gaussian import Gaussian


def _project_simplex(v: Float[Array, " p"]) -> Float[Array, " p"]:
    """Euclidean projection onto the probability simplex (sort-based)."""
    p = v.shape[0]
    u = jnp.sort(v)[::-1]
    css = jnp.cumsum(u) - 1.0
    ind = jnp.arange(1, p + 1, dtype=v.dtype)
    rho = jnp.sum((u - css / ind > 0).astype(jnp.int32))
    theta = css[rho - 1] / rho.astype(v.dtype)
    return jnp.maximum(v - theta, 0.0)


def _ci_objective(infos, w, criterion):
    """`J(ω)` = log det or Tr of `M(ω)⁻¹`, `M = Σ ω_i P_i⁻¹`, and its gradient."""
    n = infos.shape[-1]
    info = linalg.symmetrize(jnp.einsum("i,ijk->jk", w, infos))
    chol = linalg.cholesky(info)
    cov = linalg.symmetrize(linalg.cho_solve(chol, jnp.eye(n, dtype=info.dtype)))
    if criterion == "det":
        val = -2.0 * jnp.sum(jnp.log(jnp.diagonal(chol)))
        grad = -jnp.einsum("jk,ijk->i", cov, infos)  # −Tr(M⁻¹ Y_i)
    else:
        val = jnp.trace(cov)
        grad = -jnp.einsum("jk,ijk->i", cov @ cov, infos)  # −Tr(M⁻¹ Y_i M⁻¹)
    val = jnp.where(jnp.all(jnp.isfinite(chol)), val, jnp.inf)
    return val, grad, cov


class CIWeights(eqx.Module):
    """Result of `ci_weights`: simplex weights, fused covariance `(Σ ω_i P_i⁻¹)⁻¹`, objective
    value, Frank–Wolfe gap (an upper bound on `J(ω) − J*`), iterations and convergence flag."""

    weights: Float[Array, " p"]
    cov: Float[Array, "n n"]
    value: Float[Array, ""]
    gap: Float[Array, ""]
    iterations: Array
    converged: Array


def ci_weights(
    infos: Float[Array, "p n n"],
    criterion: Literal["det", "trace"] = "det",
    *,
    rtol: float | None = None,
    max_iter: int = 200,
) -> CIWeights:
    """Covariance-intersection weights (`docs/math/marginal.md`): `ω` in the simplex minimizing
    `log det` (`"det"`) or `Tr` (`"trace"`) of `(Σ ω_i Y_i)⁻¹` for the
    information matrices `Y_i = P_i⁻¹` (both objectives are convex in `ω`).

    Projected gradient with backtracking (step halved until the quadratic upper bound holds,
    doubled after each accepted step), from the uniform weights; stops when the Frank–Wolfe
    gap `gᵀω − min_i g_i ≤ rtol (1 + |J|)` (default `rtol = √eps`) or after `max_iter`.
    `ω` is not differentiated (its inputs are `stop_gradient`-ed); derivatives of the fused
    estimate are those at fixed `ω`.
    """
    infos = lax.stop_gradient(infos)
    p = infos.shape[0]
    dtype = infos.dtype
    tol = jnp.asarray(jnp.finfo(dtype).eps ** 0.5 if rtol is None else rtol, dtype)
    eps = jnp.asarray(jnp.finfo(dtype).eps, dtype)
    w0 = jnp.full((p,), 1.0 / p, dtype)
    val0, g0, cov0 = _ci_objective(infos, w0, criterion)

    def gap_of(w, g):
        return jnp.dot(g, w) - jnp.min(g)

    def outer_cond(c):
        w, val, g, cov, eta, k = c
        return (gap_of(w, g) > tol * (1.0 + jnp.abs(val))) & (k < max_iter)

    def outer_body(c):
        w, val, g, cov, eta, k = c

        def try_step(eta):
            wn = _project_simplex(w - eta * g)
            vn, gn, covn = _ci_objective(infos, wn, criterion)
            d = wn - w
            ok = vn <= val + jnp.dot(g, d) + jnp.dot(d, d) / (2.0 * eta) + 10.0 * eps * jnp.abs(val)
            return wn, vn, gn, covn, ok

        def inner_cond(ic):
            *_, ok, j = ic
            return ~ok & (j < 60)

        def inner_body(ic):
            eta = ic[0]
            eta = 0.5 * eta
            wn, vn, gn, covn, ok = try_step(eta)
            return eta, wn, vn, gn, covn, ok, ic[-1] + 1

        wn, vn, gn, covn, ok = try_step(eta)
        eta, wn, vn, gn, covn, ok, _ = lax.while_loop(inner_cond, inner_body, (eta, wn, vn, gn, covn, ok, 0))
        # If backtracking failed (round-off at the optimum), keep the current point.
        w, val, g, cov = (jnp.where(ok, a, b) for a, b in ((wn, w), (vn, val), (gn, g), (covn, cov)))
        return w, val, g, cov, 2.0 * eta, k + 1

    spread = jnp.max(g0) - jnp.min(g0)
    eta0 = 1.0 / jnp.maximum(spread, jnp.finfo(dtype).tiny ** 0.5)
    w, val, g, cov, _, k = lax.while_loop(outer_cond, outer_body, (w0, val0, g0, cov0, eta0, jnp.asarray(0)))
    gap = gap_of(w, g)
    converged = (gap <= tol * (1.0 + jnp.abs(val))) & jnp.isfinite(val)
    return CIWeights(weights=w, cov=cov, value=val, gap=gap, iterations=k, converged=converged)


def covariance_intersection(
    means: Float[Array, "p n"],
    covs: Float[Array, "p n n"],
    criterion: Literal["det", "trace"] = "det",
    *,
    rtol: float | None = None,
    max_iter: int = 200,
) -> tuple[Gaussian, CIWeights]:
    """Fuse `p` estimates `(x̂_i, P_i)` with unknown cross-correlations by CI:
    `P_CI = (Σ ω_i P_i⁻¹)⁻¹`, `x̂_CI = P_CI Σ ω_i P_i⁻¹ x̂_i`, `ω` from `ci_weights`."""
    n = covs.shape[-1]
    eye = jnp.eye(n, dtype=covs.dtype)
    chols = [linalg.cholesky(linalg.symmetrize(covs[i])) for i in range(covs.shape[0])]
    infos = jnp.stack([linalg.symmetrize(linalg.cho_solve(c, eye)) for c in chols])
    info_means = jnp.stack([linalg.cho_solve(c, means[i]) for i, c in enumerate(chols)])
    sol = ci_weights(infos, criterion, rtol=rtol, max_iter=max_iter)
    info = linalg.symmetrize(jnp.einsum("i,ijk->jk", sol.weights, infos))
    mean = linalg.psd_solve(info, sol.weights @ info_means)
    return Gaussian(mean, sol.cov), sol
