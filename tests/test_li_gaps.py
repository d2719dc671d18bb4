"""The Li et al. (Variational Robust KFs) gaps of `li-identity` y2 and `li-torsion` y2/y3 (see
`benchmarks/li_gaps.py`).

An independent NumPy oracle of the authors' MATLAB filters (`kf_dob_forward.m`, `akf_forward_vb.m`,
`student_forward_adap.m`; it lives in the benchmark script and does not use jdrkf) is checked
against jdrkf on identical data, and then used to test the causes:

- the authors' VBKF updates its posterior covariance with the Joseph form and the *nominal* R
  (jdrkf's `VBKF`, used by the experiment, takes the adapted R_t). With the nominal R the torsion
  Case 1 (y2) angle errors rise from ours (~1.7) to the paper's level (~2.7);
- with that quirk the identity VBKF equals STKF-AR1 (both nominal), the paper's Table III tie.

Expected values are either exact identities (oracle = jdrkf, the oracle reducing to a plain KF) or
the paper's numbers with per-run spreads measured by the benchmark (stated where used).
"""

from __future__ import annotations

import jax
import numpy as np
import pytest

import benchmark_scripts

from jdrkf import KalmanFilter
from jdrkf.experiments import li_variational as lv
from jdrkf.filters import STKF_AR1, VBKF


orc = benchmark_scripts.load("li_gaps")


def _identity(runs, steps, case="y2", seed=11):
    m, p = lv.identity_model(), lv.identity_prior()
    tr = lv.identity_scenario(jax.random.key(seed), case, runs, steps)
    g = np.asarray(m.G)
    args = (np.asarray(m.F), np.asarray(m.H), g @ np.asarray(m.Q) @ g.T, np.asarray(m.R), np.asarray(p.mean), np.asarray(p.cov))
    return m, p, tr, args


def _torsion(case, runs, steps, seed=5):
    m, p = lv.torsion_model(), lv.torsion_prior()
    tr = lv.torsion_scenario(jax.random.key(seed), case, runs, steps)
    args = tuple(np.asarray(a) for a in (m.F, m.H, m.Q, m.R, p.mean, p.cov))
    return m, p, tr, args


def _jd(flt, m, p, tr):
    return np.asarray(jax.vmap(lambda y: flt(m, p, y).filtered_means)(tr.observations))


def test_oracle_vbkf_reduces_to_kf():
    """With α = β huge and ρ = 1, λ = β/α stays 1 (to 1e-9): the VBKF is the KF with the nominal R,
    and the Joseph form equals (I − KH)P⁻ for the optimal gain, for either covariance variant."""
    _, _, tr, args = _identity(2, 300)
    z = np.asarray(tr.observations)
    kf = orc.oracle_kf(*args, z)
    for cov in ("nominal", "adapted"):
        vb = orc.oracle_vbkf(*args, z, 1e12, 1e12, 1.0, cov=cov)
        np.testing.assert_allclose(vb, kf, rtol=0, atol=1e-8)


def test_oracle_matches_jdrkf_identity():
    """Identical identity-y2 episodes: KF and VBKF (oracle with jdrkf's choices: adapted R_t in the
    Joseph form, first VB pass at ρβ) to rounding; the authors' STKF-AR as written against
    `STKF_AR1(covariance='nominal')` to the stopping rule's tolerance (tol 1e-5 relative, the two
    codes normalise the change differently, so a pass may differ near the threshold)."""
    m, p, tr, args = _identity(3, 800)
    z, xs = np.asarray(tr.observations), np.asarray(tr.states)
    np.testing.assert_allclose(orc.oracle_kf(*args, z), _jd(KalmanFilter(), m, p, tr), rtol=0, atol=1e-10)
    vb = orc.oracle_vbkf(*args, z, 50.0, 50.0, 0.99, cov="adapted", first="forgotten")
    np.testing.assert_allclose(vb, _jd(VBKF(50.0, 50.0, 0.99), m, p, tr), rtol=0, atol=1e-10)
    st = orc.oracle_stkf_ar(*args, z, 1e8, 100.0, 1.0, 0.99)
    ours = _jd(STKF_AR1(1e8, 1.0, 1.0, 100.0, 1.0, 0.99, covariance="nominal"), m, p, tr)
    assert np.abs(st - ours).max() < 1e-4 * max(1.0, np.abs(xs).max())


def test_oracle_matches_jdrkf_torsion():
    """Identical torsion-y2 episodes (augmented 5-state model, absolute-variance VBKF β₀ = 2.03):
    KF and VBKF (jdrkf's choices) to rounding relative to the state scale (|ω| ~ 1e3)."""
    m, p, tr, args = _torsion("y2", 2, 1000)
    z, xs = np.asarray(tr.observations), np.asarray(tr.states)
    scale = np.abs(xs).max()
    np.testing.assert_allclose(orc.oracle_kf(*args, z), _jd(KalmanFilter(), m, p, tr), rtol=0, atol=1e-10 * scale)
    vb = orc.oracle_vbkf(*args, z, 20.0, 20.3, 0.98, cov="adapted", first="forgotten")
    np.testing.assert_allclose(vb, _jd(VBKF(20.0, 20.3, 0.98), m, p, tr), rtol=0, atol=1e-10 * scale)


