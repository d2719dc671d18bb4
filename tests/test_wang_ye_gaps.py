"""The two Wang & Ye (2022) Tables I–III gaps (see `benchmarks/wang_ye_gaps.py`).

An independent NumPy oracle of the authors' MATLAB filters (`KF.m`, `Huber.m`, `MKF.m`,
`WKF.m` + `FrankWolfe.m`, `GenerateData.m`; it lives in the benchmark script and does not
use jdrkf) is checked against jdrkf on identical data, and then used to test the causes:

- Gap A (WKF): the published WKF/KF ratios fit a WKF whose nominal joint covariance is
  `B Bᵀ`, `B = [Q^½; H Q^½ + R^½ 1ᵀ]` ("sqrt-broadcast"), not the model's independent-noise
  covariance that jdrkf's `WassersteinKF` (and the authors' current code) uses; the stored
  `Results.mat` fits the block-diagonal version.
- Gap B (Table I MKF): under the paper's stated settings the authors' MKF (= ours) is behind
  the WKF on average; the paper's single-episode 9.91 is an ordinary draw of its RMSE.

Expected values are the paper's and the authors' stored numbers; the statistical tolerances
are stated where used (per-episode standard deviations measured with the benchmark).
"""

from __future__ import annotations

import importlib.util
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jdrkf import KalmanFilter, WassersteinKF
from jdrkf.experiments import wang_ye as wy

ROOT = Path(__file__).resolve().parent.parent


def _load_oracle():
    spec = importlib.util.spec_from_file_location("wang_ye_gaps", ROOT / "benchmarks" / "wang_ye_gaps.py")
    mod = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


orc = _load_oracle()
T = 1000


@pytest.fixture(scope="module")
def gains():
    """Oracle gain sequences (authors' Frank–Wolfe, tolerance 1e-4) for T = 1000; they have
    converged by then (change < 1e-6), so longer runs repeat the last gain."""
    return {"KF": orc.oracle_kf_gains(T),
            **{form: orc.oracle_wkf_gains(T, 0.1, form) for form in ("independent", "sqrt-broadcast", "block-diagonal")}}


def _extend(g, n):
    return g if n <= g.shape[0] else np.concatenate([g, np.repeat(g[-1:], n - g.shape[0], 0)])


def _ratio(gains, form, x, y):
    kf = orc.rmse(x, orc.oracle_linear(_extend(gains["KF"], y.shape[1]), y))
    return orc.rmse(x, orc.oracle_linear(_extend(gains[form], y.shape[1]), y)) / kf


# ------------------------------------------------------------------ oracle vs jdrkf


@pytest.mark.parametrize("alpha,outliers", [(1.0, False), (0.0, True)])
def test_oracle_matches_jdrkf_kf_huber_mkf(alpha, outliers):
    """Same closed-form recursions in float64 on the same data: agreement to round-off
    (1e-15 observed; 1e-9 leaves room for the 100-step accumulation)."""
    traj = wy.scenario(jax.random.key(3), 1, alpha, outliers, 100)
    model, p0 = wy.nominal_model(), wy.prior()
    y = np.asarray(traj.observations)[..., 0]
    cases = {
        "KF": (KalmanFilter(), orc.oracle_linear(orc.oracle_kf_gains(100), y)),
        "HKF": (wy.filters()["HKF"], orc.oracle_mkf(y, wy.HUBER_K, wy.EPS, 1.0)),
        "MKF": (wy.mkf(), orc.oracle_mkf(y, wy.HUBER_K, wy.EPS, wy.MKF_THETA2)),
    }
    for name, (flt, ref) in cases.items():
        ours = np.asarray(flt(model, p0, traj.observations[0]).filtered_means)
        np.testing.assert_allclose(ours, ref[0], rtol=1e-9, atol=1e-9, err_msg=name)


