"""Outlier models of the whitened innovation `μ = S^{-1/2}(y − H x⁻)`: Huber's
least-favourable laws of Wang & Ye (2022), Lemmas 1 and 2.

A model gives the influence function `ψ = −(ln p)'` of its least-favourable density
`p`, applied componentwise to `μ` in the DR estimator (eq. 38), and the minimal Fisher
information `i_min = E_p[ψ']`, which scales the covariance correction (eq. 41).

The constants `K` (Lemma 1) and `a, b, c` (Lemma 2) are roots of scalar equations in
`eps`. They are found by bracketed Newton steps (`jdrkf._root`), and their
derivatives come from the implicit function theorem at the root, never from the
iterations, so both models are differentiable in `eps`
(under `jit`, `vmap` and `grad`) and `eps` can be tuned by gradient descent.
"""

from __future__ import annotations

import abc
import math
from fractions import Fraction

import equinox as eqx
import jax
import jax.numpy as jnp
from jax import lax
from jax.scipy.special import erf, erfc, log_ndtr
from jaxtyping import Array, ArrayLike, Bool, Float

from .._root import bracketed_newton, implicit_root
from .._validation import as_float_array, check_fraction, in_range, is_concrete

__all__ = ["AbstractOutlierModel", "EpsContamination", "EpsNormal"]

_SQRT2 = math.sqrt(2.0)
_LOG_SQRT_2PI = 0.5 * math.log(2.0 * math.pi)
_EPS_NORMAL_MAX = 0.0303


# --------------------------------------------------------------------------- roots


def _implicit_root(residual, guess, lo, hi, max_iter):
    """`x(p)` with `residual(x(p), p) = 0` (`residual` increasing in `x`), found by
    bracketed Newton from `guess(p)` in `[lo, hi]` (at most `max_iter` steps). Its
    derivatives come from the implicit function theorem at the root,
    `dx = −(∂r/∂p dp) / (∂r/∂x)`, so none flows through the iterations (and higher
    derivatives work too)."""

    def root(p):
        def solve(x0):
            return bracketed_newton(lambda x: residual(x, p), x0, lo, hi, max_iter, x_scale=1.0).x, ()

        return implicit_root(lambda x: residual(x, p), solve, lax.stop_gradient(guess(p)))[0]

    return root


def _log_tail_excess(k):
    """`ln g(K)` with `g(K) = 2φ(K)/K − 2Φ(−K)`, decreasing from `+∞` to `0` on `K > 0`.

    Written as `ln 2 + ln φ(K) − ln K + ln(1 − K R(K))` with the Mills ratio
    `R = Φ(−K)/φ(K)` taken from `log_ndtr`, so nothing under- or overflows."""
    log_phi = -0.5 * k * k - _LOG_SQRT_2PI
    kr = k * jnp.exp(log_ndtr(-k) - log_phi)
    tiny = jnp.finfo(k.dtype).tiny
    return math.log(2.0) + log_phi - jnp.log(k) + jnp.log(jnp.maximum(1.0 - kr, tiny))


# Bracket of K = e^t: g(0.05) ≈ 15 and g(15) ≈ 3e-53, so every target in
# [3e-53, 15] has its root inside (smaller targets give K = 15).
_LOG_K_LO, _LOG_K_HI = math.log(0.05), math.log(15.0)


# ln K as a function of ln g(K); the guess is the large-K asymptote g(K) ≈ 2φ(K)/K³.
_log_tail_root = _implicit_root(
    lambda t, log_target: log_target - _log_tail_excess(jnp.exp(t)),
    lambda log_target: 0.5 * jnp.log(jnp.maximum(2.0 * (math.log(2.0) - _LOG_SQRT_2PI - log_target), 0.25)),
    _LOG_K_LO,
    _LOG_K_HI,
    16,
)


def _solve_tail(log_target):
    """The `K > 0` with `ln g(K) = log_target` (`g` as in `_log_tail_excess`)."""
    return jnp.exp(_log_tail_root(log_target))


