"""Independent NumPy/SciPy reference implementations (test oracles).

Plain, loop-based, float64 code meant to be obviously correct rather than fast.
Does NOT depend on jax or jdrkf.

Time convention
---------------
Prior x_0 ~ N(m0, P0).  For k = 1..T (Python index t = k - 1):

    x_k = F_t x_{k-1} + B_t u_t + G_t w_t,   w_t ~ N(process_mean_t, Q_t)
    y_k = H_t x_k + v_t,                      v_t ~ N(noise_mean_t, R_t)

with ys[t] = y_k and inputs[t] = u_k.  Any model array may carry a leading
time axis of length T (detected by ndim).  NaN entries of ys[t] are missing.
"""

import numpy as np
import scipy.linalg


def _at(a, t, static_ndim):
    """Return a[t] if `a` carries a leading time axis (ndim == static_ndim + 1), else a."""
    if a is None:
        return None
    if a.ndim == static_ndim + 1:
        return a[t]
    if a.ndim == static_ndim:
        return a
    raise ValueError(f"array has ndim {a.ndim}, expected {static_ndim} or {static_ndim + 1}")


def _f64(a):
    """Convert to a float64 array (None passes through)."""
    return None if a is None else np.asarray(a, dtype=np.float64)


def _gaussian_logpdf(e, S):
    """log N(e; 0, S) via the explicit formula."""
    d = e.shape[0]
    sign, logdet = np.linalg.slogdet(S)
    if sign <= 0:
        raise np.linalg.LinAlgError("innovation covariance is not positive definite")
    maha = e @ np.linalg.solve(S, e)
    return -0.5 * (d * np.log(2.0 * np.pi) + logdet + maha)


def numpy_kalman_filter(m0, P0, ys, F, H, Q, R, G=None, B=None, inputs=None,
                        process_mean=None, noise_mean=None):
    """Reference Kalman filter (covariance form, Joseph update, NaN = missing).

    Returns a dict with 'filtered_means' (T,n), 'filtered_covariances' (T,n,n),
    'predicted_means' (T,n), 'predicted_covariances' (T,n,n),
    'loglik_increments' (T,) and 'marginal_loglik' (float).
    Predicted quantities at index t are those of x_k given y_1..y_{k-1}.
    """
    m0, P0, ys = _f64(m0), _f64(P0), _f64(ys)
    F, H, Q, R = _f64(F), _f64(H), _f64(Q), _f64(R)
    G, B, inputs = _f64(G), _f64(B), _f64(inputs)
    process_mean, noise_mean = _f64(process_mean), _f64(noise_mean)

    T, m_dim = ys.shape
    n = m0.shape[0]
    if (B is None) != (inputs is None):
        raise ValueError("B and inputs must be given together")

    filtered_means = np.zeros((T, n))
    filtered_covs = np.zeros((T, n, n))
    predicted_means = np.zeros((T, n))
    predicted_covs = np.zeros((T, n, n))
    loglik_increments = np.zeros(T)

    m = m0.copy()
    P = P0.copy()
    for t in range(T):
        F_t = _at(F, t, 2)
        H_t = _at(H, t, 2)
        Q_t = _at(Q, t, 2)
        R_t = _at(R, t, 2)
        G_t = _at(G, t, 2) if G is not None else np.eye(n)
        mu_w = _at(process_mean, t, 1) if process_mean is not None else np.zeros(Q_t.shape[0])
        mu_v = _at(noise_mean, t, 1) if noise_mean is not None else np.zeros(m_dim)

        # ---- predict ----
        m_pred = F_t @ m + G_t @ mu_w
        if B is not None:
            m_pred = m_pred + _at(B, t, 2) @ inputs[t]
        P_pred = F_t @ P @ F_t.T + G_t @ Q_t @ G_t.T
        predicted_means[t] = m_pred
        predicted_covs[t] = P_pred

        # ---- update (observed components only) ----
        y = ys[t]
        o = np.flatnonzero(~np.isnan(y))
        if o.size == 0:
            m, P = m_pred, P_pred
            loglik_increments[t] = 0.0
        else:
            H_o = H_t[o, :]
            R_oo = R_t[np.ix_(o, o)]
            e = y[o] - H_o @ m_pred - mu_v[o]
            S = H_o @ P_pred @ H_o.T + R_oo
            K = P_pred @ H_o.T @ np.linalg.inv(S)
            m = m_pred + K @ e
            I_KH = np.eye(n) - K @ H_o
            P = I_KH @ P_pred @ I_KH.T + K @ R_oo @ K.T
            loglik_increments[t] = _gaussian_logpdf(e, S)

        filtered_means[t] = m
        filtered_covs[t] = P

    return {
        "filtered_means": filtered_means,
        "filtered_covariances": filtered_covs,
        "predicted_means": predicted_means,
        "predicted_covariances": predicted_covs,
        "loglik_increments": loglik_increments,
        "marginal_loglik": float(np.sum(loglik_increments)),
    }


