"""The prior / likelihood / outlier objects of `DRParticleFilter` (Wang 2022, Methods 1–7)
and the deprecated string spellings of the previous release.

Oracles: the deprecated spellings (the previous release's interface, still converted) for
bitwise-identical runs with the same key; the documented ranges for the eager and traced
checks; central finite differences for the gradients.
"""

import math
import re

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jdrkf
from jdrkf._gaussian import Gaussian
from jdrkf._nonlinear import NonlinearModel, _simulate_nonlinear
from jdrkf.filters._dr_particle import DRParticleFilter, DropOutliers, NearestOutliers
from jdrkf.sets import (
    AbstractParticleLikelihood,
    AbstractParticlePrior,
    AugmentedWassersteinLikelihood,
    InflatedLikelihood,
    ParticleKL,
    ParticleWasserstein,
    ParticleWassersteinSample,
    WassersteinLikelihood,
)

T = 10
PRIOR = Gaussian(jnp.zeros(1), jnp.eye(1))


def _f(x, t):
    return x / 2 + 25 * x / (1 + x**2) + 8 * jnp.cos(1.2 * (t + 1).astype(x.dtype))


def _h(x, t):
    return x**2 / 20


def _f_general(x, w, t):
    return _f(x, t) + w


def _h_general(x, v, t):
    return x**2 / 20 * (1 + v / 4) + v


def _growth():
    return NonlinearModel(_f, _h, jnp.eye(1) * 10.0, jnp.eye(1))


def _nonadditive():
    """Growth dynamics with a heteroscedastic, non-additive measurement."""
    return NonlinearModel(
        _f_general,
        _h_general,
        jnp.eye(1) * 10.0,
        jnp.eye(1),
        additive=False,
        state_dim=1,
        obs_dim=1,
    )


@pytest.fixture(scope="module")
def data():
    tr = _simulate_nonlinear(jax.random.key(7), _growth(), PRIOR, T, 1)
    return tr.observations[0], tr.states[0]


@eqx.filter_jit
def _run(flt, model, ys, key, observed=None):
    return flt(model, PRIOR, ys, key, observed=observed)


# ------------------------------------------------------ deprecated spellings: same numbers

# (id, old keywords, new keywords, model, y modification) — every old spelling of the
# previous release's tests. The old and new filters have the same structure, so the
# second run reuses the first one's compilation.
_SPELLINGS = [
    ("theta", dict(theta=1.0), lambda: dict(likelihood=InflatedLikelihood(1.0)), _growth, None),
    ("inflate", dict(likelihood="inflate", theta=5.0), lambda: dict(likelihood=InflatedLikelihood(5.0)), _growth, None),
    ("prior_none", dict(prior="none"), lambda: dict(prior=None), _growth, None),
    (
        "kl",
        dict(prior="kl", prior_radius=0.05, theta=2.0, ess_threshold=0.0),
        lambda: dict(prior=ParticleKL(0.05), likelihood=InflatedLikelihood(2.0), ess_threshold=0.0),
        _growth,
        None,
    ),
    (
        "wasserstein",
        dict(prior="wasserstein", prior_radius=0.3, theta=1.0, ess_threshold=0.0),
        lambda: dict(prior=ParticleWasserstein(0.3), likelihood=InflatedLikelihood(1.0), ess_threshold=0.0),
        _growth,
        None,
    ),
    pytest.param(
        "wasserstein_sample",
        dict(prior="wasserstein_sample", prior_radius=0.5, num_integration_points=100),
        lambda: dict(prior=ParticleWassersteinSample(0.5, num_integration_points=100)),
        _growth,
        None,
        marks=pytest.mark.slow,
    ),
    pytest.param(
        "wasserstein_likelihood",
        dict(likelihood="wasserstein", likelihood_radius=0.3, num_likelihood_particles=4, num_integration_points=100),
        lambda: dict(likelihood=WassersteinLikelihood(0.3, num_particles=4, num_integration_points=100)),
        _nonadditive,
        None,
        marks=pytest.mark.slow,
    ),
    (
        "wasserstein_augmented",
        dict(likelihood="wasserstein_augmented", likelihood_radius=0.3, num_likelihood_particles=4),
        lambda: dict(likelihood=AugmentedWassersteinLikelihood(0.3, num_particles=4)),
        _nonadditive,
        None,
    ),
    (
        "drop",
        dict(theta=5.0, outlier="drop", outlier_threshold=1e-6),
        lambda: dict(likelihood=InflatedLikelihood(5.0), outlier=DropOutliers(1e-6)),
        _growth,
        "outlier",
    ),
    (
        "nearest",
        dict(theta=5.0, outlier="nearest", num_likelihood_particles=20),
        lambda: dict(likelihood=InflatedLikelihood(5.0), outlier=NearestOutliers(num_particles=20)),
        _growth,
        "outlier",
    ),
    (
        "drop_missing",
        dict(theta=5.0, outlier="drop"),
        lambda: dict(likelihood=InflatedLikelihood(5.0), outlier=DropOutliers()),
        _growth,
        "missing",
    ),
]


