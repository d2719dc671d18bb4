"""The Jang, Hakobyan & Yang (2025) Table 1 gaps (see `benchmarks/jang_gaps.py`).

The benchmark holds a NumPy/SciPy re-implementation of the authors' code
(`jangminhyuk/SteadyStateDRKF`: `main.py`'s random stream and pykalman EM, `KF.py`,
`risk_sensitive.py`, `BCOT.py` + `utils.optimize`). These tests check it against jdrkf where the
two should agree, and check the causes it demonstrates:

- Gaussian KF: the oracle's KF is jdrkf's, and the authors' protocol on their own seeds
  (2024–2043) lands on Table 1, so the gap to our 100 runs is the particular 20 seeds
  (heavy-tailed per-run costs), not the filter;
- BCOT: with its quirks switched off the oracle is jdrkf's `BCOTKF`; the authors' trust-constr
  (20 iterations) stops far short of the worst case, and applying A twice raises cost and MSE;
- risk-sensitive: the authors' heuristic gain lowers the U-quadratic MSE to Table 1's level, the
  standard recursion (ours) does not.

Expected values are the paper's (Table 1) or independent computations (jdrkf against the oracle);
statistical margins are stated where used.
"""

from __future__ import annotations

import jax.numpy as jnp
import numpy as np
import equinox as eqx
import pytest

import benchmark_scripts

from jdrkf import BCOTKF, Gaussian, LinearModel
from jdrkf import em_noise_covariances
from jdrkf.sets import bcot_worst_case


orc = benchmark_scripts.load("jang_gaps")


@pytest.fixture(scope="module")
def replica():
    """EM nominals and draws of the authors' 20 experiments, both settings (NumPy EM oracle)."""
    return {s: orc.replica_data(s, orc.AUTHOR_SEEDS) for s in orc.SETTINGS}


def test_replayed_stream_and_em_match_the_authors_protocol():
    """The replayed EM data: 5 outputs of 2 components; the EM oracle agrees with jdrkf's EM when
    both run the full 100 iterations, and on seed 2027 (Gaussian) it stops early, as pykalman does
    (measured: 73 NumPy, 74 pykalman), while jdrkf's EM runs 100 iterations."""
    v = orc.SETTINGS["gaussian"][1]
    ys, draws = orc.authors_draws(2024, "gaussian")
    assert ys.shape == (5, 2) and set(draws) == set(orc.STREAM_ORDER)
    assert draws["KF"][1].shape == (orc.T, 4) and draws["KF"][2].shape == (orc.T + 1, 2)
    assert not np.allclose(draws["KF"][1], draws["SS-KF"][1])  # each filter its own noise
    em_jdrkf = eqx.filter_jit(lambda y: em_noise_covariances(orc.A, orc.C, y, jnp.zeros(4), v * jnp.eye(4), max_iter=100))
    q, r, it = orc.em_oracle(ys, v * np.eye(4))
    em = em_jdrkf(jnp.asarray(ys))
    assert it == 100 and int(em.iterations) == 100
    np.testing.assert_allclose(q, np.asarray(em.Q), rtol=0, atol=1e-10)
    np.testing.assert_allclose(r, np.asarray(em.R), rtol=0, atol=1e-10)
    ys27, _ = orc.authors_draws(2027, "gaussian")
    _, _, it27 = orc.em_oracle(ys27, v * np.eye(4))
    em27 = em_jdrkf(jnp.asarray(ys27))
    assert 60 <= it27 < 100 and int(em27.iterations) == 100


def test_authors_protocol_on_their_seeds_lands_on_table_one(replica):
    """KF and SS-KF of the authors' code on seeds 2024–2043 reproduce Table 1 (mean and sd over the
    20 experiments). Margins: 1% Gaussian, 3% U-quadratic on means (the early EM stops are round-off
    dependent: moving them by ±4 iterations moves the means by up to 1.3% / 3%), 5% on the sds."""
    for setting, margin in (("gaussian", 0.01), ("uquadratic", 0.03)):
        for name in ("KF", "SS-KF"):
            cost, mse = orc.run_filter(replica[setting], name)
            for values, metric in ((cost, "cost"), (mse, "mse")):
                mean, sd = orc.PAPER[setting][name][metric]
                assert abs(values.mean() / mean - 1) < margin, (setting, name, metric, values.mean(), mean)
                assert abs(values.std() / sd - 1) < 0.05 + margin, (setting, name, metric, values.std(), sd)


