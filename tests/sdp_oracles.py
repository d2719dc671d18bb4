"""Independent CVXPY (Clarabel) reference solvers for the DR-MMSE problems.

NumPy in / NumPy out; does NOT depend on jax or jdrkf.  Used by
``tests/test_sets.py`` to check the first-order solvers in ``jdrkf.sets``.

Problems (Wang & Ye 2022, eqs. (32)-(37) and Theorem 8; docs/math/wasserstein.md)
-----------------------------------------------------------------------------
Decoupled:  max_{Σx ∈ 𝒮x, Σv ∈ 𝒮v}  Tr(Σx) − i_min Tr(Σx Hᵀ (H Σx Hᵀ + Σv)⁻¹ H Σx)
Joint:      max_{S ∈ 𝒮}              Tr(S_xx − S_xy S_yy⁻¹ S_yx)

with the Schur-complement epigraph  [[U, Σx Hᵀ], [H Σx, H Σx Hᵀ + Σv]] ⪰ 0  (the
objective becomes Tr(Σx) − i_min Tr(U)), and the sets

* Gelbrich/Wasserstein ball (eq. 34-35):  Tr(Σ + N − 2V) ≤ θ²,
  [[N^½ Σ N^½, V], [V, I]] ⪰ 0, V ⪰ 0   (⇔ 𝓑(Σ, N) ≤ θ);
* KL ball (eqs. 18/21):  ½[Tr(N⁻¹Σ) − d − log det Σ + log det N] ≤ c;
* moment set (eq. 37):   θ₁ N ⪯ Σ ⪯ θ₂ N.

The module also carries plain NumPy/SciPy closed forms (linear oracles of the three
sets, objective gradients, distances) used to validate the SDP solutions, and a NumPy
Frank–Wolfe that *polishes* them: Clarabel's optimal values are accurate to ~1e-9 but
its primal matrices only to ~1e-4, so by default the returned covariances (and
`value`) are those of the certified FW solution, cross-checked against the SDP (the raw
SDP results stay in the dict under `sdp_*`).
"""

import warnings

import cvxpy as cp
import numpy as np
import scipy.optimize

_SOLVER_OPTS = {"solver": cp.CLARABEL, "max_iter": 500}
# Clarabel sometimes stalls just short of 1e-10 ("AlmostSolved"); retry looser.
_TOLERANCES = (1e-10, 1e-9, 1e-8)


# ----------------------------------------------------------------------------- helpers


def _sym(a):
    a = np.asarray(a, dtype=np.float64)
    return 0.5 * (a + a.T)


def _sqrtm_psd(a):
    lam, vec = np.linalg.eigh(_sym(a))
    return _sym((vec * np.sqrt(np.clip(lam, 0.0, None))) @ vec.T)


def _solve(prob):
    """Solve with tight Clarabel tolerances, falling back to looser ones; return the value."""
    with warnings.catch_warnings():
        # "Solution may be inaccurate": the status is checked below instead.
        warnings.simplefilter("ignore", UserWarning)
        for tol in _TOLERANCES:
            prob.solve(**_SOLVER_OPTS, tol_gap_abs=tol, tol_gap_rel=tol, tol_feas=tol)
            if prob.status == cp.OPTIMAL:
                return float(prob.value)
    raise RuntimeError(f"Clarabel status {prob.status!r}")


def _psd(expr):
    """PSD constraint on the (explicitly symmetrized) expression."""
    return 0.5 * (expr + expr.T) >> 0


def _set_constraints(kind, sigma, nominal, radius):
    """Constraints `sigma ∈ set(kind, nominal, radius)` (sigma a symmetric cvxpy variable)."""
    nominal = _sym(nominal)
    d = nominal.shape[0]
    if kind in ("wasserstein", "kl") and radius == 0:
        # A radius-0 ball has no interior (Clarabel reports "inaccurate"): pin the nominal.
        return [sigma == nominal]
    if kind == "wasserstein":
        root = _sqrtm_psd(nominal)
        v = cp.Variable((d, d), symmetric=True)
        return [
            cp.trace(sigma) + np.trace(nominal) - 2 * cp.trace(v) <= radius**2,
            _psd(cp.bmat([[root @ sigma @ root, v], [v, np.eye(d)]])),
            v >> 0,
            sigma >> 0,
        ]
    if kind == "kl":
        inv = _sym(np.linalg.inv(nominal))
        logdet_n = np.linalg.slogdet(nominal)[1]
        return [
            0.5 * (cp.trace(inv @ sigma) - d - cp.log_det(sigma) + logdet_n) <= radius,
        ]
    if kind == "moment":
        theta1, theta2 = radius
        return [sigma << theta2 * nominal, sigma >> theta1 * nominal]
    raise ValueError(f"unknown set kind {kind!r}")


