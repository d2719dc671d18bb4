"""The Wang & Ye (2022) Tables I–III gaps and the breakdown τ-KF gap (see `benchmarks/wang_ye_gaps.py`).

An independent NumPy oracle of the authors' MATLAB filters (`KF.m`, `Huber.m`, `MKF.m`,
`WKF.m` + `FrankWolfe.m`, `GenerateData.m`; it lives in the benchmark script and does not
use jdrkf) is checked against jdrkf on identical data, and then used to test the causes:

- Gap A (WKF): the published WKF/KF ratios fit a WKF whose nominal joint covariance is
  `B Bᵀ`, `B = [Q^½; H Q^½ + R^½ 1ᵀ]` ("sqrt-broadcast"), not the model's independent-noise
  covariance that jdrkf's `WassersteinKF` (and the authors' current code) uses; the stored
  `Results.mat` fits the block-diagonal version.
- Gap B (Table I MKF): under the paper's stated settings the authors' MKF (= ours) is behind
  the WKF on average; the paper's single-episode 9.91 is an ordinary draw of its RMSE.
- Gap C (breakdown τ-KF): the authors ran Zorzi's τ-KF as a one-step predictor fed y_{k−1},
  with covariances passed where unit-variance noise factors belong (process covariance
  (GQGᵀ)²); the oracle of that filter (checked against a Kalman predictor and jdrkf's
  `TauKF`) reaches the paper's breakdown numbers, ours (filtered, correct noise) does not.

Expected values are the paper's and the authors' stored numbers; the statistical tolerances
are stated where used (per-episode standard deviations measured with the benchmark).
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import benchmark_scripts

from jdrkf import KalmanFilter, WassersteinKF
from jdrkf.filters import TauKF
from jdrkf.experiments import wang_ye as wy


orc = benchmark_scripts.load("wang_ye_gaps")
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


# ------------------------------------------------------------------ Gap C: the breakdown τ-KF
#
# The oracle's τ-KF (Zorzi's "delayed" predictor, τ = 0) is checked against a textbook Kalman
# predictor written here and against jdrkf's `TauKF`; then the authors' variant (the predictor
# fed y_{k−1}, covariances passed as noise factors) is checked against the paper's numbers.


def _kalman_predictor(y, p1):
    """One-step Kalman predictor x̂_{k+1|k} from x̂_{1|0} = 0, P_{1|0} = p1 (textbook Riccati:
    K = F P Hᵀ S⁻¹, P ← F P Fᵀ + Q − K S Kᵀ); entry t is the prediction made from y_1..y_{t+1}."""
    f, h, q, r = (np.asarray(m) for m in (wy.nominal_model().F, wy.nominal_model().H, wy.nominal_model().Q, wy.nominal_model().R))
    xh, p, out = np.zeros((y.shape[0], 2)), p1, np.zeros((*y.shape, 2))
    for t in range(y.shape[1]):
        s = h @ p @ h.T + r
        k = f @ p @ h.T / s
        xh = xh @ f.T + (y[:, t] - xh @ h[0])[:, None] * k[:, 0][None, :]
        p = f @ p @ f.T + q - k @ s @ k.T
        out[:, t] = xh
    return out


def _tau_episodes(key, runs, alpha, prob, num_steps):
    traj = wy.scenario(jax.random.key(key), runs, alpha, True, num_steps, prob=prob, magnitude=50.0)
    return traj, np.asarray(traj.states), np.asarray(traj.observations)[..., 0]


def test_tau_oracle_with_zero_tolerance_is_the_kalman_predictor():
    """c = 0 (and c → 0) with the correct noise factors B = [chol(Q), 0], D = [0, chol(R)]: the
    Kalman predictor to round-off (c = 1e-14 moves V by ~1e-7 relative); c = 1.5e-4 does differ."""
    _, _, y = _tau_episodes(21, 3, 1.0, 0.2, 300)
    f, q = orc.F, orc.Q
    p1 = f @ f.T + q
    ref = _kalman_predictor(y, p1)
    b, d = orc.tau_factors("sqrt")
    np.testing.assert_allclose(b[:, :2] @ b[:, :2].T, np.asarray(wy.nominal_model().Q), rtol=1e-14)
    for c, tol in ((0.0, 1e-10), (1e-14, 1e-5)):
        gains, thetas, _ = orc.oracle_tau_gains(300, b, d, c, v0=p1)
        assert np.all(thetas >= 0) and (c > 0) == np.all(thetas > 0)
        np.testing.assert_allclose(orc.oracle_tau_predict(gains, y), ref, rtol=tol, atol=tol * np.abs(ref).max())
    gains, _, _ = orc.oracle_tau_gains(300, b, d, 1.5e-4, v0=p1)
    assert np.max(np.abs(orc.oracle_tau_predict(gains, y) - ref)) > 1e-2 * np.abs(ref).max()


@pytest.mark.parametrize("c", [1.5e-4, 1e-2])
def test_tau_oracle_matches_jdrkf_taukf_predicted_means(c):
    """With the correct factors the oracle's predictions are jdrkf's `TauKF(0, c)` predicted means
    x̂_{k|k−1} (jdrkf robustifies F P₀ Fᵀ + Q at its first step; the oracle is started there), and
    its θ_k are jdrkf's: the same recursion in float64 (2e-12 observed on estimates of ~100)."""
    traj, _, y = _tau_episodes(22, 2, 1.0, 0.3, 200)
    res = jax.vmap(lambda yy: TauKF(0.0, c, outputs="all")(wy.nominal_model(), wy.prior(), yy))(traj.observations)
    pm, th_j = np.asarray(res.predicted_means), np.asarray(res.info["theta"])
    b, d = orc.tau_factors("sqrt")
    th1, v1 = orc.kl_robustify(orc.F @ orc.F.T + orc.Q, c)
    gains, thetas, _ = orc.oracle_tau_gains(200, b, d, c, v0=v1)
    np.testing.assert_allclose(pm[:, 0], 0.0, atol=1e-12)
    np.testing.assert_allclose(orc.oracle_tau_predict(gains, y)[:, :-1], pm[:, 1:], rtol=1e-9, atol=1e-8)
    np.testing.assert_allclose(np.concatenate([[th1], thetas[:-1]]), th_j[0], rtol=1e-10)
    # θ solves the KL budget: Σ φ₀(θ p_i) = c, with φ₀(s) = s/(1 − s) + log(1 − s)
    p = np.linalg.eigvalsh(np.asarray(res.info["nominal_predicted_cov"])[0, 5])
    s = th_j[0, 5] * p
    assert np.sum(s / (1 - s) + np.log(1 - s)) == pytest.approx(c, rel=1e-9)


