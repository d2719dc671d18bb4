"""`AbstractFilter.batch`: Monte Carlo runs sharing one model, with the covariance
recursion computed once for the batch when no observation is missing."""

import jax
import jax.extend.core
import jax.numpy as jnp
import numpy as np
import pytest

import jdrkf
from jdrkf.sets import KL, EpsContamination, Moment, Wasserstein

B, T = 5, 15


def _setup(nan=False):
    model = jdrkf.LinearModel([[0.9802, 0.0196], [0.0, 0.9802]], [[1.0, -1.0]], [[1.9608, 0.0195], [0.0195, 1.9605]], [[1.0]])
    prior = jdrkf.Gaussian(np.zeros(2), np.eye(2))
    traj = jdrkf.simulate(jax.random.key(0), model, prior, T, B)
    ys = np.array(traj.observations)
    if nan:
        ys[2, 4, 0] = np.nan
    return model, prior, jnp.asarray(ys)


SHARED = {
    "KF": jdrkf.KalmanFilter(),
    "DRKF-W": jdrkf.DRKF(state_set=Wasserstein(0.3), noise_set=Wasserstein(0.1)),
    "DRKF-KL-huber": jdrkf.DRKF(state_set=KL(0.05), noise_set=Moment(1.1), outliers=EpsContamination(0.05, k=1.4)),
    "HKF": jdrkf.HuberKF(0.05, 1.4),
    "WKF": jdrkf.WassersteinKF(0.1),
    "W-DRKF": jdrkf.WassersteinDRKF(0.3, 0.1),
    "tau-KF": jdrkf.TauKF(0.0, 1e-3),
    "RS-KF": jdrkf.RiskSensitiveKF(0.01),
    "BCOT": jdrkf.BCOTKF(0.2),
}


def _main_scan_carry_shapes(closed_jaxpr):
    """Carry shapes of the outermost `scan` (the filter's time loop) in a jaxpr."""
    for eqn in closed_jaxpr.jaxpr.eqns:
        if eqn.primitive.name == "scan":
            c, k = eqn.params["num_consts"], eqn.params["num_carry"]
            return [tuple(v.aval.shape) for v in eqn.invars[c:c + k]]
        for sub in jax.extend.core.jaxprs_in_params(eqn.params):
            shapes = _main_scan_carry_shapes(jax.extend.core.ClosedJaxpr(sub, ()))
            if shapes is not None:
                return shapes
    return None


def _branch_carry_shapes(flt, model, prior, ys):
    """Carry shapes of the filter loop in each branch of `batch`'s `lax.cond`
    (`[dense, masked]`: `lax.cond` lists the false branch first), or of its single
    `vmap` when there is no cond."""
    jaxpr = jax.make_jaxpr(lambda y: flt.batch(model, prior, y))(ys)  # traced ys: a lax.cond
    conds = [e for e in jaxpr.jaxpr.eqns if e.primitive.name == "cond"]
    if not conds:
        return [_main_scan_carry_shapes(jaxpr)]
    return [_main_scan_carry_shapes(br) for br in conds[0].params["branches"]]


@pytest.mark.parametrize("name", sorted(SHARED))
def test_dense_branch_carries_one_covariance_for_the_batch(name):
    flt = SHARED[name]
    assert type(flt).shared_covariance
    model, prior, ys = _setup()
    dense, masked = _branch_carry_shapes(flt, model, prior, ys)
    # Without NaN the covariances are carried unbatched, so every worst-case solve runs
    # once per time step for the whole batch; with NaN each run has its own.
    assert (B, 2, 2) in masked and (2, 2) not in masked
    assert (2, 2) in dense and (B, 2, 2) not in dense


def test_filters_without_shared_covariance_run_plain_vmap():
    model, prior, ys = _setup()
    flt = jdrkf.RBKF(measurement_weight=jdrkf.sets.GaussianKernel(2.0))
    assert not type(flt).shared_covariance
    (shapes,) = _branch_carry_shapes(flt, model, prior, ys)
    assert (B, 2, 2) in shapes