# ----------------------------------------------------------------------------- objectives


def posterior_trace(state_cov, H, noise_cov, i_min=1.0):
    """Tr(Σx − i_min Σx Hᵀ (H Σx Hᵀ + Σv)⁻¹ H Σx)."""
    sx, sv, H = _sym(state_cov), _sym(noise_cov), np.asarray(H, dtype=np.float64)
    s = H @ sx @ H.T + sv
    return float(np.trace(sx) - i_min * np.trace(sx @ H.T @ np.linalg.solve(s, H @ sx)))


def schur_trace(cov, n):
    """Tr(S_xx − S_xy S_yy⁻¹ S_yx)."""
    s = _sym(cov)
    return float(np.trace(s[:n, :n] - s[:n, n:] @ np.linalg.solve(s[n:, n:], s[n:, :n])))


def decoupled_gradient(state_cov, H, noise_cov, i_min=1.0):
    """(∇_{Σx} f, ∇_{Σv} f) of the decoupled objective, both PSD for 0 ≤ i_min ≤ 1.

    With K = Σx Hᵀ (H Σx Hᵀ + Σv)⁻¹:
    ∇_{Σx} f = (1 − i_min) I + i_min (I − K H)ᵀ (I − K H),  ∇_{Σv} f = i_min Kᵀ K.
    """
    sx, sv, H = _sym(state_cov), _sym(noise_cov), np.asarray(H, dtype=np.float64)
    n = sx.shape[0]
    k = np.linalg.solve(H @ sx @ H.T + sv, H @ sx).T
    ikh = np.eye(n) - k @ H
    return _sym((1 - i_min) * np.eye(n) + i_min * ikh.T @ ikh), _sym(i_min * k.T @ k)


def joint_gradient(cov, n):
    """∇f(S) = [I, −K]ᵀ [I, −K], K = S_xy S_yy⁻¹."""
    s = _sym(cov)
    k = np.linalg.solve(s[n:, n:], s[n:, :n]).T
    g = np.hstack([np.eye(n), -k])
    return _sym(g.T @ g)


# ----------------------------------------------------------------------------- distances


def bures_distance(a, b):
    """Bures distance via scipy/eigh square roots."""
    ra = _sqrtm_psd(a)
    d2 = np.trace(a) + np.trace(b) - 2 * np.trace(_sqrtm_psd(ra @ _sym(b) @ ra))
    return float(np.sqrt(max(d2, 0.0)))


def kl_divergence(cov, nominal):
    """KL(N(0, cov) ‖ N(0, nominal)) = ½[Tr(N⁻¹Σ) − d − ln det(N⁻¹Σ)]."""
    cov, nominal = _sym(cov), _sym(nominal)
    d = cov.shape[0]
    return float(
        0.5
        * (
            np.trace(np.linalg.solve(nominal, cov))
            - d
            - np.linalg.slogdet(cov)[1]
            + np.linalg.slogdet(nominal)[1]
        )
    )


# ----------------------------------------------------------------------------- closed-form LMOs


def wasserstein_lmo_closed_form(direction, nominal, rho):
    """argmax ⟨D, L⟩ s.t. 𝓑(L, N) ≤ ρ for D ⪰ 0, D ≠ 0 (the Gelbrich oracle).

    L = T N T with T = (I − tD)⁻¹, t ∈ (0, 1/d₁) the root of
    ρ² = Tr(N (tDT)²), found by Brent's method in eigen-coordinates.
    Returns (L, gamma = 1/t).
    """
    direction, nominal = _sym(direction), _sym(nominal)
    d, v = np.linalg.eigh(direction)
    if rho == 0 or d[-1] <= 0:
        return nominal.copy(), np.inf
    m_diag = np.einsum("ij,jk,ki->i", v.T, nominal, v)
    d1 = d[-1]

    def h(t):
        return rho**2 - np.sum(m_diag * (t * d / (1 - t * d)) ** 2)

    # Bracket (A.1): h(lo) >= 0 >= h(hi); equality (up to round-off) when D ∝ I.
    lo = rho / (d1 * (rho + np.sqrt(np.trace(nominal))))
    hi = rho / (d1 * (rho + np.sqrt(m_diag[-1])))
    if h(lo) <= 0:
        t = lo
    elif h(hi) >= 0:
        t = hi
    else:
        t = scipy.optimize.brentq(h, lo, hi, xtol=1e-300, rtol=4 * np.finfo(float).eps, maxiter=500)
    T = np.linalg.inv(np.eye(d.size) - t * direction)
    return _sym(T @ nominal @ T), 1.0 / t


