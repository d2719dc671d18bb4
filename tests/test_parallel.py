"""Parallel-in-time Kalman filter and RTS smoother (`ParallelKalmanFilter`, `parallel_smooth`)
against the NumPy Kalman filter and RTS pass of the tests (oracles.py, test_smoother.py), the
sequential `KalmanFilter` / `jdrkf.smooth`, dynamax's parallel LGSSM filter and smoother, finite
differences (jit × vmap × grad), and the result codes of the sequential filter."""

import warnings

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from oracles import numpy_kalman_filter
from test_smoother import _assert_smoothed, _oracle, _random_problem

import jdrkf

_FILTER_FIELDS = ("filtered_means", "filtered_covariances", "predicted_means", "predicted_covariances", "loglik_increments")
_SMOOTH_FIELDS = (
    "smoothed_means",
    "smoothed_covariances",
    "smoothed_cross_covariances",
    "smoothed_initial_mean",
    "smoothed_initial_covariance",
)


def _missing(ys, seed, fraction=0.3):
    """`ys` with a random `fraction` of entries set to NaN (one step fully missing), and the mask."""
    rng = np.random.default_rng(seed)
    ys = np.array(ys)
    ys[rng.random(ys.shape) < fraction] = np.nan
    ys[3] = np.nan
    return ys, ~np.isnan(ys)


def _assert_filter_close(res, want, rtol=1e-9, atol=1e-11):
    for name in _FILTER_FIELDS:
        np.testing.assert_allclose(getattr(res, name), want[name] if isinstance(want, dict) else getattr(want, name),
                                   rtol=rtol, atol=atol, err_msg=name)
    want_ll = want["marginal_loglik"] if isinstance(want, dict) else want.marginal_loglik
    np.testing.assert_allclose(res.marginal_loglik, want_ll, rtol=1e-10)


@pytest.mark.parametrize("time_varying", [True, False], ids=["time-varying", "constant"])
@pytest.mark.parametrize("missing", [False, True], ids=["complete", "missing"])
def test_matches_numpy_oracle_and_sequential_kalman(time_varying, missing):
    """Controls, noise means, G ≠ I; NaN entries missing for the NumPy oracle, `observed` for jdrkf."""
    model, prior, ys, inputs, o = _random_problem(11, T=29, time_varying=time_varying)
    observed = None
    if missing:
        ys, observed = _missing(ys, 11)
    filt, want = _oracle(o, ys)
    res = jdrkf.ParallelKalmanFilter(outputs="all")(model, prior, ys, inputs=inputs, observed=observed)
    assert res.result == jdrkf.RESULTS.successful
    _assert_filter_close(res, filt)
    seq = jdrkf.KalmanFilter(outputs="all")(model, prior, ys, inputs=inputs, observed=observed)
    _assert_filter_close(res, seq)
    assert res.info is None and seq.info is None

    sm = jdrkf.parallel_smooth(model, prior, ys, inputs=inputs, observed=observed)
    assert sm.result == jdrkf.RESULTS.successful
    _assert_smoothed(sm, want)
    seq_sm = jdrkf.smooth(jdrkf.KalmanFilter(), model, prior, ys, inputs=inputs, observed=observed)
    for name in _SMOOTH_FIELDS:
        np.testing.assert_allclose(getattr(sm, name), getattr(seq_sm, name), rtol=1e-9, atol=1e-11, err_msg=name)
    # The same SmootherResult, field for field (the filter's outputs included).
    assert jax.tree.structure(sm) == jax.tree.structure(seq_sm)
    np.testing.assert_allclose(sm.marginal_loglik, filt["marginal_loglik"], rtol=1e-10)


def test_long_series_and_outputs_selection():
    """T = 2000 (a scan tree 11 levels deep) on a stable constant model; `outputs` as in KalmanFilter."""
    rng = np.random.default_rng(12)
    n, m, T = 3, 2, 2000
    F = 0.95 * np.linalg.qr(rng.normal(size=(n, n)))[0]
    c = rng.normal(size=(n, n))
    Q, R, H = c @ c.T / n + 0.1 * np.eye(n), np.diag([0.5, 0.2]), rng.normal(size=(m, n))
    model, prior = jdrkf.LinearModel(F, H, Q, R), jdrkf.Gaussian(np.ones(n), np.eye(n))
    ys = np.asarray(jdrkf.simulate(jax.random.key(12), model, prior, T, 1).observations[0])
    filt = numpy_kalman_filter(np.ones(n), np.eye(n), ys, F, H, Q, R)
    res = jdrkf.ParallelKalmanFilter()(model, prior, ys)
    seq = jdrkf.KalmanFilter()(model, prior, ys)
    for name in ("filtered_means", "filtered_covariances"):
        np.testing.assert_allclose(getattr(res, name), filt[name], rtol=1e-9, atol=1e-10)
    np.testing.assert_allclose(res.marginal_loglik, filt["marginal_loglik"], rtol=1e-10)
    for name in ("predicted_means", "predicted_covariances", "loglik_increments", "info"):
        assert getattr(res, name) is None and getattr(seq, name) is None
    only = jdrkf.ParallelKalmanFilter(outputs="loglik_increments")(model, prior, ys)
    assert only.filtered_means is None and only.marginal_loglik is None
    np.testing.assert_allclose(only.loglik_increments, filt["loglik_increments"], rtol=1e-9)