def numpy_dare_filter(F, H, Q, R, G=None):
    """Steady-state predicted covariance P and gain K of a time-invariant model.

    P solves P = F P F' - F P H' (H P H' + R)^{-1} H P F' + G Q G' (filtering DARE,
    the dual of scipy's control DARE with A = F', B = H', Q = G Q G').
    K = P H' (H P H' + R)^{-1}.  Steady filtered covariance is (I - K H) P.
    Returns (P, K).
    """
    F, H, Q, R = _f64(F), _f64(H), _f64(Q), _f64(R)
    n = F.shape[0]
    G = np.eye(n) if G is None else _f64(G)
    GQG = G @ Q @ G.T
    P = scipy.linalg.solve_discrete_are(F.T, H.T, GQG, R)
    P = 0.5 * (P + P.T)
    K = P @ H.T @ np.linalg.inv(H @ P @ H.T + R)
    return P, K


def numpy_simulate_lgssm(rng, m0, P0, F, H, Q, R, T, G=None):
    """Simulate one trajectory; returns (xs (T,n), ys (T,m)), x_0 not returned.

    Zero-mean noises, no control.  Model arrays may carry a leading time axis.
    """
    m0, P0 = _f64(m0), _f64(P0)
    F, H, Q, R, G = _f64(F), _f64(H), _f64(Q), _f64(R), _f64(G)
    n = m0.shape[0]
    m_dim = _at(H, 0, 2).shape[0]
    xs = np.zeros((T, n))
    ys = np.zeros((T, m_dim))
    x = rng.multivariate_normal(m0, P0)
    for t in range(T):
        F_t, H_t, Q_t, R_t = _at(F, t, 2), _at(H, t, 2), _at(Q, t, 2), _at(R, t, 2)
        G_t = _at(G, t, 2) if G is not None else np.eye(n)
        w = rng.multivariate_normal(np.zeros(Q_t.shape[0]), Q_t)
        x = F_t @ x + G_t @ w
        v = rng.multivariate_normal(np.zeros(R_t.shape[0]), R_t)
        xs[t] = x
        ys[t] = H_t @ x + v
    return xs, ys


# --------------------------------------------------------------------------
# Self-check
# --------------------------------------------------------------------------

def _random_spd(rng, d, jitter=0.1):
    A = rng.standard_normal((d, d))
    return A @ A.T / d + jitter * np.eye(d)


def _random_stable(rng, n, radius=0.9):
    A = rng.standard_normal((n, n))
    return radius * A / np.max(np.abs(np.linalg.eigvals(A)))