@pytest.mark.parametrize(("name", "old", "new", "model", "modify"), _SPELLINGS, ids=[
    p.values[0] if hasattr(p, "values") else p[0] for p in _SPELLINGS
])
def test_old_spelling_is_new_spelling(data, name, old, new, model, modify):
    ys = data[0]
    observed = None
    if modify == "outlier":
        ys = ys.at[4, 0].set(1e3)
    elif modify == "missing":
        ys = ys.at[3].set(jnp.nan)
        observed = ~jnp.isnan(ys)
    n = 8 if model is _nonadditive else 40
    key = jax.random.key(3)
    with pytest.warns(DeprecationWarning) as record:
        old_flt = DRParticleFilter(n, **old, outputs="all")
    assert len(record) == 1
    assert "deprecated; use " in str(record[0].message)
    new_flt = DRParticleFilter(n, **new(), outputs="all")
    assert jax.tree.structure(old_flt) == jax.tree.structure(new_flt)
    a = _run(old_flt, model(), ys, key, observed)
    b = _run(new_flt, model(), ys, key, observed)
    np.testing.assert_array_equal(np.asarray(a.filtered_means), np.asarray(b.filtered_means))
    np.testing.assert_array_equal(np.asarray(a.marginal_loglik), np.asarray(b.marginal_loglik))
    if modify == "outlier":
        assert bool(b.info["outlier"][4])


@pytest.mark.parametrize(
    ("old", "message"),
    [
        (dict(theta=2.0), "theta= is deprecated; use likelihood=jdrkf.sets.InflatedLikelihood(inflation)"),
        (dict(prior="kl", prior_radius=0.1), "prior='kl', prior_radius= are deprecated; use prior=jdrkf.sets.ParticleKL(radius)"),
        (dict(outlier="drop"), "outlier='drop' is deprecated; use outlier=jdrkf.DropOutliers(threshold)"),
        (
            dict(likelihood="wasserstein_augmented", likelihood_radius=0.2),
            "likelihood='wasserstein_augmented', likelihood_radius= are deprecated; "
            "use likelihood=jdrkf.sets.AugmentedWassersteinLikelihood(radius, num_particles)",
        ),
        (dict(prior_radius=0.1), "prior_radius= is deprecated; use prior=jdrkf.sets.ParticleKL(radius)"),  # no prior: no effect
    ],
)
def test_deprecation_message_names_the_replacement(old, message):
    with pytest.warns(DeprecationWarning, match=re.escape(message)) as record:
        DRParticleFilter(10, **old)
    assert len(record) == 1


def test_default_likelihood():
    flt = DRParticleFilter(10)
    assert isinstance(flt.likelihood, InflatedLikelihood) and float(flt.likelihood.inflation) == 5.0
    assert flt.prior is None and flt.outlier is None
    assert isinstance(flt.likelihood, AbstractParticleLikelihood)
    assert isinstance(ParticleKL(0.1), AbstractParticlePrior)
    assert jdrkf.DropOutliers is DropOutliers and jdrkf.NearestOutliers is NearestOutliers
    assert jdrkf.filters.DropOutliers is DropOutliers


