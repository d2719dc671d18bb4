"""`NonlinearModel`, `_simulate_nonlinear` and the noise laws' `log_prob` (Wang 2022).

Oracles: NumPy re-implementations of the model functions and of the simulation
recursion fed with the same standard-normal draws (`jax.random.normal` on the
documented keys, then SciPy's symmetric square roots), SciPy densities, and sample
moments within `Z` standard errors.
"""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg
import scipy.stats

import jdrkf
from jdrkf._nonlinear import NonlinearModel, _simulate_nonlinear
from jdrkf.experiments.wang_nonlinear import growth_f, growth_h
from jdrkf._noise import GaussianNoise, MixtureNoise, OutlierNoise, ScaledNoise, StudentTNoise, UQuadraticNoise


Z = 6.0


# --------------------------------------------------------------------------- models


def np_growth_f(x, t):
    return x / 2 + 25 * x / (1 + x**2) + 8 * np.cos(1.2 * (t + 1))


def growth_model(**kw):
    return NonlinearModel(growth_f, growth_h, 10.0 * jnp.eye(1), jnp.eye(1), **kw)


def general_f(x, w, t):
    """2-D rotation with multiplicative and additive noise (q = 3)."""
    c, s = jnp.cos(0.3), jnp.sin(0.3)
    rot = jnp.array([[c, -s], [s, c]])
    return (1.0 + 0.1 * w[2]) * (rot @ x) + w[:2]


def general_h(x, v, t):
    """Range with multiplicative noise, and bearing (r = 1, m = 2)."""
    return jnp.stack([jnp.sqrt(x[0] ** 2 + x[1] ** 2 + 1.0) * jnp.exp(v[0]), jnp.arctan2(x[1], x[0] + 3.0)])


def np_general_f(x, w, t):
    c, s = np.cos(0.3), np.sin(0.3)
    return (1.0 + 0.1 * w[2]) * (np.array([[c, -s], [s, c]]) @ x) + w[:2]


def np_general_h(x, v, t):
    return np.array([np.sqrt(x[0] ** 2 + x[1] ** 2 + 1.0) * np.exp(v[0]), np.arctan2(x[1], x[0] + 3.0)])


GQ = np.diag([0.2, 0.1, 0.5])
GR = np.array([[0.05]])


def general_model(**kw):
    return NonlinearModel(general_f, general_h, GQ, GR, additive=False, state_dim=2, obs_dim=2, **kw)


# --------------------------------------------------------------------------- validation


def test_dimensions_and_fields():
    m = growth_model()
    assert (m.state_dim, m.obs_dim, m.additive) == (1, 1, True)
    g = general_model()
    assert (g.state_dim, g.obs_dim, g.additive, g.process_noise_dim, g.measurement_noise_dim) == (2, 2, False, 3, 1)
    np.testing.assert_array_equal(g.process_mean, np.zeros(3))


@pytest.mark.parametrize(
    "kwargs, match",
    [
        (dict(Q=np.ones((2, 3))), "Q must be square"),
        (dict(Q=np.array([[1.0, 0.5], [0.0, 1.0]])), "Q must be symmetric"),
        (dict(R=np.ones(2)), "R must have 2 dimensions"),
        (dict(f="x"), "f must be a callable"),
        (dict(h=lambda x, t: jnp.concatenate([x, x])), r"h\(x, t\) must return an array of shape \(1,\)"),
        (dict(f=lambda x, t: x @ jnp.ones((3, 3))), r"calling f\(x, t\) .* failed"),
        (dict(f=lambda x, t: x.astype(jnp.float32)), "returns dtype float32"),
        (dict(state_dim=2), "state_dim=2 but Q has shape"),
        (dict(obs_dim=0), "obs_dim must be a positive int"),
        (dict(process_noise=GaussianNoise(np.eye(2))), "process_noise draws vectors of dimension 2 but 1"),
        (dict(measurement_noise=np.eye(1)), "measurement_noise must be a jdrkf noise law"),
        (dict(measurement_noise=GaussianNoise(np.eye(1, dtype=np.float32))), "has dtype float32"),
    ],
)
def test_validation_errors(kwargs, match):
    args = dict(f=growth_f, h=growth_h, Q=10.0 * np.eye(1), R=np.eye(1))
    args.update(kwargs)
    f, h, Q, R = (args.pop(k) for k in ("f", "h", "Q", "R"))
    with pytest.raises(ValueError, match=match):
        NonlinearModel(f, h, Q, R, **args)


