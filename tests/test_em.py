"""EM estimation of nominal noise covariances (Jang, Hakobyan & Yang's protocol) against an
independent NumPy reference: its E-step conditions the *joint* Gaussian of
`(x_{0:T-1}, y_{0:T-1})` in one batch (no Kalman/RTS recursion), its M-step is plain
loops, and its driver is the seed's `main.py` loop."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg
import scipy.stats

from jdrkf._em import EMResult, em_noise_covariances


_em_jit = eqx.filter_jit(em_noise_covariances)


def em(*args, tol=1e-4, min_eig=1e-4, **kwargs):
    # tol and min_eig as arrays (traced), so only shapes and static options recompile.
    return _em_jit(*args, tol=jnp.asarray(tol), min_eig=jnp.asarray(min_eig), **kwargs)


# ----------------------------------------------------------------------------------
# NumPy reference
# ----------------------------------------------------------------------------------


def _ref_joint(F, H, ys, drive, m0, P0, Q, R, b, d):
    """Mean and covariance of x_{0:T-1} (stacked) and of y_{0:T-1} (stacked)."""
    T, m = ys.shape
    n = F.shape[0]
    mx = np.zeros((T, n))
    V = np.zeros((T, n, n))
    mx[0], V[0] = m0, P0
    for t in range(T - 1):
        mx[t + 1] = F @ mx[t] + drive[t] + b
        V[t + 1] = F @ V[t] @ F.T + Q
    Sx = np.zeros((T * n, T * n))
    for s in range(T):
        blk = V[s]
        for t in range(s, T):  # blk = Cov(x_t, x_s) = F^{t-s} V_s
            Sx[t * n:(t + 1) * n, s * n:(s + 1) * n] = blk
            Sx[s * n:(s + 1) * n, t * n:(t + 1) * n] = blk.T
            blk = F @ blk
    Hb = np.kron(np.eye(T), H)
    my = (mx @ H.T + d).ravel()
    Sy = Hb @ Sx @ Hb.T + np.kron(np.eye(T), R)
    Sxy = Sx @ Hb.T
    return mx.ravel(), Sx, my, Sy, Sxy


def ref_posterior(F, H, ys, drive, m0, P0, Q, R, b, d):
    """Log-likelihood and smoothed moments by conditioning the joint Gaussian."""
    T, _ = ys.shape
    n = F.shape[0]
    mx, Sx, my, Sy, Sxy = _ref_joint(F, H, ys, drive, m0, P0, Q, R, b, d)
    chol = scipy.linalg.cho_factor(Sy, lower=True)
    resid = ys.ravel() - my
    ll = -0.5 * (resid @ scipy.linalg.cho_solve(chol, resid) + 2 * np.sum(np.log(np.diag(chol[0]))) + resid.size * np.log(2 * np.pi))
    mean = mx + Sxy @ scipy.linalg.cho_solve(chol, resid)
    cov = Sx - Sxy @ scipy.linalg.cho_solve(chol, Sxy.T)
    cov = (cov + cov.T) / 2
    ms = mean.reshape(T, n)
    Ps = np.array([cov[t * n:(t + 1) * n, t * n:(t + 1) * n] for t in range(T)])
    C = np.array([cov[(t + 1) * n:(t + 2) * n, t * n:(t + 1) * n] for t in range(T - 1)])  # Cov(x_{t+1}, x_t)
    return ll, ms, Ps, C


def ref_loglik(F, H, ys, drive, m0, P0, Q, R, b, d):
    # scipy's own log-density (eigh-based), independent of the Cholesky above.
    _, _, my, Sy, _ = _ref_joint(F, H, ys, drive, m0, P0, Q, R, b, d)
    return scipy.stats.multivariate_normal(my, Sy).logpdf(ys.ravel())


def ref_em_step(F, H, ys, drive, params, smoothed, estimate_offsets=True, offset_update="pykalman"):
    _, _, b, d = params
    T, m = ys.shape
    n = F.shape[0]
    ms, Ps, C = smoothed
    d_new, b_new = np.zeros(m), np.zeros(n)
    for t in range(T):
        d_new += (ys[t] - H @ ms[t]) / T
    for t in range(T - 1):
        b_new += (ms[t + 1] - F @ ms[t] - drive[t]) / (T - 1)
    if not estimate_offsets:
        d_new, b_new = d, b
    dd, bb = (d, b) if offset_update == "pykalman" else (d_new, b_new)
    R_new = np.zeros((m, m))
    for t in range(T):
        e = ys[t] - H @ ms[t] - dd
        R_new += (np.outer(e, e) + H @ Ps[t] @ H.T) / T
    Q_new = np.zeros((n, n))
    for t in range(T - 1):
        e = ms[t + 1] - F @ ms[t] - drive[t] - bb
        Q_new += (np.outer(e, e) + F @ Ps[t] @ F.T + Ps[t + 1] - C[t] @ F.T - F @ C[t].T) / (T - 1)
    return (Q_new + Q_new.T) / 2, (R_new + R_new.T) / 2, b_new, d_new


def enforce_positive_definiteness(S, eps=1e-4):
    # as in Jang, Hakobyan & Yang's main.py
    S = (S + S.T) / 2
    lam = np.min(np.linalg.eigvalsh(S))
    if lam < eps:
        S = S + (eps - lam) * np.eye(S.shape[0])
    return S


def ref_em(F, H, ys, m0, P0, *, Q0=None, R0=None, drive=None, max_iter=100, tol=1e-4, **kw):
    """The seed's driver: one EM iteration at a time, log-likelihood after each,
    break when the gain (from the second iteration on) is <= tol."""
    T, m = ys.shape
    n = F.shape[0]
    drive = np.zeros((T - 1, n)) if drive is None else drive
    params = (np.eye(n) if Q0 is None else Q0, np.eye(m) if R0 is None else R0, np.zeros(n), np.zeros(m))
    ll, *smoothed = ref_posterior(F, H, ys, drive, m0, P0, *params)
    lls = [ll]
    converged = False
    for i in range(max_iter):
        params = ref_em_step(F, H, ys, drive, params, smoothed, **kw)
        ll, *smoothed = ref_posterior(F, H, ys, drive, m0, P0, *params)
        lls.append(ll)
        if i > 0 and lls[-1] - lls[-2] <= tol:
            converged = True
            break
    Q, R, b, d = params
    return dict(Q=enforce_positive_definiteness(Q), R=enforce_positive_definiteness(R), b=b, d=d, lls=np.array(lls), converged=converged)


# ----------------------------------------------------------------------------------
# Models and data
# ----------------------------------------------------------------------------------


def _random_model(rng, n, m):
    a = rng.normal(size=(n, n))
    F = 0.95 * a / max(1.0, np.max(np.abs(np.linalg.eigvals(a))))
    H = rng.normal(size=(m, n))
    c = rng.normal(size=(n, n))
    e = rng.normal(size=(m, m))
    return F, H, c @ c.T / n + 0.2 * np.eye(n), e @ e.T / m + 0.3 * np.eye(m)


def _simulate(rng, F, H, Q, R, m0, P0, T, b=None, d=None, drive=None):
    n, m = F.shape[0], H.shape[0]
    b = np.zeros(n) if b is None else b
    d = np.zeros(m) if d is None else d
    x = rng.multivariate_normal(m0, P0)
    ys = np.zeros((T, m))
    for t in range(T):
        ys[t] = H @ x + d + rng.multivariate_normal(np.zeros(m), R)
        u = 0.0 if drive is None or t == T - 1 else drive[t]
        x = F @ x + u + b + rng.multivariate_normal(np.zeros(n), Q)
    return ys


def _double_integrator():
    dt = 0.2
    F = np.array([[1, dt, 0, 0], [0, 1, 0, 0], [0, 0, 1, dt], [0, 0, 0, 1.0]])
    H = np.array([[1, 0, 0, 0], [0, 0, 1, 0.0]])
    return F, H


def _assert_matches(res, ref, rtol=1e-8, atol=1e-10):
    np.testing.assert_allclose(res.Q, ref["Q"], rtol=rtol, atol=atol)
    np.testing.assert_allclose(res.R, ref["R"], rtol=rtol, atol=atol)
    np.testing.assert_allclose(res.process_offset, ref["b"], rtol=rtol, atol=atol)
    np.testing.assert_allclose(res.noise_offset, ref["d"], rtol=rtol, atol=atol)
    k = len(ref["lls"]) - 1
    assert int(res.iterations) == k
    np.testing.assert_allclose(res.loglik_history[: k + 1], ref["lls"], rtol=1e-10)
    assert np.all(np.isnan(np.asarray(res.loglik_history[k + 1:])))
    np.testing.assert_allclose(res.loglik, ref["lls"][-1], rtol=1e-10)


# ----------------------------------------------------------------------------------
# Tests
# ----------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "n, m, T, offset_update, estimate_offsets, max_iter, tol",
    [
        (2, 1, 5, "pykalman", True, 15, -np.inf),
        (3, 2, 5, "joint", True, 15, -np.inf),
        (4, 2, 5, "pykalman", True, 30, -np.inf),
        (2, 2, 50, "pykalman", False, 100, 1e-2),  # stops on the gain criterion
        (3, 2, 50, "joint", True, 20, -np.inf),
        (4, 3, 50, "pykalman", True, 10, -np.inf),
    ],
)
def test_matches_numpy_reference(n, m, T, offset_update, estimate_offsets, max_iter, tol):
    rng = np.random.default_rng(100 * n + 10 * m + T)
    F, H, Q, R = _random_model(rng, n, m)
    m0, P0 = rng.normal(size=n), 0.5 * np.eye(n)
    ys = _simulate(rng, F, H, Q, R, m0, P0, T, b=0.3 * rng.normal(size=n), d=0.3 * rng.normal(size=m))
    kw = dict(max_iter=max_iter, tol=tol, offset_update=offset_update, estimate_offsets=estimate_offsets)
    res = em(F, H, ys, m0, P0, **kw)
    ref = ref_em(F, H, ys, m0, P0, **kw)
    _assert_matches(res, ref)
    assert bool(res.converged) == ref["converged"]
    if tol > -np.inf:
        assert ref["converged"] and 2 <= int(res.iterations) < max_iter


def test_matches_reference_with_inputs_and_fixed_offsets():
    rng = np.random.default_rng(7)
    n, m, p, T = 3, 2, 2, 30
    F, H, Q, R = _random_model(rng, n, m)
    B = rng.normal(size=(n, p))
    u = rng.normal(size=(T - 1, p))
    m0, P0 = np.zeros(n), np.eye(n)
    ys = _simulate(rng, F, H, Q, R, m0, P0, T, drive=u @ B.T)
    Q0, R0 = 2.0 * np.eye(n), 0.5 * np.eye(m)
    res = em(F, H, ys, m0, P0, Q0=Q0, R0=R0, inputs=u, B=B, estimate_offsets=False, max_iter=25, tol=-np.inf)
    ref = ref_em(F, H, ys, m0, P0, Q0=Q0, R0=R0, drive=u @ B.T, max_iter=25, tol=-np.inf, estimate_offsets=False)
    _assert_matches(res, ref)
    np.testing.assert_array_equal(res.process_offset, np.zeros(n))
    np.testing.assert_array_equal(res.noise_offset, np.zeros(m))


@pytest.mark.parametrize("offset_update", ["pykalman", "joint"])
def test_loglik_never_decreases(offset_update):
    rng = np.random.default_rng(3)
    F, H, Q, R = _random_model(rng, 3, 2)
    m0, P0 = np.zeros(3), np.eye(3)
    ys = _simulate(rng, F, H, Q, R, m0, P0, 40, b=np.array([0.5, -0.2, 0.1]))
    long = em(F, H, ys, m0, P0, max_iter=10, tol=-np.inf, offset_update=offset_update)
    hist = np.asarray(long.loglik_history)
    assert int(long.iterations) == 10 and hist.shape == (11,)
    assert np.all(np.diff(hist) >= -1e-9 * np.abs(hist[1:])), np.diff(hist)
    assert hist[-1] > hist[0] + 1.0  # and EM does move from Q0 = R0 = I
    # Independent check of entry 0: the joint-Gaussian log-density at the initial parameters.
    np.testing.assert_allclose(hist[0], ref_loglik(F, H, ys, np.zeros((39, 3)), m0, P0, np.eye(3), np.eye(2), np.zeros(3), np.zeros(2)), rtol=1e-10)
    for k in (1, 4) if offset_update == "pykalman" else ():  # separate runs of k iterations reproduce the history
        res = em(F, H, ys, m0, P0, max_iter=k, tol=-np.inf, offset_update=offset_update)
        assert int(res.iterations) == k
        np.testing.assert_allclose(res.loglik, hist[k], rtol=1e-12)


@pytest.mark.slow
def test_consistency_long_series():
    # Well-observed model (near-constant-velocity, every state measured). One series
    # of T = 3000 steps estimates each entry with ~5% standard error; the mean of 4
    # independent estimates (vmapped) is compared with the truth at 10%.
    rng = np.random.default_rng(0)
    F = np.array([[1.0, 0.2], [0.0, 1.0]])
    H = np.eye(2)
    Q = np.array([[0.5, 0.1], [0.1, 0.3]])
    R = np.array([[0.2, -0.05], [-0.05, 0.3]])
    m0, P0 = np.zeros(2), np.eye(2)
    ys = np.stack([_simulate(rng, F, H, Q, R, m0, P0, 3000) for _ in range(4)])
    for estimate_offsets, max_iter in ((False, 300), (True, 100)):
        fit = eqx.filter_jit(jax.vmap(lambda y, eo=estimate_offsets, k=max_iter: em_noise_covariances(
            F, H, y, m0, P0, estimate_offsets=eo, max_iter=k, tol=jnp.asarray(1e-6))))
        res = fit(ys)
        if not estimate_offsets:  # with offsets, b and d are nearly confounded (slow ridge)
            assert np.all(np.asarray(res.converged))
        assert np.linalg.norm(res.Q.mean(0) - Q) / np.linalg.norm(Q) < 0.1
        assert np.linalg.norm(res.R.mean(0) - R) / np.linalg.norm(R) < 0.1
        np.testing.assert_allclose(np.diag(res.Q.mean(0)), np.diag(Q), rtol=0.1)
        np.testing.assert_allclose(np.diag(res.R.mean(0)), np.diag(R), rtol=0.1)


def test_seed004_double_integrator_vmapped():
    F, H = _double_integrator()
    runs, T = 8, 5
    rng = np.random.default_rng(2024)
    m0, P0 = np.zeros(4), 0.01 * np.eye(4)
    ys = np.stack([_simulate(rng, F, H, 0.01 * np.eye(4), 0.01 * np.eye(2), m0, P0, T) for _ in range(runs)])
    batched = eqx.filter_jit(jax.vmap(lambda y: em_noise_covariances(F, H, y, m0, P0, Q0=np.eye(4), R0=np.eye(2))))
    res = batched(jnp.asarray(ys))
    assert isinstance(res, EMResult)
    assert res.Q.shape == (runs, 4, 4) and res.R.shape == (runs, 2, 2)
    for Sig in (np.asarray(res.Q), np.asarray(res.R)):
        assert np.all(np.isfinite(Sig))
        np.testing.assert_allclose(Sig, np.swapaxes(Sig, -1, -2), atol=1e-15)
        assert np.all(np.linalg.eigvalsh(Sig) >= 1e-4 - 1e-12)
    its = np.asarray(res.iterations)
    assert np.all((its >= 2) & (its <= 100))
    # Each run is the seed's pykalman loop, reproduced by the NumPy reference.
    for i in range(runs):
        ref = ref_em(F, H, ys[i], m0, P0)
        single = jax.tree_util.tree_map(lambda a, i=i: a[i], res)
        _assert_matches(single, ref, rtol=1e-7, atol=1e-9)
        assert bool(single.converged) == ref["converged"]


def test_lift_modes():
    # Few data and a tiny floor on a clearly rank-deficient case: "shift" moves all
    # eigenvalues up by the same amount, "clip" only raises those below the floor.
    F, H = _double_integrator()
    rng = np.random.default_rng(0)
    m0, P0 = np.zeros(4), 0.01 * np.eye(4)
    ys = _simulate(rng, F, H, 0.01 * np.eye(4), 0.01 * np.eye(2), m0, P0, 5)
    floor = 0.05
    raw = em(F, H, ys, m0, P0, min_eig=0.0, lift="clip")
    shifted = em(F, H, ys, m0, P0, min_eig=floor, lift="shift")
    clipped = em(F, H, ys, m0, P0, min_eig=floor, lift="clip")
    for name in ("Q", "R"):
        lam_raw = np.linalg.eigvalsh(getattr(raw, name))
        assert lam_raw[0] < floor  # the floor is active
        np.testing.assert_allclose(np.linalg.eigvalsh(getattr(shifted, name)), lam_raw + floor - lam_raw[0], atol=1e-12)
        np.testing.assert_allclose(np.linalg.eigvalsh(getattr(clipped, name)), np.maximum(lam_raw, floor), atol=1e-12)


def test_input_validation():
    F, H = _double_integrator()
    ys = np.zeros((5, 2))
    m0, P0 = np.zeros(4), np.eye(4)
    bad = [
        (dict(F=np.eye(3)), "H has shape"),
        (dict(F=np.ones((4, 3))), "F must be square"),
        (dict(H=np.ones((2, 3))), "H has shape"),
        (dict(ys=np.zeros((5, 3))), "ys has shape"),
        (dict(ys=np.zeros(5)), "ys must have 2 dimensions"),
        (dict(ys=np.zeros((1, 2))), "at least 2 time steps"),
        (dict(ys=np.full((5, 2), np.nan)), "non-finite"),
        (dict(initial_mean=np.zeros(3)), "initial_mean has shape"),
        (dict(initial_cov=np.eye(3)), "initial_cov has shape"),
        (dict(initial_cov=np.triu(np.ones((4, 4)))), "symmetric"),
        (dict(Q0=np.eye(3)), "Q0 has shape"),
        (dict(R0=-np.eye(2)), "positive semidefinite"),
        (dict(process_offset0=np.zeros(2)), "process_offset0 has shape"),
        (dict(noise_offset0=np.zeros(4)), "noise_offset0 has shape"),
        (dict(max_iter=-1), "max_iter"),
        (dict(max_iter=2.5), "max_iter"),
        (dict(tol=np.ones(2)), "tol must be a scalar"),
        (dict(tol=np.nan), "tol must be finite"),
        (dict(min_eig=-1.0), "min_eig must be >= 0"),
        (dict(lift="eig"), "lift"),
        (dict(offset_update="other"), "offset_update"),
        (dict(estimate_offsets=1), "estimate_offsets"),
        (dict(inputs=np.zeros((4, 2))), "together"),
        (dict(B=np.zeros((4, 2))), "together"),
        (dict(B=np.zeros((4, 2)), inputs=np.zeros((5, 2))), r"expected \(4, 2\)"),
        (dict(B=np.zeros((3, 2)), inputs=np.zeros((4, 2))), "B has shape"),
        (dict(F=np.array([["a"] * 4] * 4)), "F must"),
    ]
    for kwargs, match in bad:
        args = dict(F=F, H=H, ys=ys, initial_mean=m0, initial_cov=P0) | kwargs
        pos = [args.pop(k) for k in ("F", "H", "ys", "initial_mean", "initial_cov")]
        with pytest.raises(ValueError, match=match):
            em_noise_covariances(*pos, **args)


# ----------------------------------------------------------------------------------
# Certified convergence
# ----------------------------------------------------------------------------------


def _stationarity_data():
    rng = np.random.default_rng(11)
    F, H, Q, R = _random_model(rng, 2, 2)
    m0, P0 = np.zeros(2), np.eye(2)
    return F, H, _simulate(rng, F, H, Q, R, m0, P0, 60), m0, P0


def test_one_iteration_is_never_converged():
    # The gain test starts at the second iteration: with a tolerance every gain passes,
    # one iteration is still not converged, two are.
    F, H, ys, m0, P0 = _stationarity_data()
    one = em(F, H, ys[:20], m0, P0, max_iter=1, tol=1e6)
    two = em(F, H, ys[:20], m0, P0, max_iter=2, tol=1e6)
    assert int(one.iterations) == 1 and not bool(one.converged)
    assert int(two.iterations) == 2 and bool(two.converged)


def test_converged_result_is_a_stationary_point():
    # min_eig = 0 with "clip" returns the raw estimates (they are PSD). One more EM step of
    # the NumPy reference (joint-Gaussian E-step) barely moves them, and the central
    # finite-difference gradient of the reference log-likelihood in Q and R vanishes
    # relative to its value at the start Q = R = I.
    F, H, ys, m0, P0 = _stationarity_data()
    T = ys.shape[0]
    drive, zeros = np.zeros((T - 1, 2)), np.zeros(2)
    res = em(F, H, ys, m0, P0, max_iter=1000, tol=1e-10, estimate_offsets=False, min_eig=0.0, lift="clip")
    assert bool(res.converged) and int(res.iterations) < 1000
    Q, R = np.asarray(res.Q), np.asarray(res.R)
    _, *smoothed = ref_posterior(F, H, ys, drive, m0, P0, Q, R, zeros, zeros)
    Q1, R1, _, _ = ref_em_step(F, H, ys, drive, (Q, R, zeros, zeros), smoothed, estimate_offsets=False)
    assert np.linalg.norm(Q1 - Q) / np.linalg.norm(Q) < 1e-5
    assert np.linalg.norm(R1 - R) / np.linalg.norm(R) < 1e-5

    def gradient(Q, R, h=1e-5):
        g = []
        for which in (0, 1):
            for i, j in ((0, 0), (0, 1), (1, 1)):
                e = np.zeros((2, 2))
                e[i, j] = e[j, i] = h
                ll = [ref_loglik(F, H, ys, drive, m0, P0, Q + s * e * (which == 0), R + s * e * (which == 1), zeros, zeros) for s in (1, -1)]
                g.append((ll[0] - ll[1]) / (2 * h))
        return np.array(g)

    assert np.linalg.norm(gradient(Q, R)) < 1e-4 * np.linalg.norm(gradient(np.eye(2), np.eye(2)))


def test_likelihood_drop_is_not_convergence(monkeypatch):
    # A broken M-step (covariances scaled by 10) lowers the likelihood: the gain test
    # "gain <= tol" passes at the second iteration, but a drop is a failure, not convergence.
    import jdrkf._em as em_module

    m_step = em_module._m_step

    def broken(*args):
        q, r, b, d = m_step(*args)
        return 10 * q, 10 * r, b, d

    monkeypatch.setattr(em_module, "_m_step", broken)
    F, H, ys, m0, P0 = _stationarity_data()
    res = em_noise_covariances(F, H, ys[:50], m0, P0, max_iter=5)
    hist = np.asarray(res.loglik_history)
    assert int(res.iterations) == 2 and hist[2] < hist[1] - 1.0
    assert not bool(res.converged)