# ---------------------------------------------------------- Lemma 2, in u = c a / 2
#
# Condition 1) gives a² = 2u tan u and c = 2u / a = (2u / tan u)^{1/2}, with u ∈ [0, π/2).
# The cos² part of (30) is A cos²(cμ/2), A = φ(a) / cos² u, and
#     ∫₀ᵃ A cos²(cμ/2) dμ = A (a/2 + sin(ca)/(2c)) = φ(a) a (1 + sin 2u / 2u) / (2 cos² u),
# so condition 2) reads D(u) = eps with
#     D(u) = Φ(a) − ½ − φ(a) a h(u) = φ(a) a E(u),   h(u) = (1 + sin 2u / 2u) / (1 + cos 2u),
#     E(u) = M(a) / a − h(u),   M(a) = e^{a²/2} ∫₀ᵃ e^{−t²/2} dt = Σⱼ a^{2j+1} / (2j+1)!!.
# D increases from 0 (as 4√2 φ(0) u⁵ / 45) to ½ on [0, π/2). E(u) is a difference of
# two terms near 1 that agree to O(u⁴), so for small u it is evaluated from its
# Taylor series in x = u², computed below in exact rational arithmetic.


def _lemma2_series(num_terms):
    """Coefficients `e₂, e₃, …` of `E(u) = Σ_{k≥2} e_k u^{2k}` (as floats)."""

    def mul(p, q):
        return [sum(p[i] * q[k - i] for i in range(k + 1)) for k in range(num_terms)]

    def inv(p):
        out = [1 / p[0]]
        for k in range(1, num_terms):
            out.append(-sum(p[i] * out[k - i] for i in range(1, k + 1)) / p[0])
        return out

    fact = [math.factorial(k) for k in range(2 * num_terms + 2)]
    sin_over_u = [Fraction((-1) ** k, fact[2 * k + 1]) for k in range(num_terms)]
    cos_u = [Fraction((-1) ** k, fact[2 * k]) for k in range(num_terms)]
    s = [Fraction(0)] + [2 * t for t in mul(sin_over_u, inv(cos_u))[:-1]]  # a² = 2u tan u
    m_over_a, power, double_fact = [Fraction(0)] * num_terms, [Fraction(1)] + [Fraction(0)] * (num_terms - 1), 1
    for j in range(num_terms):
        double_fact *= 2 * j + 1
        m_over_a = [m + p / double_fact for m, p in zip(m_over_a, power, strict=True)]
        power = mul(power, s)
    numer = [Fraction(2)] + [Fraction((-4) ** k, fact[2 * k + 1]) for k in range(1, num_terms)]
    denom = [Fraction(2)] + [Fraction((-4) ** k, fact[2 * k]) for k in range(1, num_terms)]
    e = [m - h for m, h in zip(m_over_a, mul(numer, inv(denom)), strict=True)]
    assert e[0] == e[1] == 0 and e[2] == Fraction(4, 45)
    return tuple(float(c) for c in e[2:])


# The coefficients are positive and shrink by about 1/2 per term; at the switch
# x = 0.36 the 30 terms leave a relative truncation error below 1e-19, and the direct
# formula above the switch loses at most 1/E(0.6) ≈ 50 ulps to cancellation.
_E_SERIES = _lemma2_series(32)
_U_SWITCH = 0.6
_U_LO, _U_HI = 1e-8, 1.2  # D(1e-8) ≈ 5e-42, D(1.2) ≈ 0.27 (eps ≤ 0.0303 has u < 0.83)


