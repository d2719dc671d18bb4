"""Gradients of particle filters through resampling (stop-gradient resampling of
Ścibior & Wood 2021, `resampling_gradient="score"`).

Oracle: the Kalman filter on a scalar linear-Gaussian model, whose log-likelihood
gradient `∇ log p(y_{1:T}; θ)` (by `jax.grad`, cross-checked by central finite
differences) is exact. The likelihood estimate `p̂` of a bootstrap PF is unbiased and,
with the score correction, so is `∇ p̂` for `∇ p`; since `∇ p̂ = p̂ ∇ log p̂`, the
per-run statistic `s = (p̂ / p) ∇ log p̂` has mean `∇ log p` exactly. Its average over
many keys is compared with the Kalman filter's within 4 Monte Carlo standard errors;
the previous estimator (`"ignore"`) fails the same comparison by many standard errors.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jdrkf
from jdrkf._nonlinear import NonlinearModel
from jdrkf.experiments.wang_nonlinear import growth_f, growth_h
from jdrkf.filters._dr_particle import DRParticleFilter, DropOutliers
from jdrkf.filters._particle import BootstrapPF
from jdrkf.sets import InflatedLikelihood, ParticleKL

T, N, RUNS = 5, 32, 2000
THETA0 = np.array([0.8, 0.5, 0.3])  # (a, q, r): x_k = a x_{k-1} + w, w ~ N(0, q); y_k = x_k + v, v ~ N(0, r)
PRIOR = jdrkf.Gaussian(jnp.zeros(1), jnp.eye(1))


@pytest.fixture(scope="module")
def ys():
    rng = np.random.default_rng(0)
    x, out = rng.normal(), []
    for _ in range(T):
        x = THETA0[0] * x + np.sqrt(THETA0[1]) * rng.normal()
        out.append([x + np.sqrt(THETA0[2]) * rng.normal()])
    return jnp.asarray(out)


def _linear(th, r_scale=1.0):
    return jdrkf.LinearModel(F=th[0] * jnp.eye(1), H=jnp.eye(1), Q=th[1] * jnp.eye(1), R=r_scale * th[2] * jnp.eye(1))


def _nonlinear(th):
    return NonlinearModel(lambda x, t: th[0] * x, lambda x, t: x, th[1] * jnp.eye(1), th[2] * jnp.eye(1))


def _kf_loglik(th, ys, r_scale=1.0):
    return jdrkf.KalmanFilter()(_linear(th, r_scale), PRIOR, ys).marginal_loglik


def _kf_score(ys, r_scale=1.0):
    """`(log p, ∇ log p)` at `THETA0` by `jax.grad`, checked against central differences."""
    th = jnp.asarray(THETA0)
    f = jax.jit(lambda th: _kf_loglik(th, ys, r_scale))
    ll, g = float(f(th)), np.asarray(jax.grad(f)(th))
    h = 1e-6
    fd = np.array([(float(f(th + h * e)) - float(f(th - h * e))) / (2 * h) for e in np.eye(3)])
    np.testing.assert_allclose(g, fd, rtol=1e-6)
    return ll, g


def _z_scores(values, grads, ll, exact):
    """`(mean(s) − ∇ log p) / SE` with `s_r = exp(ℓ̂_r − log p) ∇ℓ̂_r`, and the z-score of
    `mean(p̂ / p)` against 1."""
    ratio = np.exp(np.asarray(values) - ll)
    s = ratio[:, None] * np.asarray(grads)
    se = s.std(axis=0, ddof=1) / np.sqrt(s.shape[0])
    z_lik = (ratio.mean() - 1.0) / (ratio.std(ddof=1) / np.sqrt(ratio.size))
    return (s.mean(axis=0) - exact) / se, z_lik


def _pf_runs(make_filter, ys, runs=RUNS):
    """`(marginal_loglik, ∇_θ marginal_loglik)` of `runs` independent keys (vmapped)."""

    def one(th, key):
        return make_filter()(_nonlinear(th), PRIOR, ys, key).marginal_loglik

    keys = jax.random.split(jax.random.key(1), runs)
    return jax.jit(jax.vmap(jax.value_and_grad(one), in_axes=(None, 0)))(jnp.asarray(THETA0), keys)


def test_bootstrap_likelihood_gradient_unbiased(ys):
    """`∇ p̂` averages to `∇ p` (KF) with the score correction; without it the same check
    fails by many standard errors (the gradient of the model parameters is then biased)."""
    ll, exact = _kf_score(ys)
    z = {}
    for mode in ("score", "ignore"):
        v, g = _pf_runs(lambda mode=mode: BootstrapPF(N, ess_threshold=1.0, resampling_gradient=mode, throw=False), ys)
        z[mode], z_lik = _z_scores(v, g, ll, exact)
        assert abs(z_lik) < 4  # p̂ itself is unbiased (the forward pass is the same in both modes)
    assert np.all(np.abs(z["score"]) < 4), z["score"]
    assert np.max(np.abs(z["ignore"])) > 10, z["ignore"]


def test_dr_particle_theta_gradient_unbiased(ys):
    """`DRParticleFilter(likelihood=InflatedLikelihood(θ))` (no prior) is a bootstrap PF of the model
    with `R → θR`: its `∇ p̂` w.r.t. the model and `θ` averages to the KF's gradient of
    `p(y; θR)` (multinomial resampling at every step)."""
    theta = 1.5
    ll, exact = _kf_score(ys, r_scale=theta)
    f = jax.jit(lambda th: _kf_loglik(th[:3], ys, th[3]))
    exact_theta = float(jax.grad(f)(jnp.asarray([*THETA0, theta]))[3])
    h = 1e-6
    fd = (float(f(jnp.asarray([*THETA0, theta + h]))) - float(f(jnp.asarray([*THETA0, theta - h])))) / (2 * h)
    np.testing.assert_allclose(exact_theta, fd, rtol=1e-6)

    def one(p, key):
        flt = DRParticleFilter(N, likelihood=InflatedLikelihood(p[3]), resampling="multinomial", ess_threshold=1.0, throw=False)
        return flt(_nonlinear(p[:3]), PRIOR, ys, key).marginal_loglik

    keys = jax.random.split(jax.random.key(2), RUNS)
    v, g = jax.jit(jax.vmap(jax.value_and_grad(one), in_axes=(None, 0)))(jnp.asarray([*THETA0, theta]), keys)
    z, z_lik = _z_scores(v, g, ll, np.append(exact, exact_theta))
    assert abs(z_lik) < 4
    assert np.all(np.abs(z) < 4), z


@pytest.mark.slow
@pytest.mark.parametrize("scheme", ["multinomial", "stratified", "residual"])
def test_bootstrap_likelihood_gradient_unbiased_schemes(ys, scheme):
    """Every scheme copies particle `i` `N w̄_i` times on average, which is all the
    correction needs (adaptive resampling, `ess_threshold=0.7`, as well)."""
    ll, exact = _kf_score(ys)
    for threshold in (1.0, 0.7):
        v, g = _pf_runs(lambda c=threshold: BootstrapPF(N, resampling=scheme, ess_threshold=c, throw=False), ys, runs=8000)
        z, z_lik = _z_scores(v, g, ll, exact)
        assert abs(z_lik) < 4 and np.all(np.abs(z) < 4), (scheme, threshold, z, z_lik)


# ------------------------------------------------------------------- forward pass unchanged


def _growth():
    return NonlinearModel(growth_f, growth_h, jnp.eye(1) * 10.0, jnp.eye(1))


@pytest.mark.parametrize(
    "make",
    [
        lambda mode: BootstrapPF(64, ess_threshold=0.5, resampling_gradient=mode, return_particles=True, outputs="all"),
        lambda mode: DRParticleFilter(64, prior=ParticleKL(0.05), likelihood=InflatedLikelihood(2.0), outlier=DropOutliers(),
                                      resampling="multinomial", ess_threshold=1.0, estimate="resampled_mean",
                                      resampling_gradient=mode, return_particles=True, outputs="all"),
    ],
    ids=["bootstrap", "dr-kl"],
)
def test_forward_values_bitwise_unchanged(make):
    """The score correction adds an exact zero to the resampled log-weights: every output
    (means, covariances, log-likelihoods, ESS, the weights of every step) is bitwise that
    of the uncorrected filter (the previous implementation) with the same key."""
    model, key = _growth(), jax.random.key(5)
    rng = np.random.default_rng(3)
    ys = jnp.asarray(rng.normal(size=(25, 1)) * 5.0)
    run = eqx.filter_jit(lambda flt, model: flt(model, PRIOR, ys, key))
    new, old = run(make("score"), model), run(make("ignore"), model)
    assert np.asarray(new.info["resampled"]).any()
    for a, b in zip(jax.tree.leaves(new), jax.tree.leaves(old), strict=True):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def test_bad_resampling_gradient():
    with pytest.raises(ValueError, match="resampling_gradient"):
        BootstrapPF(10, resampling_gradient="unbiased")
    with pytest.raises(ValueError, match="resampling_gradient"):
        DRParticleFilter(10, resampling_gradient=None)
