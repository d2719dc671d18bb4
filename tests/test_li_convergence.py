"""Li et al. (Variational Robust KFs) Example 2, `li-convergence`: the theory of
Theorems 5–6 against closed forms and a NumPy simulation of the λ recursion (47), and
the experiment run small (few runs, short horizon)."""

import math

import jax
import numpy as np
import pytest
import scipy.linalg

import jdrkf.experiments
from jdrkf.experiments import li_convergence as lc


def test_registered():
    exp = jdrkf.experiments.get("li-convergence")
    assert exp.run is lc.run and exp.default_runs >= 100
    assert lc.RHOS == (0.995, 0.99, 0.98, 0.97) and lc.NUM_STEPS == 6000


def test_true_variance_is_eq_53():
    v = lc.true_variance()
    # index t is step k = t + 1: 0.1 for k <= 2000, 2.5 for 2000 < k <= 4000, 0.1 after.
    assert v.shape == (6000,)
    assert v[0] == v[1999] == 0.1 and v[2000] == v[3999] == 2.5 and v[4000] == v[-1] == 0.1
    assert lc.jumps(6000) == (2000, 4000)
    with pytest.raises(ValueError, match="num_steps"):
        lc.jumps(3)


def test_time_constant_closed_form():
    rhos = np.array([0.995, 0.99, 0.98, 0.97])
    tau = lc.time_constant(rhos)
    np.testing.assert_allclose(rhos**tau, math.exp(-1.0), rtol=1e-12)  # ρ^τ = 1/e
    np.testing.assert_allclose(tau * 0.01, [1.99499, 0.99499, 0.49498, 0.32831], atol=1e-5)  # seconds
    for bad in (1.0, 0.0, 1.5):
        with pytest.raises(ValueError, match="rho"):
            lc.time_constant(bad)


def test_theorem5_against_numpy_simulation_of_recursion_47():
    """λ_k = ρλ_{k−1} + (1 − ρ)(e_k² + c), e_k ~ N(0, Σ) i.i.d.: stationary mean Σ + c
    (= Σ̄ for c = wPwᵀ) and variance 2(1 − ρ)Σ²/(1 + ρ)."""
    rng = np.random.default_rng(5)
    rho, sigma, c = 0.98, 1.7, 0.3
    lam = np.full(40000, sigma + c)
    for _ in range(600):  # burn-in: ρ^600 ≈ 5e-6
        lam = rho * lam + (1 - rho) * (sigma * rng.standard_normal(lam.size) ** 2 + c)
    samples = []
    for _ in range(200):
        lam = rho * lam + (1 - rho) * (sigma * rng.standard_normal(lam.size) ** 2 + c)
        samples.append(lam.copy())
    samples = np.asarray(samples)
    assert samples.mean() == pytest.approx(sigma + c, rel=2e-3)
    assert samples.var(axis=1).mean() == pytest.approx(float(lc.stationary_variance(rho, sigma)), rel=0.03)
    # and the geometric series Σ_j ρ^{2j} (1 − ρ)² 2Σ² written out
    series = sum(rho ** (2 * j) for j in range(5000)) * (1 - rho) ** 2 * 2 * sigma**2
    assert float(lc.stationary_variance(rho, sigma)) == pytest.approx(series, rel=1e-10)
    np.testing.assert_allclose(np.sqrt(lc.stationary_variance(np.array([0.99, 0.97]), 1.0)), [0.100251, 0.174519], rtol=1e-5)


def _scipy_wpw(variance):
    dt = 0.01
    f = np.array([[1.0, dt], [0.0, 1.0]])
    g = np.array([[0.5 * dt**2], [dt]])
    h = np.array([[1.0, 0.0]])
    r = np.array([[variance]])
    p = scipy.linalg.solve_discrete_are(f.T, h.T, g @ g.T, r)
    post = p - p @ h.T @ np.linalg.solve(h @ p @ h.T + r, h @ p)
    return float((h @ post @ h.T)[0, 0] / 0.1)


@pytest.mark.parametrize("variance", [0.1, 2.5])
def test_theorem5_moments_against_scipy_riccati(variance):
    wpw = _scipy_wpw(variance)
    assert lc.whitened_posterior_variance(variance) == pytest.approx(wpw, rel=1e-8)
    sbar, sig = lc.theorem5_moments(variance)
    assert sbar == pytest.approx(variance / 0.1 + 2 * wpw, rel=1e-8)
    assert sig == pytest.approx(variance / 0.1 + wpw, rel=1e-8)


def test_theory_curve_is_theorem_6():
    """After each jump the expected estimate approaches the new level as δ₀ρᵖ, p = k − m + 1."""
    rho = 0.98
    curve = lc.theory_curve(rho, 6000)
    lo, hi = (0.1 * lc.theorem5_moments(v)[0] for v in (0.1, 2.5))
    p = np.arange(1, 400)
    np.testing.assert_allclose(curve[2000 + p - 1] - hi, (lo - hi) * rho**p, rtol=1e-8, atol=1e-12)
    np.testing.assert_allclose(curve[4000 + p - 1] - lo, (hi - lo) * rho**p, rtol=1e-8, atol=1e-12)
    assert curve[1999] == pytest.approx(lo, rel=1e-10)