@pytest.mark.parametrize("name, nan", [("KF", False), ("KF", True), ("DRKF-W", False), ("HKF", True)])
def test_batch_equals_vmap(name, nan):
    flt = SHARED[name]
    model, prior, ys = _setup(nan)
    got = jax.jit(lambda y: flt.batch(model, prior, y))(ys)
    want = jax.jit(jax.vmap(lambda y: flt(model, prior, y)))(ys)
    for field in ("filtered_means", "filtered_covariances", "predicted_covariances", "loglik_increments"):
        np.testing.assert_allclose(getattr(got, field), getattr(want, field), rtol=1e-11, atol=1e-12, err_msg=field)
    np.testing.assert_array_equal(got.result._value, want.result._value)
    if nan:  # the masked run differs from the others from the missing step on
        covs = np.asarray(got.filtered_covariances)
        assert np.abs(covs[2, 4] - covs[0, 4]).max() > 1e-3


def test_known_missing_flag_compiles_one_branch():
    """`montecarlo` decides on concrete data whether any observation is NaN and passes
    that as a Python bool: no cond, only the branch needed is traced. Eagerly, `batch`
    decides the same way."""
    model, prior, ys = _setup(nan=True)
    flt = SHARED["KF"]
    for missing in (True, False):
        closed = jax.make_jaxpr(lambda y, missing=missing: flt._batch(model, prior, y, None, None, missing))(ys)
        assert not [e for e in closed.jaxpr.eqns if e.primitive.name == "cond"]
        shapes = _main_scan_carry_shapes(closed)
        assert ((B, 2, 2) in shapes) == missing and ((2, 2) in shapes) != missing
    eager = flt.batch(model, prior, ys)
    want = jax.vmap(lambda y: flt(model, prior, y))(ys)
    np.testing.assert_allclose(eager.filtered_means, want.filtered_means, rtol=1e-12)


def test_batch_with_keys_and_inputs():
    model, prior, ys = _setup()
    mdl = jdrkf.LinearModel(model.F, model.H, model.Q, model.R, B=np.eye(2))
    inputs = jnp.ones((B, T, 2))
    got = jdrkf.KalmanFilter().batch(mdl, prior, ys, jax.random.split(jax.random.key(0), B), inputs=inputs)
    want = jax.vmap(lambda y, u: jdrkf.KalmanFilter()(mdl, prior, y, inputs=u))(ys, inputs)
    assert got.filtered_means.shape == (B, T, 2)
    np.testing.assert_allclose(got.filtered_means, want.filtered_means, rtol=1e-12)


def test_batch_gradient_matches_vmap():
    model, prior, ys = _setup()

    def loss(theta, batched):
        flt = jdrkf.DRKF(state_set=Moment(theta), noise_set=Moment(1.05), outliers=EpsContamination(0.05, k=1.4))
        res = flt.batch(model, prior, ys) if batched else jax.vmap(lambda y: flt(model, prior, y))(ys)
        return jnp.mean(res.filtered_means ** 2)

    g1 = jax.grad(loss)(1.2, True)
    g2 = jax.grad(loss)(1.2, False)
    np.testing.assert_allclose(g1, g2, rtol=1e-9)


def test_batch_rejects_bad_shapes():
    model, prior, ys = _setup()
    flt = jdrkf.KalmanFilter()
    with pytest.raises(ValueError, match="ys must have 3 dimensions"):
        flt.batch(model, prior, ys[0])
    with pytest.raises(ValueError, match="keys must hold one key per run"):
        flt.batch(model, prior, ys, jax.random.split(jax.random.key(0), B + 1))
    with pytest.raises(ValueError, match="inputs must have shape"):
        flt.batch(model, prior, ys, inputs=jnp.ones((B + 1, T, 2)))
