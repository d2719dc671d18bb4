"""Tests of the distributionally robust particle filter (Wang 2022, Algorithm 2, Methods 1–7).

Oracles: `BootstrapPF` (a separate implementation) for the reductions; NumPy/SciPy
re-implementations of Theorems 5 and 6 (`brentq` on the scalar dual) for Methods 1 and 5;
the small-radius closed form of Theorem 3 (a Laplace-type kernel around the nearest
likelihood particle) for Method 4; least squares on the log-weights for Method 7.
"""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.optimize import brentq
from scipy.special import logsumexp as np_lse

from jdrkf._gaussian import Gaussian
from jdrkf._noise import MixtureNoise
from jdrkf._nonlinear import NonlinearModel, _simulate_nonlinear
from jdrkf.filters._dr_particle import DRParticleFilter, DropOutliers, NearestOutliers
from jdrkf.filters._particle import BootstrapPF
from jdrkf.sets import (
    AugmentedWassersteinLikelihood,
    InflatedLikelihood,
    ParticleKL,
    ParticleWasserstein,
    ParticleWassersteinSample,
    WassersteinLikelihood,
)
from jdrkf.sets._particle import _augmented_loglik, _continuous_loglik

T = 15


def _f(x, t):
    return x / 2 + 25 * x / (1 + x**2) + 8 * jnp.cos(1.2 * (t + 1).astype(x.dtype))


def _h(x, t):
    return x**2 / 20


def _growth(r=1.0, measurement_noise=None):
    """The paper's univariate growth model (Sec. V), additive noise."""
    return NonlinearModel(_f, _h, jnp.eye(1) * 10.0, jnp.eye(1) * r, measurement_noise=measurement_noise)


def _nonadditive():
    """Growth dynamics with a heteroscedastic, non-additive measurement y = x²/20 · (1 + v/4) + v."""
    return NonlinearModel(
        lambda x, w, t: _f(x, t) + w,
        lambda x, v, t: x**2 / 20 * (1 + v / 4) + v,
        jnp.eye(1) * 10.0,
        jnp.eye(1),
        additive=False,
        state_dim=1,
        obs_dim=1,
    )


PRIOR = Gaussian(jnp.zeros(1), jnp.eye(1))


@pytest.fixture(scope="module")
def data():
    tr = _simulate_nonlinear(jax.random.key(7), _growth(), PRIOR, T, 3)
    return tr.observations, tr.states


@eqx.filter_jit
def _run(flt, model, ys, key, observed=None):
    return flt(model, PRIOR, ys, key, observed=observed)


# ------------------------------------------------------------------- reductions


@pytest.mark.parametrize(
    "resampling,ess,estimate",
    [("systematic", 0.5, "weighted_mean"), pytest.param("multinomial", 1.0, "resampled_mean", marks=pytest.mark.slow)],
)
def test_reduces_to_bootstrap(data, resampling, ess, estimate):
    """No prior, θ = 1, no outlier treatment: bitwise BootstrapPF with the same key
    (the second case is the authors' resampling scheme and estimate)."""
    ys = data[0][0]
    key = jax.random.key(3)
    opts = dict(resampling=resampling, ess_threshold=ess, estimate=estimate)
    ref = _run(BootstrapPF(100, **opts, outputs="all"), _growth(), ys, key)
    out = _run(DRParticleFilter(100, likelihood=InflatedLikelihood(1.0), **opts, outputs="all"), _growth(), ys, key)
    for a, b in [
        (ref.filtered_means, out.filtered_means),
        (ref.filtered_covariances, out.filtered_covariances),
        (ref.predicted_means, out.predicted_means),
        (ref.loglik_increments, out.loglik_increments),
        (ref.info["ess"], out.info["ess"]),
    ]:
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    assert not np.any(np.asarray(out.info["outlier"]))


