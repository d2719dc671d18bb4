"""`SteadyStateDRKF.solve` under `jax.vmap` over many radius pairs on one system (anchors,
tangent starts and chord steps, with the continuation as rescue), against single solves
(themselves checked against the SDP (14) in test_wasserstein_dr.py) and finite differences."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jdrkf
from jdrkf.sets import _steady_state

A3 = np.array([[0.7, 0.3, 0.0], [0.0, 0.8, 0.2], [0.1, 0.0, 0.6]])
C3 = np.array([[1.0, 0.0, 0.5], [0.0, 1.0, -1.0]])
W3 = np.diag([0.3, 0.2, 0.4])
V3 = np.array([[0.5, 0.1], [0.1, 0.4]])
MODEL = jdrkf.LinearModel(F=A3, H=C3, Q=W3, R=V3)

single = eqx.filter_jit(lambda tx, tv, model: jdrkf.SteadyStateDRKF(tx, tv).solve(model))
batched = eqx.filter_jit(jax.vmap(lambda tx, tv, model: jdrkf.SteadyStateDRKF(tx, tv).solve(model), in_axes=(0, 0, None)))


def _radii(count, seed=0):
    """`count` pairs: θx ~ U[0, 1], θv ~ U[0, 0.6], with zero radii on either axis and one
    invalid (negative) pair last."""
    r = np.random.default_rng(seed).uniform(0.0, 1.0, (count, 2)) * [1.0, 0.6]
    r[0], r[1], r[2], r[-1] = (0.0, 0.0), (0.5, 0.0), (0.0, 0.3), (-0.1, 0.2)
    return jnp.asarray(r[:, 0]), jnp.asarray(r[:, 1])


@pytest.fixture
def count_many_radii(monkeypatch):
    calls = []
    original = _steady_state._many_radii

    def counted(*args):
        calls.append(args[4].shape)
        return original(*args)

    monkeypatch.setattr(_steady_state, "_many_radii", counted)
    return calls


def _check_against_single_solves(sol, tx, tv):
    valid = np.asarray((tx >= 0) & (tv >= 0))
    assert np.all(np.asarray(sol.converged) == valid)
    for i in np.flatnonzero(valid):
        ref = single(tx[i], tv[i], MODEL)
        assert bool(ref.converged)
        np.testing.assert_allclose(float(sol.value[i]), float(ref.value), rtol=1e-9)
        np.testing.assert_allclose(np.asarray(sol.gain[i]), np.asarray(ref.gain), rtol=1e-7, atol=1e-9)
        np.testing.assert_allclose(np.asarray(sol.prior_cov[i]), np.asarray(ref.prior_cov), rtol=1e-7, atol=1e-9)
    # Residual at tolerance, as in a single solve.
    assert np.all(np.asarray(sol.residual)[valid] <= 1e-9)


def test_many_radii_under_vmap_match_single_solves(count_many_radii):
    tx, tv = _radii(72)
    sol = batched(tx, tv, MODEL)
    assert count_many_radii == [(72,)]  # the anchor–chord path ran, once, on the whole batch
    _check_against_single_solves(sol, tx, tv)
    assert int(jnp.max(sol.iterations)) < _steady_state._CHORD_STEPS


def test_small_batches_map_the_continuation(count_many_radii):
    tx, tv = _radii(8, seed=1)
    sol = batched(tx, tv, MODEL)
    assert count_many_radii == []  # fewer than four pairs per anchor: plain vmap
    _check_against_single_solves(sol, tx, tv)


def test_pairs_the_chord_does_not_solve_are_rescued_by_the_continuation(monkeypatch, count_many_radii):
    # No chord steps at all: every valid pair fails the test at its tangent start and is
    # solved by the continuation branch.
    monkeypatch.setattr(_steady_state, "_CHORD_STEPS", 0)
    tx, tv = _radii(70, seed=2)
    sol = batched(tx, tv, MODEL)
    assert count_many_radii == [(70,)]
    _check_against_single_solves(sol, tx, tv)
    assert int(jnp.max(sol.iterations)) > 0  # the continuation's Newton iterations


def test_gradient_of_many_radii_against_finite_differences():
    tx, tv = _radii(66, seed=3)
    tx, tv = tx[:-1], tv[:-1]  # valid radii only
    tx = jnp.maximum(tx, 0.05)  # keep θx − h inside the domain
    value = lambda tx, tv: jdrkf.SteadyStateDRKF(tx, tv).solve(MODEL).value  # noqa: E731
    grads = eqx.filter_jit(jax.vmap(jax.grad(value, argnums=(0, 1))))(tx, tv)

    def values(tx, tv):  # single solves: independent of the batched path, and compiled once
        return jnp.asarray([float(single(a, b, MODEL).value) for a, b in zip(tx, tv, strict=True)])

    h = 1e-5
    fd_x = (values(tx + h, tv) - values(tx - h, tv)) / (2 * h)
    fd_v = (values(tx, tv + h) - values(tx, jnp.maximum(tv - h, 0.0))) / (tv + h - jnp.maximum(tv - h, 0.0))
    np.testing.assert_allclose(np.asarray(grads[0]), np.asarray(fd_x), rtol=1e-5, atol=1e-7)
    inside = np.asarray(tv > h)  # one-sided at θv = 0
    np.testing.assert_allclose(np.asarray(grads[1])[inside], np.asarray(fd_v)[inside], rtol=1e-5, atol=1e-7)


@pytest.mark.slow  # ~40 s: compiles the anchor–chord path under a second vmap
def test_many_radii_nested_in_a_vmap_over_systems(count_many_radii):
    # The outer vmap batches the chord path's loops and its rescue branch (a select there).
    tx, tv = _radii(64, seed=4)
    models = jax.tree.map(lambda *x: jnp.stack(x), MODEL, jdrkf.LinearModel(F=0.9 * A3, H=C3, Q=W3, R=V3))
    sol = eqx.filter_jit(jax.vmap(batched, in_axes=(None, None, 0)))(tx, tv, models)
    assert len(count_many_radii) == 1
    valid = np.asarray((tx >= 0) & (tv >= 0))
    for k, scale in enumerate((1.0, 0.9)):
        model = jdrkf.LinearModel(F=scale * A3, H=C3, Q=W3, R=V3)
        assert np.all(np.asarray(sol.converged[k]) == valid)
        for i in np.flatnonzero(valid)[::7]:
            np.testing.assert_allclose(float(sol.value[k, i]), float(single(tx[i], tv[i], model).value), rtol=1e-9)