def test_joint_noise_forms_match_the_authors_code():
    """`wang_ye.joint_noise_covariance` against the oracle's transcription of each `WKF.m`
    version, and the independent form against its definition."""
    for form in orc.FORMS:
        np.testing.assert_allclose(np.asarray(wy.joint_noise_covariance(form)), orc.oracle_noise(form), rtol=1e-13, atol=1e-13)
    q, h, r = orc.Q, orc.H, orc.R
    w = np.random.default_rng(0).standard_normal((200_000, 3))
    wq = w[:, :2] @ np.linalg.cholesky(q).T
    sample = np.column_stack([wq, wq @ h.T + w[:, 2:] * np.sqrt(r[0, 0])])
    np.testing.assert_allclose(np.cov(sample.T), orc.oracle_noise("independent"), atol=0.05)  # MC error ~0.01
    # sqrt-broadcast: measurement noise variance 2R, correlated with the process noise
    qh = orc.oracle_noise("sqrt-broadcast")
    assert qh[2, 2] == pytest.approx(float((h @ q @ h.T)[0, 0]) + 2.0 * r[0, 0], rel=1e-3)  # H Q^½ 1 ≈ 0 here


@pytest.mark.parametrize("form", ["independent", "sqrt-broadcast"])
def test_authors_frank_wolfe_converges_to_jdrkf_solver(form):
    """The authors' Frank–Wolfe run long (no early stop) reaches jdrkf's exact worst case
    (the O(1/k) method: 4e-7 relative gain error at 100 iterations, measured); with its default
    stop (relative gap 1e-4) it quits after 1–2 iterations about 1% off — the known ~1% gap."""
    a = np.vstack([orc.F, orc.H @ orc.F])
    sigma = a @ np.diag([5.0, 4.0]) @ a.T + orc.oracle_noise(form)
    g_ex, p_ex = (np.asarray(v) for v in wy._wkf_step(jnp.asarray(sigma), jnp.asarray(0.1, jnp.float64)))  # wasserstein_mmse_joint
    g_fw, s_fw, _ = orc.frank_wolfe(sigma, 0.1, 2, tol=0.0, iter_max=150)
    assert np.max(np.abs(g_fw - g_ex)) / np.max(np.abs(g_ex)) < 1e-5
    np.testing.assert_allclose(s_fw[:2, :2] - g_fw @ s_fw[2:, :2], p_ex, rtol=1e-4)
    g_def, _, it = orc.frank_wolfe(sigma, 0.1, 2)
    assert it <= 2
    assert 1e-4 < np.max(np.abs(g_def - g_ex)) / np.max(np.abs(g_ex)) < 5e-2


def test_wkf_gain_path_matches_the_oracle():
    """`wang_ye.wkf_gains` (jdrkf's exact solver), for the model's and for the authors'
    published nominal covariance, equals the oracle's gain path with Frank–Wolfe run 150
    iterations per step (~1e-6 relative, measured)."""
    for form in ("independent", "sqrt-broadcast"):
        ref = orc.oracle_wkf_gains(3, 0.1, form, tol=0.0, iter_max=150)
        np.testing.assert_allclose(wy.wkf_gains(0.1, 3, wy.joint_noise_covariance(form)), ref, rtol=1e-4, atol=1e-5)


@pytest.mark.slow
def test_wkf_is_the_linear_filter_with_its_gain_path():
    """The WKF's covariance path ignores the data: `WassersteinKF` equals the linear filter
    with the gains of `wang_ye.wkf_gains` (same solver; 1e-8 absorbs the solver tolerance;
    6.7e-15 relative in the benchmark)."""
    traj = wy.scenario(jax.random.key(5), 1, 0.0, True, 40)
    ours = np.asarray(WassersteinKF(0.1)(wy.nominal_model(), wy.prior(), traj.observations[0]).filtered_means)
    lin = wy.apply_gains(wy.wkf_gains(0.1, 40, wy.joint_noise_covariance()), traj.observations)[0]
    np.testing.assert_allclose(lin, ours, rtol=1e-8, atol=1e-8)


