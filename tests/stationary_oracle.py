"""Independent CVXPY (Clarabel) and NumPy references for Jang, Hakobyan & Yang (2025).

NumPy in / NumPy out; does not import jax or jdrkf.

* ``stationary_sdp``: the steady-state DR problem (13) in the authors' SDP form (14)
  (as in the authors' code): maximize Tr X over X, X⁻, Σv, X̂⁻, Y, Z subject to
  [[X⁻ − X, X⁻Cᵀ], [C X⁻, C X⁻ Cᵀ + Σv]] ⪰ 0, X̂⁻ = A X Aᵀ + Σ̂w,
  Tr(X̂⁻ + X⁻ − 2Y) ≤ θx² with [[X̂⁻, Y], [Yᵀ, X⁻]] ⪰ 0, the same for Σv around Σ̂v,
  and Σv ⪰ λmin(Σ̂v) I.
* ``step_sdp``: the per-step problem (12) for a given pseudo-nominal prior X̂⁻.
* ``dr_riccati``: the time-varying recursion (11)/(15), each step solved by the
  certified NumPy Frank–Wolfe of ``sdp_oracles`` (relative duality gap ≤ 1e-14).
"""

import warnings

import cvxpy as cp
import numpy as np

from sdp_oracles import decoupled_gradient, frank_wolfe, posterior_trace, set_lmo

_TOLERANCES = (1e-10, 1e-9, 1e-8)


def _solve(prob):
    last = None
    for tol in _TOLERANCES:
        try:
            with warnings.catch_warnings():  # "may be inaccurate": retried looser below
                warnings.simplefilter("ignore", UserWarning)
                prob.solve(solver=cp.CLARABEL, max_iter=500, tol_gap_abs=tol, tol_gap_rel=tol, tol_feas=tol)
        except cp.SolverError as err:  # pragma: no cover - retried looser
            last = err
            continue
        if prob.status == cp.OPTIMAL:
            return tol
    if prob.status == cp.OPTIMAL_INACCURATE:
        return None  # the caller sees "accurate": False and must compare loosely
    raise RuntimeError(f"Clarabel failed: {prob.status} {last}")


def _gelbrich(nominal, cov, theta, d):
    if theta == 0:  # a zero-radius ball is a point; interior-point methods dislike it
        return [cov == nominal]
    y = cp.Variable((d, d))
    block = cp.bmat([[nominal, y], [y.T, cov]])
    return [0.5 * (block + block.T) >> 0, cp.trace(nominal + cov - 2 * y) <= theta**2]


def _problem(A, C, Sw, Sv, theta_x, theta_v, nominal=None):
    n, m = A.shape[0], C.shape[0]
    X = cp.Variable((n, n), symmetric=True)
    Xm = cp.Variable((n, n), symmetric=True)
    Sigv = cp.Variable((m, m), symmetric=True)
    Xhat = A @ X @ A.T + Sw if nominal is None else nominal
    schur = cp.bmat([[Xm - X, Xm @ C.T], [C @ Xm, C @ Xm @ C.T + Sigv]])
    cons = [0.5 * (schur + schur.T) >> 0, X >> 0, Xm >> 0, Sigv >> np.min(np.linalg.eigvalsh(Sv)) * np.eye(m)]
    cons += _gelbrich(Xhat, Xm, theta_x, n) + _gelbrich(Sv, Sigv, theta_v, m)
    prob = cp.Problem(cp.Maximize(cp.trace(X)), cons)
    tol = _solve(prob)
    return {"value": prob.value, "posterior_cov": X.value, "prior_cov": Xm.value, "noise_cov": Sigv.value,
            "tolerance": tol, "accurate": tol is not None}


def stationary_sdp(A, C, Sw, Sv, theta_x, theta_v):
    """Problem (14): the steady-state least-favourable covariances and their value."""
    A, C, Sw, Sv = (np.atleast_2d(np.asarray(x, float)) for x in (A, C, Sw, Sv))
    out = _problem(A, C, Sw, Sv, theta_x, theta_v)
    out["nominal_prior_cov"] = A @ out["posterior_cov"] @ A.T + Sw
    return out


def step_sdp(nominal_prior, C, Sv, theta_x, theta_v):
    """Problem (12) for a given pseudo-nominal prior covariance."""
    C, Sv = (np.atleast_2d(np.asarray(x, float)) for x in (C, Sv))
    return _problem(np.zeros((C.shape[1],) * 2), C, np.zeros((C.shape[1],) * 2), Sv, theta_x, theta_v,
                    nominal=np.asarray(nominal_prior, float))


def step_fw(nominal_prior, C, Sv, theta_x, theta_v):
    """Problem (5) for a given pseudo-nominal prior, by the certified NumPy Frank–Wolfe."""
    (sx, sv), gap, _ = frank_wolfe(
        lambda a, b: posterior_trace(a, C, b),
        lambda a, b: decoupled_gradient(a, C, b),
        [lambda g: set_lmo(("wasserstein", theta_x), g, nominal_prior), lambda g: set_lmo(("wasserstein", theta_v), g, Sv)],
        [nominal_prior, Sv],
    )
    k = np.linalg.solve(C @ sx @ C.T + sv, C @ sx).T
    post = sx - k @ C @ sx
    return {"prior_cov": sx, "noise_cov": sv, "posterior_cov": 0.5 * (post + post.T), "gain": k, "gap": gap}


def dr_riccati(A, C, Sw, Sv, theta_x, theta_v, prior_cov, num_steps):
    """Time-varying DR Riccati recursion (Theorem 1, eqs. 8, 11): per-step problem (5),
    then X̂⁻ ← A X Aᵀ + Σ̂w. Returns the last step, the posterior traces and the next
    pseudo-nominal prior."""
    A, C, Sw, Sv = (np.atleast_2d(np.asarray(x, float)) for x in (A, C, Sw, Sv))
    nominal = np.asarray(prior_cov, float)
    traces, out = [], None
    for _ in range(num_steps):
        out = step_fw(nominal, C, Sv, theta_x, theta_v)
        traces.append(np.trace(out["posterior_cov"]))
        nominal = A @ out["posterior_cov"] @ A.T + Sw
        nominal = 0.5 * (nominal + nominal.T)
    out["traces"] = np.array(traces)
    out["next_nominal"] = nominal
    return out
