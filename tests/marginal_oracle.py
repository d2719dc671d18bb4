"""Independent CVXPY (Clarabel) oracle for the marginal DR-MMSE SDP (Chen et al. 2025,
problem (16); the authors' `MDRO.m`). NumPy in / NumPy out; no jax, no jdrkf.

    max Tr(U)  s.t.  S − blkdiag(U, 0) ⪰ 0,  S ⪰ 0,  and per sensor i, on the block
    S_i of (x, yⁱ) with nominal Σ_i:
      moment:  γ1ᵢ Σ_i ⪯ S_i ⪯ γ2ᵢ Σ_i
      KL:      ½[Tr(Σ_i⁻¹ S_i) − log det S_i + log det Σ_i − d_i] ≤ cᵢ   (exp. cone)
"""

import warnings

import cvxpy as cp
import numpy as np


def _sym(a):
    a = np.asarray(a, dtype=np.float64)
    return 0.5 * (a + a.T)


def block_indices(n, dims):
    out, start = [], n
    for d in dims:
        out.append(list(range(n)) + list(range(start, start + d)))
        start += d
    return out


def _lmi(expr):
    return 0.5 * (expr + expr.T) >> 0


def solve_marginal_sdp(cov, n, dims, kind, params, strict=True):
    """Optimal value and worst-case S of the marginal problem.

    kind 'moment': params = (gamma1, gamma2), arrays of length p;
    kind 'kl': params = (c,), the KL radii (½ factor included). `strict=False` accepts
    Clarabel's 'optimal_inaccurate' (benchmarks at p = 10; tests keep strict)."""
    cov = _sym(cov)
    d = cov.shape[0]
    S = cp.Variable((d, d), symmetric=True)
    U = cp.Variable((n, n), symmetric=True)
    E = np.zeros((d, n))
    E[:n, :n] = np.eye(n)
    cons = [_lmi(S - E @ U @ E.T), _lmi(S)]
    for i, idx in enumerate(block_indices(n, dims)):
        sig = cov[np.ix_(idx, idx)]
        Si = S[idx, :][:, idx]
        if kind == "moment":
            g1, g2 = float(params[0][i]), float(params[1][i])
            if g1 == g2:
                cons.append(Si == g1 * sig)
            else:
                cons += [_lmi(Si - g1 * sig), _lmi(g2 * sig - Si)]
        else:
            c = float(params[0][i])
            if c == 0:
                cons.append(Si == sig)
            else:
                sig_inv = np.linalg.inv(sig)
                _, logdet_sig = np.linalg.slogdet(sig)
                cons.append(
                    0.5 * (cp.trace(sig_inv @ Si) - cp.log_det(Si) + logdet_sig - len(idx)) <= c
                )
    prob = cp.Problem(cp.Maximize(cp.trace(U)), cons)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)
        for tol in (1e-10, 1e-9, 1e-8):
            prob.solve(solver=cp.CLARABEL, max_iter=500, tol_gap_abs=tol, tol_gap_rel=tol, tol_feas=tol)
            if prob.status == cp.OPTIMAL:
                break
        else:
            if strict or prob.status != cp.OPTIMAL_INACCURATE:
                raise RuntimeError(f"Clarabel status {prob.status!r}")
    return float(prob.value), _sym(S.value)


def kalman_value(cov, n):
    """Tr of the Gaussian posterior covariance Σ_xx − Σ_xy Σ_yy⁻¹ Σ_yx (NumPy)."""
    cov = _sym(cov)
    sxy, syy = cov[:n, n:], cov[n:, n:]
    gain = np.linalg.solve(syy, sxy.T).T
    return float(np.trace(cov[:n, :n] - gain @ sxy.T)), gain


def random_cov(rng, n, dims, independent=False):
    """Nominal joint covariance from a random linear-Gaussian model y_i = H_i x + v_i."""
    m = sum(dims)
    a = rng.standard_normal((n, n))
    P = a @ a.T / n + 0.3 * np.eye(n)
    H = rng.standard_normal((m, n))
    R = np.zeros((m, m))
    start = 0
    for d in dims:
        b = rng.standard_normal((d, d))
        R[start:start + d, start:start + d] = b @ b.T / d + 0.2 * np.eye(d)
        start += d
    cov = np.block([[P, P @ H.T], [H @ P, H @ P @ H.T + R]])
    if not independent:
        # perturb the cross-sensor blocks (ignored by the problem)
        cov[n:, n:] += 0.01 * np.ones((m, m))
    return _sym(cov)