def _log_d(u):
    """`ln D(u)`, see the comment above."""
    x = u * u
    coeffs = jnp.asarray(_E_SERIES[::-1], dtype=u.dtype)
    small = u < _U_SWITCH
    x_series = jnp.where(small, x, 0.1)
    log_e_series = 2.0 * jnp.log(x_series) + jnp.log(jnp.polyval(coeffs, x_series))
    u_direct = jnp.where(small, 0.9, u)
    s_direct = 2.0 * u_direct * jnp.tan(u_direct)
    a_direct = jnp.sqrt(s_direct)
    m_over_a = math.sqrt(math.pi / 2.0) * jnp.exp(0.5 * s_direct) * erf(a_direct / _SQRT2) / a_direct
    h = (1.0 + jnp.sin(2.0 * u_direct) / (2.0 * u_direct)) / (1.0 + jnp.cos(2.0 * u_direct))
    log_e = jnp.where(small, log_e_series, jnp.log(m_over_a - h))
    s = 2.0 * u * jnp.tan(u)
    return -0.5 * s - _LOG_SQRT_2PI + 0.5 * jnp.log(s) + log_e


# ln u as a function of ln eps; the guess inverts D(u) ≈ 4√2 φ(0) u⁵ / 45.
_log_u_root = _implicit_root(
    lambda t, log_eps: _log_d(jnp.exp(t)) - log_eps,
    lambda log_eps: (log_eps - math.log(4.0 * _SQRT2 / 45.0) + _LOG_SQRT_2PI) / 5.0,
    math.log(_U_LO),
    math.log(_U_HI),
    12,
)


def _solve_lemma2_u(eps):
    """The `u = ca/2 ∈ (0, π/2)` with `D(u) = eps`, for `eps > 0`."""
    return jnp.exp(_log_u_root(jnp.log(eps)))


@jax.jit
def _huber_threshold(eps):
    """`K(ε)` of Lemma 1, `+∞` at `ε = 0` (safe branch: no NaN in derivatives)."""
    positive = eps > 0
    safe = jnp.where(positive, eps, 0.25)
    k = _solve_tail(jnp.log(safe) - jnp.log1p(-safe))  # g(K) = ε / (1 − ε)
    return jnp.where(positive, k, jnp.inf)


@jax.jit
def _lemma2_constants(eps):
    """`(a, b, c, i_min)` of Lemma 2 and eq. (43); `(0, +∞, √2, 1)` at `ε = 0`."""
    positive = eps > 0
    safe = jnp.where(positive, eps, 0.01)
    u = _solve_lemma2_u(safe)
    tan_u = jnp.tan(u)
    a = jnp.sqrt(2.0 * u * tan_u)
    c = jnp.sqrt(2.0 * u / tan_u)
    b = _solve_tail(math.log(2.0) + jnp.log(safe))  # g(b) = 2ε
    phi_a = jnp.exp(-0.5 * a * a - _LOG_SQRT_2PI)
    i_min = c * c * a * phi_a / jnp.cos(u) ** 2 + erfc(a / _SQRT2) - erfc(b / _SQRT2)
    return (
        jnp.where(positive, a, 0.0),
        jnp.where(positive, b, jnp.inf),
        jnp.where(positive, c, _SQRT2),
        jnp.where(positive, i_min, 1.0),
    )


@jax.jit
def _lemma2_psi(mu, a, b, c):
    inner = jnp.abs(mu) < a
    mu_inner = jnp.where(inner, mu, 0.0)  # keeps tan away from its poles
    return jnp.where(inner, c * jnp.tan(0.5 * c * mu_inner), jnp.clip(mu, -b, b))


# ------------------------------------------------------------------------ models


def _input(mu, dtype):
    mu = jnp.asarray(mu)
    return mu if jnp.issubdtype(mu.dtype, jnp.inexact) else mu.astype(dtype)


class AbstractOutlierModel(eqx.Module):
    """A least-favourable law `p` of the whitened innovation `μ` (one component).

    The DR update (Wang & Ye 2022, eqs. 38 and 41) is
    `x̂ = x⁻ + Σ Hᵀ S^{-1/2} ψ(S^{-1/2}(y − H x⁻))` and `P = Σ − i_min Σ Hᵀ S⁻¹ H Σ`.
    """

    @abc.abstractmethod
    def psi(self, mu: Float[ArrayLike, " m"]) -> Float[Array, " m"]:
        """Influence function `ψ = −(ln p)'`, applied componentwise (odd, non-decreasing)."""

    @abc.abstractmethod
    def i_min(self) -> Float[Array, ""]:
        """Minimal Fisher information `E_p[−(ln p)'']` in `[0, 1]` (1 for the standard normal)."""

    @abc.abstractmethod
    def valid(self) -> Bool[Array, ""]:
        """Whether the parameters are in range (checked eagerly when concrete; this is the
        traced check, which filters turn into `RESULTS.invalid_hyperparameter`)."""


