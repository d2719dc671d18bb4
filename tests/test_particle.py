"""Bootstrap particle filter and resampling schemes (Wang 2022; docs/math/particle.md).

Oracles: closed-form count bounds and moments of the schemes; the Kalman filter on
the matching linear-Gaussian model (large N, tolerances from the Monte Carlo error);
a separate NumPy bootstrap PF fed with the same random numbers (the documented key
schedule of `BootstrapPF`).
"""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jdrkf
from jdrkf._nonlinear import NonlinearModel
from jdrkf.experiments.wang_nonlinear import growth_f, growth_h
from jdrkf.filters import _resampling as rs
from jdrkf.filters._particle import BootstrapPF

SCHEMES = ["multinomial", "systematic", "stratified", "residual"]


def _counts(idx, n):
    return np.bincount(np.asarray(idx), minlength=n)


@pytest.fixture(scope="module")
def batched_counts():
    """Counts of every scheme over 4000 keys for one fixed weight vector (vmap is safe:
    resampling involves no LAPACK call)."""
    n = 8
    w = np.array([0.31, 0.005, 0.12, 0.0, 0.2, 0.075, 0.19, 0.1])
    lw = jnp.log(jnp.asarray(w))
    keys = jax.random.split(jax.random.key(3), 4000)
    out = {}
    for name in SCHEMES:
        idx = jax.jit(jax.vmap(rs.RESAMPLERS[name], in_axes=(0, None)))(keys, lw)
        idx = np.asarray(idx)
        out[name] = np.stack([np.bincount(row, minlength=n) for row in idx])
    return w, out


def test_uniform_systematic_each_index_once(getkey):
    n = 37
    for _ in range(5):
        idx = rs.systematic(getkey(), jnp.zeros(n))
        np.testing.assert_array_equal(np.asarray(idx), np.arange(n))
        assert idx.dtype == jnp.int32


@pytest.mark.parametrize("name", SCHEMES)
def test_one_hot_weights(name, getkey):
    n = 11
    for j in (0, 5, n - 1):
        lw = jnp.full(n, -jnp.inf).at[j].set(0.0)
        idx = rs.RESAMPLERS[name](getkey(), lw)
        np.testing.assert_array_equal(np.asarray(idx), np.full(n, j))


def test_count_bounds(batched_counts):
    w, counts = batched_counts
    n = w.size
    nw = n * w
    for name in ("systematic", "stratified", "residual", "multinomial"):
        c = counts[name]
        assert np.all(c.sum(axis=1) == n), name
        assert np.all(c[:, 3] == 0), f"{name} selected a zero-weight particle"
    # systematic: ⌊N w_i⌋ ≤ count ≤ ⌈N w_i⌉ (Douc et al. 2005)
    c = counts["systematic"]
    assert np.all(c >= np.floor(nw)) and np.all(c <= np.ceil(nw))
    # residual: at least the deterministic ⌊N w_i⌋ copies
    assert np.all(counts["residual"] >= np.floor(nw))
    # stratified: each uniform lies in its own stratum, so |count − N w_i| < 2
    assert np.all(np.abs(counts["stratified"] - nw) < 2)
    # the bounds are not vacuous: multinomial violates the systematic one
    m = counts["multinomial"]
    assert np.any((m < np.floor(nw)) | (m > np.ceil(nw)))


@pytest.mark.parametrize("name", SCHEMES)
def test_mean_counts_unbiased(name, batched_counts):
    """E[count_i] = N w_i; the per-particle variance is at most the multinomial one
    N w (1 − w) (or ≤ 1/4 for the {⌊·⌋, ⌈·⌉} schemes), so 5 standard errors bound it."""
    w, counts = batched_counts
    c = counts[name]
    k, n = c.shape
    var = np.maximum(n * w * (1 - w), 0.25)
    z = (c.mean(axis=0) - n * w) / np.sqrt(var / k)
    assert np.all(np.abs(z) < 5), z
    # chi-square-style global check on the non-degenerate particles
    assert np.sum(z**2) < 3 * n