@pytest.mark.parametrize("rho", [0.995, 0.97])
def test_crossing_time_constant_recovers_exponential(rho):
    p = np.arange(3000)
    curve = np.concatenate([np.full(500, 3.0), 1.0 + 2.0 * rho ** (p + 1)])  # δ_p = δ₀ρᵖ from t = 500
    assert lc.crossing_time_constant(curve, 500, 3.0, 1.0) == pytest.approx(float(lc.time_constant(rho)), abs=0.05)
    up = 4.0 - curve  # the mirrored (upward) jump
    assert lc.crossing_time_constant(up, 500, 1.0, 3.0) == pytest.approx(float(lc.time_constant(rho)), abs=0.05)
    assert math.isnan(lc.crossing_time_constant(np.full(800, 3.0), 500, 3.0, 1.0))


def test_scenario_noise_levels():
    tr = lc.scenario(jax.random.key(3), 40, 1500)
    v = np.asarray(tr.observations[..., 0] - tr.states[..., 0])
    assert v[:, :500].var() == pytest.approx(0.1, rel=0.08)
    assert v[:, 500:1000].var() == pytest.approx(2.5, rel=0.08)
    assert v[:, 1000:].var() == pytest.approx(0.1, rel=0.08)


@pytest.fixture(scope="module")
def report():
    return lc.run(runs=12, seed=1, num_steps=1800, rhos=(0.98, 0.97), bootstrap=50, curves=True)


def test_report_structure(report):
    rows = {(r.filter, r.metric): r for r in report.rows}
    names = ("STKF-AR1 ρ=0.98", "STKF-AR1 ρ=0.97")
    metrics = ["time_constant_s@up", "time_constant_s@down"] + [f"ss_{s}@seg{j}" for j in (1, 2, 3) for s in ("mean", "std")]
    assert set(rows) == {(f, m) for f in names for m in metrics + ["rmse_x1", "rmse_x2"]} | {("KF", "rmse_x1"), ("KF", "rmse_x2")}
    assert all(r.runs == 12 and np.isfinite(r.mean) for r in report.rows)
    assert all(r.ci95[0] <= r.mean <= r.ci95[1] for r in report.rows)
    assert rows[("STKF-AR1 ρ=0.98", "time_constant_s@up")].paper == pytest.approx(-0.01 / math.log(0.98))
    assert rows[("STKF-AR1 ρ=0.97", "ss_std@seg2")].paper == pytest.approx(0.1 * math.sqrt(2 * 0.03 / 1.97) * lc.theorem5_moments(2.5)[1])
    assert set(report.curves) == {"true variance"} | {f"{f}: {c}" for f in names for c in ("mean 0.1 λ_k", "Theorems 5–6")}
    assert all(c.shape == (1800,) for c in report.curves.values())
    assert "li-convergence" in report.table() and any("6000" in n for n in report.notes)


def test_empirical_tracking_matches_theory_loosely(report):
    """The filter's mean variance estimate approaches each new level with a time constant
    within a loose factor of −1/ln ρ, settles near the true variance, and its across-run
    std is within a loose factor of Theorem 5's."""
    rows = {(r.filter, r.metric): r for r in report.rows}
    for rho in (0.98, 0.97):
        name = f"STKF-AR1 ρ={rho:g}"
        theory = -0.01 / math.log(rho)
        for jump in ("up", "down"):
            assert 0.6 * theory < rows[(name, f"time_constant_s@{jump}")].mean < 1.6 * theory
        for j, truth in ((1, 0.1), (2, 2.5), (3, 0.1)):
            assert rows[(name, f"ss_mean@seg{j}")].mean == pytest.approx(truth, rel=0.1)
            row = rows[(name, f"ss_std@seg{j}")]
            assert 0.6 * row.paper < row.mean < 1.6 * row.paper
    # faster forgetting: shorter time constant, larger steady-state spread (the trade-off of Fig. 7a)
    assert rows[("STKF-AR1 ρ=0.97", "ss_std@seg2")].mean > rows[("STKF-AR1 ρ=0.98", "ss_std@seg2")].mean
    # adapting to the ×25 segment beats the KF with the nominal R on position
    assert rows[("STKF-AR1 ρ=0.98", "rmse_x1")].mean < rows[("KF", "rmse_x1")].mean


def test_run_rejects_bad_arguments():
    with pytest.raises(ValueError, match="runs"):
        lc.run(runs=1, seed=0, num_steps=60)
    with pytest.raises(ValueError, match="rho"):
        lc.run(runs=2, seed=0, num_steps=60, rhos=(1.0,))