def test_short_series():
    model, prior, ys, inputs, o = _random_problem(13, T=1)
    filt, want = _oracle(o, ys)
    _assert_filter_close(jdrkf.ParallelKalmanFilter(outputs="all")(model, prior, ys, inputs=inputs), filt)
    _assert_smoothed(jdrkf.parallel_smooth(model, prior, ys, inputs=inputs), want)
    # T = 0: nothing to filter (the sequential filter's empty result); the smoothed x_0 is the prior.
    empty = jdrkf.LinearModel(model.F[0], model.H, model.Q, model.R)
    res = jdrkf.ParallelKalmanFilter(outputs="all")(empty, prior, np.zeros((0, 2)))
    assert res.filtered_means.shape == (0, 3) and float(res.marginal_loglik) == 0.0
    sm = jdrkf.parallel_smooth(empty, prior, np.zeros((0, 2)))
    np.testing.assert_allclose(sm.smoothed_initial_covariance, prior.cov)


def test_matches_dynamax_parallel_inference(monkeypatch):
    """dynamax's associative-scan filter and smoother on `model.to_dynamax(prior, inputs)`, whose
    states are our x_1..x_T (its `initial` is the predicted law of x_1)."""
    with warnings.catch_warnings():  # tensorflow_probability uses deprecated jax APIs
        warnings.simplefilter("ignore", DeprecationWarning)
        parallel = pytest.importorskip("dynamax.linear_gaussian_ssm.parallel_inference")
    # dynamax adds 1e-9·I to the matrices it solves with (a 1e-9 relative bias): switch it off.
    boosted = parallel.psd_solve
    monkeypatch.setattr(parallel, "psd_solve", lambda A, b, diagonal_boost=0.0: boosted(A, b, diagonal_boost))
    model, prior, ys, inputs, _ = _random_problem(14, T=25)
    params = model.to_dynamax(prior, inputs)
    post = jax.jit(parallel.lgssm_smoother)(params, jnp.asarray(ys), jnp.asarray(inputs))
    res = jdrkf.parallel_smooth(model, prior, ys, inputs=inputs)
    np.testing.assert_allclose(res.filter_result.filtered_means, post.filtered_means, rtol=1e-9, atol=1e-11)
    np.testing.assert_allclose(res.filter_result.filtered_covariances, post.filtered_covariances, rtol=1e-9, atol=1e-11)
    np.testing.assert_allclose(res.marginal_loglik, post.marginal_loglik, rtol=1e-9)
    np.testing.assert_allclose(res.smoothed_means, post.smoothed_means, rtol=1e-9, atol=1e-11)
    np.testing.assert_allclose(res.smoothed_covariances, post.smoothed_covariances, rtol=1e-9, atol=1e-11)


@pytest.mark.slow  # ~30 s
def test_jit_vmap_grad_against_finite_differences():
    model, prior, _, inputs, _ = _random_problem(15, T=20, time_varying=False)
    runs = 3
    ys_runs = jdrkf.simulate(jax.random.key(15), model, prior, 20, runs, inputs=inputs).observations
    flt = jdrkf.ParallelKalmanFilter(outputs="marginal_loglik")

    def loglik(theta, ys):  # theta scales F and the measurement noise
        mdl = eqx.tree_at(lambda m: (m.F, m.R), model, (theta[0] * model.F, theta[1] * model.R))
        return flt(mdl, prior, ys, inputs=inputs).marginal_loglik

    theta = jnp.array([0.95, 1.3])
    grads = jax.jit(jax.vmap(jax.grad(loglik), in_axes=(None, 0)))(theta, ys_runs)
    one = jax.jit(loglik)
    seq = jax.vmap(lambda y: jdrkf.KalmanFilter()(model, prior, y, inputs=inputs).marginal_loglik)
    np.testing.assert_allclose(jax.vmap(one, in_axes=(None, 0))(jnp.ones(2), ys_runs), seq(ys_runs), rtol=1e-10)
    h = 1e-6
    for b in range(runs):
        for i in range(2):
            e = jnp.zeros(2).at[i].set(h)
            fd = (one(theta + e, ys_runs[b]) - one(theta - e, ys_runs[b])) / (2 * h)
            assert abs(float(fd)) > 1e-2
            np.testing.assert_allclose(grads[b, i], fd, rtol=1e-6)


B_RUNS, T_SHARED = 11, 16