def kl_lmo_closed_form(direction, nominal, c):
    """argmax ⟨D, S⟩ s.t. KL(N(0,S) ‖ N(0,N)) ≤ c for D ⪰ 0, D ≠ 0 (the KL oracle).

    S = (N⁻¹ − tD)⁻¹ with t ∈ (0, 1/μ_max), μ = eig(Rᵀ D R), N = R Rᵀ, the root of
    ½ Σᵢ [1/(1 − tμᵢ) − 1 + ln(1 − tμᵢ)] = c.  Returns (S, t).
    """
    direction, nominal = _sym(direction), _sym(nominal)
    if c == 0:
        return nominal.copy(), 0.0
    r = np.linalg.cholesky(nominal)
    mu = np.linalg.eigvalsh(r.T @ direction @ r)
    mu_max = mu[-1]

    def g(t):
        u = 1 - t * mu
        return 0.5 * np.sum(1 / u - 1 + np.log(u)) - c

    # g increases from -c at t=0 to +inf as t -> 1/mu_max.
    hi = 1.0 / mu_max
    s = 1.0
    while g(hi * (1 - s)) < 0:
        s *= 0.5
    t = scipy.optimize.brentq(g, 0.0, hi * (1 - s), xtol=1e-300, rtol=4 * np.finfo(float).eps, maxiter=500)
    s_opt = np.linalg.inv(_sym(np.linalg.inv(nominal)) - t * direction)
    return _sym(s_opt), t


def kl_lmo_identity_closed_form(nominal, c):
    """KL LMO for D = I: S = (N⁻¹ − tI)⁻¹, t from the eigenvalues σᵢ of N:
    ½ Σᵢ [1/(1 − tσᵢ) − 1 + ln(1 − tσᵢ)] = c.  Returns (S, t)."""
    nominal = _sym(nominal)
    sig, vec = np.linalg.eigh(nominal)
    if c == 0:
        return nominal.copy(), 0.0

    def g(t):
        u = 1 - t * sig
        return 0.5 * np.sum(1 / u - 1 + np.log(u)) - c

    hi = 1.0 / sig[-1]
    s = 1.0
    while g(hi * (1 - s)) < 0:
        s *= 0.5
    t = scipy.optimize.brentq(g, 0.0, hi * (1 - s), xtol=1e-300, rtol=4 * np.finfo(float).eps, maxiter=500)
    lam = 1.0 / (1.0 / sig - t)
    return _sym((vec * lam) @ vec.T), t


# ----------------------------------------------------------------------------- SDP LMOs


def wasserstein_lmo_sdp(direction, nominal, rho):
    """max ⟨D, L⟩ s.t. Gelbrich ball of radius ρ (an SDP)."""
    direction, nominal = _sym(direction), _sym(nominal)
    d = nominal.shape[0]
    L = cp.Variable((d, d), symmetric=True)
    prob = cp.Problem(cp.Maximize(cp.trace(direction @ L)), _set_constraints("wasserstein", L, nominal, rho))
    value = _solve(prob)
    return {"value": value, "cov": _sym(L.value)}


def kl_lmo_sdp(direction, nominal, c):
    """max ⟨D, S⟩ s.t. KL ball of radius c (exp-cone + PSD program)."""
    direction, nominal = _sym(direction), _sym(nominal)
    d = nominal.shape[0]
    S = cp.Variable((d, d), symmetric=True)
    prob = cp.Problem(cp.Maximize(cp.trace(direction @ S)), _set_constraints("kl", S, nominal, c))
    value = _solve(prob)
    return {"value": value, "cov": _sym(S.value)}


# ----------------------------------------------------------------------------- certified polish


def set_lmo(spec, direction, nominal):
    """Closed-form linear oracle of the set `spec` = (kind, radius) for a PSD direction."""
    kind, radius = spec
    if kind == "wasserstein":
        return wasserstein_lmo_closed_form(direction, nominal, radius)[0]
    if kind == "kl":
        if np.linalg.eigvalsh(_sym(direction))[-1] <= 0:
            return _sym(nominal)
        return kl_lmo_closed_form(direction, nominal, radius)[0]
    if kind == "moment":
        return radius[1] * _sym(nominal)  # argmax over θ₁N ⪯ S ⪯ θ₂N for any D ⪰ 0
    raise ValueError(f"unknown set kind {kind!r}")


