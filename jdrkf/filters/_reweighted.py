"""Iteratively reweighted (variational) robust Kalman filters of Li, Shi, Yu, Shi,
"Variational Robust Kalman Filters: A Unified Framework": STKF (Algorithm 1), RBKF
(Algorithm 1 with the other losses of Table I), STKF-AR1/AR2 (Algorithms 2 and 3),
and the variational Bayes adaptive KF (Särkkä & Nummenmaa 2009) with forgetting or
with fixed priors.

All share one update (`irls_update`, eqs. 13–17): with `P⁻ = L_P L_Pᵀ` and
`R = L_R L_Rᵀ` (Cholesky), the whitened residuals `e_x = L_P⁻¹(x̂⁻ − x)` (process
channels) and `e_y = L_R⁻¹(y − H x)` (measurement channels) are weighted
componentwise, `P̃ = L_P diag(w_x)⁻¹ L_Pᵀ`, `R̃ = L_R diag(w_y)⁻¹ L_Rᵀ`,
`K̃ = P̃Hᵀ(HP̃Hᵀ + R̃)⁻¹`, `x = x̂⁻ + K̃(y − Hx̂⁻)`; the weights are re-evaluated at the
new `x`, starting from `x = x̂⁻`.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import Literal

import equinox as eqx
import equinox.internal as eqxi
import jax.numpy as jnp
from jax import lax
from jax.scipy.linalg import solve_triangular
from jaxtyping import Array, ArrayLike, Bool, Float, PRNGKeyArray

from .. import linalg
from .._gaussian import Gaussian, log_density
from .._validation import check_positive_int, in_range
from ..sets._weights import AbstractWeight, channel_param, student_t_weight
from ._base import DEFAULT_OUTPUTS, RESULTS, AbstractFilter, StepOutput
from ._kalman import predict
from ._steps import measurement, step_result

__all__ = ["RBKF", "STKF", "STKF_AR1", "STKF_AR2", "VBKF", "IRLSResult", "irls_update"]

Covariance = Literal["reweighted", "nominal"]
WeightFn = Callable[[Float[Array, " d"]], Float[Array, " d"]]


def _inflate(chol, w):
    """`L diag(w)⁻¹ Lᵀ`."""
    return linalg.symmetrize((chol / w) @ chol.T)


def _check_covariance(covariance):
    if covariance not in ("reweighted", "nominal"):
        raise ValueError(f"covariance must be 'reweighted' or 'nominal', got {covariance!r}")


def _check_static(max_iter, tol, covariance):
    check_positive_int("max_iter", max_iter)
    if not isinstance(tol, int | float) or not tol >= 0:
        raise ValueError(f"tol must be a number >= 0, got {tol!r}")
    _check_covariance(covariance)


class IRLSResult(eqx.Module):
    """Output of `irls_update`: the filtered law, the final gain, weights and inflated
    covariances, the whitened residuals at the final estimate, the Cholesky factors
    of `P⁻` and `R`, the log-density of the innovation under `HP̃Hᵀ + R̃`, a failure
    flag (non-positive-definite innovation covariance) and the number of iterations."""

    filtered: Gaussian
    gain: Float[Array, "n m"]
    weights_x: Float[Array, " n"]
    weights_y: Float[Array, " m"]
    prior_cov: Float[Array, "n n"]
    noise_cov: Float[Array, "m m"]
    e_x: Float[Array, " n"]
    e_y: Float[Array, " m"]
    chol_p: Float[Array, "n n"]
    chol_r: Float[Array, "m m"]
    loglik: Float[Array, ""]
    failed: Array
    iterations: Array


def irls_update(
    predicted: Gaussian,
    h: Float[Array, "m n"],
    r: Float[Array, "m m"],
    resid: Float[Array, " m"],
    weight_x: WeightFn | None,
    weight_y: WeightFn | None,
    *,
    max_iter: int,
    tol: float,
    fixed_iterations: bool = False,
    covariance: Covariance = "reweighted",
    num_observed: Float[ArrayLike, ""] | None = None,
) -> IRLSResult:
    """Fixed-point (IRLS) measurement update, Algorithm 1 lines 8–18 (eqs. 13–17).

    `resid = y − μ_v` (masked rows zero). `weight_x`, `weight_y` map whitened
    residuals to weights (`None`: weight 1, and `P̃ = P⁻` / `R̃ = R` exactly). From
    `x₀ = x̂⁻`, iteration `j` evaluates the weights at `x_{j−1}` and updates `x_j`; it
    stops when `‖x_j − x_{j−1}‖ ≤ tol ‖x_j‖` or after `max_iter` iterations (a while
    loop bounded by `max_iter`, `equinox.internal.while_loop(kind="bounded")`, which
    both forward and reverse mode differentiate: the derivative of the early-stopped
    iterate, exact where the iteration count is locally constant).
    `fixed_iterations=True` runs exactly `max_iter` iterations (`lax.fori_loop`), so
    the output is smooth in the hyper-parameters (no jumps when the count changes).

    Posterior covariance (line 18, Joseph form with the final gain `K̃`):
    `"reweighted"` uses the reweighted `P̃`, `R̃`, i.e. `(I − K̃H)P̃(I − K̃H)ᵀ + K̃R̃K̃ᵀ`
    (the covariance of the weighted least-squares problem (16) and of the VB
    posterior `Q_x`; it makes Theorem 4 and Proposition 2 exact). `"nominal"` uses
    the nominal `P⁻` and `R`, `(I − K̃H)P⁻(I − K̃H)ᵀ + K̃RK̃ᵀ`, which is what line 18
    prints (`P_k⁻`, `R_k`) and what the authors' MATLAB code computes for every
    iterative filter.
    """
    n, m = predicted.mean.shape[0], resid.shape[0]
    dtype = predicted.cov.dtype
    x_prior = predicted.mean
    chol_p = linalg.cholesky(predicted.cov)
    chol_r = linalg.cholesky(r)
    innov = resid - h @ x_prior

    def residuals(x):
        e_x = solve_triangular(chol_p, x_prior - x, lower=True)
        e_y = solve_triangular(chol_r, resid - h @ x, lower=True)
        return e_x, e_y

    def weights(x):
        e_x, e_y = residuals(x)
        w_x = jnp.ones(n, dtype) if weight_x is None else weight_x(e_x).astype(dtype)
        w_y = jnp.ones(m, dtype) if weight_y is None else weight_y(e_y).astype(dtype)
        return w_x, w_y

    def solve(w_x, w_y):
        p_t = predicted.cov if weight_x is None else _inflate(chol_p, w_x)
        r_t = r if weight_y is None else _inflate(chol_r, w_y)
        chol_s = linalg.cholesky(linalg.symmetrize(h @ p_t @ h.T + r_t))
        gain = linalg.cho_solve(chol_s, h @ p_t).T
        return x_prior + gain @ innov, gain, p_t, r_t, chol_s

    def body(carry):
        j, x, _, _, _ = carry
        w_x, w_y = weights(x)
        x_new = solve(w_x, w_y)[0]
        return j + 1, x_new, x, w_x, w_y

    w0 = weights(x_prior)
    init = (jnp.zeros((), jnp.int32), x_prior, x_prior, *w0)
    if fixed_iterations:
        _, x, _, w_x, w_y = lax.fori_loop(0, max_iter, lambda _, c: body(c), init)
        iterations = jnp.asarray(max_iter, jnp.int32)
    else:

        def cond(carry):
            j, x, x_old, _, _ = carry
            moved = jnp.linalg.norm(x - x_old) > tol * jnp.linalg.norm(x)
            return (j == 0) | ((j < max_iter) & moved)

        iterations, x, _, w_x, w_y = eqxi.while_loop(cond, body, init, max_steps=max_iter, kind="bounded")
    x, gain, p_t, r_t, chol_s = solve(w_x, w_y)
    a = jnp.eye(n, dtype=dtype) - gain @ h
    if covariance == "reweighted":
        cov = a @ p_t @ a.T + gain @ r_t @ gain.T
    else:
        cov = a @ predicted.cov @ a.T + gain @ r @ gain.T
    e_x, e_y = residuals(x)
    num_obs = m if num_observed is None else num_observed
    return IRLSResult(
        filtered=Gaussian(x, linalg.symmetrize(cov)),
        gain=gain,
        weights_x=w_x,
        weights_y=w_y,
        prior_cov=p_t,
        noise_cov=r_t,
        e_x=e_x,
        e_y=e_y,
        chol_p=chol_p,
        chol_r=chol_r,
        loglik=log_density(chol_s, innov, num_obs),
        failed=~jnp.all(jnp.isfinite(chol_s)),
        iterations=iterations,
    )


def _whitened_cov_diag(chol, a):
    """`diag(L⁻¹ A L⁻ᵀ)`."""
    z = solve_triangular(chol, a, lower=True)
    return jnp.diagonal(solve_triangular(chol, z.T, lower=True))


def _check_weight(name, w):
    if w is not None and not isinstance(w, AbstractWeight):
        raise ValueError(f"{name} must be a weight module from jdrkf.sets (StudentT, GaussianKernel, Barron, PseudoHuber, Huber) or None, got {type(w).__name__}")
    return w


def _check_len(name, x, size):
    if x is not None and x.ndim == 1 and x.shape[0] != size:
        raise ValueError(f"{name} has {x.shape[0]} entries but there are {size} channels")


class _IRLSFilter(AbstractFilter):
    """Shared static settings and step of the fixed-weight-function filters."""

    max_iter: eqx.AbstractVar[int]
    tol: eqx.AbstractVar[float]
    fixed_iterations: eqx.AbstractVar[bool]
    covariance: eqx.AbstractVar[str]

    def _weights(self) -> tuple[WeightFn | None, WeightFn | None]:
        raise NotImplementedError

    def _valid(self) -> Bool[Array, ""]:
        """Traced range check of the array hyper-parameters (`channel_param` checks
        concrete ones eagerly); out of range, steps report `RESULTS.invalid_hyperparameter`."""
        return jnp.asarray(True)

    def init(self, model, prior: Gaussian) -> Gaussian:
        return prior

    def step(self, model, state, y, t, u=None, key: PRNGKeyArray | None = None, observed=None):
        pred = predict(model, state, t, u)
        observed, h, r, resid = measurement(model, y, t, observed)
        wx, wy = self._weights()
        sol = irls_update(
            pred, h, r, resid, wx, wy,
            max_iter=self.max_iter, tol=self.tol, fixed_iterations=self.fixed_iterations,
            covariance=self.covariance, num_observed=jnp.sum(observed.astype(resid.dtype)),
        )
        filt = sol.filtered
        info = {"iterations": sol.iterations, "weights_x": sol.weights_x, "weights_y": sol.weights_y}
        result = RESULTS.where(self._valid(), step_result(sol.failed, filt), RESULTS.invalid_hyperparameter)
        out = StepOutput(predicted=pred, filtered=filt, loglik=sol.loglik, info=info, result=result)
        return filt, out


_COMMON_ARGS = """
    - `max_iter`, `tol`: iteration cap `m_iter` and relative-change threshold `ε` of
      Algorithm 1 line 10 (`‖x_j − x_{j−1}‖ ≤ ε‖x_j‖` stops; at least one iteration).
    - `fixed_iterations`: run exactly `max_iter` iterations (`lax.fori_loop`), which
      makes the output smooth in the hyper-parameters. Both modes support `jax.grad`
      and `jax.jvp` (the default early-stopped loop is bounded by `max_iter`; its
      derivative is that of the iterate actually computed).
    - `covariance`: posterior covariance of line 18, `"reweighted"` (default;
      `(I − K̃H)P̃(I − K̃H)ᵀ + K̃R̃K̃ᵀ`, the weighted-least-squares / VB covariance that
      makes Theorem 4 and Proposition 2 exact) or `"nominal"` (`P⁻` and `R` in place of
      `P̃`, `R̃`, as line 18 is printed and as the authors' MATLAB code computes it).
    - `throw`, `outputs`: as in `jdrkf.KalmanFilter`.

    `info` holds the iteration count and the final weights per step; `loglik` is the
    Gaussian log-density of the innovation under the final `HP̃Hᵀ + R̃` (a
    diagnostic; for disabled channels it is the Kalman filter's).
"""


class RBKF(_IRLSFilter):
    __doc__ = (
        """Robust Kalman filter with any loss of Table I (Algorithm 1 with `d_ν` replaced,
    Section III-A): RBKF1 = `GaussianKernel` (MKCKF), RBKF2 = `Barron`, RBKF3 =
    `PseudoHuber`; `StudentT` gives the STKF and `Huber` an IRLS Huber KF.

    **Arguments:**

    - `process_weight`, `measurement_weight`: weight modules of `jdrkf.sets` for the
      `n` process channels (whitened prior residual) and the `m` measurement
      channels; `None` = Gaussian (no reweighting). Per-channel parameters must
      have `n` resp. `m` entries.
    """
        + _COMMON_ARGS
        + """
    Defaults `max_iter=3`, `tol=1e-5` are the authors' RBKF settings.

    **Example:**

    ```python
    from jdrkf.sets._weights import GaussianKernel
    rbkf1 = RBKF(process_weight=GaussianKernel(2.0), measurement_weight=None)
    ```
    """
    )

    process_weight: AbstractWeight | None
    measurement_weight: AbstractWeight | None
    max_iter: int = eqx.field(static=True)
    tol: float = eqx.field(static=True)
    fixed_iterations: bool = eqx.field(static=True)
    covariance: str = eqx.field(static=True)

    def __init__(
        self,
        process_weight: AbstractWeight | None = None,
        measurement_weight: AbstractWeight | None = None,
        *,
        max_iter: int = 3,
        tol: float = 1e-5,
        fixed_iterations: bool = False,
        covariance: Covariance = "reweighted",
        throw: bool = True,
        outputs: str | Sequence[str] = DEFAULT_OUTPUTS,
    ):
        self.process_weight = _check_weight("process_weight", process_weight)
        self.measurement_weight = _check_weight("measurement_weight", measurement_weight)
        _check_static(max_iter, tol, covariance)
        self.max_iter, self.tol, self.fixed_iterations, self.covariance = max_iter, float(tol), fixed_iterations, covariance
        self.throw, self.outputs = throw, outputs

    def _valid(self):
        ok = jnp.asarray(True)
        for weight in (self.process_weight, self.measurement_weight):
            if weight is not None:
                ok = ok & weight.valid()
        return ok

    def _weights(self):
        return self.process_weight, self.measurement_weight

    def init(self, model, prior):
        if self.process_weight is not None:
            self.process_weight.check_size("process_weight", model.state_dim)
        if self.measurement_weight is not None:
            self.measurement_weight.check_size("measurement_weight", model.obs_dim)
        return prior


class STKF(_IRLSFilter):
    __doc__ = (
        """Student's t-based Kalman filter (Algorithm 1): the IRLS update with the
    Student-t weight `d_ν(e) = ν/(ν τ² + e²)` (eq. 17) on every channel.

    **Arguments:**

    - `nu_x`, `tau2_x`: degrees of freedom and scale of the `n` process channels
      (scalars or `(n,)`); `nu_x=None` (default) or `inf` disables them (Gaussian).
    - `nu_y`, `tau2_y`: the same for the `m` measurement channels (default `ν = 4`,
      `τ² = 1`, the paper's Example 1).
    """
        + _COMMON_ARGS
        + """
    Defaults `max_iter=4`, `tol=0.01` are the paper's Example 1 (the authors'
    `STKF.m` caps at 2 iterations). With all `ν = inf` and `τ² = 1` it is the
    Kalman filter (Proposition 1). With `nu_x=None`, `tol=0` and `max_iter=N` it
    equals `VBKF.student_t_equivalent(nu_y, tau2_y, N)` exactly (Theorem 4).

    **Example:**

    ```python
    stkf = STKF(nu_y=4.0)                                  # Example 1 of the paper
    res = stkf(model, prior, ys); res.info["iterations"]   # (T,) iterations per step
    g = jax.grad(lambda nu: loss(STKF(nu_y=nu)(model, prior, ys)))(4.0)
    ```
    """
    )

    nu_x: Float[Array, "*n"] | None
    tau2_x: Float[Array, "*n"]
    nu_y: Float[Array, "*m"] | None
    tau2_y: Float[Array, "*m"]
    max_iter: int = eqx.field(static=True)
    tol: float = eqx.field(static=True)
    fixed_iterations: bool = eqx.field(static=True)
    covariance: str = eqx.field(static=True)

    def __init__(
        self,
        nu_x: Float[ArrayLike, "*n"] | None = None,
        tau2_x: Float[ArrayLike, "*n"] = 1.0,
        nu_y: Float[ArrayLike, "*m"] | None = 4.0,
        tau2_y: Float[ArrayLike, "*m"] = 1.0,
        *,
        max_iter: int = 4,
        tol: float = 0.01,
        fixed_iterations: bool = False,
        covariance: Covariance = "reweighted",
        throw: bool = True,
        outputs: str | Sequence[str] = DEFAULT_OUTPUTS,
    ):
        self.nu_x = None if nu_x is None else channel_param("nu_x", nu_x, allow_inf=True)
        self.tau2_x = channel_param("tau2_x", tau2_x)
        self.nu_y = None if nu_y is None else channel_param("nu_y", nu_y, allow_inf=True)
        self.tau2_y = channel_param("tau2_y", tau2_y)
        _check_static(max_iter, tol, covariance)
        self.max_iter, self.tol, self.fixed_iterations, self.covariance = max_iter, float(tol), fixed_iterations, covariance
        self.throw, self.outputs = throw, outputs

    def _valid(self):
        ok = in_range(self.tau2_x, 0.0, lower_open=True) & in_range(self.tau2_y, 0.0, lower_open=True)
        for nu in (self.nu_x, self.nu_y):
            if nu is not None:
                ok = ok & in_range(nu, 0.0, lower_open=True, allow_inf=True)
        return ok

    def _weights(self):
        wx = None if self.nu_x is None else (lambda e: student_t_weight(e, self.nu_x, self.tau2_x))
        wy = None if self.nu_y is None else (lambda e: student_t_weight(e, self.nu_y, self.tau2_y))
        return wx, wy

    def init(self, model, prior):
        for name, size in (("nu_x", model.state_dim), ("tau2_x", model.state_dim), ("nu_y", model.obs_dim), ("tau2_y", model.obs_dim)):
            _check_len(name, getattr(self, name), size)
        return prior


# ----------------------------------------------------------------------------- STKF-AR


def _channels(name, x, size):
    _check_len(name, x, size)
    return jnp.broadcast_to(x, (size,))


class STKF_AR1(AbstractFilter):
    """Student's t-based KF with recursive hyper-parameters, STKF-AR1 (Algorithm 2,
    eqs. 42–45), and with the outlier switch of STKF-AR2 (Algorithm 3) when `eta` or
    `xi` is given (use `STKF_AR2`).

    Per channel `i` (the `n` process channels, then the `m` measurement channels)
    with forgetting `ρ_i < 1`: predict `ν_i ← ρ_i ν_i + 1`, `τ²_i⁻ = ρ_i τ²_i` (eq. 43);
    run the STKF update (Algorithm 1) with `(ν_i, τ²_i⁻)`; then (eq. 44)
    `τ²_i⁺ = τ²_i⁻ + (e_i² + [W P Wᵀ]_ii) / ν_i` with the whitened residual `e` at the
    posterior mean and `W = blkdiag(L_P⁻¹, L_R⁻¹ H)`. Channels with `ρ_i = 1` keep
    their `ν_i`, `τ²_i` (eq. 45). Missing measurement channels keep theirs too.

    **Arguments:** `nu_x`, `tau2_x`, `rho_x` (process channels; scalars or `(n,)`),
    `nu_y`, `tau2_y`, `rho_y` (measurement channels; scalars or `(m,)`): initial
    `ν`, `τ²` and forgetting factors `ρ ∈ (0, 1]`; `nu = inf` disables a channel.
    `max_iter`, `tol`, `fixed_iterations`, `covariance`, `throw`, `outputs`:
    as in `STKF` (defaults: the authors' `student_forward_adap`, 4 iterations, 1e-5).
    `gate` (static, optional): the authors' `student_forward_adap_y2` outlier gate, not
    in the paper: the measurement channels' `τ²` update is skipped (`τ²` kept) at
    steps with `‖e_y‖² > gate` (they use 40), `e_y` the whitened posterior residual.

    Proposition 2: all `ρ = 1` gives the STKF. With process `ν = inf`, `ρ_x = 1`,
    measurement `ρ_y = ρ_c` and `ν_y = 1/(1 − ρ_c)` (the fixed point of eq. 43),
    `tol = 0`, it equals `VBKF(alpha0=ν_y/2, beta0=ν_y τ²_y/2, rho=ρ_c,
    shape_increment=0.5, start="predicted", covariance_in_iterations=False)` exactly.
    For other initial `ν_y` the two differ while `ν` converges: eq. 43 forgets `τ²`
    by `ρ`, whereas the VB recursion forgets `β = ντ²/2` by `ρ`, i.e. `τ²` by `ρν_{k−1}/ν_k`.

    `info`: iterations, final weights, `nu` and `tau2` (`(n + m,)`, after the step).
    """

    nu_x: Float[Array, "*n"]
    tau2_x: Float[Array, "*n"]
    rho_x: Float[Array, "*n"]
    nu_y: Float[Array, "*m"]
    tau2_y: Float[Array, "*m"]
    rho_y: Float[Array, "*m"]
    eta: Float[Array, "*d"] | None
    xi: Float[Array, "*d"] | None
    gate: float | None = eqx.field(static=True)
    max_iter: int = eqx.field(static=True)
    tol: float = eqx.field(static=True)
    fixed_iterations: bool = eqx.field(static=True)
    covariance: str = eqx.field(static=True)

    def __init__(
        self,
        nu_x: Float[ArrayLike, "*n"] = jnp.inf,
        tau2_x: Float[ArrayLike, "*n"] = 1.0,
        rho_x: Float[ArrayLike, "*n"] = 1.0,
        nu_y: Float[ArrayLike, "*m"] = 100.0,
        tau2_y: Float[ArrayLike, "*m"] = 1.0,
        rho_y: Float[ArrayLike, "*m"] = 0.99,
        *,
        eta: Float[ArrayLike, "*d"] | None = None,
        xi: Float[ArrayLike, "*d"] | None = None,
        gate: float | None = None,
        max_iter: int = 4,
        tol: float = 1e-5,
        fixed_iterations: bool = False,
        covariance: Covariance = "reweighted",
        throw: bool = True,
        outputs: str | Sequence[str] = DEFAULT_OUTPUTS,
    ):
        self.nu_x = channel_param("nu_x", nu_x, allow_inf=True)
        self.tau2_x = channel_param("tau2_x", tau2_x)
        self.rho_x = channel_param("rho_x", rho_x, upper=1.0)
        self.nu_y = channel_param("nu_y", nu_y, allow_inf=True)
        self.tau2_y = channel_param("tau2_y", tau2_y)
        self.rho_y = channel_param("rho_y", rho_y, upper=1.0)
        if eta is not None and xi is not None:
            raise ValueError("give eta or xi, not both")
        self.eta = None if eta is None else channel_param("eta", eta)
        self.xi = None if xi is None else channel_param("xi", xi, lower_open=False, allow_inf=True)
        if gate is not None and (not isinstance(gate, int | float) or not gate > 0):
            raise ValueError(f"gate must be a number > 0 or None, got {gate!r}")
        self.gate = None if gate is None else float(gate)
        _check_static(max_iter, tol, covariance)
        self.max_iter, self.tol, self.fixed_iterations, self.covariance = max_iter, float(tol), fixed_iterations, covariance
        self.throw, self.outputs = throw, outputs

    def init(self, model, prior: Gaussian):
        n, m = model.state_dim, model.obs_dim
        nu = jnp.concatenate([_channels("nu_x", self.nu_x, n), _channels("nu_y", self.nu_y, m)])
        tau2 = jnp.concatenate([_channels("tau2_x", self.tau2_x, n), _channels("tau2_y", self.tau2_y, m)])
        for name in ("rho_x", "rho_y"):
            _check_len(name, getattr(self, name), n if name == "rho_x" else m)
        for name in ("eta", "xi"):
            v = getattr(self, name)
            if v is not None:
                _check_len(name, v, n + m)
        dtype = prior.cov.dtype
        return prior, nu.astype(dtype), tau2.astype(dtype)

    def _valid(self) -> Bool[Array, ""]:
        """Traced range check (the intervals of the eager `channel_param` checks)."""
        ok = jnp.asarray(True)
        for nu, tau2, rho in ((self.nu_x, self.tau2_x, self.rho_x), (self.nu_y, self.tau2_y, self.rho_y)):
            ok = ok & in_range(nu, 0.0, lower_open=True, allow_inf=True) & in_range(tau2, 0.0, lower_open=True)
            ok = ok & in_range(rho, 0.0, 1.0, lower_open=True)
        if self.eta is not None:
            ok = ok & in_range(self.eta, 0.0, lower_open=True)
        if self.xi is not None:
            ok = ok & in_range(self.xi, 0.0, allow_inf=True)
        return ok

    def step(self, model, state, y, t, u=None, key: PRNGKeyArray | None = None, observed=None):
        belief, nu_prev, tau2_prev = state
        n = belief.mean.shape[0]
        m = y.shape[0]
        rho = jnp.concatenate([jnp.broadcast_to(self.rho_x, (n,)), jnp.broadcast_to(self.rho_y, (m,))])
        adaptive = rho < 1.0
        # Eq. 43 (ρ < 1) or 45 (ρ = 1).
        nu = jnp.where(adaptive, rho * nu_prev + 1.0, nu_prev)
        tau2_minus = jnp.where(adaptive, rho * tau2_prev, tau2_prev)

        pred = predict(model, belief, t, u)
        observed, h, r, resid = measurement(model, y, t, observed)
        sol = irls_update(
            pred, h, r, resid,
            lambda e: student_t_weight(e, nu[:n], tau2_minus[:n]),
            lambda e: student_t_weight(e, nu[n:], tau2_minus[n:]),
            max_iter=self.max_iter, tol=self.tol, fixed_iterations=self.fixed_iterations,
            covariance=self.covariance, num_observed=jnp.sum(observed.astype(resid.dtype)),
        )
        filt = sol.filtered
        # Eq. 44: whitened residuals and diag(W P Wᵀ) at the posterior.
        e = jnp.concatenate([sol.e_x, sol.e_y])
        wpw = jnp.concatenate(
            [_whitened_cov_diag(sol.chol_p, filt.cov), _whitened_cov_diag(sol.chol_r, h @ filt.cov @ h.T)]
        )
        finite, nu_s = jnp.isfinite(nu), jnp.where(jnp.isfinite(nu), nu, 1.0)
        tau2_plus = tau2_minus + jnp.where(finite, (e**2 + wpw) / nu_s, 0.0)
        tau2 = jnp.where(adaptive, tau2_plus, tau2_prev)
        if self.eta is not None or self.xi is not None:
            # Algorithm 3: revert outlying updates, ξ = η sqrt(2ν²/(ν+1)³) τ² by default.
            if self.xi is not None:
                xi = jnp.broadcast_to(self.xi, nu.shape)
            else:
                xi = jnp.where(finite, self.eta * jnp.sqrt(2.0 * nu_s**2 / (nu_s + 1.0) ** 3) * tau2_minus, 0.0)
            tau2 = jnp.where(adaptive & (jnp.abs(tau2_plus - tau2_minus) > xi), tau2_prev, tau2)
        if self.gate is not None:
            gated = jnp.sum(sol.e_y**2) > self.gate
            tau2 = jnp.where(jnp.concatenate([jnp.zeros(n, bool), jnp.full(m, gated)]), tau2_prev, tau2)
        keep = jnp.concatenate([jnp.ones(n, bool), observed])
        nu, tau2 = jnp.where(keep, nu, nu_prev), jnp.where(keep, tau2, tau2_prev)
        info = {"iterations": sol.iterations, "weights_x": sol.weights_x, "weights_y": sol.weights_y, "nu": nu, "tau2": tau2}
        result = RESULTS.where(self._valid(), step_result(sol.failed, filt), RESULTS.invalid_hyperparameter)
        out = StepOutput(predicted=pred, filtered=filt, loglik=sol.loglik, info=info, result=result)
        return (filt, nu, tau2), out


class STKF_AR2(STKF_AR1):
    """STKF-AR2 (Algorithm 3): STKF-AR1 whose `τ²` update (eq. 44) of an adaptive channel
    is reverted to the previous `τ²_{k−1}⁺` when `|τ²⁺ − τ²⁻| > ξ` (the step is taken
    as an outlier). `ξ = η sqrt(2ν²/(ν + 1)³) τ²` (the paper's advice, `η ∈ [0.25, 1]`,
    evaluated each step at the current `ν_k` and `τ²_k⁻`), or a fixed `xi`.
    `xi = inf` never reverts and gives STKF-AR1 (the paper writes `ξ = 0`, which under
    Algorithm 3's rule would revert every update). `ν` is not reverted (line 7 of
    Algorithm 3 reverts `τ²` only). Other arguments as in `STKF_AR1`.
    """

    def __init__(self, *args, eta: Float[ArrayLike, "*d"] | None = None, xi: Float[ArrayLike, "*d"] | None = None, **kwargs):
        if eta is None and xi is None:
            eta = 1.0
        super().__init__(*args, eta=eta, xi=xi, **kwargs)


# ----------------------------------------------------------------------------- VBKF


class VBKF(AbstractFilter):
    """Variational Bayes adaptive Kalman filter (Särkkä & Nummenmaa 2009) with
    forgetting, in the whitened form of the authors' `akf_forward_vb.m`: the noise
    covariance is `R_k = L_R diag(λ) L_Rᵀ` with independent `λ_i ~ Inv-Gam(α_i, β_i)`.

    Per step: `α⁻ = ρα`, `β⁻ = ρβ` (with `fixed_prior=True`: `α⁻ = alpha0`,
    `β⁻ = beta0` every step), `α = α⁻ + shape_increment`; then `num_iter` times:
    `λ = β/α`, Kalman update with `R_k` (Joseph form), `β = β⁻ + ½e_y² + ½ diag(W P Wᵀ)`
    with `e_y = L_R⁻¹(y − Hx)`, `W = L_R⁻¹H`. The prior covariance is not adapted.
    (`λ` scales the nominal `R`; for a diagonal `R`, the authors' absolute-variance
    version `R_k = diag(λ_abs)` with `(α₀, β₀)` is `beta0 = β₀ / R_ii` here.)

    **Arguments:**

    - `alpha0`, `beta0`: initial (or fixed) inverse-gamma shape and scale, scalars
      or `(m,)`; `rho ∈ (0, 1]`: forgetting factor (scalar or `(m,)`).
    - `num_iter` (static): VB iterations per step.
    - `fixed_prior` (static): reset `(α⁻, β⁻)` to `(alpha0, beta0)` every step.
    - `shape_increment` (static, default ½): added to `α` per observation.
    - `start` (static): `"scale"` (default, Särkkä's order: the first update uses
      `λ = β⁻/α`) or `"predicted"` (update `β` first at the predicted mean/covariance).
    - `covariance_in_iterations` (static, default `True`): include `½ diag(W P Wᵀ)` in
      `β` inside the iterations (it always enters the `β` carried to the next step).
    - `covariance` (static): the posterior covariance of each pass, `"reweighted"`
      (default; the Joseph form with the adapted `R_k`, `(I − KH)P⁻(I − KH)ᵀ + KR_kKᵀ`, the
      VB posterior) or `"nominal"` (`K R Kᵀ` with the nominal `R`, as the authors'
      `akf_forward_vb.m` computes it; see `jdrkf.STKF`'s `covariance`).
    - `throw`, `outputs`: as in `jdrkf.KalmanFilter` (missing channels keep
      their `α`, `β`).

    Theorem 4 (STKF ≡ VBKF with fixed priors) is exact for the settings of
    `VBKF.student_t_equivalent`: `α = ν/2` (`shape_increment=0`), `β⁻ = ντ²/2`,
    `start="predicted"`, `covariance_in_iterations=False`, so that the iterates use
    `λ = τ² + e²/ν`, eq. 18. The authors' `VBKF_fixed.m` (`α = β = 2`, 4 iterations)
    uses `start="scale"` and the covariance term, so it is only close to STKF.

    `info`: `lam` (`β/α` after the step), `alpha`, `beta`.

    **Example:**

    ```python
    vbkf = VBKF(alpha0=50.0, beta0=50.0, rho=0.99)         # Example 1, Case 2
    vbkf(model, prior, ys).info["lam"]                     # (T, m) scale of R per step
    ```
    """

    alpha0: Float[Array, "*m"]
    beta0: Float[Array, "*m"]
    rho: Float[Array, "*m"]
    num_iter: int = eqx.field(static=True)
    fixed_prior: bool = eqx.field(static=True)
    shape_increment: float = eqx.field(static=True)
    start: str = eqx.field(static=True)
    covariance_in_iterations: bool = eqx.field(static=True)
    covariance: str = eqx.field(static=True)

    def __init__(
        self,
        alpha0: Float[ArrayLike, "*m"] = 50.0,
        beta0: Float[ArrayLike, "*m"] = 50.0,
        rho: Float[ArrayLike, "*m"] = 0.99,
        num_iter: int = 4,
        *,
        fixed_prior: bool = False,
        shape_increment: float = 0.5,
        start: Literal["scale", "predicted"] = "scale",
        covariance_in_iterations: bool = True,
        covariance: Covariance = "reweighted",
        throw: bool = True,
        outputs: str | Sequence[str] = DEFAULT_OUTPUTS,
    ):
        self.alpha0 = channel_param("alpha0", alpha0)
        self.beta0 = channel_param("beta0", beta0)
        self.rho = channel_param("rho", rho, upper=1.0)
        num_iter = check_positive_int("num_iter", num_iter)
        if not isinstance(shape_increment, int | float) or not shape_increment >= 0:
            raise ValueError(f"shape_increment must be a number >= 0, got {shape_increment!r}")
        if start not in ("scale", "predicted"):
            raise ValueError(f"start must be 'scale' or 'predicted', got {start!r}")
        self.num_iter, self.fixed_prior, self.shape_increment = num_iter, fixed_prior, float(shape_increment)
        _check_covariance(covariance)
        self.start, self.covariance_in_iterations, self.covariance = start, covariance_in_iterations, covariance
        self.throw, self.outputs = throw, outputs

    @classmethod
    def student_t_equivalent(
        cls, nu: Float[ArrayLike, "*m"], tau2: Float[ArrayLike, "*m"] = 1.0, num_iter: int = 4, **kwargs
    ) -> VBKF:
        """The VBKF with fixed prior `Inv-Gam(ν/2, ντ²/2)` that equals
        `STKF(nu_x=None, nu_y=nu, tau2_y=tau2, max_iter=num_iter, tol=0)` (Theorem 4)."""
        nu = channel_param("nu", nu)
        tau2 = channel_param("tau2", tau2)
        return cls(
            0.5 * nu, 0.5 * nu * tau2, 1.0, num_iter, fixed_prior=True, shape_increment=0.0,
            start="predicted", covariance_in_iterations=False, **kwargs,
        )

    def init(self, model, prior: Gaussian):
        m = model.obs_dim
        dtype = prior.cov.dtype
        alpha = _channels("alpha0", self.alpha0, m).astype(dtype)
        beta = _channels("beta0", self.beta0, m).astype(dtype)
        _check_len("rho", self.rho, m)
        return prior, alpha, beta

    def step(self, model, state, y, t, u=None, key: PRNGKeyArray | None = None, observed=None):
        belief, alpha_prev, beta_prev = state
        pred = predict(model, belief, t, u)
        observed, h, r, resid = measurement(model, y, t, observed)
        obs_f = observed.astype(resid.dtype)
        m = resid.shape[0]
        if self.fixed_prior:
            alpha_minus = jnp.broadcast_to(self.alpha0, (m,)).astype(resid.dtype)
            beta_minus = jnp.broadcast_to(self.beta0, (m,)).astype(resid.dtype)
        else:
            alpha_minus, beta_minus = self.rho * alpha_prev, self.rho * beta_prev
        alpha = alpha_minus + self.shape_increment * obs_f
        chol_r = linalg.cholesky(r)
        innov = resid - h @ pred.mean
        num_obs = jnp.sum(obs_f)

        def kf(beta):
            r_t = _inflate(chol_r, alpha / beta)
            chol_s = linalg.cholesky(linalg.symmetrize(h @ pred.cov @ h.T + r_t))
            gain = linalg.cho_solve(chol_s, h @ pred.cov).T
            a = jnp.eye(pred.mean.shape[0], dtype=pred.cov.dtype) - gain @ h
            r_c = r if self.covariance == "nominal" else r_t
            cov = linalg.symmetrize(a @ pred.cov @ a.T + gain @ r_c @ gain.T)
            return Gaussian(pred.mean + gain @ innov, cov), chol_s

        def beta_of(g: Gaussian, with_cov: bool):
            e = solve_triangular(chol_r, resid - h @ g.mean, lower=True)
            b = beta_minus + 0.5 * e**2
            if with_cov:
                b = b + 0.5 * _whitened_cov_diag(chol_r, h @ g.cov @ h.T)
            return b

        beta = beta_minus if self.start == "scale" else beta_of(pred, self.covariance_in_iterations)

        def body(_, carry):
            g, _ = carry
            return kf(beta_of(g, self.covariance_in_iterations))

        filt, chol_s = lax.fori_loop(0, self.num_iter - 1, body, kf(beta))
        beta = jnp.where(observed, beta_of(filt, True), beta_prev)
        alpha = jnp.where(observed, alpha, alpha_prev)
        info = {"lam": beta / alpha, "alpha": alpha, "beta": beta}
        if self.fixed_prior:
            alpha, beta = alpha_prev, beta_prev
        failed = ~jnp.all(jnp.isfinite(chol_s))
        valid = in_range(self.alpha0, 0.0, lower_open=True) & in_range(self.beta0, 0.0, lower_open=True)
        valid = valid & in_range(self.rho, 0.0, 1.0, lower_open=True)
        out = StepOutput(
            predicted=pred, filtered=filt, loglik=log_density(chol_s, innov, num_obs), info=info,
            result=RESULTS.where(valid, step_result(failed, filt), RESULTS.invalid_hyperparameter),
        )
        return (filt, alpha, beta), out