def test_vbkf_nominal_covariance_is_the_authors_joseph_form():
    """`VBKF(covariance='nominal')` against the oracle of `akf_forward_vb.m` with the nominal R in
    the covariance (first pass at ρβ, jdrkf's order), identity and torsion y2 episodes, to rounding;
    the authors' reading of β on the first pass moves the estimates by far less than the
    covariance form does (< 1e-3 of the state scale)."""
    for (m, p, tr, args), (a0, b0, rho) in ((_identity(2, 800), (50.0, 50.0, 0.99)), (_torsion("y2", 2, 1000), (20.0, 20.3, 0.98))):
        z, xs = np.asarray(tr.observations), np.asarray(tr.states)
        scale = np.abs(xs).max()
        ours = _jd(VBKF(a0, b0, rho, covariance="nominal"), m, p, tr)
        np.testing.assert_allclose(orc.oracle_vbkf(*args, z, a0, b0, rho, cov="nominal", first="forgotten"), ours,
                                   rtol=0, atol=1e-10 * scale)
        authors = orc.oracle_vbkf(*args, z, a0, b0, rho, cov="nominal", first="previous")
        assert np.abs(authors - ours).max() < 1e-3 * scale
        assert np.abs(_jd(VBKF(a0, b0, rho), m, p, tr) - ours).max() > 10 * np.abs(authors - ours).max()
    with pytest.raises(ValueError, match="covariance must be"):
        VBKF(covariance="adapted")


def test_nominal_covariance_raises_torsion_y2_angle_errors():
    """The cause of li-torsion y2 VBKF x2/x3 (paper 2.609/2.717, ours 1.61/1.85): on the same
    1300-step episodes (the ×100 window is steps 800–1198), the authors' nominal-R Joseph form
    raises the angle RMSEs by more than 30% and leaves the disturbance error (x1) within 5%; the
    first-pass β choice changes nothing visible (< 1e-3 relative)."""
    _, _, tr, args = _torsion("y2", 4, 1300)
    z, xs = np.asarray(tr.observations), np.asarray(tr.states)
    ours = orc.rmse(xs, orc.oracle_vbkf(*args, z, 20.0, 20.3, 0.98, cov="adapted", first="forgotten")).mean(0)
    theirs = orc.rmse(xs, orc.oracle_vbkf(*args, z, 20.0, 20.3, 0.98, cov="nominal", first="previous")).mean(0)
    first = orc.rmse(xs, orc.oracle_vbkf(*args, z, 20.0, 20.3, 0.98, cov="adapted", first="previous")).mean(0)
    assert theirs[1] > 1.3 * ours[1] and theirs[2] > 1.3 * ours[2]
    assert abs(theirs[0] / ours[0] - 1.0) < 0.05
    np.testing.assert_allclose(first, ours, rtol=1e-3)


def test_nominal_covariance_gives_the_identity_tie():
    """Table III prints VBKF = STKF-AR1 in Case 2. The authors' VBKF as written (nominal R in the
    covariance) tracks their STKF-AR1 to < 1e-3 of the state scale on the same episodes, while
    jdrkf's VBKF (adapted R_t) differs from it by more than that (it equals STKF-AR1 with the
    reweighted covariance instead)."""
    _, _, tr, args = _identity(2, 2000)
    z, xs = np.asarray(tr.observations), np.asarray(tr.states)
    st = orc.oracle_stkf_ar(*args, z, 1e8, 100.0, 1.0, 0.99)
    theirs = orc.oracle_vbkf(*args, z, 50.0, 50.0, 0.99, cov="nominal", first="previous")
    ours = orc.oracle_vbkf(*args, z, 50.0, 50.0, 0.99, cov="adapted", first="forgotten")
    tol = 1e-3 * np.abs(xs).max()
    assert np.abs(theirs - st).max() < tol
    assert np.abs(ours - st).max() > 10 * np.abs(theirs - st).max()


@pytest.mark.slow
def test_li_gaps_script_quick(tmp_path):
    """The benchmark (--quick, 24 runs): the authors' VBKF puts the paper's y2 θ_m, θ_t inside the
    central 95% of the per-run values, where jdrkf's VBKF has them above every run."""
    res = orc.main(["--quick", "--out", str(tmp_path)])
    y2 = res["torsion_vbkf"]["y2"]
    for x in ("x2", "x3"):
        assert y2["authors' code (both)"][x]["paper_inside_spread"]
        assert y2["jdrkf VBKF (adapted R_t, ρβ first)"][x]["paper_percentile"] == 100.0
    assert (tmp_path / "li_gaps_quick.md").is_file() and (tmp_path / "li_gaps_quick.json").is_file()
