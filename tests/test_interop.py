"""`LinearModel.from_dynamax` / `.to_dynamax` against dynamax's own Kalman filter, and
`LinearModel.to_cuthbert` against cuthbert's (at the end of the file).

dynamax (the `bench` extra) conditions its first state on `emissions[0]`; jdrkf predicts
`x_1` from the prior of `x_0` first. The oracle is `dynamax.linear_gaussian_ssm.lgssm_filter`
on the same observation and input arrays: equal filtered means, covariances and marginal
log-likelihood (to 1e-10, float64) check the time shift of both conversions. dynamax adds
`1e-9 I` to the innovation covariance before solving for the gain (`psd_solve`'s
`diagonal_boost`), a relative change of about 1e-9; the oracle runs with it off
(`exact_dynamax`), and one test keeps dynamax's default at a tolerance that covers it.
"""

import sys
import warnings

import equinox as eqx
import jax.numpy as jnp
import numpy as np
import pytest

import jdrkf

with warnings.catch_warnings():  # tensorflow_probability (dynamax's dependency) uses deprecated jax APIs
    warnings.simplefilter("ignore", DeprecationWarning)
    pytest.importorskip("dynamax.linear_gaussian_ssm")
    from dynamax.linear_gaussian_ssm import inference as dynamax_inference
    from dynamax.linear_gaussian_ssm import lgssm_filter
    from dynamax.linear_gaussian_ssm.inference import make_lgssm_params


@pytest.fixture
def exact_dynamax(monkeypatch):
    """dynamax's Kalman filter without its 1e-9 diagonal boost in the gain's solve."""
    solve = dynamax_inference.psd_solve
    monkeypatch.setattr(dynamax_inference, "psd_solve", lambda a, b: solve(a, b, diagonal_boost=0.0))


T, N, M, P = 12, 3, 2, 2


def _spd(rng, n, shape=()):
    a = rng.standard_normal(shape + (n, n))
    return a @ np.swapaxes(a, -1, -2) / n + 0.5 * np.eye(n)


def _dynamax_params(rng, time_varying=False, inputs=True):
    tv = (T,) if time_varying else ()
    return make_lgssm_params(
        initial_mean=jnp.asarray(rng.standard_normal(N)),
        initial_cov=jnp.asarray(_spd(rng, N)),
        dynamics_weights=jnp.asarray(0.6 * rng.standard_normal(tv + (N, N))),
        dynamics_cov=jnp.asarray(_spd(rng, N, tv)),
        emissions_weights=jnp.asarray(rng.standard_normal(tv + (M, N))),
        # dynamax's diagonal form of a time-varying emission covariance: shape (T, m)
        emissions_cov=jnp.asarray(0.2 + rng.random((T, M)) if time_varying else _spd(rng, M)),
        dynamics_bias=jnp.asarray(rng.standard_normal(tv + (N,))),
        dynamics_input_weights=jnp.asarray(rng.standard_normal(tv + (N, P))) if inputs else None,
        emissions_bias=jnp.asarray(rng.standard_normal(tv + (M,))),
    )


def _assert_same_filter(res, post, tol=1e-10):
    np.testing.assert_allclose(res.filtered_means, post.filtered_means, rtol=0, atol=tol)
    np.testing.assert_allclose(res.filtered_covariances, post.filtered_covariances, rtol=0, atol=tol)
    np.testing.assert_allclose(res.marginal_loglik, post.marginal_loglik, rtol=0, atol=tol)


@pytest.mark.parametrize("time_varying", [False, True])
@pytest.mark.parametrize("with_inputs", [False, True])
def test_from_dynamax_filters_like_lgssm_filter(rng, exact_dynamax, time_varying, with_inputs):
    params = _dynamax_params(rng, time_varying, with_inputs)
    ys = jnp.asarray(rng.standard_normal((T, M)))
    us = jnp.asarray(rng.standard_normal((T, P))) if with_inputs else None
    model, prior = jdrkf.LinearModel.from_dynamax(params, num_timesteps=None if time_varying else T)
    assert (model.B is not None) == with_inputs
    res = jdrkf.KalmanFilter()(model, prior, ys, inputs=us)
    _assert_same_filter(res, lgssm_filter(params, ys, us))


@pytest.mark.parametrize("time_varying", [False, True])
def test_to_dynamax_filters_like_kalman_filter(rng, exact_dynamax, time_varying):
    # noise input G (n x q), process and measurement noise means, controls
    model, prior, ys, us = _random_case(rng, time_varying, q=2, varying_h=False)
    params = model.to_dynamax(prior, us)
    _assert_same_filter(jdrkf.KalmanFilter()(model, prior, ys, inputs=us), lgssm_filter(params, ys, us))
    # the initial law of dynamax is the prediction of x_1, written out here
    mdl0 = model.at(0)
    m1 = mdl0.F @ prior.mean + mdl0.B @ us[0] + mdl0.G @ mdl0.process_mean
    p1 = mdl0.F @ prior.cov @ mdl0.F.T + mdl0.G @ mdl0.Q @ mdl0.G.T
    np.testing.assert_allclose(params.initial.mean, m1, rtol=0, atol=1e-12)
    np.testing.assert_allclose(params.initial.cov, p1, rtol=0, atol=1e-12)


