"""Time-varying and steady-state Wasserstein DR Kalman filters (Jang, Hakobyan & Yang,
"On the steady-state distributionally robust Kalman filter"; seed 004)."""

from __future__ import annotations

from typing import ClassVar

import equinox as eqx
import jax
import jax.numpy as jnp
from jax import lax
from jax.flatten_util import ravel_pytree
from jaxtyping import Array, ArrayLike, Bool, Float, Int, PRNGKeyArray

from .. import linalg
from .._gaussian import Gaussian
from .._models import LinearModel
from ..sets._base import radius
from ..sets._solve import _dense_solve, default_rtol, worst_case
from ..sets._wasserstein import Wasserstein
from ._base import AbstractFilter
from ._dr import _decoupled_step
from ._kalman import SteadyStateGain, _constant_gain_step


def _posterior(prior_cov, noise_cov, h):
    """Posterior covariance `Σ⁻ − Σ⁻Cᵀ(CΣ⁻Cᵀ + Σv)⁻¹CΣ⁻` (eq. 8) and the gain (eq. 9)."""
    gain = linalg.psd_solve(linalg.symmetrize(h @ prior_cov @ h.T + noise_cov), h @ prior_cov).T
    a = jnp.eye(prior_cov.shape[0], dtype=prior_cov.dtype) - gain @ h
    return linalg.symmetrize(a @ prior_cov @ a.T + gain @ noise_cov @ gain.T), gain


def _time_invariant(model: LinearModel, who: str):
    if not isinstance(model, LinearModel):
        raise ValueError(f"model must be a jdrkf.LinearModel, got {type(model).__name__}")
    if model.num_steps is not None:
        raise ValueError(f"{who} needs a time-invariant model (no leading time axis)")
    return model.F, model.H, linalg.symmetrize(model.G @ model.Q @ model.G.T), model.R


class CovarianceRecursion(eqx.Module):
    """The DR Riccati recursion (eqs. 5, 8, 11, 15) over `num_steps` steps, stacked:
    `nominal_prior_cov` (the pseudo-nominal `Σ̂⁻_t`), the worst-case `prior_cov`
    (`Σ⁻*_t`) and `noise_cov` (`Σv*_t`), `posterior_cov` (`Σ_t`), `gain` (`K*_t`) and the
    solver's `converged` flags."""

    nominal_prior_cov: Float[Array, "T n n"]
    prior_cov: Float[Array, "T n n"]
    noise_cov: Float[Array, "T m m"]
    posterior_cov: Float[Array, "T n n"]
    gain: Float[Array, "T n m"]
    converged: Bool[Array, " T"]