# ------------------------------------------------------------------------- bad arguments


@pytest.mark.parametrize(
    ("make", "match"),
    [
        (lambda: DRParticleFilter(10, prior="huber"), "prior"),
        (lambda: DRParticleFilter(10, prior=ParticleKL), "prior"),
        (lambda: DRParticleFilter(10, prior=InflatedLikelihood()), "prior"),
        (lambda: DRParticleFilter(10, likelihood="kl"), "likelihood"),
        (lambda: DRParticleFilter(10, likelihood=ParticleKL(0.1)), "likelihood"),
        (lambda: DRParticleFilter(10, outlier="clip"), "outlier"),
        (lambda: DRParticleFilter(10, outlier=1e-6), "outlier"),
        (lambda: DRParticleFilter(10, outlier=DropOutliers), "outlier"),
        (lambda: ParticleKL(-1.0), "radius"),
        (lambda: ParticleWasserstein(-0.1), "radius"),
        (lambda: ParticleWassersteinSample(0.0), "radius"),
        (lambda: ParticleWassersteinSample(0.5, num_integration_points=0), "num_integration_points"),
        (lambda: InflatedLikelihood(0.0), "inflation"),
        (lambda: InflatedLikelihood(-2.0), "inflation"),
        (lambda: InflatedLikelihood(jnp.nan), "inflation"),
        (lambda: InflatedLikelihood(jnp.ones(2)), "inflation"),
        (lambda: WassersteinLikelihood(0.0), "radius"),
        (lambda: WassersteinLikelihood(0.1, num_particles=0), "num_particles"),
        (lambda: AugmentedWassersteinLikelihood(-1.0), "radius"),
        (lambda: AugmentedWassersteinLikelihood(0.1, num_particles=2.0), "num_particles"),
        (lambda: DropOutliers(-1e-6), "threshold"),
        (lambda: NearestOutliers(1e-6, num_particles=0), "num_particles"),
        # Old keywords: checked under their own names, as before.
        (lambda: DRParticleFilter(10, theta=0.0), "theta"),
        (lambda: DRParticleFilter(10, theta=jnp.ones(2)), "theta"),
        (lambda: DRParticleFilter(10, prior_radius=-1.0), "prior_radius"),
        (lambda: DRParticleFilter(10, prior="wasserstein_sample"), "prior_radius"),
        (lambda: DRParticleFilter(10, likelihood="wasserstein", likelihood_radius=0.0), "likelihood_radius"),
        (lambda: DRParticleFilter(10, num_likelihood_particles=0), "num_likelihood_particles"),
        # An object and an old keyword that would configure it.
        (lambda: DRParticleFilter(10, likelihood=InflatedLikelihood(2.0), theta=3.0), "theta"),
        (lambda: DRParticleFilter(10, prior=ParticleKL(0.1), prior_radius=0.2), "prior_radius"),
        (lambda: DRParticleFilter(10, outlier=DropOutliers(), outlier_threshold=1e-3), "outlier_threshold"),
        (lambda: DRParticleFilter(10, likelihood=AugmentedWassersteinLikelihood(), num_likelihood_particles=5), "num_likelihood_particles"),
        (lambda: DRParticleFilter(10, outlier=NearestOutliers(), num_likelihood_particles=5), "num_likelihood_particles"),
        (lambda: DRParticleFilter(10, prior=ParticleWassersteinSample(0.5), num_integration_points=10), "num_integration_points"),
        (lambda: DRParticleFilter(10, likelihood=WassersteinLikelihood(), likelihood_radius=0.2), "likelihood_radius"),
    ],
)
def test_bad_arguments_name_the_argument(make, match):
    with pytest.raises(ValueError, match=match):
        make()