class EpsContamination(AbstractOutlierModel):
    """ε-contamination set `{(1 − ε) Φ + ε H : H symmetric}` (Lemma 1; Huber's
    minimax M-estimator).

    The least-favourable density (29) is Gaussian on `|μ| ≤ K` and Laplacian beyond,
    where `K = K(ε)` is the unique positive root of (p integrates to one)

        (1 − ε) [2Φ(K) − 1 + 2φ(K)/K] = 1,

    e.g. `K(0.01) = 1.945`, `K(0.05) = 1.398`, `K(0.1) = 1.140`. Then
    `ψ(μ) = clip(μ, −K, K)` (eq. 39) and `i_min = (1 − ε)(1 − 2Φ(−K))` (eq. 42).
    `ε = 0` gives `K = +∞`: `ψ` is the identity and `i_min = 1` (the Kalman filter).
    `K(ε)` is capped at 15 (reached only for `ε < 1e-52`).

    **Arguments:**

    - `eps`: contamination fraction, a scalar in `[0, 0.5)` (a `ValueError` when concrete;
      traced, `valid()` is `False` and filters report `RESULTS.invalid_hyperparameter`).
    - `k`: optional clipping threshold `K > 0` that replaces `K(ε)` in (39) and (42),
      e.g. the rounded `k = 1.4` that Wang & Ye use with `eps = 0.05`. With `k` set,
      `ε = 0` gives `i_min = 1 − 2Φ(−k)` and a clipping `ψ`.

    The derivative of `K(ε)` comes from the implicit function theorem,
    `dK/dε = −K² / (2φ(K)(1 − ε)²)`. As `ε → 0⁺`, `K → ∞` and
    `d i_min / dε = 2φ(K)/K − (K² + 1)/(1 − ε) → −∞` (slowly, `K² ≈ 2 ln(1/ε)`); at
    `ε = 0` exactly the gradient is the finite one with `K = ∞` held fixed (`−1`).
    """

    eps: Float[Array, ""]
    k: Float[Array, ""] | None

    def __init__(self, eps: Float[ArrayLike, ""], k: Float[ArrayLike, ""] | None = None):
        self.eps = check_fraction("eps", eps, 0.5, closed=False)
        if k is not None:
            k = as_float_array("k", k, (0,))
            if is_concrete(k) and not float(k) > 0.0:
                raise ValueError(f"k must be > 0 (the clipping threshold K of eq. 39), got {float(k)}")
            k = k.astype(self.eps.dtype)
        self.k = k

    def valid(self) -> Bool[Array, ""]:
        """`0 ≤ ε < 0.5` and, if given, `k > 0`."""
        ok = in_range(self.eps, 0.0, 0.5, upper_open=True)
        return ok if self.k is None else ok & in_range(self.k, 0.0, lower_open=True, allow_inf=True)

    def threshold(self) -> Float[Array, ""]:
        """`K`: the override `k` if given, else `K(ε)` of Lemma 1 (`+∞` at `ε = 0`)."""
        return _huber_threshold(self.eps) if self.k is None else self.k

    def psi(self, mu: Float[ArrayLike, " m"]) -> Float[Array, " m"]:
        """Huber's `ψ(μ) = clip(μ, −K, K)` (eq. 39)."""
        k = self.threshold()
        mu = _input(mu, k.dtype)
        k = k.astype(mu.dtype)
        return jnp.clip(mu, -k, k)

    def i_min(self) -> Float[Array, ""]:
        """`(1 − ε)(1 − 2Φ(−K))` (eq. 42): the mass `(29)` puts on the Gaussian middle."""
        return (1.0 - self.eps) * erf(self.threshold() / _SQRT2)