def frank_wolfe(f, grad, lmos, start, rtol=1e-14, max_iter=5000):
    """Backtracking Frank–Wolfe (docs/math/wasserstein.md) for a concave f over a product of sets.

    NumPy reference used to *polish* the SDP solutions: Clarabel's optimal values are
    accurate to ~1e-9 but its primal matrices only to ~1e-5..1e-4 (rank-deficient
    Gelbrich/Schur blocks).  The FW gap is a certificate: f* ≤ f(S) + gap (concavity).
    Returns (blocks, gap, iterations).
    """
    S = [_sym(b) for b in start]
    beta = 1.0
    gap = np.inf
    for it in range(max_iter):
        G = grad(*S)
        P = [lmo(g) - b for lmo, g, b in zip(lmos, G, S)]
        gap = float(sum(np.sum(g * p) for g, p in zip(G, P)))
        f0 = f(*S)
        if gap <= rtol * max(abs(f0), 1.0):
            return S, gap, it
        norm2 = float(sum(np.sum(p * p) for p in P))
        beta *= 0.5
        while True:
            eta = min(gap / (beta * norm2), 1.0)
            cand = [_sym(b + eta * p) for b, p in zip(S, P)]
            if f(*cand) >= f0 + eta * gap - 0.5 * eta**2 * beta * norm2:
                break
            beta *= 2.0
        S = cand
    raise RuntimeError(f"Frank–Wolfe polish did not converge (gap {gap:.3e})")


def _check_agreement(sdp_value, fw_value, sdp_covs, fw_covs):
    scale = max(abs(sdp_value), 1.0)
    if abs(sdp_value - fw_value) > 1e-7 * scale:
        raise RuntimeError(f"SDP value {sdp_value!r} and FW value {fw_value!r} disagree")
    for a, b in zip(sdp_covs, fw_covs):
        if np.max(np.abs(a - b)) > 1e-3 * max(np.max(np.abs(b)), 1.0):
            raise RuntimeError("SDP and FW worst-case covariances disagree")


# ----------------------------------------------------------------------------- DR-MMSE SDPs


def _decoupled_sdp(M, H, R, state_set, noise_set, i_min, polish):
    M, R, H = _sym(M), _sym(R), np.asarray(H, dtype=np.float64)
    n, m = M.shape[0], R.shape[0]
    if H.shape != (m, n):
        raise ValueError(f"H has shape {H.shape}, expected {(m, n)}")
    sx = cp.Variable((n, n), symmetric=True)
    sv = cp.Variable((m, m), symmetric=True)
    u = cp.Variable((n, n), symmetric=True)
    cons = [_psd(cp.bmat([[u, sx @ H.T], [H @ sx, H @ sx @ H.T + sv]]))]
    cons += _set_constraints(state_set[0], sx, M, state_set[1])
    cons += _set_constraints(noise_set[0], sv, R, noise_set[1])
    prob = cp.Problem(cp.Maximize(cp.trace(sx) - i_min * cp.trace(u)), cons)
    value = _solve(prob)
    state_cov, noise_cov = _sym(sx.value), _sym(sv.value)
    out = {"value": value, "sdp_value": value, "state_cov": state_cov, "noise_cov": noise_cov,
           "sdp_state_cov": state_cov, "sdp_noise_cov": noise_cov, "fw_gap": None}
    if polish:
        (px, pv), gap, _ = frank_wolfe(
            lambda a, b: posterior_trace(a, H, b, i_min),
            lambda a, b: decoupled_gradient(a, H, b, i_min),
            [lambda g: set_lmo(state_set, g, M), lambda g: set_lmo(noise_set, g, R)],
            [M, R],
        )
        fw_value = posterior_trace(px, H, pv, i_min)
        _check_agreement(value, fw_value, (state_cov, noise_cov), (px, pv))
        out.update(value=fw_value, state_cov=px, noise_cov=pv, fw_gap=gap)
    out["value_at_solution"] = posterior_trace(out["state_cov"], H, out["noise_cov"], i_min)
    return out


