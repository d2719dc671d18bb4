"""Failure signals of the public resamplers (`jdrkf.filters.resampling`) on invalid
log-weights (NaN, +inf, all -inf = all-zero weights, the log of a negative weight), and
of the particle filters that call them.

Oracles: the definition of valid log-weights (no NaN, no +inf, one finite entry at
least) and the documented outputs: `ValueError` for concrete input, a run-time error
(`throw=True`) or the identity indices (`throw=False`) for traced input, NaN from `ess`
and `normalized_weights`; per-row results under `vmap` equal to unbatched calls.
"""

import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jdrkf
from jdrkf._nonlinear import NonlinearModel
from jdrkf.filters import resampling as rs
from jdrkf.filters._dr_particle import DRParticleFilter
from jdrkf.filters._particle import BootstrapPF
from jdrkf.sets import InflatedLikelihood

SCHEMES = ["multinomial", "systematic", "stratified", "residual"]
N = 6
_BASE = np.log(np.array([0.1, 0.3, 0.05, 0.25, 0.2, 0.1]))
INVALID = {
    "nan": _BASE.copy(),
    "inf": _BASE.copy(),
    "all_zero": np.full(N, -np.inf),
    "negative": _BASE.copy(),
}
INVALID["nan"][2] = np.nan
INVALID["inf"][4] = np.inf
with np.errstate(invalid="ignore"):
    INVALID["negative"][1] = np.log(-0.3)  # a negative weight: its log is NaN


@pytest.mark.parametrize("scheme", SCHEMES)
@pytest.mark.parametrize("case", list(INVALID))
def test_concrete_invalid_weights_raise(scheme, case):
    with pytest.raises(ValueError, match="log_weights"):
        rs.RESAMPLERS[scheme](jax.random.key(0), jnp.asarray(INVALID[case]))


@pytest.mark.parametrize("scheme", SCHEMES)
def test_traced_invalid_weights(scheme):
    """Under `jit`: a run-time error by default; with `throw=False` the identity indices.
    Valid weights with zero entries pass both ways."""
    fn = rs.RESAMPLERS[scheme]
    raising = jax.jit(fn)
    quiet = jax.jit(lambda k, lw: fn(k, lw, throw=False))
    key = jax.random.key(1)
    for case, lw in INVALID.items():
        with pytest.raises(Exception, match="log_weights"):
            jax.block_until_ready(raising(key, jnp.asarray(lw)))
        np.testing.assert_array_equal(np.asarray(quiet(key, jnp.asarray(lw))), np.arange(N), err_msg=case)
    valid = jnp.asarray(_BASE).at[2].set(-jnp.inf)
    idx = np.asarray(raising(key, valid))
    assert idx.min() >= 0 and idx.max() < N and not np.any(idx == 2)
    np.testing.assert_array_equal(np.asarray(quiet(key, valid)), idx)


@pytest.mark.parametrize("scheme", SCHEMES)
def test_vmap_flags_only_invalid_rows(scheme):
    fn = rs.RESAMPLERS[scheme]
    rows = jnp.asarray(np.stack([_BASE, INVALID["nan"], _BASE + 3.0, INVALID["all_zero"]]))
    keys = jax.random.split(jax.random.key(2), rows.shape[0])
    out = np.asarray(jax.jit(jax.vmap(lambda k, lw: fn(k, lw, throw=False)))(keys, rows))
    for i in (0, 2):
        np.testing.assert_array_equal(out[i], np.asarray(fn(keys[i], rows[i])))
    for i in (1, 3):
        np.testing.assert_array_equal(out[i], np.arange(N))
    with pytest.raises(Exception, match="log_weights"):
        jax.block_until_ready(jax.jit(jax.vmap(fn))(keys, rows))


@pytest.mark.parametrize("fn", [rs.ess, rs.normalized_weights])
def test_ess_and_normalized_weights(fn):
    for case, lw in INVALID.items():
        with pytest.raises(ValueError, match="log_weights"):
            fn(jnp.asarray(lw))
        assert np.all(np.isnan(np.asarray(jax.jit(fn)(jnp.asarray(lw))))), case
    w = np.exp(_BASE) / np.exp(_BASE).sum()
    np.testing.assert_allclose(float(rs.ess(jnp.asarray(_BASE))), 1.0 / np.sum(w * w), rtol=1e-12)
    np.testing.assert_allclose(np.asarray(rs.normalized_weights(jnp.asarray(_BASE + 7.0))), w, rtol=1e-12)


# ----------------------------------------------------------------- the particle filters


def _sqrt_model():
    """`y = √x + v`: NaN likelihoods for the particles with `x < 0`."""
    return NonlinearModel(lambda x, t: 0.9 * x, lambda x, t: jnp.sqrt(x), jnp.eye(1), jnp.eye(1))


PRIOR = jdrkf.Gaussian(jnp.zeros(1), jnp.eye(1))


@pytest.mark.parametrize(
    "make",
    [lambda throw: BootstrapPF(50, ess_threshold=1.0, throw=throw),
     pytest.param(lambda throw: DRParticleFilter(50, likelihood=InflatedLikelihood(2.0), ess_threshold=1.0, throw=throw), marks=pytest.mark.slow)],
    ids=["bootstrap", "dr"],
)
def test_filter_with_nan_weights_reports_failure(make):
    """NaN likelihoods (NaN weights) and an infinite observation (all weights zero) in one
    run of a vmapped batch: that run reports `nonfinite_state`, the others succeed (the
    filters resample with `throw=False`, so no run-time error), and with `throw=True` the
    call raises."""
    model, flt = _sqrt_model(), make(False)
    ys = jnp.ones((3, 8, 1))
    run = eqx.filter_jit(jax.vmap(lambda f, m, y, k: f(m, PRIOR, y, k), in_axes=(None, None, 0, 0)))
    keys = jax.random.split(jax.random.key(0), 3)
    res = run(flt, model, ys, keys)
    assert np.all(np.asarray(res.result == jdrkf.RESULTS.nonfinite_state))
    linear = NonlinearModel(lambda x, t: 0.9 * x, lambda x, t: x, jnp.eye(1), jnp.eye(1))
    ys_inf = ys.at[1, 4, 0].set(jnp.inf)
    res = run(flt, linear, ys_inf, keys)
    np.testing.assert_array_equal(np.asarray(res.result == jdrkf.RESULTS.successful), [True, False, True])
    np.testing.assert_array_equal(np.asarray(res.result == jdrkf.RESULTS.nonfinite_state), [False, True, False])
    assert np.all(np.isfinite(np.asarray(res.marginal_loglik)[[0, 2]]))
    assert not math.isfinite(float(res.marginal_loglik[1]))
    with pytest.raises(Exception, match="non-finite"):
        jax.block_until_ready(run(make(True), model, ys, keys))