def _self_check():
    from filterpy.kalman import KalmanFilter

    tol = 1e-10
    rng = np.random.default_rng(0)
    ok = True

    # (a) convergence to the DARE solution
    n, m, q = 3, 2, 2
    F = _random_stable(rng, n)
    H = rng.standard_normal((m, n))
    G = rng.standard_normal((n, q))
    Q = _random_spd(rng, q)
    R = _random_spd(rng, m)
    m0 = rng.standard_normal(n)
    P0 = _random_spd(rng, n)
    T = 500
    _, ys = numpy_simulate_lgssm(rng, m0, P0, F, H, Q, R, T, G=G)
    out = numpy_kalman_filter(m0, P0, ys, F, H, Q, R, G=G)
    P_inf, K_inf = numpy_dare_filter(F, H, Q, R, G=G)
    Pf_inf = (np.eye(n) - K_inf @ H) @ P_inf
    da = np.max(np.abs(out["filtered_covariances"][-1] - Pf_inf))
    dp = np.max(np.abs(out["predicted_covariances"][-1] - P_inf))
    print(f"(a) |P_filt[T-1] - (I-KH)P_dare|_max = {da:.3e}")
    print(f"    |P_pred[T-1] - P_dare|_max       = {dp:.3e}")
    ok &= da < tol and dp < tol

    # (b) against filterpy, no missing data
    n, m = 3, 2
    F = rng.standard_normal((n, n)) * 0.5
    H = rng.standard_normal((m, n))
    G = rng.standard_normal((n, n))
    Q = _random_spd(rng, n)
    R = _random_spd(rng, m)
    m0 = rng.standard_normal(n)
    P0 = _random_spd(rng, n)
    T = 50
    _, ys = numpy_simulate_lgssm(rng, m0, P0, F, H, Q, R, T, G=G)
    out = numpy_kalman_filter(m0, P0, ys, F, H, Q, R, G=G)

    kf = KalmanFilter(dim_x=n, dim_z=m)
    kf.F, kf.H, kf.Q, kf.R = F, H, G @ Q @ G.T, R
    kf.x = m0.copy()          # 1-D state => filterpy keeps x 1-D, z reshaped to (m,)
    kf.P = P0.copy()
    fm, fP, pm, pP, ll = [], [], [], [], []
    for t in range(T):
        kf.predict()
        pm.append(kf.x.copy()); pP.append(kf.P.copy())
        kf.update(ys[t])
        fm.append(kf.x.copy()); fP.append(kf.P.copy())
        ll.append(kf.log_likelihood)
    db = {
        "filtered_means": np.max(np.abs(np.array(fm) - out["filtered_means"])),
        "filtered_covariances": np.max(np.abs(np.array(fP) - out["filtered_covariances"])),
        "predicted_means": np.max(np.abs(np.array(pm) - out["predicted_means"])),
        "predicted_covariances": np.max(np.abs(np.array(pP) - out["predicted_covariances"])),
        "loglik_increments": np.max(np.abs(np.array(ll) - out["loglik_increments"])),
    }
    print("(b) vs filterpy KalmanFilter (T=50, no missing):")
    for k, v in db.items():
        print(f"    max|diff| {k:22s} = {v:.3e}")
    ok &= all(v < tol for v in db.values())

    # (c) against filterpy with time-varying model, control, noise means and
    #     missing data (update with H_o, R_oo; all-missing step => update(None))
    n, m, q, p = 3, 3, 2, 1
    T = 40
    Fs = np.stack([_random_stable(rng, n, 0.95) for _ in range(T)])
    Hs = rng.standard_normal((T, m, n))
    Gs = rng.standard_normal((T, n, q))
    Qs = np.stack([_random_spd(rng, q) for _ in range(T)])
    Rs = np.stack([_random_spd(rng, m) for _ in range(T)])
    Bm = rng.standard_normal((n, p))
    us = rng.standard_normal((T, p))
    mu_w = rng.standard_normal((T, q))
    mu_v = rng.standard_normal(m)
    m0 = rng.standard_normal(n)
    P0 = _random_spd(rng, n)
    ys = rng.standard_normal((T, m)) * 3.0
    ys[rng.random((T, m)) < 0.3] = np.nan
    ys[5] = np.nan
    ys[17] = np.nan
    out = numpy_kalman_filter(m0, P0, ys, Fs, Hs, Qs, Rs, G=Gs, B=Bm, inputs=us,
                              process_mean=mu_w, noise_mean=mu_v)

    kf = KalmanFilter(dim_x=n, dim_z=m, dim_u=p + q)
    kf.x = m0.copy()
    kf.P = P0.copy()
    fm, fP, ll = [], [], []
    for t in range(T):
        # fold G mu_w into the control term: B_aug = [B, G], u_aug = [u, mu_w]
        B_aug = np.hstack([Bm, Gs[t]])
        u_aug = np.concatenate([us[t], mu_w[t]])
        kf.predict(u=u_aug, B=B_aug, F=Fs[t], Q=Gs[t] @ Qs[t] @ Gs[t].T)
        o = np.flatnonzero(~np.isnan(ys[t]))
        if o.size == 0:
            kf.update(None)
            ll.append(0.0)
        else:
            kf.update(ys[t, o] - mu_v[o], R=Rs[t][np.ix_(o, o)], H=Hs[t][o, :])
            ll.append(kf.log_likelihood)
        fm.append(kf.x.copy()); fP.append(kf.P.copy())
    dc = {
        "filtered_means": np.max(np.abs(np.array(fm) - out["filtered_means"])),
        "filtered_covariances": np.max(np.abs(np.array(fP) - out["filtered_covariances"])),
        "loglik_increments": np.max(np.abs(np.array(ll) - out["loglik_increments"])),
    }
    print("(c) vs filterpy (time-varying, control, means, ~30% missing + 2 all-missing steps):")
    for k, v in dc.items():
        print(f"    max|diff| {k:22s} = {v:.3e}")
    ok &= all(v < tol for v in dc.values())
    # marginal loglik cross-check against scipy
    from scipy.stats import multivariate_normal
    t = int(np.flatnonzero(~np.isnan(ys).any(axis=1))[0])
    S = Hs[t] @ out["predicted_covariances"][t] @ Hs[t].T + Rs[t]
    ref = multivariate_normal.logpdf(ys[t], Hs[t] @ out["predicted_means"][t] + mu_v, S)
    dl = abs(ref - out["loglik_increments"][t])
    print(f"    scipy logpdf check at fully-observed step {t}: {dl:.3e}")
    ok &= dl < tol

    print("SELF-CHECK", "PASSED" if ok else "FAILED")
    return ok


if __name__ == "__main__":
    import sys
    sys.exit(0 if _self_check() else 1)