def test_authors_factors_square_the_process_covariance_and_pass_more_outliers():
    """The authors' B = [GQGᵀ, 0], D = [0, DRDᵀ]: Zorzi's reduction gives the process covariance
    B Bᵀ = (GQGᵀ)² (≈ 3.84 I against 1.96 I), R² = R = 1 and A = F. The larger assumed process noise
    raises the gain, so with 30% ±50 outliers (T = 2000) the authors' variant is worse than the
    correct predictor fed the same y_{k−1}: paired per-episode difference, CI above 0."""
    m = wy.nominal_model()
    q, r, f = np.asarray(m.Q), np.asarray(m.R), np.asarray(m.F)
    b_cov, d_cov = orc.tau_factors("covariance")
    a_eff, q_eff, r_eff = orc.tau_transform(f, b_cov, np.asarray(m.H), d_cov)
    np.testing.assert_allclose(q_eff, q @ q, rtol=1e-14)
    assert np.diag(q_eff) == pytest.approx([3.845, 3.844], abs=1e-3)
    np.testing.assert_allclose(r_eff, r @ r, rtol=1e-14)
    np.testing.assert_allclose(a_eff, f, rtol=1e-14)
    b_ok, d_ok = orc.tau_factors("sqrt")
    _, q_ok, r_ok = orc.tau_transform(f, b_ok, np.asarray(m.H), d_ok)
    np.testing.assert_allclose(q_ok, q, rtol=1e-14)
    np.testing.assert_allclose(r_ok, r, rtol=1e-14)

    _, x, y = _tau_episodes(23, 8, 0.0, 0.3, 2000)
    y_delay = np.concatenate([np.zeros((y.shape[0], 1)), y[:, :-1]], axis=1)
    ok, auth = (orc.oracle_tau_gains(2000, *orc.tau_factors(form))[0] for form in ("sqrt", "covariance"))
    assert auth[-1, 0, 0] > ok[-1, 0, 0]
    diff = orc.rmse(x, orc.oracle_tau_predict(auth, y_delay)) - orc.rmse(x, orc.oracle_tau_predict(ok, y_delay))
    _, (lo, _) = orc.mean_ci(diff)
    assert lo > 0