@pytest.mark.parametrize("name", SCHEMES)
@pytest.mark.parametrize("edge", ["zero", "one"])
def test_edge_uniforms_float32(name, edge, monkeypatch, getkey):
    """Uniform draws of exactly 0 or just below 1, with float32 weights that do not sum
    to 1 (a huge cloud with zero-weight first and last particles): indices stay in range
    and never pick a zero-weight particle."""
    n = 20001
    rng = np.random.default_rng(1)
    lw = rng.normal(size=n).astype(np.float32) * 3
    lw[0] = -np.inf
    lw[-3:] = -np.inf
    lw = jnp.asarray(lw, jnp.float32)
    total = jnp.sum(jnp.exp(lw - jax.scipy.special.logsumexp(lw)))
    assert total.dtype == jnp.float32
    value = 0.0 if edge == "zero" else float(np.nextafter(np.float32(1), np.float32(0)))
    monkeypatch.setattr(rs, "_uniform", lambda key, shape, dtype: jnp.full(shape, value, dtype))
    fn = rs.RESAMPLERS[name]
    idx = np.asarray(jax.jit(lambda k, x: fn(k, x))(getkey(), lw))  # fresh trace: sees the patched _uniform
    assert idx.min() >= 1 and idx.max() <= n - 4
    assert idx.shape == (n,)


def test_resampling_bad_input(getkey):
    with pytest.raises(ValueError, match="log_weights"):
        rs.systematic(getkey(), jnp.zeros((3, 2)))
    with pytest.raises(ValueError, match="log_weights"):
        rs.multinomial(getkey(), jnp.zeros(0))
    # float32 weights resolve 2^-24 of the total: too coarse beyond 2^22 particles
    too_many = jax.ShapeDtypeStruct((2**22 + 1,), jnp.float32)
    with pytest.raises(ValueError, match="use float64"):
        jax.eval_shape(rs.systematic, jax.random.key(0), too_many)
    jax.eval_shape(rs.systematic, jax.random.key(0), jax.ShapeDtypeStruct((2**22,), jnp.float32))