class EpsNormal(AbstractOutlierModel):
    """ε-normal (Kolmogorov) set `{P symmetric : sup |P − Φ| ≤ ε}` (Lemma 2).

    The least-favourable density (30) is `∝ cos²(cμ/2)` on `|μ| ≤ a`, Gaussian on
    `a ≤ |μ| ≤ b` and Laplacian beyond `b`, where `0 ≤ a ≤ b` and `c` solve

    1. `c tan(ca/2) = a`, `0 ≤ ca < π` (continuity of `ψ` at `a`);
    2. `∫₀ᵃ p = Φ(a) − ½ − ε`;
    3. `∫_b^∞ p = φ(b)/b = Φ(−b) + ε`, which fixes `b` from `ε` alone.

    With `u = ca/2`, 1) gives `a² = 2u tan u`, and 2) becomes one equation in `u`
    (integrated in closed form; see the source). Then `ψ(μ) = c tan(cμ/2)` on
    `|μ| ≤ a`, `μ` on `a ≤ |μ| ≤ b`, `b sign μ` beyond (eq. 40), and
    `i_min = c² a φ(a) / cos²(ca/2) + 2Φ(b) − 2Φ(a)` (eq. 43).

    The form (30) needs `a ≤ b`, i.e. `ε ≤ 0.030333` (Remark 2); `eps` is limited
    to `[0, 0.0303]`. Examples: `ε = 0.03` gives `(a, b, c) = (1.3462, 1.3534, 1.2324)`,
    `ε = 0.0303` gives `(1.3492, 1.3499, 1.2317)`; the values `a = b = 1.3496`,
    `c = 1.2316` quoted by Wang & Ye at `ε = 0.03` are Huber's table entry at the
    limit `ε ≈ 0.03033`.

    `ε = 0` is the regular limit `a → 0` (like `ε^{1/5}`), `c → √2`, `b → ∞`: the
    density is the standard normal, `ψ` the identity and `i_min = 1`, so it is
    accepted. As `ε → 0⁺` the derivatives of `a` (like `ε^{-4/5}`), `b` and, slowly,
    `i_min` diverge; at `ε = 0` exactly the gradient is the finite one with the limit
    constants held fixed (zero).

    **Arguments:**

    - `eps`: the Kolmogorov radius, a scalar in `[0, 0.0303]` (a `ValueError` when
      concrete; traced, `valid()` is `False` and filters report
      `RESULTS.invalid_hyperparameter`).
    """

    eps: Float[Array, ""]

    def __init__(self, eps: Float[ArrayLike, ""]):
        hint = " (Lemma 2 needs a <= b; Remark 2. Use EpsContamination for larger eps)"
        self.eps = check_fraction("eps", eps, _EPS_NORMAL_MAX, hint=hint)

    def valid(self) -> Bool[Array, ""]:
        """`0 ≤ ε ≤ 0.0303` (compared in the precision of `eps`)."""
        return in_range(self.eps, 0.0, _EPS_NORMAL_MAX)

    def constants(self) -> tuple[Float[Array, ""], Float[Array, ""], Float[Array, ""]]:
        """`(a, b, c)` of Lemma 2 (`(0, +∞, √2)` at `ε = 0`)."""
        return _lemma2_constants(self.eps)[:3]

    def psi(self, mu: Float[ArrayLike, " m"]) -> Float[Array, " m"]:
        """`ψ` of eq. (40): `c tan(cμ/2)` on `|μ| ≤ a`, `μ` up to `b`, `±b` beyond."""
        a, b, c = self.constants()
        mu = _input(mu, a.dtype)
        return _lemma2_psi(mu, *(v.astype(mu.dtype) for v in (a, b, c)))

    def i_min(self) -> Float[Array, ""]:
        """`c² a φ(a) / cos²(ca/2) + 2Φ(b) − 2Φ(a)` (eq. 43)."""
        return _lemma2_constants(self.eps)[3]
