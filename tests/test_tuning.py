"""Gradients of Monte Carlo RMSE through whole filters (vs central finite differences),
and the optax / grid-search tuning helpers."""

import equinox as eqx
import jax
import numpy as np
import optax
import pytest

import jdrkf
from jdrkf import tuning
from jdrkf.experiments import wang_ye
from jdrkf.sets import EpsContamination, Moment, Wasserstein


@pytest.fixture(scope="module")
def objective():
    train = wang_ye.scenario(jax.random.key(3), 3, 1.0, True, 60)
    return tuning.rmse_objective(wang_ye.nominal_model(), wang_ye.prior(), train)


CASES = {
    # name: (filter as a function of one scalar, point)
    "moment-theta2": (lambda x: jdrkf.DRKF(state_set=Moment(x), noise_set=Moment(1.02), outliers=EpsContamination(0.05, k=1.4)), 1.03),
    "wasserstein-theta_x": (lambda x: jdrkf.DRKF(state_set=Wasserstein(x), noise_set=Wasserstein(0.1), outliers=EpsContamination(0.05)), 0.2),
    "wasserstein-theta_v": (lambda x: jdrkf.DRKF(state_set=Wasserstein(0.2), noise_set=Wasserstein(x), outliers=EpsContamination(0.05)), 0.1),
    "eps": (lambda x: jdrkf.DRKF(state_set=Moment(1.02), noise_set=Moment(1.02), outliers=EpsContamination(x)), 0.05),
    "wkf-rho": (lambda x: jdrkf.WassersteinKF(x), 0.1),
    "huber-k": (lambda x: jdrkf.HuberKF(0.05, x), 1.4),
}


# wasserstein-theta_x covers the Wasserstein path in the default tier (suite time budget).
_SLOW_CASES = {"wasserstein-theta_v"}


@pytest.mark.parametrize("name", [pytest.param(n, marks=pytest.mark.slow) if n in _SLOW_CASES else n for n in sorted(CASES)])
def test_gradient_matches_finite_differences(objective, name):
    make, x0 = CASES[name]
    f = jax.jit(lambda x: objective(make(x)))
    grad = jax.grad(lambda x: objective(make(x)))(x0)
    h = 1e-5 * x0
    fd = (f(x0 + h) - f(x0 - h)) / (2 * h)
    assert abs(fd) > 1e-4  # the objective does depend on the parameter
    np.testing.assert_allclose(grad, fd, rtol=1e-5)


def test_fit_reduces_loss_and_respects_bounds(objective):
    mkf = wang_ye.mkf(1.08)
    where = lambda f: (f.state_set.theta2, f.noise_set.theta2)  # noqa: E731
    res = tuning.fit(mkf, objective, where=where, bounds=(1.0, None), shared=True, optimizer=optax.adam(0.1), steps=15)
    assert res.params.shape == (16, 1) and res.losses.shape == (16,)
    assert res.loss < 0.995 * res.losses[0]
    assert np.all(res.params >= 1.0)
    t2x, t2v = where(res.filter)
    assert float(t2x) == float(t2v) and float(t2x) < 1.08
    np.testing.assert_allclose(objective(res.filter), res.loss, rtol=1e-10)


def test_grid_search_finds_the_minimum_of_its_grid(objective):
    mkf = wang_ye.mkf()
    grid = np.array([1.0, 1.02, 1.05, 1.1])
    res = tuning.grid_search(mkf, objective, where=lambda f: (f.state_set.theta2, f.noise_set.theta2), grid=grid)
    direct = [float(objective(wang_ye.mkf(g))) for g in grid]
    np.testing.assert_allclose(res.losses, direct, rtol=1e-10)
    assert res.loss == min(direct)
    assert float(res.filter.state_set.theta2) == grid[int(np.argmin(direct))]


def test_sigmoid_bounds_and_bad_arguments(objective):
    flt = jdrkf.DRKF(state_set=Moment(1.02), noise_set=Moment(1.02), outliers=EpsContamination(0.05))
    res = tuning.fit(flt, objective, where=lambda f: f.outliers.eps, bounds=(0.0, 0.5), steps=3)
    assert np.all((res.params > 0) & (res.params < 0.5))
    with pytest.raises(ValueError, match="bounds"):
        tuning.fit(flt, objective, where=lambda f: f.outliers.eps, bounds=(0.5, 0.1), steps=1)
    with pytest.raises(ValueError, match="where"):
        tuning.fit(jdrkf.HuberKF(0.05, 1.4), objective, where=lambda f: f.outliers.k.shape, steps=1)
    with pytest.raises(ValueError, match="grid"):
        tuning.grid_search(flt, objective, where=lambda f: (f.state_set.theta2, f.noise_set.theta2), grid=np.ones((3, 3)))


def test_objective_is_jittable_as_a_function_of_the_filter(objective):
    flt = wang_ye.mkf()
    np.testing.assert_allclose(eqx.filter_jit(objective)(flt), objective(flt), rtol=1e-12)