def test_general_form_needs_dimensions():
    with pytest.raises(ValueError, match="state_dim and obs_dim are required"):
        NonlinearModel(general_f, general_h, GQ, GR, additive=False)
    with pytest.raises(ValueError, match=r"h\(x, v, t\) must return an array of shape \(3,\)"):
        NonlinearModel(general_f, general_h, GQ, GR, additive=False, state_dim=2, obs_dim=3)


def test_inputs_horizon_and_logpdf_errors():
    m = growth_model()
    with pytest.raises(ValueError, match="takes no controls"):
        m.check_inputs(jnp.zeros((3, 1)), 3)
    m.check_inputs(None, 3)
    scaled = growth_model(measurement_noise=ScaledNoise(GaussianNoise(np.eye(1)), np.ones(4)))
    with pytest.raises(ValueError, match="scale has 4 entries but 5 steps"):
        scaled.check_horizon(5)
    with pytest.raises(ValueError, match="needs additive measurement noise"):
        general_model().measurement_logpdf(jnp.zeros(2), jnp.zeros(2), 0)
    with pytest.raises(ValueError, match="OutlierNoise.*has no density"):
        growth_model(measurement_noise=OutlierNoise(np.eye(1), 0.1, 100.0)).measurement_logpdf(jnp.zeros(1), jnp.zeros(1), 0)
    with pytest.raises(ValueError, match="base law .*OutlierNoise.* has no density"):
        ScaledNoise(OutlierNoise(np.eye(1), 0.1, 100.0), np.ones(3)).log_prob(jnp.zeros(1), 0)
    with pytest.raises(ValueError, match="needs a PRNG key"):
        _simulate_nonlinear(None, m, jdrkf.Gaussian(np.zeros(1), np.eye(1)), 3, 1)
    with pytest.raises(ValueError, match="prior draws vectors of dimension 2"):
        _simulate_nonlinear(jax.random.key(0), m, jdrkf.Gaussian(np.zeros(2), np.eye(2)), 3, 1)
    with pytest.raises(ValueError, match="must be a jdrkf.NonlinearModel"):
        _simulate_nonlinear(jax.random.key(0), "model", jdrkf.Gaussian(np.zeros(1), np.eye(1)), 3, 1)


# --------------------------------------------------------------------------- functions


def test_transition_and_observe(rng):
    m = growth_model()
    for t in range(3):
        x, w, v = rng.normal(size=(3, 1))
        np.testing.assert_allclose(m.transition(jnp.asarray(x), jnp.asarray(w), jnp.asarray(t)), np_growth_f(x, t) + w, rtol=1e-13)
        np.testing.assert_allclose(m.observe(jnp.asarray(x), jnp.asarray(v), jnp.asarray(t)), x**2 / 20 + v, rtol=1e-13)
    g = general_model()
    x, w, v = rng.normal(size=2), rng.normal(size=3), rng.normal(size=1)
    np.testing.assert_allclose(g.transition(jnp.asarray(x), jnp.asarray(w), 0), np_general_f(x, w, 0), rtol=1e-13)
    np.testing.assert_allclose(g.observe(jnp.asarray(x), jnp.asarray(v), 0), np_general_h(x, v, 0), rtol=1e-13)


@eqx.filter_jit
def _standard_normals(key, runs, T, n, q, r):
    """The standard-normal draws of the documented key schedule of `_simulate_nonlinear`."""

    def run(i):
        k0, kseq = jax.random.split(jax.random.fold_in(key, i))
        kw, kv = jax.vmap(jax.random.split, out_axes=1)(jax.random.split(kseq, T))
        normal = lambda d: jax.vmap(lambda k: jax.random.normal(k, (d,), jnp.float64))  # noqa: E731
        return jax.random.normal(k0, (n,), jnp.float64), normal(q)(kw), normal(r)(kv)

    return jax.vmap(run)(jnp.arange(runs))


def _numpy_simulation(key, prior_mean, prior_cov, Q, R, f, h, additive, T, runs):
    """The documented key schedule, with NumPy arithmetic (symmetric square roots from SciPy)."""
    sq = lambda a: np.real(scipy.linalg.sqrtm(np.asarray(a)))  # noqa: E731
    sp, sq_q, sq_r = sq(prior_cov), sq(Q), sq(R)
    z0, zw, zv = (np.asarray(a) for a in _standard_normals(key, runs, T, len(prior_mean), Q.shape[0], R.shape[0]))
    x0s, xs, ys = [], [], []
    for r in range(runs):
        x = prior_mean + sp @ z0[r]
        x0s.append(x)
        states, obs = [], []
        for t in range(T):
            w, v = sq_q @ zw[r, t], sq_r @ zv[r, t]
            x = f(x, t) + w if additive else f(x, w, t)
            states.append(x)
            obs.append(h(x, t) + v if additive else h(x, v, t))
        xs.append(states)
        ys.append(obs)
    return np.array(x0s), np.array(xs), np.array(ys)