# ------------------------------------------------------------------ Gap A: the cause


def test_stored_breakdown_run_fits_the_sqrt_broadcast_wkf(gains):
    """Authors' stored breakdown run (α = 0, ε_real = 0.5, ±50, T = 10⁴): WKF/KF = 25.82/24.45 =
    1.056. Per-episode sd of the ratio at T = 10⁴ is ~0.004 (measured), so 0.02 is ~5 sd of the
    single stored episode; the independent-noise WKF (ours) sits at ~1.14."""
    x, y = orc.oracle_simulate(np.random.default_rng(11), 4, 10_000, 0.0, 0.5, 50.0)
    stored = 25.82 / 24.45
    assert abs(_ratio(gains, "sqrt-broadcast", x, y).mean() - stored) < 0.02
    assert _ratio(gains, "independent", x, y).mean() - stored > 0.05
    assert stored - _ratio(gains, "block-diagonal", x, y).mean() > 0.1


def test_table2_ratio_fits_sqrt_broadcast_and_results_mat_fits_block_diagonal(gains):
    """Table II (α = 0, 5% ±100, T = 1000): paper WKF/KF = 1.026; the authors' stored
    Results.mat (same protocol, realized rate 5.9%): 15.86/17.30 = 0.917. Per-episode sd of the
    ratio is ~0.02 (measured); a published single episode is consistent when within 2 sd of a
    setting's mean, and excluded beyond 3 sd."""
    x, y = orc.oracle_simulate(np.random.default_rng(12), 30, T, 0.0, 0.05, 100.0)
    z = {form: (16.56 / 16.14 - r.mean()) / r.std(ddof=1) for form in ("independent", "sqrt-broadcast", "block-diagonal")
         for r in [_ratio(gains, form, x, y)]}
    assert abs(z["sqrt-broadcast"]) < 2
    assert abs(z["independent"]) > 3 and abs(z["block-diagonal"]) > 3
    x, y = orc.oracle_simulate(np.random.default_rng(13), 30, T, 0.0, 0.059, 100.0)
    z = {form: (15.86 / 17.30 - r.mean()) / r.std(ddof=1) for form in ("independent", "sqrt-broadcast", "block-diagonal")
         for r in [_ratio(gains, form, x, y)]}
    assert abs(z["block-diagonal"]) < 2
    assert abs(z["independent"]) > 3 and abs(z["sqrt-broadcast"]) > 3


# ------------------------------------------------------------------ Gap B


def test_table1_mkf_gap_is_episode_noise_with_the_authors_settings(gains):
    """Table I (α = 1, no outliers): the authors' MKF (k = 1.4, ε = 0.05, θ₂ = 1.02; = jdrkf's,
    tested above) has a per-episode RMSE sd of ~2, so the paper's 9.91 is inside its central 95%;
    on average it is behind the WKF (mean MKF/WKF CI above 1, as in the authors' own stored
    α = 1 run, 11.45/10.39), while the unclipped MKF is level with it (CI containing the
    paper's 9.91/9.95)."""
    x, y = orc.oracle_simulate(np.random.default_rng(14), 40, T, 1.0, 0.0, 100.0)
    wkf = orc.rmse(x, orc.oracle_linear(gains["sqrt-broadcast"], y))
    mkf = orc.rmse(x, orc.oracle_mkf(y, 1.4, 0.05, 1.02))
    assert abs(9.91 - mkf.mean()) < 1.96 * mkf.std(ddof=1)
    m, (lo, hi) = orc.mean_ci(mkf / wkf)
    assert lo > 1.0
    _, (lo, hi) = orc.mean_ci(orc.rmse(x, orc.oracle_mkf(y, np.inf, 0.0, 1.02)) / wkf)
    assert lo <= 9.91 / 9.95 <= hi
