"""EM estimation of the nominal noise covariances of a linear-Gaussian model.

The protocol of Jang, Hakobyan & Yang (2025; their code's `main.py`): pykalman's
`KalmanFilter.em` with `em_vars` = transition/observation covariances and offsets,
run one iteration at a time from `Q = I`, `R = I` until the log-likelihood gain is
at most `1e-4` (at most 100 iterations), then symmetrized with the smallest
eigenvalue lifted to `1e-4`. Written here in JAX (jit- and vmap-able), following
pykalman's conventions and update equations (Shumway & Stoffer 1982; Ghahramani &
Hinton 1996).
"""

from __future__ import annotations

import math
from typing import Literal

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jax import lax
from jaxtyping import Array, ArrayLike, Bool, Float, Int

from . import linalg
from ._gaussian import Gaussian
from ._models import LinearModel
from ._validation import as_float_array, check_covariance, check_shape, is_concrete, psd_rtol
from .filters import KalmanFilter, smooth


__all__ = ["EMResult", "em_noise_covariances"]

Lift = Literal["shift", "clip"]
OffsetUpdate = Literal["pykalman", "joint"]


class EMResult(eqx.Module):
    """Output of `em_noise_covariances`.

    - `Q`, `R`: estimated process / measurement noise covariances, symmetrized and
      with small eigenvalues lifted (see `lift`).
    - `process_offset` (`b`), `noise_offset` (`d`): estimated offsets (the initial
      ones when `estimate_offsets=False`).
    - `loglik`: log-likelihood `log p(y_{0:T-1})` of the raw (un-lifted) final
      estimates.
    - `loglik_history`: `(max_iter + 1,)`; entry `k` is the log-likelihood after `k`
      EM iterations (entry 0: the initial parameters), NaN after `iterations`.
    - `iterations`: EM iterations performed.
    - `converged`: `True` only when the loop stopped on the gain criterion (not on the
      cap, nor on a non-finite log-likelihood) after at least two iterations, the last
      iteration did not lower the log-likelihood beyond round-off, and the returned
      raw `Q`, `R` are finite and positive semidefinite and the offsets finite.
    """

    Q: Float[Array, "n n"]
    R: Float[Array, "m m"]
    process_offset: Float[Array, " n"]
    noise_offset: Float[Array, " m"]
    loglik: Float[Array, ""]
    loglik_history: Float[Array, " K"]
    iterations: Int[Array, ""]
    converged: Bool[Array, ""]


def _smoother_statistics(f, h, ys, drive, m0, p0, q, r, b, d):
    """Kalman filter + RTS smoother (`jdrkf.smooth`) in pykalman's convention (`y_0`
    measures `x_0`).

    pykalman's `x_t` is `x_{t+1}` of a time-varying `jdrkf.LinearModel` whose first
    transition (`F = 0`, process noise `N(m0, p0)`) makes the predicted law of its `x_1`
    the initial law `N(m0, p0)`; later transitions are `x ↦ F x + B u + b + w`.
    Returns the log-likelihood, smoothed means `(T, n)` and covariances `(T, n, n)` and
    the lag-one cross covariances `Cov(x_{t+1}, x_t | y_{0:T-1})` `(T-1, n, n)`.
    """
    n = m0.shape[0]
    num_steps = ys.shape[0]
    zero = jnp.zeros((1, n, n), m0.dtype)
    model = LinearModel(
        jnp.concatenate([zero, jnp.broadcast_to(f, (num_steps - 1, n, n))]),
        h,
        jnp.concatenate([p0[None], jnp.broadcast_to(q, (num_steps - 1, n, n))]),
        r,
        process_mean=jnp.concatenate([m0[None], b + drive]),
        noise_mean=d,
    )
    res = smooth(KalmanFilter(throw=False), model, Gaussian(m0, p0), ys)
    return res.marginal_loglik, res.smoothed_means, res.smoothed_covariances, res.smoothed_cross_covariances[1:]


