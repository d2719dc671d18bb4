"""Independent NumPy / SciPy / CVXPY oracles for the multi-sensor fusion filters
(Chen et al. 2025; the authors' MATLAB code lylechan42/MDRKF; docs/math/marginal.md).

NumPy in / NumPy out; does NOT import jax or jdrkf.
"""

import warnings

import cvxpy as cp
import numpy as np
import scipy.linalg
import scipy.optimize


def _sym(a):
    a = np.asarray(a, dtype=np.float64)
    return 0.5 * (a + a.T)


# ------------------------------------------------------------------ model pieces


def stacked(H_blocks, R_blocks):
    """Stacked H and block-diagonal R."""
    return np.vstack(H_blocks), scipy.linalg.block_diag(*R_blocks)


def joint_nominal(F, G, Q, H, R_bd, P):
    """Covariance of (x_k, y_k) from the previous posterior covariance P (eq. 31)."""
    M = F @ P @ F.T + G @ Q @ G.T
    return np.block([[M, M @ H.T], [H @ M, H @ M @ H.T + R_bd]])


# ------------------------------------------------------------------ covariance intersection


def ci_objective(w, Ps, criterion):
    M = sum(wi * np.linalg.inv(P) for wi, P in zip(w, Ps, strict=True))
    C = np.linalg.inv(M)
    return np.linalg.slogdet(C)[1] if criterion == "det" else np.trace(C)


def ci_weights(Ps, criterion):
    """CI weights by SLSQP from several starts (plus all vertices), best value kept."""
    p = len(Ps)
    cands = [np.eye(p)[i] for i in range(p)]
    starts = [np.full(p, 1.0 / p)] + [0.8 * np.eye(p)[i] + 0.2 / p for i in range(p)]
    for w0 in starts:
        res = scipy.optimize.minimize(
            ci_objective, w0, args=(Ps, criterion), method="SLSQP",
            bounds=[(0.0, 1.0)] * p, constraints=[{"type": "eq", "fun": lambda w: np.sum(w) - 1.0}],
            options={"ftol": 1e-15, "maxiter": 1000},
        )
        cands.append(np.clip(res.x, 0.0, None) / np.sum(np.clip(res.x, 0.0, None)))
    vals = [ci_objective(w, Ps, criterion) for w in cands]
    return cands[int(np.argmin(vals))], float(np.min(vals))


def ci_fuse(xs, Ps, w):
    infos = [np.linalg.inv(P) for P in Ps]
    M = sum(wi * Y for wi, Y in zip(w, infos, strict=True))
    C = np.linalg.inv(M)
    return C @ sum(wi * Y @ x for wi, Y, x in zip(w, infos, xs, strict=True)), C


def ci_filter(m0, P0, ys, F, G, Q, H_blocks, R_blocks, criterion):
    """Local KF updates from the common fused prior, fused by CI (weights from SciPy)."""
    x, P = np.asarray(m0, float), np.asarray(P0, float)
    means, covs, weights = [], [], []
    for y in ys:
        xp, Pp = F @ x, F @ P @ F.T + G @ Q @ G.T
        xs, Ps, o = [], [], 0
        for Hi, Ri in zip(H_blocks, R_blocks, strict=True):
            d = Hi.shape[0]
            S = Hi @ Pp @ Hi.T + Ri
            K = Pp @ Hi.T @ np.linalg.inv(S)
            xs.append(xp + K @ (y[o:o + d] - Hi @ xp))
            Ps.append(_sym(Pp - K @ S @ K.T))
            o += d
        w, _ = ci_weights(Ps, criterion)
        x, P = ci_fuse(xs, Ps, w)
        means.append(x)
        covs.append(P)
        weights.append(w)
    return np.array(means), np.array(covs), np.array(weights)


# ------------------------------------------------------------------ marginal DR-MMSE SDP


def marginal_sdp(Sigma, n, dims, kind, radius):
    """max Tr(U) s.t. S − blkdiag(U, 0) ⪰ 0, per-sensor block constraints (MDRO.m).

    kind 'moment': radius = (g1, g2), g1 Σ_i ⪯ S_Bi ⪯ g2 Σ_i;
    kind 'kl': radius = c, ½[Tr(Σ_i⁻¹ S_Bi) − log det S_Bi + log det Σ_i − d_i] ≤ c.
    Returns (gain K = S_xy S_yy⁻¹, posterior U, S)."""
    d = Sigma.shape[0]
    S = cp.Variable((d, d), symmetric=True)
    U = cp.Variable((n, n), symmetric=True)
    big = S - cp.bmat([[U, np.zeros((n, d - n))], [np.zeros((d - n, n)), np.zeros((d - n, d - n))]])
    cons = [S >> 0, 0.5 * (big + big.T) >> 0]
    start = n
    for di in dims:
        idx = np.r_[np.arange(n), np.arange(start, start + di)]
        start += di
        Si = S[idx][:, idx]
        Sig = _sym(Sigma[np.ix_(idx, idx)])
        if kind == "moment":
            g1, g2 = radius
            cons += [Si - g1 * Sig >> 0, g2 * Sig - Si >> 0]
        else:
            Sinv = np.linalg.inv(Sig)
            cons.append(0.5 * (cp.trace(Sinv @ Si) - cp.log_det(Si) + np.linalg.slogdet(Sig)[1] - len(idx)) <= radius)
    prob = cp.Problem(cp.Maximize(cp.trace(U)), cons)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        for tol in (1e-10, 1e-9, 1e-8):
            prob.solve(solver=cp.CLARABEL, max_iter=500, tol_gap_abs=tol, tol_gap_rel=tol, tol_feas=tol)
            if prob.status == cp.OPTIMAL:
                break
        else:
            raise RuntimeError(f"Clarabel status {prob.status!r}")
    Sv = _sym(S.value)
    K = Sv[:n, n:] @ np.linalg.inv(Sv[n:, n:])
    return K, _sym(U.value), Sv


def mdrkf_sdp_filter(m0, P0, ys, F, G, Q, H, R_bd, dims, kind, radius):
    """Algorithm 1 with the per-step worst case from the CVXPY SDP."""
    n = F.shape[0]
    x, P = np.asarray(m0, float), np.asarray(P0, float)
    means, covs = [], []
    for y in ys:
        Sigma = joint_nominal(F, G, Q, H, R_bd, P)
        K, U, _ = marginal_sdp(Sigma, n, dims, kind, radius)
        xp = F @ x
        x = xp + K @ (y - H @ xp)
        P = U
        means.append(x)
        covs.append(P)
    return np.array(means), np.array(covs)


def fading_memory_filter(m0, P0, ys, F, G, Q, H, R, gamma2):
    """KF gain with P = γ2 (M − K H M) (Wang, Wu, Lim 2021; S* = γ2 Σ for one sensor)."""
    x, P = np.asarray(m0, float), np.asarray(P0, float)
    means, covs = [], []
    for y in ys:
        M = F @ P @ F.T + G @ Q @ G.T
        K = M @ H.T @ np.linalg.inv(H @ M @ H.T + R)
        x = F @ x + K @ (y - H @ F @ x)
        P = gamma2 * (M - K @ H @ M)
        means.append(x)
        covs.append(P)
    return np.array(means), np.array(covs)
