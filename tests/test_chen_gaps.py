"""The Chen et al. (2025) Table I `code-dt0.1` gaps (see `benchmarks/chen_gaps.py`).

An independent NumPy oracle of the authors' MATLAB CI baseline (local Kalman updates of the
common fused prior, fused by MATLAB's `fusecovint`, fed back) and of their `KF.m` lives in the
benchmark script and does not use jdrkf. With the weights jdrkf uses (the minimizer of
log det or tr of the fused covariance) it reproduces jdrkf's `CovarianceIntersection`; with
the weights `fusecovint` actually computes (ωᵢ ∝ 1/det Pᵢ, no optimization) it lands on the
paper's CI row, which jdrkf's optimized weights miss by 25–30%. The KF acceleration row is
Monte Carlo noise: the stored report's 1000 runs are a low batch (slow test).

Expected values are hand-computed weights, the paper's Table I, and directions of effects;
tolerances are stated where used.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import benchmark_scripts

from jdrkf import KalmanFilter
from jdrkf.experiments import chen_fusion as cf
from jdrkf.filters._fusion import CovarianceIntersection

PAPER_CI = (7.9864, 23.0917, 16.7782)  # Table I, CI: MSE x, v, a
PAPER_KF_A = 20.3734  # Table I, KF: MSE a


orc = benchmark_scripts.load("chen_gaps")


def _episodes(seed, runs, steps):
    """The `code-dt0.1` test episodes of `jdrkf reproduce chen-fusion --seed seed` (first `runs`)."""
    _, true_model, _ = cf.scenario("code-dt0.1")
    tr = cf._simulate(jax.random.fold_in(jax.random.key(seed), 0), true_model, runs, steps)
    return np.asarray(tr.states), np.asarray(tr.observations)


def _jdrkf_means(flt, ys):
    model, _, prior = cf.scenario("code-dt0.1")
    if isinstance(flt, KalmanFilter):
        return np.asarray(jax.vmap(lambda y: flt(model.sensor(0), prior, y).filtered_means)(jnp.asarray(ys[..., :1])))
    return np.asarray(jax.vmap(lambda y: flt(model, prior, y).filtered_means)(jnp.asarray(ys)))


def test_fusecovint_weights_are_the_inverse_determinants_normalized():
    """MATLAB's fusecovint solves cᵢωᵢ = cᵢ₊₁ωᵢ₊₁, Σω = 1 with cᵢ = det Pᵢ (or tr Pᵢ).
    det = 8, 1, 4 → ω ∝ (1/8, 1, 1/4) = (1, 8, 2)/11; tr = 6, 3, 6 → ω = (1, 2, 1)/4."""
    covs = [2.0 * np.eye(3), np.eye(3), np.diag([1.0, 1.0, 4.0])]
    np.testing.assert_allclose(orc.fusecovint_weights(covs, "det"), np.array([1.0, 8.0, 2.0]) / 11.0, rtol=1e-12)
    np.testing.assert_allclose(orc.fusecovint_weights(covs, "trace"), np.array([1.0, 2.0, 1.0]) / 4.0, rtol=1e-12)


def test_optimal_weights_pick_the_dominating_estimate():
    """Nested covariances: the smallest one is the CI optimum under both criteria."""
    covs = [2.0 * np.eye(3), np.eye(3), 3.0 * np.eye(3)]
    for criterion in ("det", "trace"):
        np.testing.assert_allclose(orc.optimal_weights(covs, criterion), [0.0, 1.0, 0.0], atol=1e-9)


@pytest.fixture(scope="module")
def small():
    """40 runs × 120 steps of the code-dt0.1 episodes (seed 0)."""
    return _episodes(0, 40, 120)


@pytest.mark.parametrize("criterion", ["det", "trace"])
def test_oracle_with_optimized_weights_equals_jdrkf_covariance_intersection(small, criterion):
    """Same weight rule ⇒ same filter. Tolerance: the objectives are flat at interior optima
    (a 1e-6 change of ω moves log det by ~1e-13), so the two optimizers' weights agree to
    ~1e-5 and the filtered means to 1e-3 absolute (values of order 1–100); per-run MSEs to 1e-5."""
    xs, ys = small
    ours = _jdrkf_means(CovarianceIntersection(criterion, throw=False), ys)
    oracle = orc.ci_apply(orc.ci_plan(f"optimal-{criterion}", steps=ys.shape[1]), ys)
    np.testing.assert_allclose(ours, oracle, atol=1e-3)
    np.testing.assert_allclose(orc.per_run_mse(xs, ours), orc.per_run_mse(xs, oracle), rtol=1e-5)


def test_oracle_fusion_formula_equals_jdrkf_at_fixed_weights(small):
    """jdrkf's CI with rtol = 0.1 stops at its uniform starting weights: with ω = 1/3 in the
    oracle the two must agree to round-off (1e-8), checking the fusion formula itself."""
    _, ys = small
    ours = _jdrkf_means(CovarianceIntersection("det", rtol=0.1, throw=False), ys)
    oracle = orc.ci_apply(orc.ci_plan("uniform", steps=ys.shape[1]), ys)
    np.testing.assert_allclose(ours, oracle, atol=1e-8)


def test_oracle_kf_equals_jdrkf_on_sensor_one(small):
    _, ys = small
    np.testing.assert_allclose(_jdrkf_means(KalmanFilter(throw=False), ys), orc.kf_apply(ys), atol=1e-9)


def test_fusecovint_weights_are_near_uniform_and_the_det_minimizer_picks_sensor_one():
    authors = orc.ci_plan("fusecovint-det")["w"]
    optimal = orc.ci_plan("optimal-det")["w"]
    assert np.all((authors > 0.25) & (authors < 0.45))
    assert np.mean(optimal[:, 0] >= 0.99) > 0.9


def test_authors_ci_lands_on_the_paper_and_jdrkf_ci_does_not():
    """On the stored report's 1000 episodes the fusecovint-weighted CI's 95% interval holds the
    paper's three CI numbers; the det-minimizing CI (jdrkf's) is above each, paired."""
    xs, ys = _episodes(0, 1000, orc.STEPS)
    authors = orc.per_run_mse(xs, orc.ci_apply(orc.ci_plan("fusecovint-det"), ys))
    ours = orc.per_run_mse(xs, _jdrkf_means(CovarianceIntersection("det", throw=False), ys))
    for j, paper in enumerate(PAPER_CI):
        s = orc.summarize(authors[:, j], paper)
        assert s["inside_ci"], (j, s)
        assert not orc.summarize(ours[:, j], paper)["consistent"]
        d = orc.summarize(ours[:, j] - authors[:, j])
        assert d["ci95"][0] > 0.1 * paper, (j, d)


def test_no_feedback_does_not_close_the_gap(small):
    """Fusing independent local KFs (no feedback) with fusecovint's weights stays far above the
    authors' fed-back CI: the feedback is part of the authors' algorithm."""
    xs, ys = small
    fed = orc.per_run_mse(xs, orc.ci_apply(orc.ci_plan("fusecovint-det", steps=ys.shape[1]), ys)).mean(0)
    independent = orc.per_run_mse(xs, orc.ci_apply(orc.ci_plan("fusecovint-det", feedback=False, steps=ys.shape[1]), ys)).mean(0)
    assert np.all(independent > 1.1 * fed)


@pytest.mark.slow
def test_kf_acceleration_row_is_within_the_spread_of_1000_run_averages():
    """20 000 runs (seeds 0–19): the stored report's batch is among the lowest for the KF's
    MSE a, and the paper's 20.37 is within 1.96 standard errors of a 1000-run mean of the pooled one."""
    batch, pooled = [], []
    for seed in range(20):
        xs, ys = _episodes(seed, 1000, orc.STEPS)
        mse = orc.per_run_mse(xs, orc.kf_apply(ys))[:, 2]
        batch.append(mse.mean())
        pooled.append(mse)
    s = orc.summarize(np.concatenate(pooled), PAPER_KF_A)
    assert s["consistent"], s
    assert np.sum(np.asarray(batch) <= batch[0]) <= 4
    assert not s["ci95"][0] <= batch[0] <= s["ci95"][1]