def test_unknown_keyword_is_a_type_error():
    with pytest.raises(TypeError, match="radius"):
        DRParticleFilter(10, radius=0.1)


def test_inflate_error_names_the_object():
    with pytest.raises(ValueError, match="InflatedLikelihood .*additive"):
        DRParticleFilter(10)(_nonadditive(), PRIOR, jnp.zeros((3, 1)), jax.random.key(0))


# ------------------------------------------------------------------------- traced checks


@pytest.mark.parametrize(
    ("make", "good", "bad"),
    [
        (ParticleKL, 0.0, -1e-9),
        (ParticleWasserstein, 0.0, -1e-9),
        (ParticleWassersteinSample, 1e-9, 0.0),
        (InflatedLikelihood, 1e-9, 0.0),
        (WassersteinLikelihood, 1e-9, 0.0),
        (AugmentedWassersteinLikelihood, 0.0, -1e-9),
        (DropOutliers, 0.0, -1e-9),
        (NearestOutliers, 0.0, jnp.nan),
    ],
)
def test_valid_at_the_bounds(make, good, bad):
    valid = jax.jit(lambda p: make(p).valid())
    assert bool(valid(good)) and not bool(valid(bad))
    assert bool(make(good).valid())
    with pytest.raises(ValueError):
        make(bad)


def test_traced_out_of_range_is_invalid_hyperparameter(data):
    """Values set with `eqx.tree_at` (no eager check) and traced under `jit`: the run
    reports `invalid_hyperparameter` (throw=False), and only then."""
    ys = data[0][:5]
    flt = DRParticleFilter(8, prior=ParticleKL(0.05), likelihood=InflatedLikelihood(2.0), outlier=DropOutliers(), throw=False)
    result = eqx.filter_jit(lambda f: f(_growth(), PRIOR, ys, jax.random.key(0)).result)
    assert result(flt) == jdrkf.RESULTS.successful
    for where, value in [
        (lambda f: f.likelihood.inflation, -1.0),
        (lambda f: f.likelihood.inflation, 0.0),
        (lambda f: f.prior.radius, -0.1),
        (lambda f: f.outlier.threshold, -1e-6),
        (lambda f: f.outlier.threshold, jnp.inf),
    ]:
        bad = eqx.tree_at(where, flt, jnp.asarray(value))
        assert result(bad) == jdrkf.RESULTS.invalid_hyperparameter, (value,)
    good = eqx.tree_at(lambda f: f.likelihood.inflation, flt, jnp.asarray(3.0))
    assert result(good) == jdrkf.RESULTS.successful


# ------------------------------------------------------------------------------ gradients


def test_gradient_through_the_objects(data):
    """`eqx.filter_grad` reaches `likelihood.inflation` and `prior.radius` (ParticleKL);
    without resampling the filter is smooth in both: gradient = central differences
    (the setup of `test_dr_particle.test_gradient_matches_finite_differences`)."""
    ys, xs = data
    key = jax.random.key(4)
    flt = DRParticleFilter(30, prior=ParticleKL(0.05), likelihood=InflatedLikelihood(3.0), ess_threshold=0.0)

    def loss(f):
        out = f(_growth(), PRIOR, ys, key)
        return jnp.sqrt(jnp.mean((out.filtered_means - xs) ** 2))

    grads = eqx.filter_jit(eqx.filter_grad(loss))(flt)
    value = eqx.filter_jit(loss)
    for where, g in [(lambda f: f.likelihood.inflation, grads.likelihood.inflation), (lambda f: f.prior.radius, grads.prior.radius)]:
        v = where(flt)
        eps = 1e-5 * float(v)
        fd = (float(value(eqx.tree_at(where, flt, v + eps))) - float(value(eqx.tree_at(where, flt, v - eps)))) / (2 * eps)
        assert abs(float(g)) > 1e-6
        np.testing.assert_allclose(float(g), fd, rtol=1e-5)
    assert math.isfinite(float(grads.likelihood.inflation))
