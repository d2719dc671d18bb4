"""Divergence-ball robust Kalman filters: Zorzi's τ-divergence filter (τ = 0: the KL
filter of Levy & Nikoukhah) and the risk-sensitive Kalman filter.

Both inflate the one-step prediction covariance before a standard (Joseph-form)
Kalman update. The τ-filter picks the inflation θ_k at every step so that the
least-favourable model lies on the boundary of a divergence ball of radius `c`;
the risk-sensitive filter uses a fixed θ.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float

from .. import linalg
from .._root import bracketed_newton
from .._validation import as_float_array, in_range, is_concrete, renamed, renamed_attribute
from ._base import DEFAULT_OUTPUTS, RESULTS, AbstractFilter, StepOutput
from ._kalman import predict, update
from ._steps import step_result



# --- scalar functions ------------------------------------------------------------------------
#
# With w = 1 − τ, u(s) = 1 − w s and Λ(x) = −log(1 − x)/x (Λ(0) = 1):
#   g_τ(s) = u^(−1/w) = exp(s Λ(w s))                   (τ = 1: e^s; τ = 0: 1/(1 − s))
#   φ_τ(s) = (1 − g_τ(s) (1 − s)) / τ                    (τ = 0: the limit 1/(1−s) − 1 + log(1−s))
#   φ_τ'(s) = s g_τ(s) / u(s)
# The published form of φ_τ (Zorzi 2017) is algebraically the same; this one is
# evaluated without cancellation, and continuously in τ including τ = 0 and τ = 1.

_SERIES_MAX = 0.25  # |s| below this: power series of φ_τ in s (terms ≤ 0.25^k)
_SERIES_TERMS = 30
_ROOT_MAX_ITER = 200


def _log1p_rel(x):
    """`log(1 + x) / x` (1 at x = 0), for x > −1."""
    small = jnp.abs(x) < 1e-3
    xs = jnp.where(small, 0.5, x)
    poly = 1 + x * (-1 / 2 + x * (1 / 3 + x * (-1 / 4 + x * (1 / 5 - x / 6))))
    return jnp.where(small, poly, jnp.log1p(xs) / xs)


def _exprel(x):
    """`(eˣ − 1) / x` (1 at x = 0)."""
    small = jnp.abs(x) < 1e-3
    xs = jnp.where(small, 1.0, x)
    poly = 1 + x * (1 / 2 + x * (1 / 6 + x * (1 / 24 + x * (1 / 120 + x / 720))))
    return jnp.where(small, poly, jnp.expm1(xs) / xs)


def _log_g(s, tau):
    """`log g_τ(s) = −log(1 − (1−τ) s)/(1−τ)`; requires `(1−τ) s < 1`."""
    return s * _log1p_rel(-(1 - tau) * s)


def _phi_prime(s, tau):
    """`φ_τ'(s) = s g_τ(s) / (1 − (1−τ) s)`; requires `(1−τ) s < 1`."""
    return s * jnp.exp(_log_g(s, tau)) / (1 - (1 - tau) * s)


def _phi(s, tau):
    """`φ_τ(s)`, elementwise in `s`; `+inf` at or beyond the pole `s ≥ 1/(1−τ)`.

    Differentiable in `s` and `τ` (every branch is evaluated at safe arguments, so
    no NaN enters values or gradients).
    """
    w = 1 - tau
    # (a) |s| ≤ 1/4: φ_τ = S·exprel(−τS), S = Σ_{k≥2} c_k s^k / k, c_k = Σ_{j=0}^{k-2} w^j.
    # (From log(g (1 − s)) = −τ S; every term is ≥ 0 for s ≥ 0: no cancellation, any τ.)
    # Vectorized over k = 2..K (a k-axis, not an unrolled loop: much faster to compile).
    small = jnp.abs(s) <= _SERIES_MAX
    ss = jnp.where(small, s, 0.0)
    num = _SERIES_TERMS - 1
    powers = jnp.cumprod(jnp.broadcast_to(ss[..., None], ss.shape + (num,)), axis=-1) * ss[..., None]  # s^k
    w_powers = jnp.cumprod(jnp.concatenate([jnp.ones((1,), s.dtype), jnp.broadcast_to(w, (num - 1,))]))
    coef = jnp.cumsum(w_powers) / np.arange(2, _SERIES_TERMS + 1, dtype=s.dtype)  # c_k / k
    total = jnp.sum(powers * coef, axis=-1)
    phi_series = total * _exprel(-tau * total)
    # (b) 1/4 < |s|, s < 1: φ_τ = −(E/τ)·exprel(E) with E = log(g (1 − s)) ≤ 0, where
    #   E/τ = −[r·log1p(τ r)/(τ r) + log(1 − s)] / w,  r = s/(1 − s)   (τ ≤ 1/2: stable as τ → 0)
    #   E/τ = [s Λ(w s) + log(1 − s)] / τ                               (τ > 1/2: stable as τ → 1)
    mid = (~small) & (s < 1)
    sm = jnp.where(mid, s, 0.5)
    low_tau = tau <= 0.5
    w_low = jnp.where(low_tau, w, 1.0)
    tau_high = jnp.where(low_tau, 1.0, tau)
    r = sm / (1 - sm)
    e_low = -(r * _log1p_rel(tau * r) + jnp.log1p(-sm)) / w_low
    e_high = (_log_g(sm, tau) + jnp.log1p(-sm)) / tau_high
    e_over_tau = jnp.where(low_tau, e_low, e_high)
    phi_mid = -e_over_tau * _exprel(tau * e_over_tau)
    # (c) 1 ≤ s < 1/w (only for τ > 0): φ_τ = (1 + g (s − 1)) / τ, no cancellation.
    inside = w * s < 1
    big = (s >= 1) & inside
    sb = jnp.where(big, s, 0.5)
    tau_big = jnp.where(tau > 0, tau, 1.0)
    phi_big = (1 + jnp.exp(_log_g(sb, tau)) * (sb - 1)) / tau_big
    out = jnp.where(small, phi_series, jnp.where(mid, phi_mid, phi_big))
    return jnp.where(small | mid | big, out, jnp.inf)


# --- the least-favourable covariance ---------------------------------------------------------


def _solve_s(r, tau, c):
    """Root `s* > 0` of `h(s) = Σ_i φ_τ(s r_i) − c` (with `max r_i = 1`), by safeguarded
    Newton on a bracket. `h` is increasing and convex; `φ_τ(s) ≥ s²/2` makes
    `sqrt(2c/Σ r_i²)` an upper end with `h ≥ 0`, from which Newton decreases
    monotonically. Steps leaving the bracket are replaced by bisection."""
    w = 1 - tau
    pole = jnp.where(w > 0, 1 / jnp.where(w > 0, w, 1.0), jnp.inf)
    bound = jnp.sqrt(2 * c / jnp.sum(r * r))
    from_bound = bound < pole
    hi0 = jnp.where(from_bound, bound, pole)
    x0 = jnp.where(from_bound, bound, 0.5 * pole)

    def h(x):
        sx = x * r
        return jnp.sum(_phi(sx, tau)) - c, jnp.sum(r * _phi_prime(sx, tau))

    return bracketed_newton(h, x0, 0.0, hi0, _ROOT_MAX_ITER, has_slope=True).x


def _theta_of_eigenvalues(lam, tau, c):
    lam_max = lam[-1]
    positive = lam_max > 0
    lam_max = jnp.where(positive, lam_max, 1.0)
    s = _solve_s(lam / lam_max, tau, c)
    return jnp.where(positive, s / lam_max, 0.0)


def _assemble(lam, vec, theta, tau, p):
    f = lam * jnp.exp(_log_g(theta * lam, tau))
    v = linalg.symmetrize((vec * f) @ vec.T)
    # c = 0 ⇒ θ = 0 ⇒ V = P exactly (no eigen round trip).
    return jnp.where(theta > 0, v, linalg.symmetrize(p))


@jax.custom_jvp
def _robustify(p, tau, c):
    lam, vec = jnp.linalg.eigh(linalg.symmetrize(p))
    theta = _theta_of_eigenvalues(lam, tau, c)
    return theta, _assemble(lam, vec, theta, tau, p)


@_robustify.defjvp
def _robustify_jvp(primals, tangents):
    p, tau, c = primals
    dp, dtau, dc = tangents
    lam, vec = jnp.linalg.eigh(linalg.symmetrize(p))
    theta = _theta_of_eigenvalues(lam, tau, c)
    v = _assemble(lam, vec, theta, tau, p)
    dpt = vec.T @ linalg.symmetrize(dp) @ vec  # dP in the eigenbasis; dλ_i = dpt_ii
    s = theta * lam
    u = 1 - (1 - tau) * s
    g = jnp.exp(_log_g(s, tau))
    one = jnp.ones_like(tau)

    # θ by the implicit function theorem on h = Σ φ_τ(θ λ_i) − c (a symmetric function
    # of the eigenvalues, so dλ_i = (Uᵀ dP U)_ii is valid with repeated eigenvalues).
    phi_p = s * g / u
    _, dphi_dtau = jax.jvp(lambda t: _phi(s, t), (tau,), (one,))
    dh = theta * jnp.sum(phi_p * jnp.diagonal(dpt)) + jnp.sum(dphi_dtau) * dtau - dc
    dh_dtheta = jnp.sum(lam * phi_p)
    ok = dh_dtheta > 0  # False only at c = 0 (θ ∝ √c there: the tangent is set to 0)
    dtheta = jnp.where(ok, -dh / jnp.where(ok, dh_dtheta, 1.0), 0.0)

    # V = f(P) with f(λ) = λ g_τ(θλ). Daleckii–Krein: dV = U (K ∘ (Uᵀ dP U)) Uᵀ with
    # K_ij = f[λ_i, λ_j] = g(λ_i) + λ_j g[λ_i, λ_j]; the divided difference of g is
    #   g[a, b] = g(b) θ Λ(x) exprel(q) / u(b),  x = (1−τ)θ(a−b)/u(b),  q = θ(a−b)Λ(x)/u(b),
    # exact (from g(a)/g(b) = (u(a)/u(b))^(−1/(1−τ))) and free of any division by a − b.
    ub = u[None, :]
    diff = lam[:, None] - lam[None, :]
    lam_x = _log1p_rel(-(1 - tau) * theta * diff / ub)
    gdd = g[None, :] * theta * lam_x / ub * _exprel(theta * diff * lam_x / ub)
    kernel = linalg.symmetrize(g[:, None] + lam[None, :] * gdd)
    _, dlogg_dtau = jax.jvp(lambda t: _log_g(s, t), (tau,), (one,))
    df = lam * lam * g / u * dtheta + lam * g * dlogg_dtau * dtau  # ∂f/∂θ dθ + ∂f/∂τ dτ
    dvt = kernel * dpt + jnp.diag(df)
    dv = linalg.symmetrize(vec @ dvt @ vec.T)
    dv = jnp.where(theta > 0, dv, linalg.symmetrize(dp))
    return (theta, v), (dtheta, dv)


@jax.jit
def robustify_covariance(
    P: Float[ArrayLike, "n n"], tau: Float[ArrayLike, ""], c: Float[ArrayLike, ""]
) -> tuple[Float[Array, ""], Float[Array, "n n"]]:
    r"""Least-favourable covariance of the τ-divergence ball around `N(·, P)`.

    With `P = U diag(p_i) Uᵀ`, returns `(θ, V)` where `θ ≥ 0` solves
    `Σ_i φ_τ(θ p_i) = c` and `V = U diag(p_i g_τ(θ p_i)) Uᵀ` (see `TauKF` for `φ_τ`,
    `g_τ`). For `τ = 0`, `V = (P⁻¹ − θ I)⁻¹` and `½ Σ φ_0(θ p_i) = KL(N(0,V) ‖ N(0,P))`.

    Differentiable in `P`, `tau` and `c`: θ by the implicit function theorem, `V` by the
    Daleckii–Krein formula with closed-form divided differences (safe for repeated
    eigenvalues). `eigh` is used in the forward pass only. At `c = 0` (θ = 0, `V = P`),
    θ ∝ √c is not differentiable in `c`; its tangent there is set to 0.
    """
    p = jnp.asarray(P)
    dtype = p.dtype
    return _robustify(p, jnp.asarray(tau).astype(dtype), jnp.asarray(c).astype(dtype))


# --- filters ---------------------------------------------------------------------------------


def _scalar_param(name: str, value, lower: float, upper: float | None = None):
    arr = as_float_array(name, value, (0,))
    if is_concrete(arr):
        v = float(np.asarray(arr))
        if not math.isfinite(v) or v < lower or (upper is not None and v > upper):
            want = f"in [{lower:g}, {upper:g}]" if upper is not None else f">= {lower:g}"
            raise ValueError(f"{name} must be {want}, got {v:g}")
    return arr


def _with_cov(belief, cov):
    # Replace the covariance without re-running Gaussian's eager checks (NaN-safe).
    return eqx.tree_at(lambda g: g.cov, belief, cov)


class TauKF(AbstractFilter):
    r"""τ-divergence robust Kalman filter (Zorzi 2017); `tau = 0` is the KL-robust
    filter of Levy & Nikoukhah (2013).

    At step `k`, the nominal prediction `x̂_{k|k-1} = F x̂_{k-1|k-1} (+ B u + G μ_w)`,
    `P_k = F Π_{k-1} Fᵀ + G Q Gᵀ` is replaced by the least-favourable law in the
    τ-divergence ball of radius `radius` (`c` in the paper) around it, which keeps the mean and inflates the
    covariance to `V_k`: with `P_k = U diag(p_i) Uᵀ`, `θ_k > 0` solves
    `Σ_i φ_τ(θ_k p_i) = radius` and `V_k = U diag(p_i g_τ(θ_k p_i)) Uᵀ`, where

    | τ | `φ_τ(s)` | `g_τ(s)` | θ range |
    |---|---|---|---|
    | 0 | `1/(1−s) − 1 + log(1−s)` | `1/(1−s)`, i.e. `V = (P⁻¹ − θI)⁻¹` | `(0, 1/p_max)` |
    | (0,1) | `−u^{τ/(τ−1)}/(τ(1−τ)) + u^{1/(τ−1)}/(1−τ) + 1/τ`, `u = 1−(1−τ)s` | `u^{−1/(1−τ)}` | `(0, 1/((1−τ)p_max))` |
    | 1 | `s eˢ − eˢ + 1` | `eˢ` | `(0, ∞)` |

    Then a Kalman update (Joseph form) with prior covariance `V_k`:
    `x̂_{k|k} = x̂_{k|k-1} + V_k Hᵀ(H V_k Hᵀ + R)⁻¹(y_k − H x̂_{k|k-1})`, and
    `Π_k = (I − K H) V_k (I − K H)ᵀ + K R Kᵀ` propagates. This is the published
    one-step predictor (Zorzi 2017; `docs/math/divergence.md`) re-organised as predict/robustify/update: its
    `x̂_{t+1} = A x̂_t + G_t(y_t − C x̂_t)` equals `F x̂_{k|k}` and its
    `P_{t+1} = A V_t Aᵀ − G_t(C V_t Cᵀ + R)G_tᵀ + Q` equals `F Π_k Fᵀ + Q`. The first
    step robustifies `F P_0 Fᵀ + G Q Gᵀ` (the prior's prediction).

    **Tolerance convention:** `radius` bounds `Σ_i φ_τ(θ p_i)`, as Zorzi's `c` does in his code.
    For `τ = 0` this is `2·KL(N(0, V) ‖ N(0, P))`, i.e. a relative-entropy budget of
    `radius/2` nats per step. For a large `radius` the covariance recursion can grow without bound
    (e.g. along weakly observed directions); Zorzi's guaranteed tolerance (`maxtol`)
    is not implemented here. Watch `info["theta"]` and the covariances.

    **Arguments:**

    - `tau`: divergence index in `[0, 1]` (0: KL; 1: the exponential form).
    - `radius`: the tolerance `c ≥ 0` of the paper; `radius = 0` is exactly the Kalman
      filter (`c=` is a deprecated alias).
    - `throw`, `outputs`: as in `jdrkf.KalmanFilter`.

    `tau` and `radius` are differentiable hyper-parameters: θ_k comes from a safeguarded
    Newton/bisection root solve and gets its derivative from the implicit function
    theorem; `V_k` is differentiated with the Daleckii–Krein formula (safe for repeated
    eigenvalues). Reported: `predicted = N(x̂_{k|k-1}, V_k)` (the least-favourable
    prediction), `filtered`, `loglik` = log-density of `y_k` under the least-favourable
    prediction, `info = {"theta": θ_k, "nominal_predicted_cov": P_k}`. A non-positive-
    definite innovation covariance gives `RESULTS.nonpositive_innovation`; traced `tau`
    or `radius` out of range, `RESULTS.invalid_hyperparameter` (concrete: `ValueError`).

    **Example:**

    ```python
    from jdrkf.filters._divergence import TauKF
    result = TauKF(tau=0.0, radius=1.5e-4)(model, prior, ys)
    result.info["theta"]                                   # (T,) multipliers θ_k
    g = jax.grad(lambda r: loss(TauKF(0.5, r)(model, prior, ys)))(1e-3)
    ```
    """

    tau: Float[Array, ""]
    radius: Float[Array, ""]
    shared_covariance: ClassVar[bool] = True

    def __init__(self, tau: Float[ArrayLike, ""], radius: Float[ArrayLike, ""] = None, throw: bool = True,
                 outputs: str | Sequence[str] = DEFAULT_OUTPUTS, *, c: Float[ArrayLike, ""] = None):
        self.tau = _scalar_param("tau", tau, 0.0, 1.0)
        self.radius = _scalar_param("radius", renamed("c", c, "radius", radius, "TauKF"), 0.0)
        self.throw = throw
        self.outputs = outputs

    c = renamed_attribute("c", "radius")

    def init(self, model, prior):
        return prior

    def step(self, model, state, y, t, u=None, key=None, observed=None):
        nominal = predict(model, state, t, u)
        theta, v = robustify_covariance(nominal.cov, self.tau, self.radius)
        pred = _with_cov(nominal, v)
        filt, loglik, failed = update(model, pred, y, t, observed=observed)
        info = {"theta": theta, "nominal_predicted_cov": nominal.cov}
        valid = in_range(self.tau, 0.0, 1.0) & in_range(self.radius, 0.0)
        result = RESULTS.where(valid, step_result(failed, filt), RESULTS.invalid_hyperparameter)
        out = StepOutput(predicted=pred, filtered=filt, loglik=loglik, info=info, result=result)
        return filt, out


class RiskSensitiveKF(AbstractFilter):
    r"""Risk-sensitive Kalman filter (Whittle; Speyer–Fan–Banavar; Hassibi–Sayed–Kailath),
    update form with full-state weight `L = I`.

    Each step predicts `x̂_{k|k-1}`, `P_k = F Π_{k-1} Fᵀ + G Q Gᵀ`, inflates
    `P̃_k = (P_k⁻¹ − θ I)⁻¹ = (I − θ P_k)⁻¹ P_k` (a Cholesky solve, no inverse of
    `P_k`), and updates with prior covariance `P̃_k`:
    `K = P̃ Hᵀ(H P̃ Hᵀ + R)⁻¹`, `x̂_{k|k} = x̂_{k|k-1} + K(y_k − H x̂_{k|k-1})`,
    `Π_k = (I − K H) P̃ (I − K H)ᵀ + K R Kᵀ` (Joseph form of `(I − K H) P̃`).
    It is `TauKF(tau=0)` with the multiplier θ_k held fixed instead of solved for.

    The recursion exists only while `θ < 1/λ_max(P_k)`. A step that violates it
    (`I − θ P_k` not positive definite) reports `info["valid"] = False`, NaN outputs from
    then on, and the result code `RESULTS.risk_sensitive_breakdown`.

    **Arguments:**

    - `theta`: risk-sensitivity parameter `≥ 0` (differentiable); `0` is the Kalman filter.
      Out of range: `ValueError` when concrete, `RESULTS.invalid_hyperparameter` when traced.
    - `throw`, `outputs`: as in `jdrkf.KalmanFilter`.

    Reported: `predicted = N(x̂_{k|k-1}, P̃_k)`, `loglik` under that prediction,
    `info = {"valid": ..., "nominal_predicted_cov": P_k}`.

    **Example:**

    ```python
    from jdrkf.filters._divergence import RiskSensitiveKF
    result = RiskSensitiveKF(theta=0.05, throw=False)(model, prior, ys)
    ok = result.info["valid"].all()
    ```
    """

    theta: Float[Array, ""]
    shared_covariance: ClassVar[bool] = True

    def __init__(self, theta: Float[ArrayLike, ""], throw: bool = True, outputs: str | Sequence[str] = DEFAULT_OUTPUTS):
        self.theta = _scalar_param("theta", theta, 0.0)
        self.throw = throw
        self.outputs = outputs

    def init(self, model, prior):
        return prior

    def step(self, model, state, y, t, u=None, key=None, observed=None):
        nominal = predict(model, state, t, u)
        p = nominal.cov
        theta = self.theta.astype(p.dtype)
        chol = linalg.cholesky(linalg.symmetrize(jnp.eye(p.shape[0], dtype=p.dtype) - theta * p))
        valid = jnp.all(jnp.isfinite(chol))
        p_tilde = linalg.symmetrize(linalg.cho_solve(chol, p))
        p_tilde = jnp.where(valid, p_tilde, jnp.nan)
        pred = _with_cov(nominal, p_tilde)
        filt, loglik, failed = update(model, pred, y, t, observed=observed)
        result = RESULTS.where(valid, step_result(failed, filt), RESULTS.risk_sensitive_breakdown)
        result = RESULTS.where(in_range(self.theta, 0.0), result, RESULTS.invalid_hyperparameter)
        info = {"valid": valid, "nominal_predicted_cov": p}
        out = StepOutput(predicted=pred, filtered=filt, loglik=loglik, info=info, result=result)
        return filt, out
