"""The shared root-finding module (`jdrkf._root`) on problems with closed-form answers:
matrix square roots, scalar roots, convex minimizers; derivatives of roots against
closed forms and finite differences."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg

from jdrkf._root import (
    bracketed_newton,
    chord,
    default_rtol,
    dense_solve,
    implicit_root,
    newton,
)


def _spd(rng, n):
    a = rng.normal(size=(n, n))
    return a @ a.T + n * np.eye(n)


def _sqrt_residual(a):
    return lambda x: x @ x - a


def _sqrt_domain(x):
    """Symmetric positive definite: the principal square root is the only root there."""
    sym = jnp.allclose(x, x.T, rtol=0, atol=1e-8 * (1 + jnp.max(jnp.abs(x))))
    return sym & jnp.all(jnp.linalg.eigvalsh(0.5 * (x + x.T)) > 0)


def test_default_rtol():
    assert default_rtol(jnp.float64) == pytest.approx(np.finfo(np.float64).eps ** (2 / 3))
    assert default_rtol(jnp.float32) == pytest.approx(np.finfo(np.float32).eps ** (2 / 3))


def test_dense_solve_pytree(rng):
    m = rng.normal(size=(3, 3)) + 3 * np.eye(3)
    b = rng.normal(size=(2,))

    def g(x):  # a linear map on the pytree (matrix-vector part, scalar part)
        v, s = x
        return (jnp.asarray(m[:2]) @ jnp.append(v, s), jnp.asarray(m[2]) @ jnp.append(v, s))

    y = (jnp.asarray(b), jnp.asarray(0.7))
    v, s = dense_solve(g, y)
    expected = np.linalg.solve(m, np.append(b, 0.7))
    np.testing.assert_allclose(np.append(v, s), expected, rtol=1e-12)


def test_newton_matrix_square_root(rng):
    a = _spd(rng, 3)
    sol = newton(_sqrt_residual(jnp.asarray(a)), jnp.eye(3) * np.sqrt(np.trace(a) / 3), 50, in_domain=_sqrt_domain, ftol=1e-14)
    np.testing.assert_allclose(sol.x, scipy.linalg.sqrtm(a).real, rtol=1e-12, atol=1e-12)
    assert bool(sol.stopped) and 0 < int(sol.iterations) < 50
    assert float(sol.residual) <= 1e-12 * np.linalg.norm(a)


def test_newton_domain_selects_the_root():
    # x³ − x has roots −1, 0, 1; restricted to x > 0.5 Newton must return 1.
    sol = newton(lambda x: x**3 - x, jnp.asarray(0.6), 60, in_domain=lambda x: x > 0.5, ftol=1e-15)
    assert float(sol.x) == pytest.approx(1.0, abs=1e-14) and bool(sol.stopped)
    # From the same start without the domain, the first step overshoots to 5.4 and the
    # iteration still ends on a root, but every accepted step decreased |F|.
    free = newton(lambda x: x**3 - x, jnp.asarray(0.6), 60, ftol=1e-15)
    assert min(abs(float(free.x) - r) for r in (-1.0, 0.0, 1.0)) < 1e-12


def test_newton_zero_iterations_is_not_stopped(rng):
    a = _spd(rng, 2)
    sol = newton(_sqrt_residual(jnp.asarray(a)), jnp.eye(2), 0, ftol=1e-14)
    assert int(sol.iterations) == 0 and not bool(sol.stopped)
    np.testing.assert_allclose(float(sol.residual), np.linalg.norm(np.eye(2) - a))


def test_newton_objective_merit(rng):
    # φ(x) = Σ exp(a_i x_i) − b·x is strictly convex with minimizer x_i = ln(b_i/a_i)/a_i.
    a, b = rng.uniform(0.5, 2.0, 4), rng.uniform(0.5, 2.0, 4)

    def phi(x):
        return jnp.sum(jnp.exp(a * x)) - b @ x

    sol = newton(jax.grad(phi), jnp.full(4, 3.0), 60, objective=phi, xtol=1e-8)
    np.testing.assert_allclose(sol.x, np.log(b / a) / a, rtol=1e-13, atol=1e-14)
    assert bool(sol.stopped)
    # Outside its domain (infinite) the objective rejects trial points: minimizing
    # x − ln x − ln(1 − x) over (0, 1) from 0.9, where full Newton steps leave (0, 1).
    def barrier(x):
        inside = (x > 0) & (x < 1)
        xs = jnp.where(inside, x, 0.5)
        return jnp.where(inside, 3.0 * xs - jnp.log(xs) - jnp.log1p(-xs), jnp.inf)

    sol = newton(jax.grad(barrier), jnp.asarray(0.999), 60, objective=barrier, xtol=1e-8)
    root = (5.0 - np.sqrt(13.0)) / 6.0  # 3 − 1/x + 1/(1 − x) = 0  ⇔  3x² − 5x + 1 = 0
    assert float(sol.x) == pytest.approx(root, abs=1e-13)


def test_chord_from_a_close_start(rng):
    a = _spd(rng, 3)
    exact = scipy.linalg.sqrtm(a).real
    x0 = jnp.asarray(exact + 1e-4 * rng.normal(size=(3, 3)))
    x, r, k = chord(_sqrt_residual(jnp.asarray(a)), x0, None, 30)
    np.testing.assert_allclose(x, exact, rtol=1e-12, atol=1e-12)
    assert int(k) > 0 and np.max(np.abs(r)) < 1e-12


@pytest.mark.parametrize("x0", [0.0, 1.0, 3.0])
def test_bracketed_newton_cube_root(x0):
    sol = bracketed_newton(lambda x: x**3 - 2.0, jnp.asarray(x0), 0.0, 3.0, 100)
    assert float(sol.x) == pytest.approx(2.0 ** (1 / 3), rel=1e-15) and bool(sol.stopped)
    # With a hand-written derivative.
    sol2 = bracketed_newton(lambda x: (x**3 - 2.0, 3.0 * x * x), jnp.asarray(x0), 0.0, 3.0, 100, has_slope=True)
    assert float(sol2.x) == pytest.approx(2.0 ** (1 / 3), rel=1e-15)


def test_bracketed_newton_bisects_when_newton_leaves_the_bracket():
    # Newton on atan diverges from |x − 1| > 1.39; the bracket keeps it converging.
    sol = bracketed_newton(lambda x: jnp.arctan(x - 1.0), jnp.asarray(8.0), -10.0, 10.0, 200)
    assert float(sol.x) == pytest.approx(1.0, abs=1e-14) and bool(sol.stopped)
    capped = bracketed_newton(lambda x: jnp.arctan(x - 1.0), jnp.asarray(8.0), -10.0, 10.0, 1)
    assert int(capped.iterations) == 1 and not bool(capped.stopped)


def test_bracketed_newton_stops_when_a_converged_step_rounds_onto_the_bracket_end():
    """At the noise floor f(x) > 0 at the root's double (here 1e-17 at x = 0.75, as a rounded
    residual would be), so x becomes the bracket's upper end, and the Newton step, below the
    step tolerance, rounds back onto x. That is convergence: the search must stop there, not
    bisect the bracket (the earlier rule restarted from the midpoint: 52 steps here, up to 30
    in the Wasserstein oracle)."""
    f = lambda x: (x - 0.75 + jnp.where(x == 0.75, 1e-17, 0.0), jnp.ones_like(x))  # noqa: E731
    sol = bracketed_newton(f, jnp.asarray(1.0), 0.0, 2.0, 100, has_slope=True)
    assert float(sol.x) == 0.75 and bool(sol.stopped) and int(sol.iterations) <= 3, sol


def _sqrt_by_root(p):
    """`√p` as the root of `x² − p` on `[0, max(1, p)]`, with implicit derivatives."""

    def solve(x0):
        sol = bracketed_newton(lambda x: x * x - p, x0, 0.0, jnp.maximum(1.0, p), 100)
        return sol.x, (sol.iterations, sol.stopped)

    return implicit_root(lambda x: x * x - p, solve, jnp.ones_like(p))


def test_implicit_root_scalar_derivatives():
    p = jnp.asarray(2.5)
    x, (k, stopped) = _sqrt_by_root(p)
    assert float(x) == pytest.approx(np.sqrt(2.5), rel=1e-15)
    assert k.dtype == jnp.zeros((), int).dtype and stopped.dtype == bool and bool(stopped)

    def f(q):
        return _sqrt_by_root(q)[0]

    assert float(jax.grad(f)(p)) == pytest.approx(0.5 / np.sqrt(2.5), rel=1e-13)
    assert float(jax.jvp(f, (p,), (jnp.asarray(1.0),))[1]) == pytest.approx(0.5 / np.sqrt(2.5), rel=1e-13)
    assert float(jax.grad(jax.grad(f))(p)) == pytest.approx(-0.25 * 2.5**-1.5, rel=1e-12)
    ps = jnp.asarray([0.3, 1.0, 7.0])
    np.testing.assert_allclose(jax.vmap(jax.grad(f))(ps), 0.5 / np.sqrt(ps), rtol=1e-13)


def test_implicit_root_matrix_square_root_vs_finite_differences(rng):
    a0, da = _spd(rng, 3), rng.normal(size=(3, 3))
    da = da + da.T

    def sqrt_root(a):
        def solve(guess):
            sol = newton(_sqrt_residual(a), guess, 50, in_domain=_sqrt_domain, ftol=1e-15)
            return sol.x, sol.stopped

        x, _ = implicit_root(_sqrt_residual(a), solve, jnp.eye(3) * jnp.sqrt(jnp.trace(jax.lax.stop_gradient(a)) / 3))
        return x

    a0j = jnp.asarray(a0)
    _, tangent = jax.jvp(sqrt_root, (a0j,), (jnp.asarray(da),))
    h = 1e-6
    fd = (scipy.linalg.sqrtm(a0 + h * da).real - scipy.linalg.sqrtm(a0 - h * da).real) / (2 * h)
    np.testing.assert_allclose(tangent, fd, rtol=1e-7, atol=1e-8)
    # Reverse mode: d Tr(√A) / dA = ½ (√A)⁻¹ (symmetric A).
    g = jax.grad(lambda a: jnp.trace(sqrt_root(a)))(a0j)
    np.testing.assert_allclose(0.5 * (g + g.T), 0.5 * np.linalg.inv(scipy.linalg.sqrtm(a0).real), rtol=1e-10, atol=1e-12)
