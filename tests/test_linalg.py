"""jdrkf.linalg and jdrkf.Gaussian against SciPy and finite differences."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg
import scipy.stats

import jdrkf
from jdrkf import linalg


def _spd(rng, d):
    a = rng.normal(size=(d, d))
    return a @ a.T / d + 0.3 * np.eye(d)


def _bures2_ref(a, b):
    ra = scipy.linalg.sqrtm(a).real
    return np.trace(a) + np.trace(b) - 2 * np.trace(scipy.linalg.sqrtm(ra @ b @ ra).real)


def test_psd_sqrt_matches_scipy(rng):
    a = _spd(rng, 4)
    np.testing.assert_allclose(linalg.psd_sqrt(a), scipy.linalg.sqrtm(a).real, atol=1e-12)


@pytest.mark.parametrize("repeated", [False, True])
def test_psd_sqrt_gradient_finite_even_for_repeated_eigenvalues(rng, repeated):
    a = np.eye(3) * 2.0 if repeated else _spd(rng, 3)
    w = rng.normal(size=(3, 3))
    grad = jax.grad(lambda x: jnp.sum(w * linalg.psd_sqrt(x)))(jnp.asarray(a))
    assert np.all(np.isfinite(grad))
    eps = 1e-6
    for i, j in [(0, 0), (0, 1), (2, 1)]:
        e = np.zeros((3, 3))
        e[i, j] = e[j, i] = eps
        fd = (np.sum(w * scipy.linalg.sqrtm(a + e).real) - np.sum(w * scipy.linalg.sqrtm(a - e).real)) / (2 * eps)
        ad = grad[i, j] + (grad[j, i] if i != j else 0.0)
        np.testing.assert_allclose(ad, fd, rtol=1e-6, atol=1e-8)


def test_cho_and_psd_solve(rng):
    a, b = _spd(rng, 4), rng.normal(size=(4, 2))
    np.testing.assert_allclose(linalg.psd_solve(a, b), np.linalg.solve(a, b), atol=1e-12)
    np.testing.assert_allclose(linalg.psd_solve(a, b[:, 0]), np.linalg.solve(a, b[:, 0]), atol=1e-12)
    np.testing.assert_allclose(linalg.symmetrize(np.triu(a)), (np.triu(a) + np.triu(a).T) / 2)


@pytest.mark.parametrize("d", [2, 8])
def test_psd_inv_value_and_directional_derivative(rng, d):
    # Value vs NumPy's inverse; the custom JVP −X dA X vs central differences of NumPy's
    # inverse along a symmetric direction, for both the unrolled (d ≤ 6) and LAPACK paths.
    a = _spd(rng, d)
    da = rng.normal(size=(d, d))
    da = da + da.T
    np.testing.assert_allclose(linalg.psd_inv(a), np.linalg.inv(a), rtol=1e-10, atol=1e-12)
    _, tangent = jax.jvp(linalg.psd_inv, (jnp.asarray(a),), (jnp.asarray(da),))
    eps = 1e-6
    fd = (np.linalg.inv(a + eps * da) - np.linalg.inv(a - eps * da)) / (2 * eps)
    np.testing.assert_allclose(tangent, fd, rtol=1e-6, atol=1e-8)
    assert np.all(np.isnan(linalg.psd_inv(-np.eye(d))))


def test_psd_solve_fwd_value_and_derivatives(rng):
    # Same value as psd_solve; its inverse-based derivative vs central differences of NumPy's
    # solve, in forward (jvp in both arguments) and reverse mode.
    a, b = _spd(rng, 5), rng.normal(size=(5, 2))
    da, db = rng.normal(size=(5, 5)), rng.normal(size=(5, 2))
    da = da + da.T
    np.testing.assert_allclose(linalg.psd_solve_fwd(a, b), np.linalg.solve(a, b), rtol=1e-12, atol=1e-12)
    _, tangent = jax.jvp(linalg.psd_solve_fwd, (jnp.asarray(a), jnp.asarray(b)), (jnp.asarray(da), jnp.asarray(db)))
    eps = 1e-6
    fd = (np.linalg.solve(a + eps * da, b + eps * db) - np.linalg.solve(a - eps * da, b - eps * db)) / (2 * eps)
    np.testing.assert_allclose(tangent, fd, rtol=1e-6, atol=1e-8)
    w = rng.normal(size=(5, 2))
    gb = jax.grad(lambda bb: jnp.sum(w * linalg.psd_solve_fwd(jnp.asarray(a), bb)))(jnp.asarray(b))
    np.testing.assert_allclose(gb, np.linalg.solve(a, w), rtol=1e-10, atol=1e-12)
    # jit x vmap x grad (in the matrix): ∂/∂A Σ w∘A⁻¹b = −A⁻¹ w xᵀ, symmetrized, per batch member.
    batch = np.stack([_spd(rng, 5) for _ in range(3)])
    ga = jax.jit(jax.vmap(jax.grad(lambda aa: jnp.sum(w * linalg.psd_solve_fwd(aa, jnp.asarray(b))))))(jnp.asarray(batch))
    for ai, gi in zip(batch, np.asarray(ga), strict=True):
        m = -np.linalg.solve(ai, w) @ np.linalg.solve(ai, b).T
        np.testing.assert_allclose(gi, 0.5 * (m + m.T), rtol=1e-9, atol=1e-12)


def test_psd_logdet_value_and_derivative(rng):
    a = _spd(rng, 6)
    da = rng.normal(size=(6, 6))
    da = da + da.T
    np.testing.assert_allclose(linalg.psd_logdet(a), np.linalg.slogdet(a)[1], rtol=1e-12)
    _, tangent = jax.jvp(linalg.psd_logdet, (jnp.asarray(a),), (jnp.asarray(da),))
    eps = 1e-6
    fd = (np.linalg.slogdet(a + eps * da)[1] - np.linalg.slogdet(a - eps * da)[1]) / (2 * eps)
    np.testing.assert_allclose(tangent, fd, rtol=1e-7)
    assert np.isnan(linalg.psd_logdet(-np.eye(3)))
    # jit x vmap x grad: ∇ log det A = A⁻¹ (symmetric A), batched.
    batch = np.stack([_spd(rng, 6) for _ in range(3)])
    grads = jax.jit(jax.vmap(jax.grad(linalg.psd_logdet)))(jnp.asarray(batch))
    np.testing.assert_allclose(grads, np.linalg.inv(batch), rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(jax.jit(jax.vmap(linalg.psd_inv))(jnp.asarray(batch)), np.linalg.inv(batch), rtol=1e-10, atol=1e-12)


def test_bures_distance_matches_sqrtm_formula(rng):
    for d in [1, 2, 5]:
        a, b = _spd(rng, d), _spd(rng, d)
        np.testing.assert_allclose(linalg.bures_distance_squared(a, b), _bures2_ref(a, b), rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(linalg.bures_distance(a, b) ** 2, _bures2_ref(a, b), rtol=1e-10, atol=1e-12)
    a = _spd(rng, 3)
    assert float(linalg.bures_distance(a, a)) == 0.0
    # Scalar case: (sqrt(a) - sqrt(b))^2.
    np.testing.assert_allclose(linalg.bures_distance_squared([[4.0]], [[9.0]]), 1.0, rtol=1e-12)


def test_bures_gradient_matches_finite_differences(rng):
    a, b = _spd(rng, 3), np.eye(3)  # b = I: repeated singular values in the fidelity term
    grad = jax.grad(linalg.bures_distance_squared)(jnp.asarray(a), jnp.asarray(b))
    eps = 1e-6
    for i, j in [(0, 0), (1, 2)]:
        e = np.zeros((3, 3))
        e[i, j] = e[j, i] = eps
        fd = (_bures2_ref(a + e, b) - _bures2_ref(a - e, b)) / (2 * eps)
        np.testing.assert_allclose(grad[i, j] + (grad[j, i] if i != j else 0.0), fd, rtol=1e-6)
    # The distance itself has a (zero) finite gradient at a == b.
    g0 = jax.grad(linalg.bures_distance)(jnp.asarray(a), jnp.asarray(a))
    assert np.all(np.isfinite(g0))


def test_gaussian_log_prob_kl_gelbrich(rng):
    m1, m2, s1, s2 = rng.normal(size=3), rng.normal(size=3), _spd(rng, 3), _spd(rng, 3)
    g1, g2 = jdrkf.Gaussian(m1, s1), jdrkf.Gaussian(m2, s2)
    x = rng.normal(size=(4, 3))
    np.testing.assert_allclose(g1.log_prob(x), scipy.stats.multivariate_normal(m1, s1).logpdf(x), rtol=1e-12)
    kl_ref = 0.5 * (
        np.trace(np.linalg.solve(s2, s1)) + (m2 - m1) @ np.linalg.solve(s2, m2 - m1) - 3
        + np.log(np.linalg.det(s2) / np.linalg.det(s1))
    )
    np.testing.assert_allclose(g1.kl_divergence(g2), kl_ref, rtol=1e-10)
    np.testing.assert_allclose(
        g1.gelbrich_distance(g2) ** 2, np.sum((m1 - m2) ** 2) + _bures2_ref(s1, s2), rtol=1e-10
    )


def test_gaussian_sample_moments(getkey):
    mean, cov = np.array([1.0, -2.0]), np.array([[2.0, 0.5], [0.5, 1.0]])
    x = np.asarray(jdrkf.Gaussian(mean, cov).sample(getkey(), (200_000,)))
    np.testing.assert_allclose(x.mean(0), mean, atol=0.02)
    np.testing.assert_allclose(np.cov(x.T), cov, atol=0.03)


def test_gaussian_validation():
    with pytest.raises(ValueError, match=r"cov has shape \(3, 3\) but mean has shape \(2,\)"):
        jdrkf.Gaussian(np.zeros(2), np.eye(3))
    with pytest.raises(ValueError, match="symmetric"):
        jdrkf.Gaussian(np.zeros(2), np.array([[1.0, 0.5], [0.0, 1.0]]))
    with pytest.raises(ValueError, match="mean must have 1 dimensions"):
        jdrkf.Gaussian(np.zeros((2, 1)), np.eye(2))


@pytest.mark.parametrize("d", [1, 2, 3, 6, 7])
def test_cholesky_and_cho_solve_match_numpy_both_paths(rng, d):
    # d <= UNROLL_MAX uses the unrolled code, larger d LAPACK.
    a, b = _spd(rng, d), rng.normal(size=(d, 3))
    chol = linalg.cholesky(a)
    np.testing.assert_allclose(chol, np.linalg.cholesky(a), atol=1e-12)
    np.testing.assert_allclose(linalg.cho_solve(chol, b), np.linalg.solve(a, b), atol=1e-11)
    np.testing.assert_allclose(linalg.cho_solve(chol, b[:, 0]), np.linalg.solve(a, b[:, 0]), atol=1e-11)
    batched = jax.vmap(linalg.cholesky)(np.stack([a, 2 * a]))
    np.testing.assert_allclose(batched[1], np.linalg.cholesky(2 * a), atol=1e-12)
    # Gradient of a solve through the factorization vs the closed form d(a⁻¹b) = -a⁻¹ da a⁻¹ b.
    w = rng.normal(size=(d, 3))
    g = jax.grad(lambda x: jnp.sum(w * linalg.psd_solve(x, b)))(jnp.asarray(a))
    x = np.linalg.solve(a, b)
    ref = -np.linalg.solve(a, w) @ x.T
    np.testing.assert_allclose(linalg.symmetrize(g), linalg.symmetrize(ref), atol=1e-10)


@pytest.mark.parametrize("d", [1, 3, 7])
def test_cholesky_flags_non_positive_definite_with_nan(d):
    a = -np.eye(d)
    assert np.isnan(np.asarray(linalg.cholesky(a))).any()
    assert np.isnan(np.asarray(linalg.cholesky(np.zeros((d, d))))).any()


@pytest.mark.parametrize("d", [1, 2, 5, 6, 9])
def test_gauss_jordan_solve_matches_numpy(rng, d):
    # Unrolled Gauss–Jordan (d ≤ 6) and the Cholesky fallback (d = 9) against NumPy, for a
    # vector, a matrix and a vmapped batch of right-hand sides; NaN for an indefinite matrix.
    a = _spd(rng, d)
    b_vec, b_mat = rng.normal(size=d), rng.normal(size=(d, 3))
    np.testing.assert_allclose(linalg.gauss_jordan_solve(a, b_vec), np.linalg.solve(a, b_vec), rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(linalg.gauss_jordan_solve(a, b_mat), np.linalg.solve(a, b_mat), rtol=1e-10, atol=1e-12)
    stack = np.stack([_spd(rng, d) for _ in range(4)])
    got = jax.vmap(linalg.gauss_jordan_solve)(stack, np.repeat(b_vec[None], 4, 0))
    np.testing.assert_allclose(got, np.linalg.solve(stack, b_vec[None, :, None])[..., 0], rtol=1e-10, atol=1e-12)
    indefinite = np.eye(d)
    indefinite[-1, -1] = -1.0
    assert np.all(np.isnan(linalg.gauss_jordan_solve(indefinite, b_vec)))


def test_gauss_jordan_solve_jit_vmap_grad(rng):
    # jit x vmap x grad of a scalar of the solution, against central differences of NumPy's solve.
    d = 4
    a = np.stack([_spd(rng, d) for _ in range(3)])
    b = rng.normal(size=(3, d))
    loss = jax.jit(jax.grad(lambda a, b: jnp.sum(jax.vmap(linalg.gauss_jordan_solve)(a, b) ** 2), argnums=(0, 1)))
    ga, gb = loss(a, b)
    ref = lambda a, b: np.sum(np.linalg.solve(a, b[..., None]) ** 2)  # noqa: E731
    eps = 1e-6
    da = rng.normal(size=a.shape)
    da = da + np.swapaxes(da, -1, -2)  # `a` is symmetric by contract: symmetric directions only
    db = rng.normal(size=b.shape)
    fd_a = (ref(a + eps * da, b) - ref(a - eps * da, b)) / (2 * eps)
    fd_b = (ref(a, b + eps * db) - ref(a, b - eps * db)) / (2 * eps)
    np.testing.assert_allclose(np.sum(np.asarray(ga) * da), fd_a, rtol=1e-6)
    np.testing.assert_allclose(np.sum(np.asarray(gb) * db), fd_b, rtol=1e-6)


@pytest.mark.parametrize("k", [1, 2, 6, 7])
def test_matmul_equals_at_for_vectors_and_matrices(rng, k):
    # k ≤ UNROLL_MAX: sums of column scalings; k = 7: `@`
    a, b, x = rng.normal(size=(3, k)), rng.normal(size=(k, 4)), rng.normal(size=k)
    for left, right in [(a, b), (a, x), (x, b), (x, x)]:
        np.testing.assert_allclose(linalg.matmul(left, right), left @ right, rtol=1e-13, atol=1e-14)
    # under vmap the batched operand keeps its meaning
    xs = rng.normal(size=(5, k))
    np.testing.assert_allclose(jax.vmap(linalg.matmul, in_axes=(None, 0))(a, xs), xs @ a.T, rtol=1e-13, atol=1e-14)
    np.testing.assert_allclose(linalg.matmul(np.zeros((2, 0)), np.zeros(0)), np.zeros(2))


def test_matmul_gradient_under_jit_vmap_matches_at(rng):
    a, xs = rng.normal(size=(3, 4)), rng.normal(size=(5, 4))

    def grads(mm):
        loss = lambda a, x: jnp.sum(jnp.sin(mm(a, x)))  # noqa: E731
        return jax.jit(jax.vmap(jax.grad(loss, argnums=(0, 1)), in_axes=(None, 0)))(a, xs)

    for got, want in zip(grads(linalg.matmul), grads(lambda a, x: a @ x)):
        np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-13)
    # the derivative itself, against central differences of the first run's loss
    eps, x0 = 1e-6, xs[0]
    fd = np.array([(np.sum(np.sin((a + eps * e) @ x0)) - np.sum(np.sin((a - eps * e) @ x0))) / (2 * eps)
                   for e in np.eye(12).reshape(12, 3, 4)]).reshape(3, 4)
    np.testing.assert_allclose(grads(linalg.matmul)[0][0], fd, rtol=1e-6, atol=1e-8)


def test_unrolls_follows_the_size_limit_and_lapack_only():
    assert linalg.unrolls(linalg.UNROLL_MAX) and not linalg.unrolls(linalg.UNROLL_MAX + 1)
    with linalg.lapack_only():
        assert not linalg.unrolls(1)
    assert linalg.unrolls(1)
