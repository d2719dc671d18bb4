"""Plain `jax.vmap` over Monte Carlo runs computes the data-independent work once.

For every filter with `shared_covariance`, `jax.vmap(flt, in_axes=(None, None, 0))`
must carry the covariances of its time loop unbatched and run every solver loop
(worst-case solves, root finding) unbatched: checked on the jaxpr. A missing-data
mask shared by all runs keeps that; a per-run mask makes the covariance path per run.
"""

import jax
import jax.extend.core
import jax.numpy as jnp
import numpy as np
import pytest

import jdrkf
from jdrkf.sets import KL, EpsContamination, MarginalKL, MarginalMoment, Moment, Wasserstein

B, T = 7, 15  # B differs from every state, observation and solver dimension below


def _linear():
    model = jdrkf.LinearModel([[0.9802, 0.0196], [0.0, 0.9802]], [[1.0, -1.0]], [[1.9608, 0.0195], [0.0195, 1.9605]], [[1.0]])
    prior = jdrkf.Gaussian(np.zeros(2), np.eye(2))
    traj = jdrkf.simulate(jax.random.key(0), model, prior, T, B)
    return model, prior, traj.observations


def _multisensor():
    model = jdrkf.MultiSensorModel(
        [[0.9, 0.1], [0.0, 0.95]], [[[1.0, 0.0]], [[0.0, 1.0]], [[1.0, 1.0]]], [[0.3, 0.0], [0.0, 0.2]],
        [[[1.0]], [[2.0]], [[1.5]]],
    )
    prior = jdrkf.Gaussian(np.zeros(2), np.eye(2))
    ys = jax.random.normal(jax.random.key(1), (B, T, 3))
    return model, prior, ys


LINEAR = {
    "KF": jdrkf.KalmanFilter(),
    "SS-KF": jdrkf.SteadyStateKalmanFilter(),
    "DRKF-W": jdrkf.DRKF(state_set=Wasserstein(0.3), noise_set=Wasserstein(0.1)),
    "DRKF-KL-huber": jdrkf.DRKF(state_set=KL(0.05), noise_set=Moment(1.1), outliers=EpsContamination(0.05, k=1.4)),
    "HKF": jdrkf.HuberKF(0.05, 1.4),
    "WKF": jdrkf.WassersteinKF(0.1),
    "W-DRKF": jdrkf.WassersteinDRKF(0.3, 0.1),
    "SS-DRKF": jdrkf.SteadyStateDRKF(0.3, 0.1),
    "tau-KF": jdrkf.TauKF(0.0, 1e-3),
    "RS-KF": jdrkf.RiskSensitiveKF(0.01),
    "BCOT": jdrkf.BCOTKF(0.2),
}
FUSION = {
    "CKF": jdrkf.CKF(),
    "CI": jdrkf.CovarianceIntersection(),
    "MC-MDRKF": jdrkf.MarginalDRKF(MarginalMoment(0.7, 1.2)),
    "KL-MDRKF": jdrkf.MarginalDRKF(MarginalKL(0.05)),
}


def _loops(jaxpr, found=None):
    """All `scan` and `while` equations in a (closed) jaxpr, nested ones included."""
    found = [] if found is None else found
    for eqn in getattr(jaxpr, "jaxpr", jaxpr).eqns:
        if eqn.primitive.name in ("scan", "while"):
            found.append(eqn)
        for sub in jax.extend.core.jaxprs_in_params(eqn.params):
            _loops(sub, found)
    return found


def _carry_shapes(eqn):
    """Shapes of a loop's floating-point carries (flags and result codes left out)."""
    if eqn.primitive.name == "scan":
        c, k = eqn.params["num_consts"], eqn.params["num_carry"]
        carry = eqn.invars[c:c + k]
    else:
        carry = eqn.invars[eqn.params["cond_nconsts"] + eqn.params["body_nconsts"]:]
    return [tuple(v.aval.shape) for v in carry if jnp.issubdtype(v.aval.dtype, jnp.inexact)]


def _covariance_carry(carry, n):
    """How a time loop with carry shapes `carry` holds an `n × n` covariance: `"per run"`,
    `"shared"` or `None`, whether as one array or entry by entry (`KalmanFilter` carries
    the entries of small covariances: `n²` scalars, `(B,)` arrays under `vmap` when per run)."""
    if (B, n, n) in carry or carry.count((B,)) >= n * n:
        return "per run"
    if (n, n) in carry or carry.count(()) >= n * n:
        return "shared"
    return None


def _time_loop(jaxpr):
    """The filter's time loop: the outermost scan of length T."""
    return next(e for e in _loops(jaxpr) if e.primitive.name == "scan" and e.params["length"] == T)


def _batched(shapes):
    return [s for s in shapes if s[:1] == (B,)]


def _case(name):
    if name in LINEAR:
        return LINEAR[name], *_linear()
    return FUSION[name], *_multisensor()


ALL = sorted(LINEAR) + sorted(FUSION)


@pytest.mark.parametrize("name", ALL)
def test_plain_vmap_shares_the_covariance_path(name):
    flt, model, prior, ys = _case(name)
    assert type(flt).shared_covariance
    n = model.state_dim
    jaxpr = jax.make_jaxpr(jax.vmap(flt, in_axes=(None, None, 0)))(model, prior, ys)
    carry = _carry_shapes(_time_loop(jaxpr))
    # the covariance is carried once, not once per run (steady-state filters carry none)
    assert _covariance_carry(carry, n) == (None if name in ("SS-KF", "SS-DRKF") else "shared"), carry
    assert (B, n) in carry or carry.count((B,)) >= n  # the means are per run
    # Every solver loop (worst-case solves, root finding, CI weights) runs once per step.
    solver_loops = [e for e in _loops(jaxpr) if e.primitive.name == "while"]
    for loop in solver_loops:
        assert not _batched(_carry_shapes(loop)), (loop.primitive.name, _carry_shapes(loop))