class WassersteinDRKF(AbstractFilter):
    """Time-varying Wasserstein DR Kalman filter (Jang et al., Theorem 1, eqs. 6–11).

    Each step predicts with the nominal model, `x̄⁻ = A x̄ + B u + ŵ` and the
    pseudo-nominal `Σ̂⁻ = A Σ Aᵀ + Σ̂w` (eqs. 10–11), solves the decoupled DR-MMSE
    problem (5) — Gelbrich balls of radii `θx` around `Σ̂⁻` and `θv` around `Σ̂v` — by
    the first-order solver of `jdrkf.sets.worst_case` (Frank–Wolfe with the closed-form
    oracle, Newton polish, implicit derivatives), and updates with the worst-case
    gain `K* = Σ⁻*Cᵀ(CΣ⁻*Cᵀ + Σv*)⁻¹` and nominal noise mean `v̂` (eqs. 7–9).

    It equals `jdrkf.DRKF(Wasserstein(theta_x), Wasserstein(theta_v))`. `predicted` is the
    worst-case prior `N(x̄⁻, Σ⁻*)`; `info` holds the pseudo-nominal prior, the worst-case
    noise covariance, the solver's iterations and gap. The paper measures `y_0`
    before any prediction; with jdrkf's time convention (`prior` is the law of `x_0`,
    `ys[0] = y_1`) pass the law of `x_{-1}`, or update on `y_0` first (as
    `jdrkf.closed_loop` does).

    **Arguments:** `theta_x`, `theta_v` (radii ≥ 0, differentiable); `rtol`, `max_iter`,
    `throw`, `nan_as_missing` as in `jdrkf.DRKF`.
    """

    theta_x: Float[Array, ""]
    theta_v: Float[Array, ""]
    rtol: float | None = eqx.field(static=True)
    max_iter: int = eqx.field(static=True)
    throw: bool = eqx.field(static=True)
    nan_as_missing: bool = eqx.field(static=True)
    shared_covariance: ClassVar[bool] = True

    def __init__(self, theta_x: Float[ArrayLike, ""], theta_v: Float[ArrayLike, ""], *, rtol: float | None = None,
                 max_iter: int = 500, throw: bool = True, nan_as_missing: bool = True):
        self.theta_x = radius("theta_x", theta_x)
        self.theta_v = radius("theta_v", theta_v)
        self.rtol, self.max_iter, self.throw, self.nan_as_missing = rtol, max_iter, throw, nan_as_missing

    def init(self, model, prior: Gaussian) -> Gaussian:
        return prior

    def step(self, model, state, y, t, u=None, key: PRNGKeyArray | None = None):
        return _decoupled_step(self, model, state, y, t, u, Wasserstein(self.theta_x), Wasserstein(self.theta_v), None)

    def covariance_recursion(self, model: LinearModel, nominal_prior_cov: Float[ArrayLike, "n n"], num_steps: int) -> CovarianceRecursion:
        """Run the covariance part of the filter (the DR Riccati recursion (15)) for
        `num_steps` measurement updates, starting from the pseudo-nominal prior
        covariance `Σ̂⁻_0` of the first measured state. No data are needed: with
        `nan_as_missing=False`-style full observations the covariances do not depend
        on them. Its fixed point is the limit of the time-varying filter, which in
        general differs from `SteadyStateDRKF.solve` (see there)."""
        a, h, w, v = _time_invariant(model, "covariance_recursion")
        nominal = jnp.asarray(nominal_prior_cov, a.dtype)
        if nominal.shape != a.shape:
            raise ValueError(f"nominal_prior_cov has shape {tuple(nominal.shape)} but expected {tuple(a.shape)}")
        sx, sv = Wasserstein(self.theta_x), Wasserstein(self.theta_v)

        def body(nom, _):
            sol = worst_case(sx, sv, nom, h, v, rtol=self.rtol, max_iter=self.max_iter)
            post, gain = _posterior(sol.state_cov, sol.noise_cov, h)
            out = CovarianceRecursion(nom, sol.state_cov, sol.noise_cov, post, gain, sol.converged)
            return linalg.symmetrize(a @ post @ a.T + w), out

        _, out = lax.scan(body, nominal, None, length=int(num_steps))
        return out