def _m_step(f, h, ys, drive, mss, pss, cross, b, d, estimate_offsets, offset_update):
    """Closed-form M-step for `(Q, R, b, d)` given the smoothed moments.

    `R(d) = (1/T) Σ_t (y_t − H m_t − d)(·)ᵀ + H P_t Hᵀ`, `d = (1/T) Σ_t (y_t − H m_t)`,
    `Q(b) = (1/(T−1)) Σ_t e_t e_tᵀ + F P_t Fᵀ + P_{t+1} − C_t Fᵀ − F C_tᵀ` with
    `e_t = m_{t+1} − F m_t − B u_t − b`, `C_t = Cov(x_{t+1}, x_t | y)`, and
    `b = (1/(T−1)) Σ_t (m_{t+1} − F m_t − B u_t)`.
    """
    resid = ys - mss @ h.T  # (T, m): y_t − H m_t
    trans = mss[1:] - mss[:-1] @ f.T - drive  # (T-1, n): m_{t+1} − F m_t − B u_t
    d_new = jnp.mean(resid, axis=0) if estimate_offsets else d
    b_new = jnp.mean(trans, axis=0) if estimate_offsets else b
    # pykalman (`_em_multiple`) updates the covariances with the offsets of the previous
    # iteration and the offsets last; "joint" uses the new offsets (exact joint M-step).
    d_cov, b_cov = (d, b) if offset_update == "pykalman" else (d_new, b_new)
    er = resid - d_cov
    r_new = jnp.mean(er[:, :, None] * er[:, None, :] + h @ pss @ h.T, axis=0)
    eq = trans - b_cov
    fc = f @ jnp.swapaxes(cross, -1, -2)  # F C_tᵀ
    q_terms = eq[:, :, None] * eq[:, None, :] + f @ pss[:-1] @ f.T + pss[1:] - jnp.swapaxes(fc, -1, -2) - fc
    q_new = jnp.mean(q_terms, axis=0)
    return linalg.symmetrize(q_new), linalg.symmetrize(r_new), b_new, d_new


def _lift(a, min_eig, lift):
    """Symmetrize; then `shift` adds `(min_eig − λ_min)·I` when `λ_min < min_eig`
    (the seed's `enforce_positive_definiteness`) or `clip` raises each eigenvalue
    below `min_eig` to it. Also returns whether `a` itself is finite and positive
    semidefinite, `λ_min ≥ −psd_rtol · max(|λ|_max, tiny)`."""
    a = linalg.symmetrize(a)
    lam, vec = jnp.linalg.eigh(a)
    top = jnp.maximum(jnp.max(jnp.abs(lam)), jnp.finfo(a.dtype).tiny)
    psd = jnp.all(jnp.isfinite(a)) & (lam[0] >= -psd_rtol(a.dtype, a.shape[0]) * top)
    if lift == "shift":
        shift = jnp.maximum(min_eig - lam[0], jnp.zeros((), a.dtype))
        return a + shift * jnp.eye(a.shape[0], dtype=a.dtype), psd
    return linalg.symmetrize((vec * jnp.maximum(lam, min_eig)) @ vec.T), psd


def _check_scalar(name, x, dtype, *, nonnegative=False, allow_inf=False):
    arr = jnp.asarray(x)
    if arr.ndim != 0:
        raise ValueError(f"{name} must be a scalar, got shape {tuple(arr.shape)}")
    if is_concrete(arr):
        v = float(arr)
        if math.isnan(v) or (not allow_inf and math.isinf(v)):
            raise ValueError(f"{name} must be finite, got {v}")
        if nonnegative and v < 0:
            raise ValueError(f"{name} must be >= 0, got {v}")
    return arr.astype(dtype)


