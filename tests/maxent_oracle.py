"""Independent cvxpy + Clarabel oracles for the max-entropy problems of Wang (2022),
written from the problem statements (eqs. 27, 34 and the smoothed semi-discrete problem of
`maxent_wasserstein_continuous`), not from the JAX code."""

import cvxpy as cp
import numpy as np


def _solve(prob):
    prob.solve(solver=cp.CLARABEL, tol_gap_abs=1e-11, tol_gap_rel=1e-11, tol_feas=1e-11)
    assert prob.status == cp.OPTIMAL, prob.status


def kl_ball(q, theta):
    """`max H(p)` s.t. `Σ p ln(p/q) ≤ θ`, `Σp = 1` (eq. 34) as an exponential-cone program."""
    q = np.asarray(q, float)
    p = cp.Variable(q.size, nonneg=True)
    prob = cp.Problem(cp.Maximize(cp.sum(cp.entr(p))), [cp.sum(cp.rel_entr(p, q)) <= theta, cp.sum(p) == 1])
    _solve(prob)
    return np.asarray(p.value)


def coupling(q, cost, theta):
    """`max −Σ P ln P` s.t. `Σ_j P_ij = q_i`, `Σ c_ij P_ij ≤ θ` (eq. 27); returns `P`."""
    q, cost = np.asarray(q, float), np.asarray(cost, float)
    P = cp.Variable(cost.shape, nonneg=True)
    prob = cp.Problem(cp.Maximize(cp.sum(cp.entr(P))), [cp.sum(P, axis=1) == q, cp.sum(cp.multiply(cost, P)) <= theta])
    _solve(prob)
    return np.asarray(P.value)


def semi_discrete(q, cost, weights, theta, eps):
    """Discretized Theorem 3 with entropic cell smoothing: over couplings `π_ki ≥ 0` of
    point `k` (weight `w_k`) and atom `i`, with `a_k = Σ_i π_ki`, maximize
    `−Σ a_k ln(a_k/w_k) − ε Σ π_ki ln(π_ki/a_k) = (1−ε)Σ entr(a) + εΣ entr(π) + Σ a ln w`
    s.t. `Σ_k π_ki = q_i`, `Σ c_ki π_ki ≤ θ`. Returns `(a, π)`."""
    q, cost, w = np.asarray(q, float), np.asarray(cost, float), np.asarray(weights, float)
    pi = cp.Variable(cost.shape, nonneg=True)
    a = cp.sum(pi, axis=1)
    obj = (1 - eps) * cp.sum(cp.entr(a)) + eps * cp.sum(cp.entr(pi)) + a @ np.log(w)
    prob = cp.Problem(cp.Maximize(obj), [cp.sum(pi, axis=0) == q, cp.sum(cp.multiply(cost, pi)) <= theta])
    _solve(prob)
    return np.asarray(a.value), np.asarray(pi.value)