@pytest.mark.parametrize("additive", [True, False])
def test_simulation_matches_numpy_loop(additive):
    key, T, runs = jax.random.key(3), 12, 3
    if additive:
        model = growth_model()
        prior = jdrkf.Gaussian(np.array([0.5]), np.array([[2.0]]))
        ref = _numpy_simulation(key, np.array([0.5]), np.array([[2.0]]), 10.0 * np.eye(1), np.eye(1), np_growth_f, lambda x, t: x**2 / 20, True, T, runs)
    else:
        model = general_model()
        pc = np.array([[1.0, 0.3], [0.3, 0.5]])
        prior = jdrkf.Gaussian(np.array([1.0, -1.0]), pc)
        ref = _numpy_simulation(key, np.array([1.0, -1.0]), pc, GQ, GR, np_general_f, np_general_h, False, T, runs)
    traj = _simulate_nonlinear(key, model, prior, T, runs)
    assert isinstance(traj, jdrkf.Trajectories) and traj.transition_matrices is None
    assert traj.states.shape == (runs, T, model.state_dim) and traj.observations.shape == (runs, T, model.obs_dim)
    for got, want in zip((traj.initial_states, traj.states, traj.observations), ref, strict=True):
        np.testing.assert_allclose(got, want, rtol=1e-9, atol=1e-9)
    np.testing.assert_array_equal(traj.observations, traj.clean_observations)
    assert not np.any(traj.outliers)


def test_simulation_with_laws_statistics():
    """Linear dynamics with Student-t process noise and outlier measurement noise:
    moments of the increments, and the outlier bookkeeping."""
    a = 0.5
    q = np.array([[1.0, 0.3], [0.3, 0.6]])
    r = 0.2 * np.eye(2)
    model = NonlinearModel(
        lambda x, t: a * x,
        lambda x, t: x,
        q,
        r,
        process_noise=StudentTNoise(q, 5.0),
        measurement_noise=OutlierNoise(r, 0.1, 50.0),
    )
    T, runs = 200, 100
    traj = _simulate_nonlinear(jax.random.key(7), model, jdrkf.Gaussian(np.zeros(2), np.eye(2)), T, runs)
    x_prev = np.concatenate([np.asarray(traj.initial_states)[:, None], np.asarray(traj.states)[:, :-1]], axis=1)
    w = (np.asarray(traj.states) - a * x_prev).reshape(-1, 2)
    v_clean = (np.asarray(traj.clean_observations) - np.asarray(traj.states)).reshape(-1, 2)
    out = (np.asarray(traj.observations) - np.asarray(traj.clean_observations)).reshape(-1, 2)
    flags = np.asarray(traj.outliers).reshape(-1, 2)
    for d, cov in ((w, q), (v_clean, r)):
        dev = d[:, :, None] * d[:, None, :]
        se = dev.reshape(len(d), -1).std(axis=0) / np.sqrt(len(d))
        assert np.all(np.abs(dev.mean(axis=0).ravel() - cov.ravel()) <= Z * se)
        assert np.all(np.abs(d.mean(axis=0)) <= Z * d.std(axis=0) / np.sqrt(len(d)))
    np.testing.assert_array_equal(flags, out != 0)
    np.testing.assert_allclose(np.abs(out[flags]), 50.0)
    n_flag = flags.size
    assert abs(flags.mean() - 0.1) <= Z * np.sqrt(0.1 * 0.9 / n_flag)


def test_sample_noise_shapes_and_moments():
    model = general_model(measurement_noise=MixtureNoise(GR, 0.2, 9.0))
    w = np.asarray(model.sample_process_noise(jax.random.key(0), 0, (4000, 5)))
    assert w.shape == (4000, 5, 3)
    assert model.sample_process_noise(jax.random.key(0), 0).shape == (3,)
    v = np.asarray(model.sample_measurement_noise(jax.random.key(1), 0, (20000,)))
    assert v.shape == (20000, 1)
    w = w.reshape(-1, 3)
    dev = w[:, :, None] * w[:, None, :]
    se = dev.reshape(len(w), -1).std(axis=0) / np.sqrt(len(w))
    assert np.all(np.abs(dev.mean(axis=0).ravel() - GQ.ravel()) <= Z * se)
    var = (1 - 0.2 + 0.2 * 9.0) * GR[0, 0]
    assert abs(np.mean(v**2) - var) <= Z * np.std(v**2) / np.sqrt(len(v))