def test_papers_kf_cell_is_carried_by_a_few_runs(replica):
    """Gaussian KF on the authors' seeds: heavy tailed — the two costliest of the 20 runs carry more
    than 40% of the total cost (measured 49%) and the median run costs less than 40% of the mean, so
    the 20-run mean of Table 1 depends on which seeds hold a catastrophic EM nominal."""
    cost, _ = orc.run_filter(replica["gaussian"], "KF")
    top2 = np.sort(cost)[-2:].sum() / cost.sum()
    assert top2 > 0.4 and np.median(cost) < 0.4 * cost.mean()


def test_oracle_kf_equals_jdrkf_closed_loop_on_our_episodes():
    """Two closed-loop episodes of `jdrkf reproduce jang-lqr`'s system and U-quadratic noise (a fixed
    mismatched nominal instead of an EM one): the oracle's KF on jdrkf's draws gives jdrkf's cost and
    MSE to 1e-10 (the benchmark checks the 100 stored test runs the same way)."""
    import jax

    from jdrkf import KalmanFilter, closed_loop
    from jdrkf import LQRController
    from jdrkf.experiments import jang

    v = orc.SETTINGS["uquadratic"][1]
    q, r = 3 * v * np.eye(4) + 0.001 * np.ones((4, 4)), 0.3 * v * np.eye(2)
    x0_law, w_law, v_law, prior = jang._laws("uquadratic")
    a, b, c = jang.lqr_system()
    ctrl = LQRController.design(a, b, jang.LQR_Q, jang.LQR_R)
    model = LinearModel(F=a, H=c, Q=q, R=r, B=b)
    run = jax.jit(jax.vmap(lambda k: closed_loop(k, KalmanFilter(), model, prior, ctrl, jnp.asarray(jang.reference_trajectory()),
                                                 true_model=jang._true_model("uquadratic"), initial_state=x0_law,
                                                 process_noise=w_law, measurement_noise=v_law)))
    res = run(jax.random.split(jax.random.key(3), 2))
    ep = {"q": np.stack([q, q]), "r": np.stack([r, r]), "v": v, "x0": np.asarray(res.initial_state),
          "ws": np.asarray(res.process_noise), "vs": np.asarray(res.measurement_noise)}
    cost, mse = orc.run_filter(ep, "KF")
    np.testing.assert_allclose(cost, np.asarray(res.cost(jang.LQR_Q, jang.LQR_R)), rtol=1e-10)
    np.testing.assert_allclose(mse, np.asarray(res.mse()), rtol=1e-10)


def test_bcot_oracle_with_quirks_off_equals_bcotkf():
    """The authors' step problem (their objective and budget) solved to convergence (SLSQP), mean
    predicted once: the filter equals `jdrkf.BCOTKF` on a 2-state problem (measured 2e-8)."""
    rng = np.random.default_rng(1)
    a, c = np.array([[0.9, 0.5], [0.0, 0.8]]), np.array([[1.0, 0.5]])
    q, r, p0 = np.array([[0.3, 0.05], [0.05, 0.2]]), np.array([[0.5]]), np.eye(2)
    ys = rng.normal(size=(4, 1))
    for radius in (0.1, 1.0):
        jd = BCOTKF(radius)(LinearModel(F=a, H=c, Q=q, R=r), Gaussian(np.zeros(2), p0), jnp.asarray(ys))
        m, p = np.zeros(2), p0.copy()
        for t in range(ys.shape[0]):
            bm, d, sig = orc.bcot_slsqp(radius, a, q, c, r, p)
            mm = c @ a @ sig @ a.T + c @ bm
            kk = c @ a @ sig @ a.T @ c.T + c @ bm @ c.T + d
            slope = mm.T @ np.linalg.inv(kk)
            m = a @ m + slope @ (ys[t] - c @ a @ m)
            p = a @ sig @ a.T + bm - mm.T @ np.linalg.inv(kk) @ mm
            np.testing.assert_allclose(m, np.asarray(jd.filtered_means[t]), atol=1e-6)
            np.testing.assert_allclose(p, np.asarray(jd.filtered_covariances[t]), atol=1e-6)