def _joint_sdp(S_hat, n, spec, polish):
    S_hat = _sym(S_hat)
    d = S_hat.shape[0]
    if not 0 < n < d:
        raise ValueError(f"n={n} must lie strictly between 0 and d={d}")
    s = cp.Variable((d, d), symmetric=True)
    u = cp.Variable((n, n), symmetric=True)
    cons = [_psd(cp.bmat([[u, s[:n, n:]], [s[n:, :n], s[n:, n:]]]))]
    cons += _set_constraints(spec[0], s, S_hat, spec[1])
    prob = cp.Problem(cp.Maximize(cp.trace(s[:n, :n]) - cp.trace(u)), cons)
    value = _solve(prob)
    cov = _sym(s.value)
    out = {"value": value, "sdp_value": value, "cov": cov, "sdp_cov": cov, "fw_gap": None}
    if polish:
        (pc,), gap, _ = frank_wolfe(
            lambda a: schur_trace(a, n),
            lambda a: [joint_gradient(a, n)],
            [lambda g: set_lmo(spec, g, S_hat)],
            [S_hat],
        )
        fw_value = schur_trace(pc, n)
        _check_agreement(value, fw_value, (cov,), (pc,))
        out.update(value=fw_value, cov=pc, fw_gap=gap)
    out["value_at_solution"] = schur_trace(out["cov"], n)
    return out


def decoupled_wasserstein_sdp(M, H, R, theta_x, theta_v, i_min=1.0, polish=True):
    """Eqs. (34)-(35): decoupled Gelbrich balls around M (state) and R (noise).

    Returns dict(value, state_cov, noise_cov, sdp_value, sdp_state_cov, sdp_noise_cov,
    fw_gap, value_at_solution).  `sdp_*` are Clarabel's (value ~1e-9 relative, matrices
    ~1e-4).  With `polish` (default), `value`, `state_cov`, `noise_cov` are those of the
    NumPy Frank–Wolfe solution (relative gap <= 1e-14, so the value is certified to that
    accuracy; matrices ~1e-6), which must agree with the SDP (value to 1e-7 relative,
    matrices to 1e-3) or a RuntimeError is raised; without, they are the SDP's.
    """
    return _decoupled_sdp(M, H, R, ("wasserstein", theta_x), ("wasserstein", theta_v), i_min, polish)


def decoupled_kl_sdp(M, H, R, c_x, c_v, i_min=1.0, polish=True):
    """Eq. (32) with the KL balls (18)/(21) of radii c_x, c_v (cvxpy `log_det`)."""
    return _decoupled_sdp(M, H, R, ("kl", c_x), ("kl", c_v), i_min, polish)


def decoupled_mixed_sdp(M, H, R, state_set, noise_set, i_min=1.0, polish=True):
    """Eq. (32) with any set per block: ("wasserstein", θ), ("kl", c), ("moment", (θ₁, θ₂))."""
    return _decoupled_sdp(M, H, R, tuple(state_set), tuple(noise_set), i_min, polish)


def moment_sdp(M, H, R, t2x, t2v, t1x=0.5, t1v=0.5, i_min=1.0):
    """Eqs. (36)-(37), plain SDP (no polish); Theorem 5 says Σx* = θ2x M, Σv* = θ2v R."""
    return _decoupled_sdp(M, H, R, ("moment", (t1x, t2x)), ("moment", (t1v, t2v)), i_min, False)


def joint_wasserstein_sdp(S_hat, n, rho, polish=True):
    """Theorem 8 / WKF: one Gelbrich ball of radius rho around the joint (x, y) covariance.

    Returns dict(value, cov, ...), see `decoupled_wasserstein_sdp` for `polish`.
    """
    return _joint_sdp(S_hat, n, ("wasserstein", rho), polish)


def joint_kl_sdp(S_hat, n, c, polish=True):
    """Theorem 8: one KL ball of radius c around the joint (x, y) covariance."""
    return _joint_sdp(S_hat, n, ("kl", c), polish)


# ----------------------------------------------------------------------------- instances


def random_spd(rng, d, floor=0.3):
    a = rng.normal(size=(d, d))
    return _sym(a @ a.T / d + floor * np.eye(d))


def random_instance(rng, n, m):
    """(M, H, R): well-conditioned SPD prior and noise covariances, Gaussian H."""
    M = random_spd(rng, n, 0.5)
    H = rng.normal(size=(m, n))
    R = random_spd(rng, m, 0.3)
    return M, H, R


def random_joint(rng, n, m):
    """Joint (x, y) covariance S_hat = [[M, M Hᵀ], [H M, H M Hᵀ + R]] (SPD, d = n + m)."""
    M, H, R = random_instance(rng, n, m)
    return _sym(np.block([[M, M @ H.T], [H @ M, H @ M @ H.T + R]]))