def test_round_trip_of_parameters(rng, exact_dynamax):
    params = _dynamax_params(rng, inputs=True)
    model, prior = jdrkf.LinearModel.from_dynamax(params, num_timesteps=T)
    us = jnp.asarray(rng.standard_normal((T, P)))
    back = model.to_dynamax(prior, us)
    np.testing.assert_allclose(back.initial.mean, params.initial.mean, rtol=0, atol=1e-14)
    np.testing.assert_allclose(back.initial.cov, params.initial.cov, rtol=0, atol=1e-14)
    # dynamax ignores dynamics entry 0; entries 1.. repeat the time-invariant originals
    for got, want in zip(back.dynamics, params.dynamics, strict=True):
        np.testing.assert_array_equal(got[1:], jnp.broadcast_to(want, got[1:].shape))
    for got, want in zip(back.emissions, params.emissions, strict=True):
        np.testing.assert_array_equal(got, want)
    # and dynamax filters the round-tripped parameters as the originals
    ys = jnp.asarray(rng.standard_normal((T, M)))
    _assert_same_filter(lgssm_filter(back, ys, us), lgssm_filter(params, ys, us))


def test_time_invariant_alternative_update_first(rng, exact_dynamax):
    """The README's route for time-invariant params: the model of step 1 (dynamax's own
    matrices), `update` with `ys[0]`, then filter `ys[1:]` with `inputs[1:]`."""
    params = _dynamax_params(rng, inputs=True)
    ys = jnp.asarray(rng.standard_normal((T, M)))
    us = jnp.asarray(rng.standard_normal((T, P)))
    model, prior = jdrkf.LinearModel.from_dynamax(params, num_timesteps=T)
    model1 = model.at(1)
    assert model1.num_steps is None
    first, loglik0, _ = jdrkf.update(model1, prior, ys[0], 0)
    res = jdrkf.KalmanFilter()(model1, first, ys[1:], inputs=us[1:])
    post = lgssm_filter(params, ys, us)
    np.testing.assert_allclose(first.mean, post.filtered_means[0], rtol=0, atol=1e-10)
    np.testing.assert_allclose(res.filtered_means, post.filtered_means[1:], rtol=0, atol=1e-10)
    np.testing.assert_allclose(loglik0 + res.marginal_loglik, post.marginal_loglik, rtol=0, atol=1e-10)


def test_from_dynamax_matches_default_dynamax_up_to_its_diagonal_boost(rng):
    params = _dynamax_params(rng, time_varying=True, inputs=False)
    ys = jnp.asarray(rng.standard_normal((T, M)))
    model, prior = jdrkf.LinearModel.from_dynamax(params)
    _assert_same_filter(jdrkf.KalmanFilter()(model, prior, ys), lgssm_filter(params, ys), tol=1e-7)


def test_from_dynamax_rejects_what_it_cannot_represent(rng):
    params = _dynamax_params(rng, inputs=True)
    with pytest.raises(ValueError, match="num_timesteps is required"):
        jdrkf.LinearModel.from_dynamax(params)
    with pytest.raises(ValueError, match="num_timesteps is 5"):
        jdrkf.LinearModel.from_dynamax(_dynamax_params(rng, time_varying=True), num_timesteps=5)
    d = params._replace(emissions=params.emissions._replace(input_weights=jnp.ones((M, P))))
    with pytest.raises(ValueError, match="params.emissions.input_weights must be zero"):
        jdrkf.LinearModel.from_dynamax(d, num_timesteps=T)
    with pytest.raises(ValueError, match="params must be a dynamax ParamsLGSSM"):
        jdrkf.LinearModel.from_dynamax({"initial": None}, num_timesteps=T)


def test_to_dynamax_needs_the_first_input_and_says_so_without_dynamax(rng, monkeypatch):
    model, prior = jdrkf.LinearModel.from_dynamax(_dynamax_params(rng, inputs=True), num_timesteps=T)
    with pytest.raises(ValueError, match="no inputs were given"):
        model.to_dynamax(prior)
    monkeypatch.setitem(sys.modules, "dynamax.linear_gaussian_ssm", None)  # import fails as if not installed
    with pytest.raises(ImportError, match=r"pip install 'jdrkf\[bench\]'"):
        model.to_dynamax(prior, jnp.zeros((T, P)))


# cuthbert (the `bench` extra): `LinearModel.to_cuthbert` against cuthbert's own square-root
# Kalman filter, which shares jdrkf's time index (its first state is the law of x_0).


