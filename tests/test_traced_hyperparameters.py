"""Hyper-parameters that arrive traced (under `jit`, `vmap` over a grid) are range-checked
at run time: out of range → `RESULTS.invalid_hyperparameter` (raises with `throw=True`);
in range → the same output as the concrete value. Concrete values raise `ValueError`
when the set or filter is built.

Oracle: the documented range of each parameter (the result code is the specification),
and the concrete (eager) run for valid values. Every invalid example below returned
`RESULTS.successful` (finite output) before the run-time checks existed.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jdrkf
from jdrkf._nonlinear import NonlinearModel
from jdrkf.filters._bcot import BCOTKF
from jdrkf.sets import bcot_worst_case
from jdrkf.filters._divergence import RiskSensitiveKF, TauKF
from jdrkf.filters._reweighted import RBKF, STKF, STKF_AR1, VBKF
from jdrkf.sets import Barron, GaussianKernel
from jdrkf.sets import (
    KL,
    EpsContamination,
    EpsNormal,
    MarginalKL,
    MarginalMoment,
    Moment,
    Wasserstein,
    marginal_mmse,
    maxent_kl_solve,
    maxent_transport_solve,
    worst_case,
)

INVALID = jdrkf.RESULTS.invalid_hyperparameter
OK = jdrkf.RESULTS.successful
MESSAGE = "outside its valid range"
SLOW = pytest.mark.slow  # solver compilations of 20–60 s


def _linear():
    model = jdrkf.LinearModel(
        F=np.array([[0.9, 0.2], [0.0, 0.8]]), H=np.array([[1.0, 0.5]]), Q=0.2 * np.eye(2), R=np.eye(1)
    )
    ys = np.random.default_rng(0).normal(size=(6, 1))
    return model, jdrkf.Gaussian(jnp.zeros(2), jnp.eye(2)), ys


def _multisensor():
    rng = np.random.default_rng(1)
    model = jdrkf.MultiSensorModel(
        np.array([[0.9, 0.1], [0.0, 0.7]]), [rng.normal(size=(1, 2)), rng.normal(size=(1, 2))], 0.3 * np.eye(2),
        [np.eye(1), 2.0 * np.eye(1)],
    )
    return model, jdrkf.Gaussian(jnp.zeros(2), jnp.eye(2)), rng.normal(size=(3, 2))


def _nonlinear():
    model = NonlinearModel(lambda x, t: 0.5 * x + 25 * x / (1 + x**2), lambda x, t: x**2 / 20, jnp.eye(1), jnp.eye(1))
    return model, jdrkf.Gaussian(jnp.zeros(1), jnp.eye(1)), np.random.default_rng(2).normal(size=(4, 1))


# (name, data, make(p, throw) -> filter, valid value, invalid value). The examples
# come first: negative Wasserstein radius, ε-contamination outside [0, 0.5), ε-normal above
# 0.0303, Moment(θ₂ < 1), negative KL radius.
FAMILIES = [
    ("wasserstein_state", _linear, lambda p, throw: jdrkf.DRKF(state_set=Wasserstein(p), throw=throw), 0.1, -0.1),
    ("eps_contamination", _linear, lambda p, throw: jdrkf.DRKF(outliers=EpsContamination(p), throw=throw), 0.05, 0.7),
    ("eps_contamination_negative", _linear, lambda p, throw: jdrkf.DRKF(outliers=EpsContamination(p), throw=throw), 0.05, -0.1),
    ("eps_normal", _linear, lambda p, throw: jdrkf.DRKF(outliers=EpsNormal(p), throw=throw), 0.02, 0.2),
    ("moment_theta2", _linear, lambda p, throw: jdrkf.DRKF(state_set=Moment(p), noise_set=Moment(p), throw=throw), 1.05, 0.5),
    ("kl_state", _linear, lambda p, throw: jdrkf.DRKF(state_set=KL(p), throw=throw), 0.05, -0.1),
    pytest.param("moment_theta1", _linear, lambda p, throw: jdrkf.DRKF(state_set=Moment(1.1, theta1=p), throw=throw), 0.5, 1.5, marks=SLOW),
    pytest.param("kl_noise", _linear, lambda p, throw: jdrkf.DRKF(noise_set=KL(p), throw=throw), 0.05, jnp.nan, marks=SLOW),
    ("huber_k", _linear, lambda p, throw: jdrkf.DRKF(outliers=EpsContamination(0.05, k=p), throw=throw), 1.4, -1.0),
    pytest.param("joint_wasserstein", _linear, lambda p, throw: jdrkf.DRKF(joint_set=Wasserstein(p), throw=throw), 0.1, -0.1, marks=SLOW),
    ("huber_kf", _linear, lambda p, throw: jdrkf.HuberKF(p, throw=throw), 0.05, 0.5),
    pytest.param("wasserstein_kf", _linear, lambda p, throw: jdrkf.WassersteinKF(p, throw=throw), 0.1, -0.1, marks=SLOW),
    pytest.param("wasserstein_drkf", _linear, lambda p, throw: jdrkf.WassersteinDRKF(0.05, p, throw=throw), 0.05, -0.1, marks=SLOW),
    pytest.param("steady_state_drkf", _linear, lambda p, throw: jdrkf.SteadyStateDRKF(p, 0.05, throw=throw), 0.05, -0.1, marks=SLOW),
    ("tau_kf_tau", _linear, lambda p, throw: TauKF(p, 1e-3, throw=throw), 0.5, 1.5),
    ("tau_kf_c", _linear, lambda p, throw: TauKF(0.0, p, throw=throw), 1e-3, -1e-3),
    ("risk_sensitive", _linear, lambda p, throw: RiskSensitiveKF(p, throw=throw), 0.05, -0.05),
    pytest.param("bcot", _linear, lambda p, throw: BCOTKF(p, throw=throw), 0.1, -0.1, marks=SLOW),
    ("stkf_nu", _linear, lambda p, throw: STKF(nu_y=p, throw=throw), 4.0, -4.0),
    pytest.param("stkf_ar1_rho", _linear, lambda p, throw: STKF_AR1(rho_y=p, throw=throw), 0.99, 1.5, marks=SLOW),
    ("vbkf_alpha", _linear, lambda p, throw: VBKF(alpha0=p, throw=throw), 50.0, -1.0),
    ("rbkf_gaussian_kernel", _linear, lambda p, throw: RBKF(measurement_weight=GaussianKernel(p), throw=throw), 2.0, -2.0),
    pytest.param("rbkf_barron", _linear, lambda p, throw: RBKF(process_weight=Barron(p), throw=throw), 1.0, 2.5, marks=SLOW),
    pytest.param("marginal_moment", _multisensor, lambda p, throw: jdrkf.MarginalDRKF(MarginalMoment(0.9, p), throw=throw), 1.1, 0.9, marks=SLOW),
    pytest.param("marginal_kl", _multisensor, lambda p, throw: jdrkf.MarginalDRKF(MarginalKL(p), throw=throw), 0.05, -0.05, marks=SLOW),
    pytest.param("dr_particle_theta", _nonlinear, lambda p, throw: jdrkf.DRParticleFilter(16, likelihood=jdrkf.sets.InflatedLikelihood(p), throw=throw), 2.0, -2.0, marks=SLOW),
]
IDS = [f.values[0] if hasattr(f, "values") else f[0] for f in FAMILIES]


def _call(flt, model, prior, ys):
    return flt(model, prior, ys, jax.random.key(0)) if flt.stochastic_init else flt(model, prior, ys)


@pytest.mark.parametrize(("name", "data", "make", "good", "bad"), FAMILIES, ids=IDS)
def test_traced(name, data, make, good, bad):
    model, prior, ys = data()
    concrete = _call(make(good, False), model, prior, ys)
    assert concrete.result == OK
    # A traced scalar under jit: in range, the output of the concrete value; out of range,
    # with throw=True, an error with the message of RESULTS.invalid_hyperparameter.
    run = jax.jit(lambda p: _call(make(p, True), model, prior, ys))
    traced = run(good)
    np.testing.assert_allclose(traced.filtered_means, concrete.filtered_means, rtol=1e-13, atol=1e-14)
    np.testing.assert_allclose(traced.filtered_covariances, concrete.filtered_covariances, rtol=1e-13, atol=1e-14)
    with pytest.raises(Exception, match=MESSAGE):
        jax.block_until_ready(run(bad))
    # vmap over a grid (throw=False): only the invalid entry is flagged. (Batched solver
    # loops run until every entry stops, so the valid entry matches to round-off only.)
    res = jax.jit(jax.vmap(lambda p: _call(make(p, False), model, prior, ys)))(jnp.array([good, bad]))
    np.testing.assert_array_equal(np.asarray(res.result._value), [OK._value, INVALID._value])
    np.testing.assert_allclose(res.filtered_means[0], concrete.filtered_means, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(res.filtered_covariances[0], concrete.filtered_covariances, rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize(("name", "data", "make", "good", "bad"), FAMILIES, ids=IDS)
def test_concrete_raises(name, data, make, good, bad):
    with pytest.raises(ValueError):
        make(bad, True)


def test_check_is_shared_under_vmap_over_data():
    # The range check does not depend on the data: vmapped over ys it is traced unbatched
    # (the result code of every run is the same, and the filter stays shared).
    model, prior, ys = _linear()
    batch = jnp.stack([ys, -ys, 2 * ys])
    run = jax.jit(lambda p, y: jax.vmap(lambda yy: jdrkf.DRKF(state_set=Wasserstein(p), throw=False)(model, prior, yy))(y))
    np.testing.assert_array_equal(np.asarray(run(-0.1, batch).result._value), [INVALID._value] * 3)
    np.testing.assert_array_equal(np.asarray(run(0.1, batch).result._value), [OK._value] * 3)


def test_gradient_through_check():
    # The check adds no derivative: d/dθ of the filtered trace equals a central difference.
    model, prior, ys = _linear()

    def loss(theta):
        return jnp.sum(jnp.trace(RiskSensitiveKF(theta)(model, prior, ys).filtered_covariances, axis1=1, axis2=2))

    g = jax.grad(loss)(0.1)
    h = 1e-5
    np.testing.assert_allclose(g, (loss(0.1 + h) - loss(0.1 - h)) / (2 * h), rtol=1e-7)


# ------------------------------------------------------------------------- set methods


@pytest.mark.parametrize(
    ("make", "good", "bad"),
    [
        (Wasserstein, 0.0, -1e-9),
        (KL, 0.0, jnp.inf),
        (Moment, 1.0, 0.999),
        (EpsContamination, 0.0, 0.5),
        (EpsNormal, 0.0303, 0.0304),
        (MarginalKL, jnp.array([0.0, 1.0]), jnp.array([0.1, -0.1])),
        (lambda g: MarginalMoment(g, 1.5), jnp.array([1.0, 0.5]), jnp.array([0.5, 0.0])),
    ],
)
def test_valid_at_the_bounds(make, good, bad):
    # Closed/open ends as documented (and as the eager checks enforce).
    valid = jax.jit(lambda p: make(p).valid())
    assert bool(valid(good)) and not bool(valid(bad))
    assert bool(make(good).valid())
    with pytest.raises(ValueError):
        make(bad)


# ------------------------------------------------------------------------ solver results


def test_bcot_worst_case_not_converged_for_invalid_radius():
    p, q, r = np.eye(2), 0.2 * np.eye(2), np.eye(1)
    a, c = np.array([[0.9, 0.2], [0.0, 0.8]]), np.array([[1.0, 0.5]])
    solve = jax.jit(lambda rad: bcot_worst_case(p, q, r, a, c, rad).converged)
    assert bool(solve(0.1)) and not bool(solve(-0.1))


def test_marginal_mmse_not_converged_for_invalid_radius():
    cov = np.array([[1.0, 0.3, 0.2], [0.3, 1.5, 0.1], [0.2, 0.1, 2.0]])
    solve = jax.jit(lambda c: marginal_mmse(cov, 1, (1, 1), MarginalKL(c)).converged)
    assert bool(solve(0.05)) and not bool(solve(-0.05))


@pytest.mark.parametrize("solver", ["kl", "transport"])
def test_maxent_not_converged_for_invalid_radius(solver):
    q = jnp.array([0.2, 0.3, 0.5])
    cost = jnp.abs(jnp.arange(3.0)[:, None] - jnp.arange(3.0)[None, :])
    if solver == "kl":
        solve = jax.jit(lambda t: maxent_kl_solve(q, t).converged)
    else:
        solve = jax.jit(lambda t: maxent_transport_solve(q, cost, t).converged)
    assert bool(solve(0.05)) and not bool(solve(-0.05))


@pytest.mark.parametrize("make", [Wasserstein, KL, Moment])
def test_worst_case_not_converged_for_invalid_radius(make):
    bad = 0.5 if make is Moment else -0.1
    solve = jax.jit(lambda p: worst_case(make(p), None, np.eye(2), np.array([[1.0, 0.5]]), np.eye(1)).converged)
    assert not bool(solve(bad))


def test_steady_state_solve_not_converged_for_invalid_radius():
    model, _, _ = _linear()
    solve = jax.jit(lambda p: jdrkf.SteadyStateDRKF(p, 0.05).solve(model).converged)
    assert not bool(solve(-0.1))


@pytest.fixture
def swallowed_raise(monkeypatch):
    """A runtime that swallows the check's exception (seen in a GPU benchmark process, where
    `throw=True` did not raise): the check returns its token unchanged."""
    monkeypatch.setattr(type(OK), "error_if", lambda self, token, pred: token)


@pytest.mark.parametrize("kind", ["filter", "smoother", "parallel", "closed_loop"])
def test_swallowed_raise_gives_nan_outputs_and_the_code(swallowed_raise, kind):
    """If the raise of `throw=True` does not surface, a failed call's float outputs are NaN (not
    plausible numbers; under `vmap` every run's, as the raise would stop the whole call) and
    `result` holds the codes; a successful call is unchanged."""
    model, prior, ys = _linear()
    ys2 = np.stack([ys, ys])
    flt = lambda r: jdrkf.DRKF(state_set=Wasserstein(r), noise_set=Wasserstein(r))  # noqa: E731
    if kind == "filter":
        run = lambda r: jax.vmap(flt(r), in_axes=(None, None, 0))(model, prior, ys2)  # noqa: E731
    elif kind == "smoother":
        run = lambda r: jax.vmap(jdrkf.RTSSmoother(flt(r)), in_axes=(None, None, 0))(model, prior, ys2)  # noqa: E731
    elif kind == "parallel":  # a NaN observation without a mask is its failure
        bad = ys2.copy()
        bad[1, 2, 0] = np.nan
        run = lambda r: jax.vmap(jdrkf.ParallelKalmanFilter(), in_axes=(None, None, 0))(  # noqa: E731
            model, prior, jnp.where(r < 0, jnp.asarray(bad), jnp.asarray(ys2)))
    else:
        model = jdrkf.LinearModel(F=model.F, H=model.H, Q=model.Q, R=model.R, B=np.array([[0.0], [1.0]]))

        def run(r):
            return jdrkf.closed_loop(jax.random.key(0), flt(r), model, prior, lambda x, ref: -x[1:], jnp.zeros((6, 2)))
    good, failed = jax.jit(run)(0.1), jax.jit(run)(-0.1)
    floats = lambda out: [x for x in jax.tree.leaves(out) if jnp.issubdtype(x.dtype, jnp.inexact)]  # noqa: E731
    assert all(np.isfinite(np.asarray(x)).all() for x in floats(good))
    assert np.all(np.asarray(good.result._value) == 0)
    codes = np.atleast_1d(np.asarray(failed.result._value))
    assert np.any(codes != 0)
    assert all(np.isnan(np.asarray(x)).all() for x in floats(failed))
    if kind == "parallel":  # only the second run failed
        assert codes[0] == 0