def _lu_shapes(jaxpr, found=None):
    """Operand shapes of every LU factorization in a (closed) jaxpr, nested ones included."""
    found = [] if found is None else found
    for eqn in getattr(jaxpr, "jaxpr", jaxpr).eqns:
        if eqn.primitive.name == "lu":
            found.append(tuple(eqn.invars[0].aval.shape))
        for sub in jax.extend.core.jaxprs_in_params(eqn.params):
            _lu_shapes(sub, found)
    return found


def test_vmap_shares_the_covariance_path():
    """Under `vmap` over runs, the scan's `I + C_i J_j` factorizations are traced once for all
    runs; a per-run mask makes them per run."""
    model, prior, _, _, _ = _random_problem(16, T=T_SHARED, time_varying=False)
    model = jdrkf.LinearModel(model.F, model.H, model.Q, model.R)
    ys = jdrkf.simulate(jax.random.key(16), model, prior, T_SHARED, B_RUNS).observations
    flt = jdrkf.ParallelKalmanFilter()
    shapes = _lu_shapes(jax.make_jaxpr(jax.vmap(lambda y: flt(model, prior, y)))(ys))
    assert shapes and all(B_RUNS not in s for s in shapes), shapes
    mask = np.ones(ys.shape, bool)
    mask[0, 2, 0] = False
    per_run = _lu_shapes(jax.make_jaxpr(jax.vmap(lambda y, o: flt(model, prior, y, observed=o)))(ys, mask))
    assert per_run and all(s[0] == B_RUNS for s in per_run), per_run


def test_result_codes_match_the_sequential_filter():
    model, prior, ys, inputs, _ = _random_problem(17, T=9, time_varying=False)
    run = lambda flt, mdl, y: flt(mdl, prior, y, inputs=inputs)
    # A traced indefinite R (checked eagerly when concrete): the innovation covariance fails.
    bad = eqx.tree_at(lambda m: m.R, model, -model.R)
    for flt in (jdrkf.ParallelKalmanFilter(throw=False), jdrkf.KalmanFilter(throw=False)):
        res = jax.jit(run, static_argnums=0)(flt, bad, ys)
        assert res.result == jdrkf.RESULTS.nonpositive_innovation
        # A NaN that the filter is told to use: only detectable in traced data.
        nan = jax.jit(run, static_argnums=0)(flt, model, jnp.asarray(ys).at[4, 1].set(jnp.nan))
        assert nan.result == jdrkf.RESULTS.nan_observation
        inf = run(flt, model, jnp.asarray(ys).at[4, 1].set(jnp.inf))
        assert inf.result == jdrkf.RESULTS.nonfinite_state
    with pytest.raises(Exception, match="H P Hᵀ \\+ R was not numerically positive definite"):
        jax.jit(run, static_argnums=0)(jdrkf.ParallelKalmanFilter(), bad, ys)
    with pytest.raises(ValueError, match=r"ys\[4, 1\] is NaN"):
        run(jdrkf.ParallelKalmanFilter(), model, _with_nan(ys))
    with pytest.raises(ValueError, match="ys has shape"):
        run(jdrkf.ParallelKalmanFilter(), model, ys[:, :1])
    with pytest.raises(ValueError, match="model must be a jdrkf.LinearModel"):
        jdrkf.parallel_smooth("model", prior, ys)


def _with_nan(ys):
    ys = np.array(ys)
    ys[4, 1] = np.nan
    return ys


def test_smoother_result_codes():
    # F = 0 and Q = 0 make the predicted covariance of x_2 zero: no smoother gain exists.
    model = jdrkf.LinearModel([[0.0]], [[1.0]], [[0.0]], [[1.0]])
    prior = jdrkf.Gaussian(np.zeros(1), np.eye(1))
    ys = np.ones((4, 1))
    res = jdrkf.parallel_smooth(model, prior, ys, throw=False)
    assert res.filter_result.result == jdrkf.RESULTS.successful
    assert res.result == jdrkf.RESULTS.nonpositive_predicted_covariance
    with pytest.raises(Exception, match="not numerically positive"):
        jdrkf.parallel_smooth(model, prior, ys)
    bad = jdrkf.parallel_smooth(model, prior, jnp.full((4, 1), jnp.inf), throw=False)
    assert bad.result == jdrkf.RESULTS.nonfinite_state


def test_is_a_filter_for_every_consumer():
    """`init`/`step` are the Kalman filter's; `jdrkf.smooth` runs it with the sequential backward pass."""
    model, prior, ys, inputs, o = _random_problem(18, T=8)
    filt, want = _oracle(o, ys)
    flt = jdrkf.ParallelKalmanFilter()
    _, out = flt.step(model, flt.init(model, prior), jnp.asarray(ys[0]), 0, jnp.asarray(inputs[0]))
    np.testing.assert_allclose(out.filtered.mean, filt["filtered_means"][0], rtol=1e-10)
    np.testing.assert_allclose(out.loglik, filt["loglik_increments"][0], rtol=1e-10)
    _assert_smoothed(jdrkf.smooth(flt, model, prior, ys, inputs=inputs), want)