class SteadyStateDR(eqx.Module):
    """Solution of the steady-state DR problem (13)/(14).

    - `gain`: `K_ss = Σ⁻*Cᵀ(CΣ⁻*Cᵀ + Σv*)⁻¹` (Algorithm 1, line 3).
    - `prior_cov` (`Σ⁻*_ss`), `noise_cov` (`Σv*_ss`), `posterior_cov` (`Σ*_ss`), and the
      stationary pseudo-nominal prior `nominal_prior_cov = A Σ*_ss Aᵀ + Σ̂w`.
    - `value`: `Tr Σ*_ss`, the optimal value of (14).
    - `adjoint`: the multiplier `Λ` of the stationarity constraint (see `SteadyStateDRKF`).
    - `iterations`: Newton iterations; `residual`: the norm of the optimality system at
      the solution; `converged`: `residual` small relative to the solution.
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


def _stationary_residual(a, h, w, v, theta_x, theta_v):
    """Optimality system of (13) in `z = (Σ⁻, Σv, s_x, s_v, Λ)`.

    With `Σ = post(Σ⁻, Σv)`, `Σ̂⁻ = A Σ Aᵀ + Σ̂w`, weight `Ŵ = I + AᵀΛA` and the gradients
    `D_x = (I − KC)ᵀŴ(I − KC)`, `D_v = KᵀŴK` of `Tr(Ŵ post)`:
    `Σ⁻ = LMO_{Σ̂⁻}(D_x)`, `Σv = LMO_{Σ̂v}(D_v)` (each with its scalar multiplier, as the
    sets' residuals write them) and `Λ = D_x (I − θx s_x D_x)⁻¹` (the sensitivity of the
    weighted value to the pseudo-nominal, i.e. the multiplier of `Σ̂⁻ = A Σ Aᵀ + Σ̂w`).
    """
    sx, sv = Wasserstein(theta_x), Wasserstein(theta_v)
    n = a.shape[0]
    eye = jnp.eye(n, dtype=a.dtype)

    def residual(z):
        prior, noise, mx, mv, lam = z
        post, gain = _posterior(prior, noise, h)
        nominal = linalg.symmetrize(a @ post @ a.T + w)
        weight = eye + a.T @ lam @ a
        e = eye - gain @ h
        dx = linalg.symmetrize(e.T @ weight @ e)
        dv = linalg.symmetrize(gain.T @ weight @ gain)
        r_prior, q_x = sx.residual(prior, mx, dx, nominal)
        r_noise, q_v = sv.residual(noise, mv, dv, v)
        t = linalg.psd_solve(eye - sx.theta.astype(a.dtype) * mx * dx, eye)
        return r_prior, r_noise, q_x, q_v, lam - linalg.symmetrize(dx @ t)

    return residual


def _initial_guess(a, h, w, v, theta_x, theta_v):
    """Nominal steady state (filtering DARE), its adjoint (the discrete Lyapunov
    equation `Λ = EᵀE + EᵀAᵀΛAE`, `E = I − KC`), and one linear oracle per set for the
    weighted gradients there."""
    n = a.shape[0]
    eye = jnp.eye(n, dtype=a.dtype)
    nominal = linalg.solve_dare(a, h, w, v)
    _, gain = _posterior(nominal, v, h)
    e = eye - gain @ h
    m = a @ e
    lam = jnp.linalg.solve(jnp.eye(n * n, dtype=a.dtype) - jnp.kron(m.T, m.T), (e.T @ e).reshape(-1)).reshape(n, n)
    lam = linalg.symmetrize(lam)
    weight = eye + a.T @ lam @ a
    prior, mx = Wasserstein(theta_x).oracle(e.T @ weight @ e, nominal)
    noise, mv = Wasserstein(theta_v).oracle(gain.T @ weight @ gain, v)
    return prior, noise, mx, mv, lam


def _newton(residual, z0, max_iter, in_domain):
    """Newton's method with backtracking on `‖F‖` and a dense Jacobian (`jacfwd`);
    trial points outside `in_domain` (or with non-finite residuals) are rejected."""
    flat0, unravel = ravel_pytree(z0)
    dtype = flat0.dtype
    eps = jnp.finfo(dtype).eps

    def f(x):
        return ravel_pytree(residual(unravel(x)))[0]

    def merit(x):
        r = f(x)
        ok = jnp.all(jnp.isfinite(r)) & in_domain(unravel(x))
        return jnp.where(ok, jnp.linalg.norm(r), jnp.inf)

    def cond(c):
        x, k, nr, stalled = c
        return (k < max_iter) & ~stalled & (nr > 10 * eps * (1.0 + jnp.linalg.norm(x)))

    def body(c):
        x, k, nr, _ = c
        jac, r = jax.jacfwd(lambda y: (f(y), f(y)), has_aux=True)(x)
        dx = jnp.linalg.solve(jac, r)

        def ls_cond(b):
            step, nt, j = b
            return (nt >= (1.0 - 1e-4 * step) * nr) & (j < 40)

        def ls_body(b):  # backtracking (Armijo on ‖F‖): steps 1, 1/2, 1/4, …
            step, _, j = b
            step = jnp.where(j == 0, step, 0.5 * step)
            return step, merit(x - step * dx), j + 1

        step, nt, _ = lax.while_loop(ls_cond, ls_body, (jnp.ones((), dtype), jnp.asarray(jnp.inf, dtype), 0))
        ok = nt < nr
        return jnp.where(ok, x - step * dx, x), k + 1, jnp.where(ok, nt, nr), ~ok

    init = (flat0, jnp.zeros((), int), merit(flat0), jnp.zeros((), bool))
    x, k, nr, _ = lax.while_loop(cond, body, init)
    return unravel(x), k, nr, nr <= default_rtol(dtype) * (1.0 + jnp.linalg.norm(x))


def _continuation(a, h, w, v, theta_x, theta_v, max_iter):
    """Solve the optimality system for radii `τ(θx, θv)`, `τ: 0 → 1`. At `τ = 0` the
    initial guess is exact (the nominal steady state and its adjoint); each stage is
    a Newton solve warm-started at the previous one; the step in `τ` doubles after a
    success and halves after a failure (first try: `τ = 1` directly)."""
    dtype = a.dtype
    zero = jnp.zeros((), dtype)
    # On the branch of the convex problem's KKT point the ball multipliers are positive
    # (negative roots of the sets' scalar equations belong to the minimizing oracle) and
    # `I + AᵀΛA`, the multiplier of the Schur inequality of (14), is PSD; the system has
    # other roots, with an indefinite weight and a lower value.
    def in_domain(z):
        weight = jnp.linalg.eigvalsh(linalg.symmetrize(jnp.eye(a.shape[0], dtype=dtype) + a.T @ z[4] @ a))
        return (z[2] > 0) & (z[3] > 0) & (weight[0] > 0)

    def cond(c):
        _, tau, dtau, _, _, _ = c
        return (tau < 1) & (dtau >= 2.0**-10)

    def body(c):
        z, tau, dtau, iters, nr, ok = c
        t = jnp.minimum(tau + dtau, 1.0)
        zt, k, nrt, okt = _newton(_stationary_residual(a, h, w, v, t * theta_x, t * theta_v), z, max_iter, in_domain)
        z = jax.tree.map(lambda x, y: jnp.where(okt, x, y), zt, z)
        return (z, jnp.where(okt, t, tau), jnp.where(okt, 2.0 * dtau, 0.5 * dtau), iters + k,
                jnp.where(okt, nrt, nr), okt)

    z0 = _initial_guess(a, h, w, v, zero, zero)
    init = (z0, zero, jnp.ones((), dtype), jnp.zeros((), int), zero, jnp.zeros((), bool))
    z, tau, _, iters, nr, _ = lax.while_loop(cond, body, init)
    converged = tau >= 1
    return z, iters, jnp.where(converged, nr, jnp.inf), converged


@eqx.filter_jit
def _steady_state(a, h, w, v, theta_x, theta_v, max_iter):
    with linalg.lapack_only():
        return _steady_state_impl(a, h, w, v, theta_x, theta_v, max_iter)


def _steady_state_impl(a, h, w, v, theta_x, theta_v, max_iter):
    params = (a, h, w, v, theta_x, theta_v)

    def solve(_, guess):
        del guess
        p = jax.tree.map(lax.stop_gradient, params)
        z, k, nr, ok = _continuation(*p, max_iter)
        return z, (k.astype(nr.dtype), nr, ok.astype(nr.dtype))

    zero = jnp.zeros((), a.dtype)
    guess = _initial_guess(*jax.tree.map(lax.stop_gradient, (a, h, w, v)), zero, zero)
    z, (k, nr, ok) = lax.custom_root(_stationary_residual(*params), guess, solve, _dense_solve, has_aux=True)
    prior, noise, _, _, lam = z
    prior = linalg.symmetrize(prior)
    noise = jnp.where(theta_v == 0, v, linalg.symmetrize(noise))  # exact at zero radius
    post, gain = _posterior(prior, noise, h)
    converged = ok > 0
    return SteadyStateDR(
        gain=gain,
        prior_cov=prior,
        noise_cov=noise,
        posterior_cov=post,
        nominal_prior_cov=linalg.symmetrize(a @ post @ a.T + w),
        value=jnp.trace(post),
        adjoint=linalg.symmetrize(lam),
        iterations=k.astype(int),
        residual=nr,
        converged=converged,
    )


class SteadyStateDRKF(AbstractFilter):
    r"""Steady-state (time-invariant) Wasserstein DR Kalman filter (Jang et al., Algorithm 1).

    `solve(model)` finds the least-favourable stationary covariances of problem
    (13)/(14) — maximize `Tr Σ` subject to `Σ = post(Σ⁻, Σv)`, `Σ̂⁻ = AΣAᵀ + Σ̂w`,
    `𝓑(Σ⁻, Σ̂⁻) ≤ θx`, `𝓑(Σv, Σ̂v) ≤ θv` — **without an SDP solver**, then the filter runs
    with the constant gain `K_ss` at Kalman-filter cost per step (lines 4–8).

    *Method.* Problem (14) is convex, and at its optimum the Schur-complement
    inequality is tight. Its KKT conditions, with the multiplier `Λ` of the stationarity
    constraint, say that `(Σ⁻, Σv)` solve a per-step problem (5) around the stationary
    pseudo-nominal `Σ̂⁻` but for the *weighted* objective `Tr((I + AᵀΛA) post(Σ⁻, Σv))`,
    so both are closed-form Gelbrich oracles (algorithms.md §A.1) of its gradients, and
    that `Λ = D_x(I − θx s_x D_x)⁻¹` (the envelope gradient of that weighted problem
    with respect to its nominal; at `θx = 0` it is the adjoint discrete Lyapunov equation
    of the Kalman filter). This smooth system (`n² + m² + 2 + n²` unknowns) is solved by
    Newton's method with backtracking, continued in the radii from `0` (where the
    nominal steady state (DARE) and its adjoint solve it exactly) to `(θx, θv)` — in one
    stage when that converges, in more otherwise, keeping the ball multipliers positive and
    `I + AᵀΛA ⪰ 0` (the Schur multiplier; the system also has spurious roots); derivatives with respect to `θx`,
    `θv` and the model come from the implicit function theorem on the same system
    (`lax.custom_root`). The value matches the SDP (14) solved by Clarabel to ~1e-10
    (tests).

    The optimum of (14) is in general **not** the fixed point of the time-varying
    recursion (15) (`WassersteinDRKF.covariance_recursion`), whose per-step objective
    has weight `I` instead of `I + AᵀΛA`: the two differ (e.g. by 0.3% of the trace on a
    3-state system), also with `θv = 0` and `θx ≤ θ_max`, where the paper's Corollary 1
    claims equality; the gap is small there (≈4e-6 relative on the paper's 2-D
    benchmark at `θx = θ_max`, which is the floor of the paper's Fig. 1).

    `step` is that of `jdrkf.SteadyStateKalmanFilter` with this gain: `predicted` reports
    the worst-case prior `N(x̄⁻, Σ⁻*)`, `filtered` the posterior `Σ*`, and `loglik` is the
    log-density of `y` under `N(Cx̄⁻ + v̂, CΣ⁻*Cᵀ + Σv*)`.

    The solve calls LAPACK (traced under `linalg.lapack_only`): to solve for many models,
    map with `jax.lax.map` rather than `vmap` (jaxlib 0.10's batched LAPACK kernels can
    deadlock; see the README).

    **Arguments:** `theta_x`, `theta_v` (radii ≥ 0, differentiable); `max_iter`
    (Newton iterations per continuation stage, default 20); `throw`, `nan_as_missing` as in
    `jdrkf.SteadyStateKalmanFilter`. A solve that does not converge makes `init` fail
    (with `throw`) or the run report `RESULTS.solver_not_converged`.
    """

    theta_x: Float[Array, ""]
    theta_v: Float[Array, ""]
    max_iter: int = eqx.field(static=True)
    throw: bool = eqx.field(static=True)
    nan_as_missing: bool = eqx.field(static=True)

    def __init__(self, theta_x: Float[ArrayLike, ""], theta_v: Float[ArrayLike, ""], *, max_iter: int = 20,
                 throw: bool = True, nan_as_missing: bool = True):
        self.theta_x = radius("theta_x", theta_x)
        self.theta_v = radius("theta_v", theta_v)
        self.max_iter, self.throw, self.nan_as_missing = int(max_iter), throw, nan_as_missing

    def solve(self, model: LinearModel) -> SteadyStateDR:
        """Least-favourable stationary covariances and the constant gain of (14)."""
        a, h, w, v = _time_invariant(model, "SteadyStateDRKF")
        dtype = a.dtype
        return _steady_state(a, h, w, v, self.theta_x.astype(dtype), self.theta_v.astype(dtype), self.max_iter)

    def init(self, model: LinearModel, prior: Gaussian):
        sol = self.solve(model)
        innov = linalg.symmetrize(model.H @ sol.prior_cov @ model.H.T + sol.noise_cov)
        ss = SteadyStateGain(predicted_cov=sol.prior_cov, innovation_cov=innov, gain=sol.gain, filtered_cov=sol.posterior_cov)
        return prior.mean, ss, linalg.cholesky(innov), sol.noise_cov, sol.converged

    def step(self, model, state, y, t, u=None, key: PRNGKeyArray | None = None):
        mean, ss, chol_s, noise_cov, converged = state
        (mean, ss, chol_s), out = _constant_gain_step(self, model, (mean, ss, chol_s), y, u, noise_cov, converged)
        return (mean, ss, chol_s, noise_cov, converged), out
