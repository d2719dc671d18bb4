"""Time-varying and steady-state Wasserstein DR Kalman filters (Jang, Hakobyan & Yang,
"On the steady-state distributionally robust Kalman filter", 2025; see `docs/math/steady_state.md`)."""

from __future__ import annotations

from collections.abc import Sequence
from typing import ClassVar

import equinox as eqx
import jax.numpy as jnp
from jax import lax
from jaxtyping import Array, ArrayLike, Bool, Float, PRNGKeyArray

from .. import linalg
from .._gaussian import Gaussian
from .._models import LinearModel
from .._validation import check_scalar, in_range, renamed, renamed_attribute
from ..sets._solve import worst_case
from ..sets._steady_state import SteadyStateDR, posterior_and_gain, solve_steady_state
from ..sets._wasserstein import Wasserstein
from ._base import DEFAULT_OUTPUTS, RESULTS, AbstractFilter
from ._dr import decoupled_step
from ._kalman import SteadyStateGain
from ._steps import constant_gain_step


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

    It equals `jdrkf.DRKF(Wasserstein(radius_x), Wasserstein(radius_v))`. `predicted` is the
    worst-case prior `N(x̄⁻, Σ⁻*)`; `info` holds the pseudo-nominal prior, the worst-case
    noise covariance, the solver's iterations and gap. The paper measures `y_0`
    before any prediction; with jdrkf's time convention (`prior` is the law of `x_0`,
    `ys[0] = y_1`) pass the law of `x_{-1}`, or update on `y_0` first (as
    `jdrkf.closed_loop` does).

    **Arguments:** `radius_x`, `radius_v` (the radii `θx`, `θv` ≥ 0 of the balls on the
    prior and on the noise, differentiable; `theta_x=`, `theta_v=` are deprecated
    aliases); `rtol`, `max_iter`, `throw`, `outputs` as in `jdrkf.DRKF`.
    """

    radius_x: Float[Array, ""]
    radius_v: Float[Array, ""]
    rtol: float | None = eqx.field(static=True)
    max_iter: int = eqx.field(static=True)
    shared_covariance: ClassVar[bool] = True

    def __init__(self, radius_x: Float[ArrayLike, ""] = None, radius_v: Float[ArrayLike, ""] = None, *, rtol: float | None = None,
                 max_iter: int = 500, throw: bool = True, outputs: str | Sequence[str] = DEFAULT_OUTPUTS,
                 theta_x: Float[ArrayLike, ""] = None, theta_v: Float[ArrayLike, ""] = None):
        self.radius_x = check_scalar("radius_x", renamed("theta_x", theta_x, "radius_x", radius_x, "WassersteinDRKF"))
        self.radius_v = check_scalar("radius_v", renamed("theta_v", theta_v, "radius_v", radius_v, "WassersteinDRKF"))
        self.rtol, self.max_iter, self.throw, self.outputs = rtol, max_iter, throw, outputs

    theta_x = renamed_attribute("theta_x", "radius_x")
    theta_v = renamed_attribute("theta_v", "radius_v")

    def init(self, model, prior: Gaussian) -> Gaussian:
        return prior

    def step(self, model, state, y, t, u=None, key: PRNGKeyArray | None = None, observed=None):
        return decoupled_step(self, model, state, y, t, u, observed, Wasserstein(self.radius_x), Wasserstein(self.radius_v), None)

    def covariance_recursion(self, model: LinearModel, nominal_prior_cov: Float[ArrayLike, "n n"], num_steps: int) -> CovarianceRecursion:
        """Run the covariance part of the filter (the DR Riccati recursion (15)) for
        `num_steps` measurement updates, starting from the pseudo-nominal prior
        covariance `Σ̂⁻_0` of the first measured state. No data are needed: with
        full observations the covariances do not depend on them. Its fixed point is the limit of the time-varying filter, which in
        general differs from `SteadyStateDRKF.solve` (see there)."""
        a, h, w, v = _time_invariant(model, "covariance_recursion")
        nominal = jnp.asarray(nominal_prior_cov, a.dtype)
        if nominal.shape != a.shape:
            raise ValueError(f"nominal_prior_cov has shape {tuple(nominal.shape)} but expected {tuple(a.shape)}")
        sx, sv = Wasserstein(self.radius_x), Wasserstein(self.radius_v)

        def body(nom, _):
            sol = worst_case(sx, sv, nom, h, v, rtol=self.rtol, max_iter=self.max_iter)
            post, gain = posterior_and_gain(sol.state_cov, sol.noise_cov, h)
            out = CovarianceRecursion(nom, sol.state_cov, sol.noise_cov, post, gain, sol.converged)
            return linalg.symmetrize(a @ post @ a.T + w), out

        _, out = lax.scan(body, nominal, None, length=int(num_steps))
        return out


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
    so both are closed-form Gelbrich oracles (`jdrkf.sets.Wasserstein`) of its gradients, and
    that `Λ = D_x(I − θx s_x D_x)⁻¹` (the envelope gradient of that weighted problem
    with respect to its nominal; at `θx = 0` it is the adjoint discrete Lyapunov equation
    of the Kalman filter). This smooth system (`n(n+1) + m(m+1)/2 + 2` unknowns: upper
    triangles of `Σ⁻`, `Σv`, `Λ`, and the two multipliers) is solved by Newton's method
    with backtracking, started at the best of a few fixed-point sweeps (oracles, then
    `Λ`) and continued in the radii from `0` (where the nominal steady state (DARE) and
    its adjoint solve it exactly) to `(θx, θv)` — in one stage when that converges, in
    more otherwise, keeping the ball multipliers positive, `I + AᵀΛA ≻ 0` (the Schur
    multiplier) and `Σ⁻, Σv ≻ 0`. The system also has spurious roots — one with an
    indefinite `Σ⁻` appears when `Σ̂w` is nearly singular, self-consistent because the
    pseudo-nominal `Σ̂⁻ = AΣAᵀ + Σ̂w` then inherits `Σ`'s negative eigenvalue; it is
    infeasible for (14) and has a larger trace — so `converged` means: residual at
    tolerance *at a point of that domain*, i.e. a feasible KKT point of the convex
    problem, hence its optimum. Derivatives with respect to `θx`,
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

    The solve calls LAPACK (traced under `linalg.lapack_only`). For many radius pairs on
    one model, `jax.vmap` over the radii: its batching rule solves the system at a few
    anchor radii and reaches every pair by chord steps with its anchor's Jacobian
    (`docs/math/steady_state.md`; per pair 18–130× faster than a single solve in
    `benchmarks/steady_state_solver.py`). For many
    models, map with `jax.lax.map`: under `vmap` over models every solve runs the slowest
    one's iterations in lockstep.

    **Arguments:** `radius_x`, `radius_v` (the radii `θx`, `θv` ≥ 0, differentiable;
    `theta_x=`, `theta_v=` are deprecated aliases); `max_iter`
    (Newton iterations per continuation stage, default 20); `throw`, `outputs` as in
    `jdrkf.SteadyStateKalmanFilter`. A solve that does not converge makes `init` fail
    (with `throw`) or the run report `RESULTS.solver_not_converged`.
    """

    radius_x: Float[Array, ""]
    radius_v: Float[Array, ""]
    max_iter: int = eqx.field(static=True)
    shared_covariance: ClassVar[bool] = True

    def __init__(self, radius_x: Float[ArrayLike, ""] = None, radius_v: Float[ArrayLike, ""] = None, *, max_iter: int = 20,
                 throw: bool = True, outputs: str | Sequence[str] = DEFAULT_OUTPUTS,
                 theta_x: Float[ArrayLike, ""] = None, theta_v: Float[ArrayLike, ""] = None):
        self.radius_x = check_scalar("radius_x", renamed("theta_x", theta_x, "radius_x", radius_x, "SteadyStateDRKF"))
        self.radius_v = check_scalar("radius_v", renamed("theta_v", theta_v, "radius_v", radius_v, "SteadyStateDRKF"))
        self.max_iter, self.throw, self.outputs = int(max_iter), throw, outputs

    theta_x = renamed_attribute("theta_x", "radius_x")
    theta_v = renamed_attribute("theta_v", "radius_v")

    def solve(self, model: LinearModel) -> SteadyStateDR:
        """Least-favourable stationary covariances and the constant gain of (14)
        (`jdrkf.sets.steady_state_worst_case`)."""
        return solve_steady_state(*_time_invariant(model, "SteadyStateDRKF"), self.radius_x, self.radius_v, self.max_iter)

    def init(self, model: LinearModel, prior: Gaussian):
        sol = self.solve(model)
        innov = linalg.symmetrize(model.H @ sol.prior_cov @ model.H.T + sol.noise_cov)
        ss = SteadyStateGain(predicted_cov=sol.prior_cov, innovation_cov=innov, gain=sol.gain, filtered_cov=sol.posterior_cov,
                             converged=sol.converged)
        return prior.mean, ss, linalg.cholesky(innov), sol.noise_cov, sol.converged

    def step(self, model, state, y, t, u=None, key: PRNGKeyArray | None = None, observed=None):
        mean, ss, chol_s, noise_cov, converged = state
        (mean, ss, chol_s), out = constant_gain_step(model, (mean, ss, chol_s), y, u, noise_cov, observed, converged)
        valid = in_range(self.radius_x, 0.0) & in_range(self.radius_v, 0.0)
        out = eqx.tree_at(lambda o: o.result, out, RESULTS.where(valid, out.result, RESULTS.invalid_hyperparameter))
        return (mean, ss, chol_s, noise_cov, converged), out
