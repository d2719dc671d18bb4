"""θ_max of Jang, Hakobyan & Yang (2025, Proposition 1 / Theorem 2, eqs. 17–20).

Oracles: the paper's value (Section 5.1, θ_max = 3.356) and an independent NumPy/SciPy
re-implementation written from the paper's formulas (symmetric square roots via
`scipy.linalg.sqrtm` instead of the code's Cholesky factors — the quantities are
invariant to that choice —, explicit inverses, information-form Riccati, plain
Python bisection), plus SciPy's DARE for the long-run nominal covariance.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg as sla

from jdrkf.sets import ThetaMax, theta_max


# --- independent NumPy oracle ----------------------------------------------------------------


def _oracle_blocks(A, C, W, V, N):
    n = A.shape[0]
    w_half = np.real(sla.sqrtm(W))
    v_half = np.real(sla.sqrtm(V))
    pw = [np.linalg.matrix_power(A, k) for k in range(N)]
    Obs = np.vstack([C @ pw[N - 1 - i] for i in range(N)])
    OR = np.vstack([pw[N - 1 - i] for i in range(N)])
    D = np.kron(np.eye(N), v_half)
    L = np.zeros((N * n, N * n))
    for i in range(N):
        for j in range(i + 1, N):
            L[i * n:(i + 1) * n, j * n:(j + 1) * n] = pw[j - i - 1] @ w_half
    H = np.kron(np.eye(N), C) @ L
    G = L @ np.linalg.inv(np.eye(N * n) + H.T @ np.linalg.inv(D @ D.T) @ H) @ L.T
    Mi = np.linalg.inv(D @ D.T + H @ H.T)
    J = OR - L @ H.T @ Mi @ Obs
    Om = Obs.T @ Mi @ Obs
    return G, J, Om


def _oracle_lambda_min(A, C, W, V, N, phi):
    """λ_min(Ω_N + Jᵀ S_φ⁻¹ J), S_φ = G − I/φ."""
    G, J, Om = _oracle_blocks(A, C, W, V, N)
    X = Om + J.T @ np.linalg.inv(G - np.eye(G.shape[0]) / phi) @ J
    return np.min(sla.eigvalsh(0.5 * (X + X.T)))


def _oracle(A, C, W, V, N, q, tol=1e-10, eig_tol=1e-10):
    G, _, _ = _oracle_blocks(A, C, W, V, N)
    phi_tilde = 1.0 / np.max(sla.eigvalsh(0.5 * (G + G.T)))
    lo, hi = 0.0, phi_tilde
    while hi - lo > tol:
        mid = 0.5 * (lo + hi)
        if _oracle_lambda_min(A, C, W, V, N, mid) > eig_tol:
            lo = mid
        else:
            hi = mid
    P = W.copy()
    for _ in range(q):
        P = A @ np.linalg.inv(np.linalg.inv(P) + C.T @ np.linalg.inv(V) @ C) @ A.T + W
    tr, lam = np.trace(P), np.max(sla.eigvalsh(P))
    theta = np.sqrt(tr / (1.0 - lo * lam)) - np.sqrt(tr) if lo * lam < 1 else np.nan
    return dict(phi_tilde=phi_tilde, phi=lo, P=P, theta=theta)


def _random_system(seed, n, m):
    rng = np.random.default_rng(seed)
    A = rng.normal(size=(n, n))
    A *= rng.uniform(0.5, 1.1) / np.max(np.abs(np.linalg.eigvals(A)))
    C = rng.normal(size=(m, n))
    X = rng.normal(size=(n, n))
    Y = rng.normal(size=(m, m))
    W = X @ X.T / n + 0.3 * np.eye(n)
    V = Y @ Y.T / m + 0.3 * np.eye(m)
    # Assumptions 1-3: (A, Σ_w^{1/2}) controllable, (A, C) observable.
    ctrb = np.hstack([np.linalg.matrix_power(A, k) @ np.linalg.cholesky(W) for k in range(n)])
    obsv = np.vstack([C @ np.linalg.matrix_power(A, k) for k in range(n)])
    assert np.linalg.matrix_rank(ctrb) == n and np.linalg.matrix_rank(obsv) == n
    return A, C, W, V


PAPER = dict(A=np.array([[0.1, 1.0], [0.0, 1.2]]), C=np.array([[1.0, -1.0]]), W=np.eye(2), V=np.eye(1))

# (seed, n, m, N, q) with θ_max defined (φλ_max < 1); few distinct (n, m, N) so few compilations
# (q is traced). Seeds 10/(3,2) and 15/(3,1) have φλ_max ≈ 0.89 and 0.98 (θ_max sensitive to φ).
VALID = [
    (12, 2, 1, 4, 10), (20, 2, 1, 4, 11),
    (10, 3, 2, 4, 8), (15, 3, 2, 4, 6),
    (13, 3, 1, 5, 11), (22, 3, 1, 5, 6), (15, 3, 1, 5, 6),
]
# φλ_max ≥ 1 for these: θ_max undefined.
UNDEFINED = [(15, 2, 1, 4, 6), (11, 3, 2, 4, 9)]


def _run(A, C, W, V, N, q, **kw):
    return theta_max(jnp.asarray(A), jnp.asarray(C), jnp.asarray(W), jnp.asarray(V), N, q, **kw)


# --- tests -------------------------------------------------------------------------------------


def test_paper_value():
    """Section 5.1: θ_max = 3.356 for N = 8, q = 20; intermediate values of an independent
    NumPy recomputation (the authors' convergence_check.py)."""
    res = _run(PAPER["A"], PAPER["C"], PAPER["W"], PAPER["V"], 8, 20)
    assert isinstance(res, ThetaMax)
    assert bool(res.valid)
    assert float(res.theta_max) == pytest.approx(3.356, rel=5e-3)
    assert float(res.phi_tilde) == pytest.approx(0.0160, rel=2e-2)
    assert float(res.phi) == pytest.approx(1.28e-3, rel=2e-2)
    P = np.asarray(res.nominal_prior_cov)
    assert np.trace(P) == pytest.approx(250.0, rel=2e-2)
    assert np.max(np.linalg.eigvalsh(P)) == pytest.approx(249.0, rel=2e-2)
    ref = _oracle(PAPER["A"], PAPER["C"], PAPER["W"], PAPER["V"], 8, 20)
    assert float(res.theta_max) == pytest.approx(ref["theta"], rel=1e-6)


@pytest.mark.parametrize("seed,n,m,N,q", VALID)
def test_matches_numpy_oracle(seed, n, m, N, q):
    A, C, W, V = _random_system(seed, n, m)
    ref = _oracle(A, C, W, V, N, q)
    res = _run(A, C, W, V, N, q)
    assert bool(res.valid)
    np.testing.assert_allclose(float(res.phi_tilde), ref["phi_tilde"], rtol=1e-9)
    np.testing.assert_allclose(float(res.phi), ref["phi"], rtol=1e-6, atol=3e-10)
    np.testing.assert_allclose(np.asarray(res.nominal_prior_cov), ref["P"], rtol=1e-9)
    np.testing.assert_allclose(float(res.theta_max), ref["theta"], rtol=1e-6)


@pytest.mark.parametrize("seed,n,m,N,q", UNDEFINED)
def test_undefined_when_phi_lambda_at_least_one(seed, n, m, N, q):
    A, C, W, V = _random_system(seed, n, m)
    ref = _oracle(A, C, W, V, N, q)
    assert np.isnan(ref["theta"])
    res = _run(A, C, W, V, N, q)
    assert not bool(res.valid)
    assert np.isnan(float(res.theta_max))
    np.testing.assert_allclose(float(res.phi), ref["phi"], rtol=1e-6, atol=3e-10)
    assert float(res.phi) * np.max(np.linalg.eigvalsh(np.asarray(res.nominal_prior_cov))) >= 1.0


def test_bisection_finds_the_boundary():
    """0 < φ < φ̃, Ω_{φI} ≻ 0 at the returned φ and not just beyond it (oracle λ_min)."""
    A, C, W, V = PAPER["A"], PAPER["C"], PAPER["W"], PAPER["V"]
    res = _run(A, C, W, V, 8, 20, tol=1e-12)
    phi, phi_tilde = float(res.phi), float(res.phi_tilde)
    assert 0.0 < phi < phi_tilde
    assert _oracle_lambda_min(A, C, W, V, 8, phi) > 1e-10
    assert _oracle_lambda_min(A, C, W, V, 8, phi + 1e-11) <= 1e-10
    # A coarser bisection keeps a feasible (smaller or equal) φ.
    coarse = _run(A, C, W, V, 8, 20, tol=1e-5)
    assert 0.0 < float(coarse.phi) <= phi
    assert phi - float(coarse.phi) <= 1e-5
    assert float(coarse.theta_max) <= float(res.theta_max)


def test_unobservable_gives_no_phi():
    """Ω_N singular ((A, C) not observable): no φ > 0, θ_max undefined."""
    A = np.diag([0.5, 0.7])
    C = np.array([[1.0, 0.0]])
    res = _run(A, C, np.eye(2), np.eye(1), 4, 5)  # same shapes as VALID[0]: no recompilation
    assert float(res.phi) == 0.0
    assert not bool(res.valid)
    assert np.isnan(float(res.theta_max))


def test_nominal_cov_converges_to_dare():
    A, C, W, V = _random_system(13, 3, 1)
    res = _run(A, C, W, V, 5, 300)
    dare = sla.solve_discrete_are(A.T, C.T, W, V)  # prior (predicted) covariance
    np.testing.assert_allclose(np.asarray(res.nominal_prior_cov), dare, rtol=1e-8)


def test_jit_and_vmap():
    A, C, W = (jnp.asarray(PAPER[k]) for k in "ACW")
    scales = jnp.asarray([0.5, 1.0, 2.0])
    jitted = jax.jit(theta_max, static_argnames=("N", "q"))
    eager = [_oracle(PAPER["A"], PAPER["C"], PAPER["W"], float(s) * PAPER["V"], 8, 20) for s in scales]
    res = jax.vmap(lambda s: jitted(A, C, W, s * jnp.eye(1, dtype=A.dtype), N=8, q=20))(scales)
    np.testing.assert_allclose(np.asarray(res.theta_max), [e["theta"] for e in eager], rtol=1e-6)
    assert np.all(np.asarray(res.valid))


def test_float32():
    A, C, W, V = (jnp.asarray(PAPER[k], jnp.float32) for k in "ACWV")
    res = theta_max(A, C, W, V)
    assert res.theta_max.dtype == jnp.float32
    assert float(res.theta_max) == pytest.approx(3.356, rel=5e-3)


@pytest.mark.parametrize(
    "kwargs,match",
    [
        (dict(A=np.ones((2, 3))), "A must be square"),
        (dict(A=np.ones(2)), "A must have 2 dimensions"),
        (dict(C=np.ones((1, 3))), "C must have shape"),
        (dict(Sigma_w=np.eye(3)), "Sigma_w must have shape"),
        (dict(Sigma_v=np.eye(2)), "Sigma_v must have shape"),
        (dict(Sigma_w=np.array([[1.0, 0.5], [0.0, 1.0]])), "Sigma_w must be symmetric"),
        (dict(N=1), "N must be >= max"),
        (dict(N=2.0), "N must be a Python integer"),
        (dict(q=0), "q must be >= 1"),
        (dict(tol=0.0), "tol must be > 0"),
        (dict(eig_tol=-1.0), "eig_tol must be >= 0"),
    ],
)
def test_input_validation(kwargs, match):
    args = dict(A=PAPER["A"], C=PAPER["C"], Sigma_w=PAPER["W"], Sigma_v=PAPER["V"], N=8, q=20)
    args.update(kwargs)
    with pytest.raises(ValueError, match=match):
        theta_max(**args)


def test_n_larger_than_N_rejected():
    A, C, W, V = _random_system(13, 3, 1)
    with pytest.raises(ValueError, match="N must be >= max"):
        theta_max(A, C, W, V, N=2)
