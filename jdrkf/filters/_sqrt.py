"""Square-root (Cholesky-factor) form of the covariance recursion.

The filters carry a lower-triangular factor `S` of each covariance `P = S Sᵀ` and update
it with orthogonal transformations only (QR triangularization, `jdrkf.linalg.tria`), so
`P` stays positive semidefinite by construction and its condition number enters the
round-off as `√κ(P)` (Kaminski, Bryson & Schmidt, "Discrete square root filtering: a
survey of current techniques", IEEE TAC 1971). Selected with `square_root=True` on
`jdrkf.KalmanFilter`, `jdrkf.DRKF`, `jdrkf.HuberKF` and `jdrkf.WassersteinKF`.
"""

from __future__ import annotations

import jax.numpy as jnp
from jax.scipy.linalg import solve_triangular
from jaxtyping import Array, ArrayLike, Float, Int

from .. import linalg
from .._gaussian import Gaussian
from .._models import LinearModel
from ..sets._base import AbstractAmbiguitySet
from ..sets._moment import Moment


def initial(prior: Gaussian) -> tuple[Float[Array, " n"], Float[Array, "n n"]]:
    """Square-root filter state `(m₀, S₀)` of the prior, `S₀ = psd_factor(P₀)` (a singular
    `P₀`, e.g. a known initial state, is allowed)."""
    return prior.mean, linalg.psd_factor(prior.cov)


def predict_sqrt(
    model: LinearModel, mean: Float[Array, " n"], chol: Float[Array, "n n"], t: Int[ArrayLike, ""], u: Float[Array, " p"] | None = None
) -> tuple[Float[Array, " n"], Float[Array, "n n"]]:
    """Time update in square-root form: `m⁻ = F m + B u + G μ_w` and
    `S⁻ = tria([F S, G S_Q])` with `S_Q S_Qᵀ = Q`, so that
    `S⁻S⁻ᵀ = F S Sᵀ Fᵀ + G Q Gᵀ` (the covariance `P⁻ = F P Fᵀ + G Q Gᵀ`)."""
    mdl = model.at(t)
    mean = mdl.F @ mean + mdl.G @ mdl.process_mean
    if mdl.B is not None:
        mean = mean + mdl.B @ u
    return mean, linalg.tria(jnp.concatenate([mdl.F @ chol, mdl.G @ linalg.psd_factor(mdl.Q)], axis=1))


def array_update(chol_prior: Float[Array, "n n"], h: Float[Array, "m n"], chol_noise: Float[Array, "m m"]) -> Float[Array, "d d"]:
    """Array (QR) form of the measurement update: the lower-triangular factor of the
    covariance of `(y, x)` under prior factor `S_x` and noise factor `S_v`,

        tria([[S_v, H S_x], [0, S_x]]) = [[L_s, 0], [L_k, L]],

    with `L_s L_sᵀ = H Σx Hᵀ + Σv = S` (innovation covariance), `L_k = Σx Hᵀ L_s⁻ᵀ` (gain
    `K = L_k L_s⁻¹`) and `L Lᵀ = Σx − K S Kᵀ` (posterior covariance). Split with `split`."""
    n, m = chol_prior.shape[0], h.shape[0]
    pre = jnp.block([[chol_noise, h @ chol_prior], [jnp.zeros((n, m), chol_prior.dtype), chol_prior]])
    return linalg.tria(pre)


def split(low: Float[Array, "d d"], m: int):
    """`(L_s, L_k, L, failed)` of a `(y, x)` factor (`array_update`); `failed` is `True`
    when the innovation covariance `L_s L_sᵀ` is not positive definite (a zero pivot) or
    its factor is not finite."""
    chol_s, cross, chol_post = low[:m, :m], low[m:, :m], low[m:, m:]
    failed = ~(jnp.all(jnp.isfinite(chol_s)) & jnp.all(jnp.diagonal(chol_s) > 0))
    return chol_s, cross, chol_post, failed


def gain(chol_s: Float[Array, "m m"], cross: Float[Array, "n m"]) -> Float[Array, "n m"]:
    """Kalman gain `K = L_k L_s⁻¹` (a triangular solve)."""
    return solve_triangular(chol_s, cross.T, lower=True, trans="T").T


def worst_case_factor(ambiguity_set: AbstractAmbiguitySet | None, nominal_factor: Float[Array, "d d"],
                      worst_cov: Float[Array, "d d"]) -> Float[Array, "d d"]:
    """Factor of a worst-case covariance: `√θ₂ Ŝ` for a moment set, whose worst case is
    `θ₂ Σ̂` (Wang & Ye 2022, Theorem 5), and `Ŝ` for none (the nominal), with no
    factorization; otherwise the set's solver returns the matrix `worst_cov`, which is
    factored right after the solve (`jdrkf.linalg.psd_factor`)."""
    if ambiguity_set is None:
        return nominal_factor
    if isinstance(ambiguity_set, Moment):
        return jnp.sqrt(ambiguity_set.theta2.astype(nominal_factor.dtype)) * nominal_factor
    return linalg.psd_factor(worst_cov)


def outer(chol: Float[Array, "n n"]) -> Float[Array, "n n"]:
    """The covariance `S Sᵀ` of a factor."""
    return linalg.symmetrize(chol @ chol.T)