def test_authors_variant_reaches_the_papers_breakdown_tau_kf_and_ours_does_not():
    """The paper's breakdown τ-KF at ε_real = 0.5 (±50 outliers, T = 10⁴, one episode each): 31.12
    (α = 0) and 31.35 (α = 1). The per-episode sd of the RMSE there is ~0.2 (measured: benchmark
    section 4), so the mean of 6 episodes of a setting that fits lies within 0.5 of the paper's
    number (2.5 sd of one episode); ours (jdrkf `TauKF`, filtered, correct noise) is more than 1
    below it (5 sd)."""
    n = 10_000
    g = orc.oracle_tau_gains(1500, *orc.tau_factors("covariance"))[0]  # converged to 1e-13 by step 1400
    g = np.concatenate([g, np.repeat(g[-1:], n - g.shape[0], 0)])
    for alpha, paper in ((0.0, 31.12), (1.0, 31.35)):
        traj, x, y = _tau_episodes(24, 6, alpha, 0.5, n)
        y0 = np.asarray(traj.initial_states) @ orc.H[0] + np.random.default_rng(int(alpha)).standard_normal(6)
        authors = orc.rmse(x, orc.oracle_tau_predict(g, np.concatenate([y0[:, None], y[:, :-1]], axis=1)))
        res = jax.vmap(lambda yy: TauKF(0.0, wy.TAU_C)(wy.nominal_model(), wy.prior(), yy))(traj.observations)
        ours = orc.rmse(x, np.asarray(res.filtered_means))
        assert abs(authors.mean() - paper) < 0.5, (alpha, authors.mean())
        assert paper - ours.mean() > 1.0, (alpha, ours.mean())


# ------------------------------------------------------------------ Gap D: breakdown MKF at α = 1


def test_conditional_prediction_is_the_textbook_interval():
    """One predictor: ŷ₀ ± t₀.₉₇₅,ₙ₋₂ s √(1 + 1/n + (x₀ − x̄)²/Sxx) (simple linear regression)."""
    from scipy import stats

    rng = np.random.default_rng(3)
    x = rng.normal(10.0, 1.0, 50)
    y = 2.0 + 0.7 * x + rng.normal(0.0, 0.3, 50)
    x0 = 8.5
    sxx = np.sum((x - x.mean()) ** 2)
    b1 = np.sum((x - x.mean()) * (y - y.mean())) / sxx
    b0 = y.mean() - b1 * x.mean()
    s = np.sqrt(np.sum((y - b0 - b1 * x) ** 2) / 48)
    half = stats.t.ppf(0.975, 48) * s * np.sqrt(1 + 1 / 50 + (x0 - x.mean()) ** 2 / sxx)
    pred, (lo, hi), sd = orc.conditional_prediction(y, x[:, None], [x0])
    np.testing.assert_allclose([pred, lo, hi, sd], [b0 + b1 * x0, b0 + b1 * x0 - half, b0 + b1 * x0 + half, s], rtol=1e-12)


def test_breakdown_mkf_gap_is_the_papers_easy_episode():
    """Fig. 2(b), ε_real = 0: the paper's MKF 9.72 is far below our mean (ours ~11.3, per-episode sd
    ~0.8), but the paper's KF, HKF and TMKF (fed F_{t+1}) of the same episode are low as well (6th,
    4th, 5th percentile of 200 episodes: benchmark section 5), and the MKF predicted from them lies
    within 0.5 of 9.72 (residual sd 0.2). On 40 episodes: the mean misses 9.72 by more than 1, the
    episode-conditional 95% prediction interval contains it."""
    mk = orc.mkf_section(0, 2, 20, 10_000, lambda _: None, eps_real=(0.0,))
    cell = mk["cells"][0]
    assert cell["filters"]["MKF"]["ci95"][0] - 9.72 > 1.0
    assert all(cell["filters"][f]["target_percentile"] <= 15.0 for f in orc.MKF_PREDICTORS), cell["filters"]
    cond = cell["conditional"]
    assert cond["consistent"] and abs(cond["prediction"] - 9.72) < 0.5, cond