def em_noise_covariances(
    F: Float[ArrayLike, "n n"],
    H: Float[ArrayLike, "m n"],
    ys: Float[ArrayLike, "T m"],
    initial_mean: Float[ArrayLike, " n"],
    initial_cov: Float[ArrayLike, "n n"],
    *,
    Q0: Float[ArrayLike, "n n"] | None = None,
    R0: Float[ArrayLike, "m m"] | None = None,
    process_offset0: Float[ArrayLike, " n"] | None = None,
    noise_offset0: Float[ArrayLike, " m"] | None = None,
    estimate_offsets: bool = True,
    max_iter: int = 100,
    tol: Float[ArrayLike, ""] = 1e-4,
    min_eig: Float[ArrayLike, ""] = 1e-4,
    lift: Lift = "shift",
    offset_update: OffsetUpdate = "pykalman",
    inputs: Float[ArrayLike, "T-1 p"] | None = None,
    B: Float[ArrayLike, "n p"] | None = None,
) -> EMResult:
    r"""EM (maximum-likelihood) estimate of the noise covariances `Q`, `R` and offsets `b`, `d`.

    Model (pykalman's convention; note that `y_0` measures `x_0` itself, unlike
    `jdrkf.LinearModel` where the prior is the law of the unmeasured `x_0`):

    $$x_0 \sim N(\mu_0, \Sigma_0),\quad x_{t+1} = F x_t + B u_t + b + w_t,\quad
    y_t = H x_t + d + v_t,\quad w_t \sim N(0, Q),\ v_t \sim N(0, R),$$

    for `t = 0..T-1` (`ys[t] = y_t`, `inputs[t] = u_t` for `t = 0..T-2`). `F`, `H`, `B`
    and the initial law are known; `Q`, `R` (and `b`, `d` if `estimate_offsets`) are
    estimated.

    Each EM iteration runs a Kalman filter and an RTS smoother with lag-one cross
    covariances (E-step, `lax.scan`), then the closed-form M-step of Shumway &
    Stoffer (1982) / Ghahramani & Hinton (1996). With `offset_update="pykalman"`
    (default) the updates come in pykalman's order: `R` and `Q` with the offsets of
    the previous iteration, then `d` and `b` (which do not depend on `R`, `Q`): an ECM
    step. `"joint"` plugs the new offsets into `R`, `Q` (the exact joint M-step). Both
    never decrease the likelihood.

    The loop (`lax.while_loop`, at most `max_iter` iterations) follows the seed's
    driver: after iteration `k ≥ 2` it stops when `loglik_k − loglik_{k−1} ≤ tol`
    (the gain of the first iteration is not tested); it also stops on a non-finite
    log-likelihood. `converged` certifies that stop: besides the gain test it needs
    `loglik_k − loglik_{k−1} ≥ −(max(tol, 0) + T·eps·(|loglik_k| + |loglik_{k−1}|))`
    (EM never lowers the likelihood, so a larger drop is a numerical failure, not
    convergence; `T·eps·|·|` bounds the round-off of summing `T` terms), finite
    offsets and finite positive semidefinite raw `Q`, `R`; reaching `max_iter`
    without passing the gain test is not convergence. `Q` and `R` are then symmetrized and their small eigenvalues
    lifted to `min_eig` (`lift="shift"`: add `(min_eig − λ_min) I` when
    `λ_min < min_eig`, as the seed does; `"clip"`: raise each eigenvalue to at least
    `min_eig`).

    **Arguments:**

    - `F` `(n, n)`, `H` `(m, n)`: known transition and observation matrices.
    - `ys`: `(T, m)` observations, `T ≥ 2`, no missing values.
    - `initial_mean` `(n,)`, `initial_cov` `(n, n)`: the (known) law of `x_0`.
    - `Q0`, `R0`: initial covariances; default identity (the seed's choice).
    - `process_offset0`, `noise_offset0`: initial offsets `b`, `d`; default zero.
    - `estimate_offsets`: estimate `b`, `d` (default) or keep them fixed.
    - `max_iter`: static cap on EM iterations (`≥ 0`); `tol`: gain tolerance
      (`-inf` runs exactly `max_iter` iterations); `min_eig`: eigenvalue floor (`≥ 0`).
    - `lift`, `offset_update`: see above.
    - `inputs` `(T-1, p)` with `B` `(n, p)`: known control inputs (both or neither).

    Jit with `eqx.filter_jit` (or mark `max_iter`, `estimate_offsets`, `lift`,
    `offset_update` static) and `jax.vmap` over a batch of `ys` (one EM per Monte
    Carlo run). Not meant to be differentiated (`while_loop`, `eigh` in the lift).
    Covariances that the data cannot pin down (e.g. `T = 5`) may come out nearly
    singular before the lift; a non-positive-definite innovation or predicted
    covariance makes the log-likelihood NaN, which stops the loop with
    `converged = False`.
    """
    if not isinstance(max_iter, int) or isinstance(max_iter, bool) or max_iter < 0:
        raise ValueError(f"max_iter must be a non-negative int, got {max_iter!r}")
    if lift not in ("shift", "clip"):
        raise ValueError(f"lift must be 'shift' or 'clip', got {lift!r}")
    if offset_update not in ("pykalman", "joint"):
        raise ValueError(f"offset_update must be 'pykalman' or 'joint', got {offset_update!r}")
    if not isinstance(estimate_offsets, bool):
        raise ValueError(f"estimate_offsets must be a bool, got {estimate_offsets!r}")

    F = as_float_array("F", F, (2,))
    n = F.shape[-1]
    check_shape("F", F, (n, n), "(F must be square)")
    H = as_float_array("H", H, (2,))
    m = H.shape[0]
    check_shape("H", H, (m, n), f"since the state dimension is {n}")
    ys = as_float_array("ys", ys, (2,))
    check_shape("ys", ys, (None, m), f"(T, m) since H has {m} rows")
    T = ys.shape[0]
    if T < 2:
        raise ValueError(f"ys must hold at least 2 time steps to estimate Q, got shape {tuple(ys.shape)}")
    if is_concrete(ys) and not np.all(np.isfinite(np.asarray(ys))):
        raise ValueError("ys contains non-finite entries (missing observations are not supported)")
    initial_mean = as_float_array("initial_mean", initial_mean, (1,))
    check_shape("initial_mean", initial_mean, (n,), f"since the state dimension is {n}")
    initial_cov = as_float_array("initial_cov", initial_cov, (2,))
    check_covariance("initial_cov", initial_cov)
    check_shape("initial_cov", initial_cov, (n, n), f"since the state dimension is {n}")
    fields = {"F": F, "H": H, "ys": ys, "initial_mean": initial_mean, "initial_cov": initial_cov}
    for name, value, shape in (("Q0", Q0, (n, n)), ("R0", R0, (m, m))):
        if value is not None:
            value = as_float_array(name, value, (2,))
            check_covariance(name, value)
            check_shape(name, value, shape, f"(the state dimension is {n}, H has {m} rows)")
            fields[name] = value
    for name, value, shape in (("process_offset0", process_offset0, (n,)), ("noise_offset0", noise_offset0, (m,))):
        if value is not None:
            value = as_float_array(name, value, (1,))
            check_shape(name, value, shape, f"(the state dimension is {n}, H has {m} rows)")
            fields[name] = value
    if (inputs is None) != (B is None):
        raise ValueError("inputs and B must be given together (got only " + ("inputs" if B is None else "B") + ")")
    if B is not None:
        B = as_float_array("B", B, (2,))
        check_shape("B", B, (n, None), f"since the state dimension is {n}")
        inputs = as_float_array("inputs", inputs, (2,))
        p = B.shape[1]
        if inputs.shape != (T - 1, p):
            raise ValueError(
                f"inputs has shape {tuple(inputs.shape)} but expected ({T - 1}, {p}) "
                f"(T - 1 transitions for T = {T} observations, B has {p} columns)"
            )
        fields["B"], fields["inputs"] = B, inputs

    dtype = jnp.result_type(*fields.values())
    F, H, ys, m0, p0 = (x.astype(dtype) for x in (F, H, ys, initial_mean, initial_cov))
    Q = fields["Q0"].astype(dtype) if "Q0" in fields else jnp.eye(n, dtype=dtype)
    R = fields["R0"].astype(dtype) if "R0" in fields else jnp.eye(m, dtype=dtype)
    b = fields["process_offset0"].astype(dtype) if "process_offset0" in fields else jnp.zeros(n, dtype)
    d = fields["noise_offset0"].astype(dtype) if "noise_offset0" in fields else jnp.zeros(m, dtype)
    drive = inputs.astype(dtype) @ B.astype(dtype).T if B is not None else jnp.zeros((T - 1, n), dtype)
    tol = _check_scalar("tol", tol, dtype, allow_inf=True)
    min_eig = _check_scalar("min_eig", min_eig, dtype, nonnegative=True)

    def e_and_m(params):
        q, r, b_, d_ = params
        ll, mss, pss, cross = _smoother_statistics(F, H, ys, drive, m0, p0, q, r, b_, d_)
        return ll, _m_step(F, H, ys, drive, mss, pss, cross, b_, d_, estimate_offsets, offset_update)

    def stopped(k, ll, ll_prev):
        return (k >= 2) & (ll - ll_prev <= tol)

    def cond(carry):
        k, _, _, ll, ll_prev, _ = carry
        return (k < max_iter) & jnp.isfinite(ll) & ~stopped(k, ll, ll_prev)

    def body(carry):
        k, _, nxt, ll, _, hist = carry
        ll_new, nxt_new = e_and_m(nxt)
        return k + 1, nxt, nxt_new, ll_new, ll, hist.at[k + 1].set(ll_new)

    params0 = (linalg.symmetrize(Q), linalg.symmetrize(R), b, d)
    ll0, nxt0 = e_and_m(params0)
    hist0 = jnp.full((max_iter + 1,), jnp.nan, dtype).at[0].set(ll0)
    nan = jnp.asarray(jnp.nan, dtype)
    init = (jnp.asarray(0, jnp.int32), params0, nxt0, ll0, nan, hist0)
    k, (q, r, b, d), _, ll, ll_prev, hist = lax.while_loop(cond, body, init)
    q_lifted, q_psd = _lift(q, min_eig, lift)
    r_lifted, r_psd = _lift(r, min_eig, lift)
    eps = jnp.finfo(dtype).eps
    slack = jnp.maximum(tol, 0) + T * eps * (jnp.abs(ll) + jnp.abs(ll_prev))
    converged = (
        jnp.isfinite(ll) & stopped(k, ll, ll_prev) & (ll - ll_prev >= -slack)
        & q_psd & r_psd & jnp.all(jnp.isfinite(b)) & jnp.all(jnp.isfinite(d))
    )
    return EMResult(
        Q=q_lifted,
        R=r_lifted,
        process_offset=b,
        noise_offset=d,
        loglik=ll,
        loglik_history=hist,
        iterations=k,
        converged=converged,
    )