def test_inflation_equals_pf_with_inflated_noise(data):
    """Method 3: θ on the nominal law = BootstrapPF on the model with covariance θR (same
    key); for Gaussian noise and for a Gaussian mixture law (both components scaled)."""
    ys, theta = data[0][1], 5.0
    key = jax.random.key(11)
    out = _run(DRParticleFilter(100, likelihood=InflatedLikelihood(theta), outputs="all"), _growth(), ys, key)
    ref = _run(BootstrapPF(100, outputs="all"), _growth(r=theta), ys, key)
    np.testing.assert_allclose(out.filtered_means, ref.filtered_means, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(out.loglik_increments, ref.loglik_increments, rtol=1e-10)
    mix = lambda s: MixtureNoise(s * jnp.eye(1), 0.1, 10.0)  # noqa: E731
    out = _run(DRParticleFilter(100, likelihood=InflatedLikelihood(theta), outputs="all"), _growth(measurement_noise=mix(1.0)), ys, key)
    ref = _run(BootstrapPF(100, outputs="all"), _growth(measurement_noise=mix(theta)), ys, key)
    np.testing.assert_allclose(out.filtered_means, ref.filtered_means, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(out.loglik_increments, ref.loglik_increments, rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize("prior", [ParticleKL, ParticleWasserstein], ids=["kl", "wasserstein"])
def test_zero_radius_prior_is_bootstrap(data, prior):
    ys = data[0][0]
    key = jax.random.key(5)
    ref = _run(BootstrapPF(100, outputs="all"), _growth(), ys, key)  # compiled already by test_reduces_to_bootstrap
    out = _run(DRParticleFilter(100, prior=prior(0.0), likelihood=InflatedLikelihood(1.0), outputs="all"), _growth(), ys, key)
    np.testing.assert_allclose(out.filtered_means, ref.filtered_means, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(out.loglik_increments, ref.loglik_increments, rtol=1e-9, atol=1e-9)


# ------------------------------------------------------------- Methods 1 and 2


def _np_kl_maxent(q, radius):
    """Theorem 6 oracle: p ∝ q^β with KL(p_β‖q) = radius (uniform if radius ≥ KL(u‖q))."""
    lq = np.log(q)

    def kl(beta):
        lp = beta * lq - np_lse(beta * lq)
        return float(np.sum(np.exp(lp) * (lp - lq)))

    if radius >= kl(0.0):
        return np.full_like(q, 1.0 / q.size)
    beta = brentq(lambda b: kl(b) - radius, 0.0, 1.0, xtol=1e-15, rtol=1e-15)
    return np.exp(beta * lq - np_lse(beta * lq))


def _np_transport_maxent(q, cost, radius):
    """Theorem 5 oracle: P_ij = q_i softmax_j(−v₀ c_ij), v₀ = 0 or the root of Σ c P = radius."""

    def coupling(v0):
        z = -v0 * cost
        return q[:, None] * np.exp(z - np_lse(z, axis=1, keepdims=True))

    def transport(log_v0):
        return float(np.sum(cost * coupling(np.exp(log_v0))))

    if radius >= float(np.sum(cost * coupling(0.0))):
        return coupling(0.0)
    lv = brentq(lambda u: transport(u) - radius, -30.0, 12.0, xtol=1e-14, rtol=1e-15)
    return coupling(np.exp(lv))


@pytest.mark.parametrize("prior", ["kl", "wasserstein"])
def test_method1_prior_weights_match_oracle(data, prior):
    """Step 2 at every step: the worst-case prior weights are the Theorem-6 (KL) resp.
    Theorem-5 (Wasserstein, support = the propagated particles) max-entropy weights of
    the previous posterior weights (no resampling, so those are not uniform)."""
    ys = data[0][0][:8]
    radius = 0.05 if prior == "kl" else 0.3
    make = ParticleKL if prior == "kl" else ParticleWasserstein
    flt = DRParticleFilter(40, prior=make(radius), likelihood=InflatedLikelihood(1.0), ess_threshold=0.0, return_particles=True, outputs="all")
    out = _run(flt, _growth(), ys, jax.random.key(2))
    prev = np.exp(np.asarray(out.info["log_weights"]))
    got = np.exp(np.asarray(out.info["prior_log_weights"]))
    x = np.asarray(out.info["particles"])[..., 0]
    active = 0
    for t in range(1, ys.shape[0]):
        q = prev[t - 1] / prev[t - 1].sum()
        if prior == "kl":
            want = _np_kl_maxent(q, radius)
            active += radius < float(np.sum(np.log(1 / q.size / q)) / q.size)
        else:
            cost = np.abs(x[t][:, None] - x[t][None, :])
            want = _np_transport_maxent(q, cost, radius).sum(axis=0)
            active += radius < float(np.sum(cost * q[:, None]) / q.size)
        np.testing.assert_allclose(got[t], want, rtol=1e-7, atol=1e-12)
    assert active >= 3  # the constraint binds at several steps, so the test can fail


def test_method2_samples(getkey):
    """Method 2: N particles with weights 1/N; the cell (nearest atom, radius ≪ spacing)
    of the samples follows q (chi-square over 200 draws)."""
    q = np.array([0.4, 0.3, 0.15, 0.1, 0.05])
    atoms = jnp.asarray(np.arange(5.0)[:, None] * 1.0)
    flt = DRParticleFilter(5, prior=ParticleWassersteinSample(0.02, num_integration_points=300))
    draw = jax.jit(lambda k: flt._worst_case_prior(atoms, jnp.log(jnp.asarray(q)), k))
    counts = np.zeros(5)
    for _ in range(40):
        x, lw = draw(getkey())
        np.testing.assert_allclose(np.exp(np.asarray(lw)), 0.2, rtol=1e-12)
        x = np.asarray(x)[:, 0]
        dist = np.abs(x[:, None] - np.arange(5.0)[None, :])
        assert dist.min(axis=1).max() < 0.4
        counts += np.bincount(dist.argmin(axis=1), minlength=5)
    chi2 = np.sum((counts - 200 * q) ** 2 / (200 * q))
    assert chi2 < 18.5  # 4 dof, p ≈ 0.001


@pytest.mark.slow
def test_method2_filter_runs(data):
    flt = DRParticleFilter(30, prior=ParticleWassersteinSample(0.5, num_integration_points=300), return_particles=True, outputs="all")
    out = _run(flt, _growth(), data[0][0][:4], jax.random.key(0))
    assert np.all(np.isfinite(out.filtered_means))
    np.testing.assert_allclose(np.exp(np.asarray(out.info["prior_log_weights"])), 1 / 30, rtol=1e-12)
    assert out.info["particles"].shape == (4, 30, 1)


# ------------------------------------------------------------- Methods 4 and 5


def _np_augmented(ys, y, radius):
    ys = np.asarray(ys)
    support = np.concatenate([np.asarray(y)[None], ys])
    cost = np.linalg.norm(ys[:, None, :] - support[None, :, :], axis=-1)
    q = np.full(ys.shape[0], 1.0 / ys.shape[0])
    return np.log(_np_transport_maxent(q, cost, radius).sum(axis=0)[0])


@pytest.mark.parametrize("radius", [0.02, 0.2, 1.0, 50.0])
def test_method5_likelihood_matches_oracle(radius):
    """Method 5 per particle vs a NumPy Theorem-5 solve on the augmented support; the
    largest radius exceeds C(0), so every row is uniform and p*(y) = 1/(R+1)."""
    rng = np.random.default_rng(int(radius * 100))
    ys = rng.normal(size=(8, 2))
    y = rng.normal(size=2) * 1.5
    got = float(jax.jit(_augmented_loglik)(jnp.asarray(ys), jnp.asarray(y), jnp.asarray(radius)))
    np.testing.assert_allclose(got, _np_augmented(ys, y, radius), rtol=1e-8)
    if radius == 50.0:
        np.testing.assert_allclose(got, -math.log(9), rtol=1e-12)


def test_method5_likelihood_decreases_with_distance():
    """Small radius: p*(y) of a particle falls with the distance of y to its likelihood
    particles (a kernel-like likelihood)."""
    ys = jnp.asarray(np.random.default_rng(1).normal(size=(20, 1)))
    f = jax.jit(lambda y: _augmented_loglik(ys, y, jnp.asarray(0.05)))
    vals = [float(f(jnp.asarray([c]))) for c in (0.0, 2.0, 4.0, 8.0)]
    assert all(a > b for a, b in zip(vals, vals[1:], strict=False))


@pytest.mark.parametrize("dim", [1, pytest.param(2, marks=pytest.mark.slow)])
def test_method4_small_radius_kernel_limit(dim):
    """Theorem 3 as θ → 0: around each atom the worst case is (1/R)·b^d e^{−bρ}/(Γ(d) S_{d−1})
    with b = d/θ (mass q_r = 1/R, mean transport distance d/b = θ), ρ the distance to the
    nearest likelihood particle. Checked at three distances (level and slope), averaged over
    the Monte Carlo points of 4 keys; tolerance 0.2 nats (MC error + the solver's smoothing)."""
    theta, num = 0.05, 5
    ys = jnp.asarray(np.random.default_rng(0).normal(size=(num, dim)) * 5.0)
    b = dim / theta
    log_sphere = math.log(2) + 0.5 * dim * math.log(math.pi) - math.lgamma(0.5 * dim)
    f = jax.jit(lambda y, k: _continuous_loglik(ys, y, jnp.asarray(theta), k, 2000))
    for off in (0.0, 0.5 * theta, 2 * theta):
        y = ys[2] + off / math.sqrt(dim)
        got = np.mean([float(f(y, jax.random.key(i))) for i in range(4)])
        want = -math.log(num) + dim * math.log(b) - b * off - math.lgamma(dim) - log_sphere
        assert abs(got - want) < 0.2, (off, got, want)


@pytest.mark.parametrize("likelihood", [pytest.param("wasserstein", marks=pytest.mark.slow), "wasserstein_augmented"])
def test_methods45_nonadditive_run(likelihood):
    model = _nonadditive()
    tr = _simulate_nonlinear(jax.random.key(4), model, PRIOR, 5, 1)
    def make(radius):
        if likelihood == "wasserstein":
            return WassersteinLikelihood(radius, num_particles=8, num_integration_points=200)
        return AugmentedWassersteinLikelihood(radius, num_particles=8)

    flt = DRParticleFilter(20, likelihood=make(0.3), outputs="all")
    ys = tr.observations[0].at[2].set(jnp.nan)  # a missing y (masked): no update, loglik 0
    out = _run(flt, model, ys, jax.random.key(1), ~jnp.isnan(ys))
    assert np.all(np.isfinite(out.filtered_means)) and np.all(np.isfinite(out.loglik_increments))
    np.testing.assert_allclose(out.filtered_means[2], out.predicted_means[2], rtol=1e-12)
    assert float(out.loglik_increments[2]) == 0.0
    assert not np.allclose(out.filtered_means, out.predicted_means)  # the likelihood does move the cloud
    # A radius beyond C(0) makes the Method-5 likelihood flat: posterior = prior weights.
    if likelihood == "wasserstein_augmented":
        flat = DRParticleFilter(20, likelihood=make(1e6), outputs="all")
        out = _run(flat, model, tr.observations[0], jax.random.key(1))
        np.testing.assert_allclose(out.filtered_means, out.predicted_means, rtol=1e-10, atol=1e-10)
        np.testing.assert_allclose(out.loglik_increments, -math.log(9), rtol=1e-10)


def test_inflate_needs_additive_model():
    model = _nonadditive()
    with pytest.raises(ValueError, match="additive"):
        DRParticleFilter(10)(model, PRIOR, jnp.zeros((3, 1)), jax.random.key(0))


# ------------------------------------------------------------- Methods 6 and 7


def test_outlier_drop(data):
    ys, theta = data[0][0], 5.0
    key = jax.random.key(9)
    base = _run(DRParticleFilter(100, likelihood=InflatedLikelihood(theta), outputs="all"), _growth(), ys, key)
    gated = _run(DRParticleFilter(100, likelihood=InflatedLikelihood(theta), outlier=DropOutliers(), outputs="all"), _growth(), ys, key)
    for a, b in [(base.filtered_means, gated.filtered_means), (base.loglik_increments, gated.loglik_increments)]:
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))  # no outlier: identical
    assert not np.any(np.asarray(gated.info["outlier"]))
    bad = ys.at[7, 0].set(1e3)
    out = _run(DRParticleFilter(100, likelihood=InflatedLikelihood(theta), outlier=DropOutliers(), outputs="all"), _growth(), bad, key)
    flags = np.asarray(out.info["outlier"])
    assert flags[7] and flags.sum() == 1
    np.testing.assert_allclose(out.filtered_means[7], out.predicted_means[7], rtol=1e-12)
    assert float(out.loglik_increments[7]) == 0.0
    np.testing.assert_array_equal(np.asarray(out.filtered_means[:7]), np.asarray(base.filtered_means[:7]))


def test_outlier_nearest(data):
    """Method 7 (nearest): y = 1e3 is replaced by a likelihood particle y' of the most
    likely prior particle x*; y' is recovered from the log-weights by least squares
    (log w_j − log q_j = c + y' h_j/(θR) − h_j²/(2θR)) and must be the largest of R draws
    h(x*) + v^r, i.e. a little above h(x*), not 1e3."""
    ys, theta = data[0][0], 5.0
    bad = ys.at[7, 0].set(1e3)
    flt = DRParticleFilter(80, likelihood=InflatedLikelihood(theta), outlier=NearestOutliers(), ess_threshold=0.0, return_particles=True, outputs="all")
    out = _run(flt, _growth(), bad, jax.random.key(9))
    flags = np.asarray(out.info["outlier"])
    assert flags[7] and flags.sum() == 1
    x = np.asarray(out.info["particles"][7, :, 0])
    hx = x**2 / 20
    z = np.asarray(out.info["log_weights"][7] - out.info["prior_log_weights"][7]) + hx**2 / (2 * theta)
    slope = np.polyfit(hx, z, 1)[0]
    y_new = slope * theta
    excess = y_new - hx.max()  # x* has the largest h(x) when y is far above every h(x)
    assert 0.0 < excess < 5.0 * math.sqrt(1.0), excess
    assert np.all(np.isfinite(out.filtered_means))


# ------------------------------------------------------------- gradients, jit, vmap


def _rtamse(flt, model, ys, xs, key):
    out = flt(model, PRIOR, ys, key)
    return jnp.sqrt(jnp.mean((out.filtered_means - xs) ** 2))


@pytest.mark.parametrize(
    "field,make,value",
    [
        ("inflation", lambda v: dict(likelihood=InflatedLikelihood(v)), 3.0),
        ("prior radius", lambda v: dict(prior=ParticleKL(v), likelihood=InflatedLikelihood(2.0)), 0.05),
        pytest.param(
            "likelihood radius",
            lambda v: dict(likelihood=AugmentedWassersteinLikelihood(v, num_particles=10)),
            0.3,
            marks=pytest.mark.slow,
        ),
    ],
)
def test_gradient_matches_finite_differences(data, field, make, value):
    """Without resampling (ess_threshold=0) the filter is smooth in its radii for a fixed
    key: reverse-mode gradient = central differences. (With resampling the ancestor
    indices carry no gradient, so the gradient ignores their dependence on θ: biased.)"""
    ys, xs = data[0][0][:10], data[1][0][:10]
    key = jax.random.key(4)

    def loss(v):
        flt = DRParticleFilter(30, ess_threshold=0.0, **make(v))
        return _rtamse(flt, _growth(), ys, xs, key)

    vg = jax.jit(jax.value_and_grad(loss))  # one compilation for the gradient and both FD points
    v = jnp.asarray(value)
    g = float(vg(v)[1])
    eps = 1e-5 * value
    fd = (float(vg(v + eps)[0]) - float(vg(v - eps)[0])) / (2 * eps)
    assert abs(g) > 1e-6
    np.testing.assert_allclose(g, fd, rtol=1e-6 if field == "inflation" else 1e-5)


@pytest.mark.parametrize(
    "likelihood",
    [InflatedLikelihood(), pytest.param(AugmentedWassersteinLikelihood(num_particles=10), marks=pytest.mark.slow)],
    ids=["inflated", "wasserstein_augmented"],
)
def test_vmap_over_runs_and_keys(data, likelihood):
    ys = data[0]
    keys = jax.random.split(jax.random.key(8), ys.shape[0])
    flt = DRParticleFilter(40, likelihood=likelihood)
    batch = jax.jit(jax.vmap(flt, in_axes=(None, None, 0, 0)))(_growth(), PRIOR, ys, keys)
    for i in range(ys.shape[0]):
        one = _run(flt, _growth(), ys[i], keys[i])
        np.testing.assert_allclose(batch.filtered_means[i], one.filtered_means, rtol=1e-10, atol=1e-10)


def test_missing_observation_keeps_weights(data):
    """An all-NaN y, masked by `observed`: no update (posterior = prior), loglik increment 0, not an outlier.
    (Same configuration as `test_outlier_drop`.)"""
    ys = data[0][0].at[3].set(jnp.nan)
    out = _run(DRParticleFilter(100, likelihood=InflatedLikelihood(5.0), outlier=DropOutliers(), outputs="all"), _growth(), ys, jax.random.key(1), ~jnp.isnan(ys))
    np.testing.assert_allclose(out.filtered_means[3], out.predicted_means[3], rtol=1e-12)
    assert float(out.loglik_increments[3]) == 0.0 and not bool(out.info["outlier"][3])


def test_bad_arguments():
    for kwargs, match in [
        (dict(num_particles=0), "num_particles"),
        (dict(prior=ParticleKL), "prior"),
        (dict(likelihood=ParticleKL(0.1)), "likelihood"),
        (dict(outlier=1e-6), "outlier"),
        (dict(resampling="foo"), "resampling"),
        (dict(ess_threshold=1.5), "ess_threshold"),
        (dict(estimate="median"), "estimate"),
    ]:
        n = kwargs.pop("num_particles", 10)
        with pytest.raises(ValueError, match=match):
            DRParticleFilter(n, **kwargs)
    flt = DRParticleFilter(10)
    with pytest.raises(ValueError, match="key"):
        flt(_growth(), PRIOR, jnp.zeros((3, 1)))
    with pytest.raises(ValueError, match="NonlinearModel"):
        flt(object(), PRIOR, jnp.zeros((3, 1)), jax.random.key(0))
    with pytest.raises(ValueError, match="ys"):
        flt(_growth(), PRIOR, jnp.zeros((3, 2)), jax.random.key(0))
