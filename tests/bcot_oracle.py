"""Independent CVXPY (Clarabel) and NumPy oracles for the BCOT DR Kalman step.

NumPy in / NumPy out; does NOT depend on jax or jdrkf. Problem (Han 2023, as in docs/math/steady_state.md):

    max_{Σ, Q, R}  Tr(P⁻ − P⁻Cᵀ(CP⁻Cᵀ + R)⁻¹CP⁻),   P⁻ = AΣAᵀ + Q,
    s.t.  B²(N(Q, R), N(Q_p, R_p)) + B²(H^½ΣH^½, H^½Σ_pH^½) ≤ radius,

with N(Q, R) = [[Q, QCᵀ], [CQ, CQCᵀ + R]] and H = I + AᵀA + AᵀCᵀCA. As an SDP:
the objective is Tr X with [[P⁻ − X, P⁻Cᵀ], [CP⁻, CP⁻Cᵀ + R]] ⪰ 0, and each squared
Bures distance is Tr(X + Y − 2Z) with [[Y, Z], [Zᵀ, X]] ⪰ 0 (the max of Tr Z over that
constraint is the fidelity Tr((Y^½XY^½)^½)).
"""

import warnings

import cvxpy as cp
import numpy as np
import scipy.linalg

_TOLERANCES = (1e-10, 1e-9, 1e-8)


def _sym(a):
    a = np.asarray(a, dtype=np.float64)
    return 0.5 * (a + a.T)


def sqrtm_psd(a):
    lam, vec = np.linalg.eigh(_sym(a))
    return _sym((vec * np.sqrt(np.clip(lam, 0.0, None))) @ vec.T)


def weight(A, C):
    """H = I + AᵀA + AᵀCᵀCA."""
    n = A.shape[0]
    return _sym(np.eye(n) + A.T @ A + A.T @ C.T @ C @ A)


def joint_noise(Q, R, C):
    """N(Q, R) = [[Q, QCᵀ], [CQ, CQCᵀ + R]]: covariance of (w, Cw + v)."""
    return _sym(np.block([[Q, Q @ C.T], [C @ Q, C @ Q @ C.T + R]]))


def bures_squared(a, b):
    """Squared Bures distance via scipy.linalg.sqrtm (independent of the eigh route)."""
    ra = np.real(scipy.linalg.sqrtm(_sym(a)))
    mid = np.real(scipy.linalg.sqrtm(_sym(ra @ _sym(b) @ ra)))
    return float(np.trace(a) + np.trace(b) - 2.0 * np.trace(mid))


def budget(Sigma, Q, R, Sigma_p, Q_p, R_p, A, C):
    """Left-hand side of the BCOT constraint."""
    hr = sqrtm_psd(weight(A, C))
    return bures_squared(joint_noise(Q, R, C), joint_noise(Q_p, R_p, C)) + bures_squared(
        hr @ Sigma @ hr, hr @ Sigma_p @ hr
    )


def posterior_trace(Sigma, Q, R, A, C):
    P = A @ Sigma @ A.T + Q
    S = C @ P @ C.T + R
    return float(np.trace(P - P @ C.T @ np.linalg.solve(S, C @ P)))


def bcot_sdp(Sigma_p, Q_p, R_p, A, C, radius):
    """Solve the BCOT step as an SDP with Clarabel; returns dict(value, Sigma, Q, R)."""
    Sigma_p, Q_p, R_p, A, C = (np.asarray(x, dtype=np.float64) for x in (Sigma_p, Q_p, R_p, A, C))
    n, m = A.shape[0], C.shape[0]
    hr = sqrtm_psd(weight(A, C))
    Sig = cp.Variable((n, n), symmetric=True)
    Q = cp.Variable((n, n), symmetric=True)
    R = cp.Variable((m, m), symmetric=True)
    X = cp.Variable((n, n), symmetric=True)
    Z1 = cp.Variable((n + m, n + m))
    Z2 = cp.Variable((n, n))
    P = A @ Sig @ A.T + Q
    N = cp.bmat([[Q, Q @ C.T], [C @ Q, C @ Q @ C.T + R]])
    N_p = joint_noise(Q_p, R_p, C)
    Y = hr @ Sig @ hr
    Y_p = _sym(hr @ Sigma_p @ hr)

    def psd(e):
        return 0.5 * (e + e.T) >> 0

    cons = [
        psd(cp.bmat([[P - X, P @ C.T], [C @ P, C @ P @ C.T + R]])),
        psd(cp.bmat([[N_p, Z1], [Z1.T, N]])),
        psd(cp.bmat([[Y_p, Z2], [Z2.T, Y]])),
        cp.trace(N) + np.trace(N_p) - 2 * cp.trace(Z1) + cp.trace(Y) + np.trace(Y_p) - 2 * cp.trace(Z2) <= radius,
    ]
    prob = cp.Problem(cp.Maximize(cp.trace(X)), cons)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        for tol in _TOLERANCES:
            prob.solve(solver=cp.CLARABEL, max_iter=500, tol_gap_abs=tol, tol_gap_rel=tol, tol_feas=tol)
            if prob.status == cp.OPTIMAL:
                break
        else:
            raise RuntimeError(f"Clarabel status {prob.status!r}")
    return {"value": float(prob.value), "Sigma": _sym(Sig.value), "Q": _sym(Q.value), "R": _sym(R.value)}