@pytest.mark.parametrize("name", ["KF", "DRKF-W", "HKF", "MC-MDRKF"])
def test_missing_data_mask_shared_or_per_run(name):
    flt, model, prior, ys = _case(name)
    n = model.state_dim
    mask = np.ones(ys.shape[1:], bool)
    mask[3, 0] = False
    shared = jax.make_jaxpr(jax.vmap(lambda y: flt(model, prior, y, observed=mask)))(ys)
    assert _covariance_carry(_carry_shapes(_time_loop(shared)), n) == "shared"
    per_run = jax.make_jaxpr(jax.vmap(lambda y, o: flt(model, prior, y, observed=o)))(ys, np.broadcast_to(mask, ys.shape))
    assert _covariance_carry(_carry_shapes(_time_loop(per_run)), n) == "per run"


@pytest.mark.parametrize("name", ["KF", "DRKF-KL-huber", "MC-MDRKF", "CI"])
def test_vmap_equals_run_by_run(name):
    flt, model, prior, ys = _case(name)
    flt = jdrkf.filters._base.with_outputs(flt, "all")
    got = jax.jit(jax.vmap(flt, in_axes=(None, None, 0)))(model, prior, ys)
    one = jax.jit(lambda y: flt(model, prior, y))
    for b in range(B):
        want = one(ys[b])
        for field in ("filtered_means", "filtered_covariances", "predicted_covariances"):
            np.testing.assert_allclose(getattr(got, field)[b], getattr(want, field), rtol=1e-10, atol=1e-12, err_msg=field)
        if name != "CI":  # CI defines no likelihood
            np.testing.assert_allclose(got.loglik_increments[b], want.loglik_increments, rtol=1e-10, err_msg=name)


def test_per_run_mask_equals_run_by_run():
    model, prior, ys = _linear()
    mask = np.ones(ys.shape, bool)
    mask[2, 4, 0] = mask[0, 9, 0] = False
    ys = jnp.where(mask, ys, jnp.nan)
    flt = jdrkf.HuberKF(0.05, 1.4)
    got = jax.jit(jax.vmap(lambda y, o: flt(model, prior, y, observed=o)))(ys, mask)
    one = jax.jit(lambda y, o: flt(model, prior, y, observed=o))
    for b in range(B):
        want = one(ys[b], mask[b])
        np.testing.assert_allclose(got.filtered_means[b], want.filtered_means, rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(got.filtered_covariances[b], want.filtered_covariances, rtol=1e-10, atol=1e-12)
    covs = np.asarray(got.filtered_covariances)
    assert np.abs(covs[2, 4] - covs[1, 4]).max() > 1e-3  # the masked run differs from step 5 on
    np.testing.assert_allclose(covs[1], covs[3], rtol=1e-12)  # unmasked runs agree


def test_gradient_through_shared_vmap_matches_loop():
    model, prior, ys = _linear()

    def loss(theta, shared):
        flt = jdrkf.DRKF(state_set=Moment(theta), noise_set=Moment(1.05), outliers=EpsContamination(0.05, k=1.4))
        if shared:
            res = jax.vmap(flt, in_axes=(None, None, 0))(model, prior, ys)
            return jnp.mean(res.filtered_means ** 2)
        return jnp.mean(jax.lax.map(lambda y: flt(model, prior, y).filtered_means, ys) ** 2)

    grad = jax.jit(jax.grad(loss), static_argnums=1)
    np.testing.assert_allclose(grad(1.2, True), grad(1.2, False), rtol=1e-9)


def test_filters_without_shared_covariance_run_per_run():
    model, prior, ys = _linear()
    flt = jdrkf.RBKF(measurement_weight=jdrkf.sets.GaussianKernel(2.0))
    assert not type(flt).shared_covariance
    jaxpr = jax.make_jaxpr(jax.vmap(flt, in_axes=(None, None, 0)))(model, prior, ys)
    assert _covariance_carry(_carry_shapes(_time_loop(jaxpr)), 2) == "per run"


def test_float32_products_run_at_full_precision():
    """GPUs may run float32 matmuls in TF32; every product a filter traces asks for HIGHEST."""
    model, prior, ys = _linear()
    f32 = lambda a: jnp.asarray(a, jnp.float32)  # noqa: E731
    model32 = jdrkf.LinearModel(f32(model.F), f32(model.H), f32(model.Q), f32(model.R))
    prior32 = jdrkf.Gaussian(f32(prior.mean), f32(prior.cov))
    flt = jdrkf.DRKF(state_set=Wasserstein(0.3), noise_set=Wasserstein(0.1), rtol=1e-5)
    jaxpr = jax.make_jaxpr(jax.vmap(flt, in_axes=(None, None, 0)))(model32, prior32, f32(ys))
    dots = []

    def collect(jx):
        for eqn in getattr(jx, "jaxpr", jx).eqns:
            if eqn.primitive.name == "dot_general":
                dots.append(eqn.params["precision"])
            for sub in jax.extend.core.jaxprs_in_params(eqn.params):
                collect(sub)

    collect(jaxpr)
    assert dots
    highest = (jax.lax.Precision.HIGHEST, jax.lax.Precision.HIGHEST)
    assert all(p == highest for p in dots), {str(p) for p in dots}