# --------------------------------------------------------------------------- densities


RM = np.array([[1.0, 0.4], [0.4, 0.8]])


def _range_model(law=None):
    h = lambda x, t: jnp.stack([jnp.sqrt(x[0] ** 2 + x[1] ** 2), x[0]])  # noqa: E731
    return NonlinearModel(lambda x, t: x, h, np.eye(2), RM, measurement_noise=law)


def _np_range(x):
    return np.array([np.hypot(x[0], x[1]), x[0]])


logpdf = eqx.filter_jit(lambda model, y, x, t: model.measurement_logpdf(y, x, t))


def test_measurement_logpdf_vs_scipy(rng):
    nu, p, k = 5.0, 0.3, 16.0
    cases = [
        (None, lambda e: scipy.stats.multivariate_normal(np.zeros(2), RM).logpdf(e)),
        (GaussianNoise(RM, np.array([0.1, -0.2])), lambda e: scipy.stats.multivariate_normal([0.1, -0.2], RM).logpdf(e)),
        (StudentTNoise(RM, nu), lambda e: scipy.stats.multivariate_t(np.zeros(2), RM * (nu - 2) / nu, df=nu).logpdf(e)),
        (
            MixtureNoise(RM, p, k),
            lambda e: np.log(
                (1 - p) * scipy.stats.multivariate_normal(np.zeros(2), RM).pdf(e)
                + p * scipy.stats.multivariate_normal(np.zeros(2), k * RM).pdf(e)
            ),
        ),
    ]
    for law, ref in cases:
        model = _range_model(law)
        for _ in range(3):
            x, y = rng.normal(size=2), rng.normal(size=2) * 2
            got = logpdf(model, jnp.asarray(y), jnp.asarray(x), jnp.asarray(0))
            np.testing.assert_allclose(got, ref(y - _np_range(x)), rtol=1e-10)


def test_measurement_logpdf_missing_component(rng):
    model = _range_model()
    x = rng.normal(size=2)
    y = np.array([np.nan, 0.7])
    got = logpdf(model, jnp.asarray(y), jnp.asarray(x), jnp.asarray(0))
    np.testing.assert_allclose(got, scipy.stats.norm(0, np.sqrt(RM[1, 1])).logpdf(0.7 - x[0]), rtol=1e-12)


def test_law_log_probs(rng):
    x = rng.normal(size=(5, 2))
    # ScaledNoise at step t: covariance a(t) R.
    scaled = ScaledNoise(StudentTNoise(RM, 4.0, mean=np.array([1.0, 0.0])), np.array([1.0, 3.0]))
    ref = scipy.stats.multivariate_t([1.0, 0.0], 3.0 * RM * 0.5, df=4.0).logpdf(x)
    np.testing.assert_allclose(scaled.log_prob(jnp.asarray(x), 1), ref, rtol=1e-10)
    # Batched Gaussian.
    np.testing.assert_allclose(GaussianNoise(RM).log_prob(jnp.asarray(x)), scipy.stats.multivariate_normal(np.zeros(2), RM).logpdf(x), rtol=1e-12)
    # U-quadratic: product of α (x − β)² on the box, −inf outside.
    low, high = np.array([-1.0, 0.0]), np.array([2.0, 1.0])
    law = UQuadraticNoise(low, high)
    pts = np.array([[0.3, 0.2], [-0.9, 0.99], [2.5, 0.3]])
    alpha, beta = 12 / (high - low) ** 3, (low + high) / 2
    ref = np.sum(np.log(alpha * (pts - beta) ** 2), axis=1)
    ref[2] = -np.inf
    np.testing.assert_allclose(law.log_prob(jnp.asarray(pts)), ref, rtol=1e-12)
    # Mixture with p = 0 is the Gaussian.
    np.testing.assert_allclose(MixtureNoise(RM, 0.0, 4.0).log_prob(jnp.asarray(x)), scipy.stats.multivariate_normal(np.zeros(2), RM).logpdf(x), rtol=1e-12)