def test_authors_step_problem_is_jdrkfs_and_their_solver_stops_short(replica):
    """At jdrkf's worst case the authors' objective equals jdrkf's value and their budget the radius
    (same problem); SLSQP on their problem reaches that value and not more; their trust-constr
    (20 iterations) stays below 60% of it (measured 41% at r = 0.2), above the nominal."""
    data = replica["gaussian"]
    bp, dp = data["q"][0], data["r"][0]
    kf = orc.KFOracle(data["q"][:1], data["r"][:1], data["v"] * np.eye(4))
    kf.init(np.zeros((1, 2)))
    sigp = kf.p[0]
    radius = 0.2
    sol = bcot_worst_case(sigp, bp, dp, orc.A, orc.C, radius)
    bq, bd, bs = (np.asarray(x) for x in (sol.process_cov, sol.noise_cov, sol.prior_cov))
    value = float(sol.value)
    assert abs(orc.bcot_value(orc.A, orc.C, bq, bd, bs) / value - 1) < 1e-10
    assert abs(orc.bcot_budget(orc.A, orc.C, bq, bd, bs, bp, dp, sigp) - radius) < 1e-8
    sl = orc.bcot_slsqp(radius, orc.A, bp, orc.C, dp, sigp)
    v_sl = orc.bcot_value(orc.A, orc.C, *sl)
    assert v_sl <= value * (1 + 1e-8) and v_sl >= value * (1 - 1e-3)
    v_tc = orc.bcot_value(orc.A, orc.C, *orc.bcot_trust_constr(radius, orc.A, bp, orc.C, dp, sigp, 20))
    assert orc.bcot_value(orc.A, orc.C, bp, dp, sigp) < v_tc < 0.6 * value


def test_double_prediction_and_trust_constr_move_bcot_towards_table_one(replica):
    """The authors' first seed (2024, Gaussian), θ = 0.2, their y₀ step and trust-constr (20
    iterations): applying A twice (their code) more than doubles the LQR cost and the MSE of the
    same filter with A applied once (measured 298 vs 133, 0.97 vs 0.12), and lands within 40% of
    Table 1's BCOT cell 434.5 / 1.377 (one run; the benchmark's 20-seed mean is 432 / 1.37)."""
    data = replica["gaussian"]
    sub = {k: (v[:1] if isinstance(v, np.ndarray) else v) for k, v in data.items() if k != "draws"}
    sub["draws"] = {n: tuple(x[:1] for x in data["draws"][n]) for n in orc.STREAM_ORDER}
    once = orc.run_filter(sub, "BCOT", 0.2, solver="trust-constr", double_predict=False, y0="authors")
    twice = orc.run_filter(sub, "BCOT", 0.2, solver="trust-constr", double_predict=True, y0="authors")
    assert twice[0].mean() > 2 * once[0].mean() and twice[1].mean() > 2 * once[1].mean()
    assert abs(twice[0].mean() / 434.5 - 1) < 0.4 and abs(twice[1].mean() / 1.377 - 1) < 0.4


def test_authors_risk_sensitive_filter_reaches_the_u_quadratic_mse_ours_does_not(replica):
    """U-quadratic, the authors' seeds: their heuristic risk-sensitive filter at θ = 1 gives an MSE
    within 10% of Table 1's 0.325 (NumPy EM: measured 0.349) and well below their KF's 0.856; the
    standard recursion (ours, jdrkf's `RiskSensitiveKF`) at θ = 0.1 stays at the KF's level."""
    data = replica["uquadratic"]
    _, mse_theirs = orc.run_filter(data, "risk-sensitive", 1.0)
    _, mse_kf = orc.run_filter(data, "KF")
    _, mse_ours = orc.run_filter(data, "RS-ours", 0.1)
    assert abs(mse_theirs.mean() / 0.325 - 1) < 0.10
    assert mse_theirs.mean() < 0.5 * mse_kf.mean()
    assert np.all(np.isfinite(mse_ours)) and mse_ours.mean() > 0.9 * mse_kf.mean()


@pytest.mark.slow
def test_authors_bcot_variant_on_their_seeds_reaches_table_one(replica):
    """The authors' BCOT (trust-constr 20 iterations, A twice, predicted y₀) on all 20 seeds at
    θ = 0.2 against Table 1's 434.5 / 1.377 (Gaussian) and 351.2 / 1.107 (U-quadratic): within 10%
    (the benchmark measured 432.2 / 1.368 and 350.7 / 1.108 with pykalman's EM; the 20-iteration
    solver is round-off sensitive; about 2 min per setting)."""
    for setting, (cost_p, mse_p) in (("gaussian", (434.5, 1.377)), ("uquadratic", (351.2, 1.107))):
        cost, mse = orc.run_filter(replica[setting], "BCOT", 0.2, solver="trust-constr", double_predict=True, y0="authors")
        assert abs(cost.mean() / cost_p - 1) < 0.10 and abs(mse.mean() / mse_p - 1) < 0.10, (setting, cost.mean(), mse.mean())