def _random_case(rng, time_varying, q, varying_h=True):
    """A random model with every optional field (time-varying ones with `time_varying`),
    a prior, observations and inputs."""
    tv = (T,) if time_varying else ()
    model = jdrkf.LinearModel(
        F=0.6 * rng.standard_normal(tv + (N, N)),
        H=rng.standard_normal((tv if varying_h else ()) + (M, N)),
        Q=_spd(rng, q, tv),
        R=_spd(rng, M),
        G=rng.standard_normal((N, q)),
        B=rng.standard_normal(tv + (N, P)),
        process_mean=rng.standard_normal(q),
        noise_mean=rng.standard_normal(tv + (M,)),
    )
    prior = jdrkf.Gaussian(rng.standard_normal(N), _spd(rng, N))
    return model, prior, jnp.asarray(rng.standard_normal((T, M))), jnp.asarray(rng.standard_normal((T, P)))


def _assert_same_as_cuthbert(res, states, tol=1e-10):
    """cuthbert's `T + 1` states start with x_0's; jdrkf's `T` start with x_1's."""
    chol = np.asarray(states.chol_cov[1:])
    np.testing.assert_allclose(res.filtered_means, states.mean[1:], rtol=0, atol=tol)
    np.testing.assert_allclose(res.filtered_covariances, chol @ np.swapaxes(chol, -1, -2), rtol=0, atol=tol)
    np.testing.assert_allclose(res.marginal_loglik, states.log_normalizing_constant[-1], rtol=0, atol=tol)


@pytest.mark.parametrize("time_varying", [False, True])
@pytest.mark.parametrize("missing", [False, True])
def test_to_cuthbert_filters_like_kalman_filter(rng, time_varying, missing):
    cuthbert = pytest.importorskip("cuthbert")
    model, prior, ys, us = _random_case(rng, time_varying, q=N + 1)  # G Q Gᵀ nonsingular
    observed = jnp.asarray(rng.random((T, M)) > 0.3).at[3].set(False) if missing else None  # step 4: nothing
    res = jdrkf.KalmanFilter()(model, prior, ys, inputs=us, observed=observed)
    kf, model_inputs = model.to_cuthbert(prior, ys, us, observed)
    for parallel in (False, True):  # the associative-scan form gives the same filter
        _assert_same_as_cuthbert(res, cuthbert.filter(kf, model_inputs, kf.init_prepare(), parallel=parallel))
    if missing:  # a missing entry's value is ignored by both
        ys_other = jnp.where(observed, ys, 1e3)
        kf, model_inputs = model.to_cuthbert(prior, ys_other, us, observed)
        _assert_same_as_cuthbert(res, cuthbert.filter(kf, model_inputs, kf.init_prepare()))


def test_to_cuthbert_with_singular_process_noise(rng):
    """`G` with fewer columns than states (`G Q Gᵀ` singular) and no inputs: cuthbert's
    sequential filter gets an `n × n` factor of `G Q Gᵀ`. (Its associative form solves with
    a process-noise factor in the log-likelihood, so it needs `G Q Gᵀ` nonsingular.)"""
    cuthbert = pytest.importorskip("cuthbert")
    model, prior, ys, _ = _random_case(rng, time_varying=True, q=1)
    model = eqx.tree_at(lambda m: m.B, model, None, is_leaf=lambda x: x is None)
    kf, model_inputs = model.to_cuthbert(prior, ys)
    assert set(model_inputs) == {"t", "y"}
    _assert_same_as_cuthbert(jdrkf.KalmanFilter()(model, prior, ys), cuthbert.filter(kf, model_inputs, kf.init_prepare()))


def test_to_cuthbert_checks_its_arguments_and_says_what_to_install(rng, monkeypatch):
    pytest.importorskip("cuthbert")
    model, prior, ys, us = _random_case(rng, time_varying=True, q=N)
    with pytest.raises(ValueError, match="no inputs were given"):
        model.to_cuthbert(prior, ys)
    with pytest.raises(ValueError, match=r"time-varying with 12 steps but 5 steps"):
        model.to_cuthbert(prior, ys[:5], us[:5])
    with pytest.raises(ValueError, match="ys has shape"):
        model.to_cuthbert(prior, ys[:, :1], us)
    with pytest.raises(ValueError, match="observed must be a boolean mask"):
        model.to_cuthbert(prior, ys, us, observed=jnp.ones(T))
    with pytest.raises(ValueError, match=r"ys\[2, 1\] is NaN"):
        model.to_cuthbert(prior, ys.at[2, 1].set(jnp.nan), us)
    monkeypatch.setitem(sys.modules, "cuthbert.gaussian", None)  # import fails as if not installed
    with pytest.raises(ImportError, match="pip install cuthbert"):
        model.to_cuthbert(prior, ys, us)