@pytest.mark.parametrize("n", [1, 5, 32, 33, 1000, 1025, 40000])
def test_exact_cumsum_matches_numpy(n):
    """The blocked matrix-product cumulative sum (one block, two levels, three levels of
    the recursion) equals NumPy's sequential sum of integer-valued floats exactly, in
    float32 up to partial sums of 2^24 and under vmap."""
    rng = np.random.default_rng(n)
    a = rng.integers(0, 2**24 // n, size=(3, n)).astype(np.float32)
    out = np.asarray(jax.jit(jax.vmap(rs._exact_cumsum))(jnp.asarray(a)))
    np.testing.assert_array_equal(out, np.cumsum(a.astype(np.int64), axis=1).astype(np.float32))


def _float_cumulative(lw):
    """The plain float cumulative sum `cumsum(w) / Σ w` (sequential, float32)."""
    w = np.exp(lw - lw.max())
    c = np.cumsum(w, dtype=np.float32)
    return c / c[-1]


def test_cumulative_weights_float32():
    """Cumulative weights in float32: monotone, exactly 1 at the end, zero increments
    exactly at zero weights, all-zero weights give all ones (no NaN); the weights they
    resample from are within `N 2^-25` of the exact ones in total variation, no worse
    than twice a sequential float32 `cumsum` on the same weights (also with thousands of
    negligible weights, whose rounding is the worst case of the quantization)."""
    rng = np.random.default_rng(7)
    for n, spread in [(1000, 1.0), (5000, 4.0), (20001, 0.1), (20001, 6.0)]:
        lw = (rng.normal(size=n) * spread).astype(np.float32)
        lw[[0, 17, n - 1]] = -np.inf
        c = np.asarray(rs._cumulative(jnp.asarray(lw)))
        assert c.dtype == np.float32
        assert np.all(np.diff(c) >= 0) and c[-1] == 1.0
        w = np.exp(lw.astype(np.float64) - lw.max())
        w /= w.sum()
        inc = np.diff(np.concatenate([[0.0], c.astype(np.float64)]))
        assert inc[0] == 0 and inc[17] == 0 and inc[n - 1] == 0
        tv = 0.5 * np.abs(inc - w).sum()
        tv_float = 0.5 * np.abs(np.diff(np.concatenate([[0.0], _float_cumulative(lw).astype(np.float64)])) - w).sum()
        assert tv <= n * 2.0**-25 and tv <= 2 * tv_float, (n, spread, tv, tv_float)
        np.testing.assert_allclose(c, np.cumsum(w), rtol=0, atol=n * 2.0**-23)
    np.testing.assert_array_equal(np.asarray(rs._cumulative(jnp.full(4, -jnp.inf))), np.ones(4))


# --------------------------------------------------------------------------- models


def _growth_model():
    # module-level f, h: equal static fields, so jitted filter calls are shared across tests
    return NonlinearModel(growth_f, growth_h, jnp.array([[10.0]]), jnp.array([[1.0]]))


GROWTH_T, GROWTH_N = 30, 500


def _growth_data(seed, runs):
    model = _growth_model()
    prior = jdrkf.Gaussian(jnp.zeros(1), jnp.eye(1))
    return model, prior, jdrkf._nonlinear._simulate_nonlinear(jax.random.key(seed), model, prior, GROWTH_T, runs)


F_LIN = np.array([[0.9, 0.2], [-0.1, 0.8]])
H_LIN = np.array([[1.0, 0.5]])
Q_LIN = np.array([[0.5, 0.1], [0.1, 0.3]])
R_LIN = np.array([[0.4]])


def _linear_models():
    f, hm = jnp.asarray(F_LIN), jnp.asarray(H_LIN)
    nl = NonlinearModel(lambda x, t: f @ x, lambda x, t: hm @ x, jnp.asarray(Q_LIN), jnp.asarray(R_LIN))
    lin = jdrkf.LinearModel(F=f, H=hm, Q=jnp.asarray(Q_LIN), R=jnp.asarray(R_LIN))
    return nl, lin


def _simulate_linear(rng, T):
    x = rng.normal(size=2)
    ys = []
    lq = np.linalg.cholesky(Q_LIN)
    for _ in range(T):
        x = F_LIN @ x + lq @ rng.normal(size=2)
        ys.append(H_LIN @ x + math.sqrt(R_LIN[0, 0]) * rng.normal(size=1))
    return np.array(ys)


_run = eqx.filter_jit(lambda pf, model, prior, ys, key, observed=None: pf(model, prior, ys, key, observed=observed))


# --------------------------------------------------------------------------- PF vs KF


def test_pf_converges_to_kf_linear_gaussian(rng):
    nl, lin = _linear_models()
    prior = jdrkf.Gaussian(jnp.array([0.5, -0.2]), jnp.eye(2))
    ys = jnp.asarray(_simulate_linear(rng, 20))
    kf = jdrkf.KalmanFilter()(lin, prior, ys)
    kf_mean, kf_cov = np.asarray(kf.filtered_means), np.asarray(kf.filtered_covariances)
    var = np.diagonal(kf_cov, axis1=1, axis2=2)
    n_part, runs = 20_000, 4
    means, covs, logliks, sds = [], [], [], []
    for r in range(runs):
        res = _run(BootstrapPF(n_part, outputs="all"), nl, prior, ys, jax.random.key(r))
        ess = np.asarray(res.info["ess"])
        assert ess.min() > 0.02 * n_part
        # Monte Carlo sd of a self-normalized weighted mean ≈ sqrt(P_ii / ESS_t); errors
        # carried over from earlier steps through resampling inflate it (factor 1.5).
        sd = 1.5 * np.sqrt(var / ess[:, None])
        assert np.all(np.abs(np.asarray(res.filtered_means) - kf_mean) < 5 * sd)
        means.append(np.asarray(res.filtered_means))
        covs.append(np.asarray(res.filtered_covariances))
        logliks.append(float(res.marginal_loglik))
        sds.append(sd)
    # the average of independent runs is closer (error shrinks like 1/sqrt(runs))
    avg_err = np.abs(np.mean(means, axis=0) - kf_mean)
    assert np.all(avg_err < 5 * np.max(sds, axis=0) / math.sqrt(runs))
    np.testing.assert_allclose(np.mean(covs, axis=0), kf_cov, rtol=0.1, atol=0.03)
    # p̂(y_{1:T}) is unbiased for p(y_{1:T}); log p̂ has sd ≈ 0.1 here (measured over keys)
    assert all(abs(ll - float(kf.marginal_loglik)) < 0.5 for ll in logliks)
    log_mean_lik = np.log(np.mean(np.exp(np.array(logliks) - float(kf.marginal_loglik))))
    assert abs(log_mean_lik) < 0.2
    # a small cloud is measurably worse (the comparison can fail)
    small = _run(BootstrapPF(20), nl, prior, ys, jax.random.key(0))
    assert np.max(np.abs(np.asarray(small.filtered_means) - kf_mean)) > 3 * np.max(avg_err)


# --------------------------------------------------------------------------- PF vs NumPy PF


def _numpy_pf(ys, x0, noise, uniforms, scheme, threshold, estimate):
    """Bootstrap PF for the growth model in NumPy (float64), given the initial particles
    `x0 (N,)`, process noise `noise (T, N)` and resampling uniforms `uniforms[t]`
    (a scalar U for systematic, N uniforms for multinomial)."""
    n = x0.size
    x, lw = x0.copy(), np.full(n, -np.log(n))
    means, logliks, ess_all = [], [], []
    for t, y in enumerate(ys):
        k = t + 1
        x = x / 2 + 25 * x / (1 + x**2) + 8 * np.cos(1.2 * k) + noise[t]
        ll = -0.5 * ((y - x**2 / 20) ** 2 + np.log(2 * np.pi))
        a = lw + ll
        amax = a.max()
        inc = amax + np.log(np.sum(np.exp(a - amax)))
        lw = a - inc
        w = np.exp(lw)
        ess = 1 / np.sum(w**2)
        mean = np.sum(w * x)
        if threshold >= 1 or ess < threshold * n:
            c = np.cumsum(w)
            c[-1] = 1.0
            u = (np.arange(n) + uniforms[t]) / n if scheme == "systematic" else uniforms[t]
            idx = np.minimum(np.searchsorted(c, u, side="right"), n - 1)
            x, lw = x[idx], np.full(n, -np.log(n))
            if estimate == "resampled_mean":
                mean = x.mean()
        means.append(mean)
        logliks.append(inc)
        ess_all.append(ess)
    return np.array(means), np.array(logliks), np.array(ess_all)


def _key_schedule_draws(key, n, T, scheme):
    """The random numbers `BootstrapPF` documents: init from split(key)[0]; step t from
    split(split(key)[1], T)[t] = (k_noise, k_res)."""
    k_init, k_steps = jax.random.split(key)
    x0 = np.asarray(jax.random.normal(k_init, (n, 1), jnp.float64))[:, 0]  # prior N(0, 1)
    noise, unif = [], []
    for kt in jax.random.split(k_steps, T):
        k_noise, k_res = jax.random.split(kt)
        noise.append(math.sqrt(10.0) * np.asarray(jax.random.normal(k_noise, (n, 1), jnp.float64))[:, 0])
        shape = () if scheme == "systematic" else (n,)
        unif.append(np.asarray(jax.random.uniform(k_res, shape, jnp.float64)))
    return x0, np.array(noise), unif


@pytest.mark.parametrize(
    "scheme,threshold,estimate",
    [("systematic", 0.5, "weighted_mean"), ("multinomial", 1.0, "resampled_mean")],
)
def test_growth_model_matches_numpy_pf(scheme, threshold, estimate):
    model, prior, tr = _growth_data(5, 1)
    ys = np.asarray(tr.observations[0])
    n, key = GROWTH_N, jax.random.key(11)
    pf = BootstrapPF(n, resampling=scheme, ess_threshold=threshold, estimate=estimate, outputs="all")
    res = _run(pf, model, prior, jnp.asarray(ys), key)
    x0, noise, unif = _key_schedule_draws(key, n, ys.shape[0], scheme)
    means, logliks, ess = _numpy_pf(ys[:, 0], x0, noise, unif, scheme, threshold, estimate)
    np.testing.assert_allclose(np.asarray(res.filtered_means)[:, 0], means, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(np.asarray(res.loglik_increments), logliks, rtol=1e-9, atol=1e-9)
    np.testing.assert_allclose(np.asarray(res.info["ess"]), ess, rtol=1e-9)
    resampled = np.asarray(res.info["resampled"])
    assert resampled.all() if threshold >= 1 else (0 < resampled.sum() < resampled.size)
    rmse = float(jdrkf.metrics.rmse(tr.states[0], res.filtered_means))
    assert rmse < 10.0  # sanity: the growth-model PF error is a few units (Wang 2022, Sec. V)


# --------------------------------------------------------------------------- jit / vmap / misc


def test_vmap_over_runs_and_keys_matches_loop():
    model, prior, tr = _growth_data(1, 3)
    keys = jax.random.split(jax.random.key(2), 3)
    batched = eqx.filter_jit(jax.vmap(BootstrapPF(GROWTH_N, return_particles=True, outputs="all"), in_axes=(None, None, 0, 0)))(
        model, prior, tr.observations, keys
    )
    assert batched.filtered_means.shape == (3, GROWTH_T, 1)
    assert batched.info["particles"].shape == (3, GROWTH_T, GROWTH_N, 1)
    pf = BootstrapPF(GROWTH_N)
    for r in range(3):
        single = _run(pf, model, prior, tr.observations[r], keys[r])
        np.testing.assert_allclose(batched.filtered_means[r], single.filtered_means, rtol=1e-10, atol=1e-10)
        np.testing.assert_allclose(batched.marginal_loglik[r], single.marginal_loglik, rtol=1e-10)
    # the returned cloud reproduces the filtered moments
    w = np.exp(np.asarray(batched.info["log_weights"][0]))
    np.testing.assert_allclose(np.sum(w * np.asarray(batched.info["particles"][0])[..., 0], axis=-1),
                               batched.filtered_means[0, :, 0], rtol=1e-10, atol=1e-10)
    # a different key gives a different run
    other = _run(pf, model, prior, tr.observations[0], keys[1])
    assert not np.allclose(other.filtered_means, batched.filtered_means[0])


def test_missing_observation_skips_update():
    model, prior, tr = _growth_data(4, 1)
    ys = tr.observations[0].at[7].set(jnp.nan)
    res = _run(BootstrapPF(GROWTH_N, outputs="all"), model, prior, ys, jax.random.key(0), ~jnp.isnan(ys))
    assert float(res.loglik_increments[7]) == 0.0
    np.testing.assert_allclose(res.filtered_means[7], res.predicted_means[7], rtol=1e-12)
    np.testing.assert_allclose(res.filtered_covariances[7], res.predicted_covariances[7], rtol=1e-12)
    assert np.all(np.isfinite(np.asarray(res.filtered_means)))


def test_no_resampling_is_importance_sampling():
    """ess_threshold = 0: sequential importance sampling; the weights then carry the
    whole likelihood, so the marginal log-likelihood is log of the mean of
    Π_k p(y_k | x_k^i) over the particles (checked against the returned cloud)."""
    model, prior, tr = _growth_data(6, 1)
    ys = tr.observations[0][:5]
    res = _run(BootstrapPF(GROWTH_N, ess_threshold=0.0, return_particles=True, outputs="all"), model, prior, ys, jax.random.key(3))
    assert not np.any(np.asarray(res.info["resampled"]))
    x = np.asarray(res.info["particles"])[..., 0]  # (T, N): the particle paths (no resampling)
    ll = -0.5 * ((np.asarray(ys)[:, 0, None] - x**2 / 20) ** 2 + np.log(2 * np.pi))
    total = ll.sum(axis=0)
    expected = np.log(np.mean(np.exp(total - total.max()))) + total.max()
    np.testing.assert_allclose(float(res.marginal_loglik), expected, rtol=1e-10)


def test_bad_arguments():
    model = _growth_model()
    prior = jdrkf.Gaussian(jnp.zeros(1), jnp.eye(1))
    for n in (0, -3, 2.5, True):
        with pytest.raises(ValueError, match="num_particles"):
            BootstrapPF(n)
    for c in (-0.1, 1.5, float("nan")):
        with pytest.raises(ValueError, match="ess_threshold"):
            BootstrapPF(10, ess_threshold=c)
    with pytest.raises(ValueError, match="resampling"):
        BootstrapPF(10, resampling="bogus")
    with pytest.raises(ValueError, match="estimate"):
        BootstrapPF(10, estimate="median")
    with pytest.raises(ValueError, match="key"):
        BootstrapPF(10)(model, prior, jnp.ones((3, 1)))
    with pytest.raises(ValueError, match="NonlinearModel"):
        _, lin = _linear_models()
        BootstrapPF(10)(lin, jdrkf.Gaussian(jnp.zeros(2), jnp.eye(2)), jnp.ones((3, 1)), jax.random.key(0))
    with pytest.raises(ValueError, match="ys"):
        BootstrapPF(10)(model, prior, jnp.ones((3, 2)), jax.random.key(0))
    general = NonlinearModel(lambda x, w, t: x + w, lambda x, v, t: x + v, jnp.eye(1), jnp.eye(1),
                             additive=False, state_dim=1, obs_dim=1)
    with pytest.raises(ValueError, match="additive"):
        BootstrapPF(10)(general, prior, jnp.ones((3, 1)), jax.random.key(0))


def test_grad_without_resampling_matches_finite_differences():
    """Without resampling the PF estimate is a smooth function of the noise scales for a
    fixed key (reparametrized draws, weights by log-densities), so `jax.grad` through
    the whole filter equals central finite differences. With resampling the indices
    are stop-gradient (a biased gradient, documented in `BootstrapPF`) but finite."""
    model, prior, traj = _growth_data(5, 1)
    ys, xs = traj.observations[0, :12], traj.states[0, :12]
    key = jax.random.key(3)

    def mse(s, threshold):
        mdl = NonlinearModel(growth_f, growth_h, s[0] * model.Q, s[1] * model.R)
        res = BootstrapPF(200, ess_threshold=threshold)(mdl, prior, ys, key)
        return jnp.mean((res.filtered_means - xs) ** 2)

    s0 = np.array([1.2, 0.9])
    f = jax.jit(lambda s: mse(s, 0.0))
    grad = jax.jit(jax.grad(lambda s: mse(s, 0.0)))(jnp.asarray(s0))
    h = 1e-5
    fd = np.array([(float(f(s0 + h * e)) - float(f(s0 - h * e))) / (2 * h) for e in np.eye(2)])
    assert np.all(np.abs(fd) > 1e-4)
    np.testing.assert_allclose(grad, fd, rtol=1e-5)
    assert np.all(np.isfinite(jax.jit(jax.grad(lambda s: mse(s, 0.5)))(jnp.asarray(s0))))
