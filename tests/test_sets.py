"""jdrkf.sets (worst-case covariances of DR-MMSE problems) against independent oracles.

Oracles (tests/sdp_oracles.py): CVXPY/Clarabel SDPs of Wang & Ye 2022, eqs. (32)-(37)
and Theorem 8, whose optimal *values* are accurate to ~1e-9; their worst-case
covariances are polished by a NumPy Frank–Wolfe with a certified duality gap (the raw
SDP matrices are only accurate to ~1e-4, see `frank_wolfe` there), and closed forms
(docs/math/wasserstein.md; Theorem 5). The first section checks the oracles
themselves; the rest checks jdrkf.sets.

Run time is dominated by XLA compilation of the jdrkf solvers (seconds per problem
structure and shape), so the solver calls go through shared jitted entry points with
consistent argument types, the default tier uses the (n, m) = (2, 1) instances and the
`slow` tier compares the remaining sizes (3, 2), (4, 2) with the SDP oracles.
"""

import functools

import hypothesis
import hypothesis.strategies as st
import jax
import jax.numpy as jnp
import numpy as np
import pytest
import sdp_oracles as O

from jdrkf.linalg import bures_distance, bures_distance_squared
from jdrkf.sets import (
    KL,
    Moment,
    Wasserstein,
    wasserstein_mmse,
    wasserstein_mmse_joint,
    worst_case,
    worst_case_joint,
)

SIZES = [(2, 1), (3, 2), (4, 2)]
N_CASES = 20
VALUE_RTOL = 1e-7
COV_ATOL = 1e-5

DECOUPLED = ["wasserstein", "kl", "wasserstein_x_kl", "moment_x_wasserstein"]
JOINT = ["joint_wasserstein", "joint_kl"]


# ============================================================================ instances


@functools.cache
def _case(kind, idx):
    """Deterministic random instance `idx` of problem `kind` (NumPy arrays, floats)."""
    rng = np.random.default_rng([sum(map(ord, kind)), idx])
    n, m = SIZES[idx % len(SIZES)]
    r1, r2 = (float(x) for x in rng.uniform(0.05, 2.0, size=2))
    if kind in JOINT:
        return {"S": O.random_joint(rng, n, m), "n": n, "r": r1}
    M, H, R = O.random_instance(rng, n, m)
    i_min = 1.0 if idx % 2 == 0 else 0.8
    return {"M": M, "H": H, "R": R, "i_min": i_min, "r1": r1, "r2": r2}


def _oracle_sets(kind, case):
    """(state_set, noise_set) specs of sdp_oracles for a decoupled kind."""
    r1, r2 = case["r1"], case["r2"]
    return {
        "wasserstein": (("wasserstein", r1), ("wasserstein", r2)),
        "kl": (("kl", r1), ("kl", r2)),
        "wasserstein_x_kl": (("wasserstein", r1), ("kl", r2)),
        "moment_x_wasserstein": (("moment", (0.5, 1.0 + r1 / 2)), ("wasserstein", r2)),
    }[kind]


def _jdrkf_sets(kind, case):
    r1, r2 = case["r1"], case["r2"]
    return {
        "wasserstein": (Wasserstein(r1), Wasserstein(r2)),
        "kl": (KL(r1), KL(r2)),
        "wasserstein_x_kl": (Wasserstein(r1), KL(r2)),
        "moment_x_wasserstein": (Moment(1.0 + r1 / 2), Wasserstein(r2)),
    }[kind]


@functools.cache
def _oracle(kind, idx):
    c = _case(kind, idx)
    if kind == "joint_wasserstein":
        return O.joint_wasserstein_sdp(c["S"], c["n"], c["r"])
    if kind == "joint_kl":
        return O.joint_kl_sdp(c["S"], c["n"], c["r"])
    if kind == "wasserstein":  # the dedicated entry point, eqs. (34)-(35)
        return O.decoupled_wasserstein_sdp(c["M"], c["H"], c["R"], c["r1"], c["r2"], c["i_min"])
    if kind == "kl":
        return O.decoupled_kl_sdp(c["M"], c["H"], c["R"], c["r1"], c["r2"], c["i_min"])
    sx, sv = _oracle_sets(kind, c)
    return O.decoupled_mixed_sdp(c["M"], c["H"], c["R"], sx, sv, c["i_min"])


def _strong(tree):
    """Float leaves as strongly typed float64 arrays: jit caches compiled programs on
    weak types as well, and XLA compilation (seconds per program) dominates this file."""

    def conv(x):
        if isinstance(x, (float, np.floating)) or (hasattr(x, "dtype") and jnp.issubdtype(x.dtype, jnp.floating)):
            return jnp.asarray(x, dtype=jnp.float64)
        return x

    return jax.tree.map(conv, tree)


def _jit(fun, **jit_kwargs):
    compiled = jax.jit(fun, **jit_kwargs)

    @functools.wraps(fun)
    def call(*args, **kwargs):
        return compiled(*_strong(args), **_strong(kwargs))

    return call


# jitted entry points (compiled once per structure and shape; eager use is tested once).
# i_min is always passed, as a keyword: jit also caches on the set of keywords given.
_wmmse_jit = _jit(wasserstein_mmse)
_worst_case_jit = _jit(worst_case)
_wmmse_joint = _jit(wasserstein_mmse_joint, static_argnums=1)
_worst_case_joint = _jit(worst_case_joint, static_argnums=2)


def _wmmse(M, H, R, theta_x, theta_v, i_min=1.0):
    return _wmmse_jit(M, H, R, theta_x, theta_v, i_min=i_min)


def _worst_case(state_set, noise_set, M, H, R, i_min=1.0):
    return _worst_case_jit(state_set, noise_set, M, H, R, i_min=i_min)


def _solve(kind, case):
    if kind == "joint_wasserstein":
        return _wmmse_joint(case["S"], case["n"], case["r"])
    if kind == "joint_kl":
        return _worst_case_joint(KL(case["r"]), case["S"], case["n"])
    if kind == "wasserstein":
        return _wmmse(case["M"], case["H"], case["R"], case["r1"], case["r2"], i_min=case["i_min"])
    sx, sv = _jdrkf_sets(kind, case)
    return _worst_case(sx, sv, case["M"], case["H"], case["R"], i_min=case["i_min"])


def _kf_value(M, H, R, i_min=1.0):
    return O.posterior_trace(M, H, R, i_min)


def _sym_unit(d, i, j):
    e = np.zeros((d, d))
    e[i, j] = e[j, i] = 1.0
    return e


# ============================================================================ oracle self-checks


@pytest.mark.parametrize("i_min", [1.0, 0.8])
def test_oracle_scalar_decoupled_closed_form(i_min):
    # n = m = 1: f is increasing in both variances, so s* = (√σ + ρ)² (A.2 test iii).
    sx, h, sw, rx, rw = 1.3, 0.7, 0.4, 0.5, 0.3
    out = O.decoupled_wasserstein_sdp([[sx]], [[h]], [[sw]], rx, rw, i_min, polish=False)
    ex, ew = (np.sqrt(sx) + rx) ** 2, (np.sqrt(sw) + rw) ** 2
    np.testing.assert_allclose(out["state_cov"], [[ex]], rtol=1e-6)
    np.testing.assert_allclose(out["noise_cov"], [[ew]], rtol=1e-6)
    np.testing.assert_allclose(out["value"], O.posterior_trace([[ex]], [[h]], [[ew]], i_min), rtol=1e-8)
    polished = O.decoupled_wasserstein_sdp([[sx]], [[h]], [[sw]], rx, rw, i_min)
    np.testing.assert_allclose(polished["state_cov"], [[ex]], rtol=1e-12)
    np.testing.assert_allclose(polished["noise_cov"], [[ew]], rtol=1e-12)


def test_oracle_h_zero_closed_form(rng):
    # H = 0: f = Tr Σx, so Σx* = (1 + ρ/√Tr M)² M (A.2 test iv). Σv* is not unique here
    # (the objective ignores it), so only the state block is compared.
    M, H, R = O.random_instance(rng, 3, 2)
    out = O.decoupled_wasserstein_sdp(M, 0 * H, R, 0.7, 0.3, polish=False)
    expected = (1 + 0.7 / np.sqrt(np.trace(M))) ** 2 * M
    np.testing.assert_allclose(out["state_cov"], expected, atol=1e-4)
    np.testing.assert_allclose(out["value"], (np.sqrt(np.trace(M)) + 0.7) ** 2, rtol=1e-8)


def test_oracle_radius_zero_is_nominal(rng):
    M, H, R = O.random_instance(rng, 3, 2)
    for solve in (O.decoupled_wasserstein_sdp, O.decoupled_kl_sdp):
        out = solve(M, H, R, 0.0, 0.0)
        np.testing.assert_allclose(out["state_cov"], M, atol=1e-10)
        np.testing.assert_allclose(out["noise_cov"], R, atol=1e-10)
        np.testing.assert_allclose(out["value"], _kf_value(M, H, R), rtol=1e-9)
    S = O.random_joint(rng, 2, 1)
    for solve in (O.joint_wasserstein_sdp, O.joint_kl_sdp):
        out = solve(S, 2, 0.0)
        np.testing.assert_allclose(out["cov"], S, atol=1e-10)
        np.testing.assert_allclose(out["value"], O.schur_trace(S, 2), rtol=1e-9)


@pytest.mark.parametrize("i_min", [1.0, 0.8])
def test_oracle_moment_theorem5(rng, i_min):
    # Theorem 5: the SDP (36)-(37) is solved by Σx = θ2x M, Σv = θ2v R.
    for n, m in SIZES:
        M, H, R = O.random_instance(rng, n, m)
        t2x, t2v = rng.uniform(1.0, 2.0, size=2)
        out = O.moment_sdp(M, H, R, t2x, t2v, i_min=i_min)
        np.testing.assert_allclose(out["state_cov"], t2x * M, atol=1e-6)
        np.testing.assert_allclose(out["noise_cov"], t2v * R, atol=1e-6)
        np.testing.assert_allclose(out["value"], O.posterior_trace(t2x * M, H, t2v * R, i_min), rtol=1e-8)


@pytest.mark.parametrize("kind", DECOUPLED + JOINT)
def test_oracle_certificates(kind):
    """Every cached oracle solution: SDP value = value at the (FW-certified) solution,
    FW gap ~0, raw SDP matrices close, constraints active, fixed point of the
    closed-form LMO (A.3; for KL the B.3 closed form)."""
    for idx in range(N_CASES):
        c, out = _case(kind, idx), _oracle(kind, idx)
        value = out["value"]
        assert abs(out["sdp_value"] - value) <= VALUE_RTOL * value
        assert out["fw_gap"] <= 1e-12 * value
        if kind in JOINT:
            S, n, r = c["S"], c["n"], c["r"]
            np.testing.assert_allclose(out["sdp_cov"], out["cov"], atol=1e-3)
            spec = ("wasserstein" if kind == "joint_wasserstein" else "kl", r)
            fixed = O.set_lmo(spec, O.joint_gradient(out["cov"], n), S)
            np.testing.assert_allclose(fixed, out["cov"], atol=1e-5)
            if kind == "joint_kl":
                assert abs(O.kl_divergence(out["cov"], S) - r) <= 1e-10
            else:
                assert abs(O.bures_distance(out["cov"], S) - r) <= 1e-10
            assert value >= O.schur_trace(S, n) - 1e-12
            continue
        M, H, R, i_min = c["M"], c["H"], c["R"], c["i_min"]
        np.testing.assert_allclose(out["sdp_state_cov"], out["state_cov"], atol=1e-3)
        np.testing.assert_allclose(out["sdp_noise_cov"], out["noise_cov"], atol=1e-3)
        gx, gv = O.decoupled_gradient(out["state_cov"], H, out["noise_cov"], i_min)
        for spec, g, nom, cov in zip(_oracle_sets(kind, c), (gx, gv), (M, R),
                                     (out["state_cov"], out["noise_cov"]), strict=True):
            np.testing.assert_allclose(O.set_lmo(spec, g, nom), cov, atol=1e-5)
            if spec[0] == "wasserstein":
                assert abs(O.bures_distance(cov, nom) - spec[1]) <= 1e-10
            elif spec[0] == "kl":
                assert abs(O.kl_divergence(cov, nom) - spec[1]) <= 1e-10
            else:
                np.testing.assert_allclose(cov, spec[1][1] * nom, atol=1e-12)
        assert value >= _kf_value(M, H, R, i_min) - 1e-12


def test_oracle_lmo_closed_forms(rng):
    for d in (2, 3, 5):
        nom = O.random_spd(rng, d)
        D = O.random_spd(rng, d, 0.0)
        rho, c = rng.uniform(0.1, 2.0, size=2)
        # Wasserstein: closed form (A.1) vs the SDP; D = I closed form; duality.
        L, gamma = O.wasserstein_lmo_closed_form(D, nom, rho)
        ref = O.wasserstein_lmo_sdp(D, nom, rho)
        np.testing.assert_allclose(np.sum(D * L), ref["value"], rtol=1e-8)
        np.testing.assert_allclose(L, ref["cov"], atol=1e-4)
        assert abs(O.bures_distance(L, nom) - rho) <= 1e-10
        phi = gamma * (rho**2 - np.trace(nom)) + gamma**2 * np.sum(np.linalg.inv(gamma * np.eye(d) - D) * nom)
        np.testing.assert_allclose(np.sum(D * L), phi, rtol=1e-10)
        LI, _ = O.wasserstein_lmo_closed_form(np.eye(d), nom, rho)
        np.testing.assert_allclose(LI, (1 + rho / np.sqrt(np.trace(nom))) ** 2 * nom, rtol=1e-12)
        # KL: closed form (B.3) vs the exp-cone program; D = I scalar closed form.
        S, _ = O.kl_lmo_closed_form(D, nom, c)
        ref = O.kl_lmo_sdp(D, nom, c)
        np.testing.assert_allclose(np.sum(D * S), ref["value"], rtol=1e-8)
        np.testing.assert_allclose(S, ref["cov"], atol=1e-4)
        assert abs(O.kl_divergence(S, nom) - c) <= 1e-10
        SI, _ = O.kl_lmo_closed_form(np.eye(d), nom, c)
        SI2, _ = O.kl_lmo_identity_closed_form(nom, c)
        np.testing.assert_allclose(SI, SI2, rtol=1e-10)


# ============================================================================ jdrkf vs SDP oracles
#
# XLA compilation dominates the run time (several seconds per problem structure and
# shape), so the default tier uses the (n, m) = (2, 1) instances (idx % 3 == 0, both
# values of i_min) and the slow tier the other sizes.

FAST = [i for i in range(N_CASES) if i % 3 == 0]
REST = [i for i in range(N_CASES) if i % 3 != 0]


def _compare_with_oracle(kind, indices):
    failures = []
    for idx in indices:
        case, ref = _case(kind, idx), _oracle(kind, idx)
        sol = _solve(kind, case)
        got = float(sol.value)
        if not bool(sol.converged):
            failures.append(f"#{idx}: not converged (gap {float(sol.gap):.3g}, {int(sol.iterations)} it.)")
        if not abs(got - ref["sdp_value"]) <= VALUE_RTOL * abs(ref["sdp_value"]):
            failures.append(f"#{idx}: value {got!r} vs SDP {ref['sdp_value']!r}")
        if not abs(got - ref["value"]) <= 1e-9 * abs(ref["value"]):  # FW-certified value
            failures.append(f"#{idx}: value {got!r} vs certified {ref['value']!r}")
        pairs = [("cov", sol.cov)] if kind in JOINT else [("state_cov", sol.state_cov), ("noise_cov", sol.noise_cov)]
        for name, arr in pairs:
            err = float(np.max(np.abs(np.asarray(arr) - ref[name])))
            if not err <= COV_ATOL * max(1.0, float(np.max(np.abs(ref[name])))):
                failures.append(f"#{idx}: {name} max abs err {err:.3g}")
    assert not failures, f"{kind}: " + "; ".join(failures)


@pytest.mark.parametrize("kind", DECOUPLED + JOINT)
def test_matches_sdp_oracle(kind):
    _compare_with_oracle(kind, FAST)


@pytest.mark.slow
@pytest.mark.parametrize("kind", DECOUPLED + JOINT)
def test_matches_sdp_oracle_larger(kind):
    _compare_with_oracle(kind, REST)


def test_eager_matches_jit():
    c = _case("wasserstein", 0)
    eager = wasserstein_mmse(c["M"], c["H"], c["R"], c["r1"], c["r2"], i_min=c["i_min"])
    jitted = _solve("wasserstein", c)
    np.testing.assert_allclose(eager.state_cov, jitted.state_cov, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(eager.noise_cov, jitted.noise_cov, rtol=1e-12, atol=1e-14)
    np.testing.assert_allclose(eager.value, jitted.value, rtol=1e-13)


# ============================================================================ closed forms


def test_wasserstein_lmo_identity_closed_form(rng):
    for d in (1, 2, 4):
        nom = O.random_spd(rng, d)
        rho = 0.7
        L = Wasserstein(rho).lmo(np.eye(d), nom)
        np.testing.assert_allclose(L, (1 + rho / np.sqrt(np.trace(nom))) ** 2 * nom, rtol=1e-12)
        np.testing.assert_allclose(jnp.trace(L), (np.sqrt(np.trace(nom)) + rho) ** 2, rtol=1e-12)


def test_wasserstein_lmo_random_direction(rng):
    for d, rank in [(2, 2), (3, 3), (4, 2), (5, 3)]:
        nom = O.random_spd(rng, d)
        a = rng.normal(size=(d, rank))
        D = a @ a.T  # rank-deficient for rank < d
        rho = float(rng.uniform(0.1, 2.0))
        L = np.asarray(Wasserstein(rho).lmo(D, nom))
        np.testing.assert_allclose(float(bures_distance(L, nom)), rho, atol=1e-10)
        ref, gamma = O.wasserstein_lmo_closed_form(D, nom, rho)
        np.testing.assert_allclose(L, ref, atol=1e-10)
        phi = gamma * (rho**2 - np.trace(nom)) + gamma**2 * np.sum(np.linalg.inv(gamma * np.eye(d) - D) * nom)
        np.testing.assert_allclose(np.sum(D * L), phi, rtol=1e-10)  # zero duality gap
    # repeated eigenvalues: the gradient [I, −K]ᵀ[I, −K] of the joint objective
    S = O.random_joint(rng, 3, 2)
    D = O.joint_gradient(S, 3)
    L = np.asarray(Wasserstein(0.9).lmo(D, S))
    np.testing.assert_allclose(L, O.wasserstein_lmo_closed_form(D, S, 0.9)[0], atol=1e-10)


def test_kl_lmo(rng):
    for d in (1, 2, 4):
        nom = O.random_spd(rng, d)
        c = float(rng.uniform(0.05, 2.0))
        # D = I: the scalar-multiplier closed form S = (Σ̂⁻¹ − tI)⁻¹ of §B.3.
        S = np.asarray(KL(c).lmo(np.eye(d), nom))
        np.testing.assert_allclose(S, O.kl_lmo_identity_closed_form(nom, c)[0], rtol=1e-10)
        np.testing.assert_allclose(O.kl_divergence(S, nom), c, atol=1e-10)
        a = rng.normal(size=(d, max(d - 1, 1)))
        D = a @ a.T
        S = np.asarray(KL(c).lmo(D, nom))
        np.testing.assert_allclose(O.kl_divergence(S, nom), c, atol=1e-10)
        np.testing.assert_allclose(S, O.kl_lmo_closed_form(D, nom, c)[0], rtol=1e-9, atol=1e-10)


def test_moment_lmo(rng):
    nom = O.random_spd(rng, 3)
    D = O.random_spd(rng, 3, 0.0)
    np.testing.assert_allclose(Moment(1.7).lmo(D, nom), 1.7 * nom, rtol=1e-15)


def test_radius_zero_returns_nominal_exactly(rng):
    M, H, R = O.random_instance(rng, 2, 1)
    D = O.random_spd(rng, 2, 0.0)
    for s in (Wasserstein(0.0), KL(0.0), Moment(1.0)):
        np.testing.assert_array_equal(s.lmo(D, M), M)
    sol = _wmmse(M, H, R, 0.0, 0.0)
    np.testing.assert_array_equal(sol.state_cov, M)
    np.testing.assert_array_equal(sol.noise_cov, R)
    np.testing.assert_allclose(sol.value, _kf_value(M, H, R), rtol=1e-12)
    for sets in [(KL(0.0), KL(0.0)), (Wasserstein(0.0), KL(0.0))]:
        sol = _worst_case(*sets, M, H, R)
        np.testing.assert_array_equal(sol.state_cov, M)
        np.testing.assert_array_equal(sol.noise_cov, R)
    sol = worst_case(Moment(1.0), Moment(1.0), M, H, R)
    np.testing.assert_array_equal(sol.state_cov, M)
    np.testing.assert_array_equal(sol.noise_cov, R)
    S = O.random_joint(rng, 2, 1)
    for sol in (_wmmse_joint(S, 2, 0.0), _worst_case_joint(KL(0.0), S, 2), worst_case_joint(Moment(1.0), S, 2)):
        np.testing.assert_array_equal(sol.cov, S)
        np.testing.assert_allclose(sol.value, O.schur_trace(S, 2), rtol=1e-12)
    # one block at radius 0, the other not: that block stays exactly nominal
    np.testing.assert_array_equal(_wmmse(M, H, R, 0.5, 0.0).noise_cov, R)
    np.testing.assert_array_equal(_wmmse(M, H, R, 0.0, 0.5).state_cov, M)


def test_tiny_radius(rng):
    # A radius far below round-off must behave like radius 0 (stay feasible), not break
    # the multiplier's Newton iteration.
    M, H, R = O.random_instance(rng, 2, 1)
    for tiny in (1e-12, 1e-20, 1e-40):
        L = np.asarray(KL(tiny).lmo(np.eye(2), M))
        assert O.kl_divergence(L, M) <= tiny + 1e-12, (tiny, L)
        L = np.asarray(Wasserstein(tiny).lmo(np.eye(2), M))
        np.testing.assert_allclose(L, M, rtol=1e-10)
        sol = _worst_case(KL(0.3), KL(tiny), M, H, R)
        assert abs(O.kl_divergence(sol.state_cov, M) - 0.3) <= 1e-10, tiny
        assert O.kl_divergence(sol.noise_cov, R) <= tiny + 1e-12, tiny
        sol = _wmmse(M, H, R, 0.3, tiny)
        assert abs(O.bures_distance(sol.state_cov, M) - 0.3) <= 1e-10, tiny
        np.testing.assert_allclose(sol.noise_cov, R, rtol=1e-10)


@pytest.mark.parametrize("i_min", [1.0, 0.8])
def test_scalar_decoupled_closed_form(i_min):
    sx, h, sw, rx, rw = 1.3, 0.7, 0.4, 0.5, 0.3
    sol = _wmmse(np.array([[sx]]), np.array([[h]]), np.array([[sw]]), rx, rw, i_min=i_min)
    np.testing.assert_allclose(sol.state_cov, [[(np.sqrt(sx) + rx) ** 2]], rtol=1e-12)
    np.testing.assert_allclose(sol.noise_cov, [[(np.sqrt(sw) + rw) ** 2]], rtol=1e-12)


def test_h_zero_closed_form(rng):
    M, H, R = O.random_instance(rng, 2, 1)
    sol = _wmmse(M, np.zeros_like(H), R, 0.7, 0.3)
    np.testing.assert_allclose(sol.state_cov, (1 + 0.7 / np.sqrt(np.trace(M))) ** 2 * M, rtol=1e-10)
    np.testing.assert_allclose(sol.value, (np.sqrt(np.trace(M)) + 0.7) ** 2, rtol=1e-12)
    # Σv* is not unique (f does not depend on it); it must still be finite and feasible.
    assert np.all(np.isfinite(np.asarray(sol.noise_cov)))
    assert float(bures_distance(sol.noise_cov, R)) <= 0.3 + 1e-10


def test_moment_closed_form_matches_sdp(rng):
    for i_min in (1.0, 0.8):
        for n, m in SIZES:
            M, H, R = O.random_instance(rng, n, m)
            t2x, t2v = (float(x) for x in rng.uniform(1.0, 2.0, size=2))
            ref = O.moment_sdp(M, H, R, t2x, t2v, i_min=i_min)
            sol = worst_case(Moment(t2x), Moment(t2v), M, H, R, i_min=i_min)
            np.testing.assert_allclose(sol.state_cov, t2x * M, rtol=1e-14)
            np.testing.assert_allclose(sol.noise_cov, t2v * R, rtol=1e-14)
            np.testing.assert_allclose(sol.state_cov, ref["state_cov"], atol=1e-6)
            np.testing.assert_allclose(sol.value, ref["value"], rtol=VALUE_RTOL)


def test_value_nondecreasing_in_radius(rng):
    M, H, R = O.random_instance(rng, 2, 1)
    S = O.random_joint(rng, 2, 1)
    radii = np.linspace(0.0, 2.0, 9)
    curves = {
        "decoupled W": [_wmmse(M, H, R, r, 0.5 * r).value for r in radii],
        "decoupled KL": [_worst_case(KL(r), KL(0.5 * r), M, H, R).value for r in radii],
        "joint W": [_wmmse_joint(S, 2, r).value for r in radii],
        "joint KL": [_worst_case_joint(KL(r), S, 2).value for r in radii],
    }
    for name, vals in curves.items():
        vals = np.asarray(vals)
        assert np.all(np.diff(vals) > 0), (name, vals)


@pytest.mark.parametrize("kind", JOINT)
def test_joint_fixed_point_residual(kind):
    make = Wasserstein if kind == "joint_wasserstein" else KL
    for idx in FAST[:4]:
        case = _case(kind, idx)
        cov = np.asarray(_solve(kind, case).cov)
        D = O.joint_gradient(cov, case["n"])  # ∇f(S*) = [I, −K]ᵀ[I, −K]
        np.testing.assert_allclose(make(case["r"]).lmo(D, case["S"]), cov, atol=1e-9)
        spec = ("wasserstein" if make is Wasserstein else "kl", case["r"])
        np.testing.assert_allclose(O.set_lmo(spec, D, case["S"]), cov, atol=1e-9)


def test_decoupled_fixed_point_residual():
    for idx in FAST[:4]:
        case = _case("wasserstein", idx)
        sol = _solve("wasserstein", case)
        gx, gv = O.decoupled_gradient(sol.state_cov, case["H"], sol.noise_cov, case["i_min"])
        np.testing.assert_allclose(O.wasserstein_lmo_closed_form(gx, case["M"], case["r1"])[0], sol.state_cov,
                                   atol=1e-9)
        np.testing.assert_allclose(O.wasserstein_lmo_closed_form(gv, case["R"], case["r2"])[0], sol.noise_cov,
                                   atol=1e-9)


# ============================================================================ derivatives
#
# jax.jacrev (= jax.grad of every output, vmapped over cotangents) of
# [value, Σx*[0,0], Σv*[0,0], Σx*[0,1]] (decoupled) or [value, S*[0,0], S*[0,n]] (joint)
# with respect to p = [radius 1, radius 2, ε_M, ε_R] (decoupled; the nominals are
# perturbed symmetrically, M + ε_M (E₀₁ + E₁₀), R + ε_R E) or p = [radius, ε] (joint,
# S + ε (E₀ₙ + Eₙ₀), an x–y entry), against central differences of the jitted solver.

GRAD_KINDS = ["wasserstein", "kl", "wasserstein_x_kl", "moment_x_wasserstein"]


def _perturbations(M, R):
    return _sym_unit(M.shape[0], 0, 1), _sym_unit(R.shape[0], 0, R.shape[0] - 1)


def _decoupled_outputs(kind):
    def outputs(p, M, H, R, i_min):
        E, F = _perturbations(M, R)
        M, R = M + p[2] * E, R + p[3] * F
        if kind == "wasserstein":
            sol = wasserstein_mmse(M, H, R, p[0], p[1], i_min=i_min)
        else:
            sx, sv = _jdrkf_sets(kind, {"r1": p[0], "r2": p[1]})
            sol = worst_case(sx, sv, M, H, R, i_min=i_min)
        return jnp.stack([sol.value, sol.state_cov[0, 0], sol.noise_cov[0, 0], sol.state_cov[0, 1]])

    return outputs


def _joint_outputs(kind, n):
    def outputs(p, S):
        S = S + p[1] * _sym_unit(S.shape[0], 0, n)
        if kind == "joint_wasserstein":
            sol = wasserstein_mmse_joint(S, n, p[0])
        else:
            sol = worst_case_joint(KL(p[0]), S, n)
        return jnp.stack([sol.value, sol.cov[0, 0], sol.cov[0, n]])

    return outputs


_JAC = {kind: _jit(jax.jacrev(_decoupled_outputs(kind))) for kind in GRAD_KINDS}
_JAC.update({kind: _jit(jax.jacrev(_joint_outputs(kind, 2))) for kind in JOINT})  # n = 2 (FAST cases)


def _fd_outputs(kind, case, p):
    """The outputs at parameters p, by the jitted solver used in test_matches_sdp_oracle."""
    case = dict(case)
    if kind in JOINT:
        n = case["n"]
        case.update(r=p[0], S=case["S"] + p[1] * _sym_unit(case["S"].shape[0], 0, n))
        sol = _solve(kind, case)
        return np.array([sol.value, sol.cov[0, 0], sol.cov[0, n]])
    E, F = _perturbations(case["M"], case["R"])
    case.update(r1=p[0], r2=p[1], M=case["M"] + p[2] * E, R=case["R"] + p[3] * F)
    sol = _solve(kind, case)
    return np.array([sol.value, sol.state_cov[0, 0], sol.noise_cov[0, 0], sol.state_cov[0, 1]])


def _jacobian(kind, case, p):
    if kind in JOINT:
        return np.asarray(_JAC[kind](jnp.asarray(p), case["S"]))
    return np.asarray(_JAC[kind](jnp.asarray(p), case["M"], case["H"], case["R"], case["i_min"]))


def _check_jacobian(kind, case, p, h=1e-5, rtol=1e-5, one_sided=()):
    """Compare jacrev with central (or, for the indices in `one_sided`, forward) differences."""
    p = np.asarray(p, dtype=np.float64)
    jac = _jacobian(kind, case, p)
    assert np.all(np.isfinite(jac)), jac
    failures = []
    for j in range(p.size):
        step = np.zeros_like(p)
        if j in one_sided:
            step[j] = 1e-7
            fd = (_fd_outputs(kind, case, p + step) - _fd_outputs(kind, case, p)) / 1e-7
        else:
            step[j] = h
            fd = (_fd_outputs(kind, case, p + step) - _fd_outputs(kind, case, p - step)) / (2 * h)
        for i in range(fd.size):
            if not abs(jac[i, j] - fd[i]) <= rtol * max(abs(fd[i]), 1e-2):
                failures.append(f"d out[{i}]/d p[{j}]: grad {jac[i, j]!r} vs FD {fd[i]!r}")
    assert not failures, f"{kind}, p={p.tolist()}: " + "; ".join(failures)
    return jac


@pytest.mark.parametrize("kind", GRAD_KINDS)
@pytest.mark.parametrize("idx", FAST[:2])
def test_grad_decoupled(kind, idx):
    c = _case(kind, idx)
    _check_jacobian(kind, c, [c["r1"], c["r2"], 0.0, 0.0])


@pytest.mark.parametrize("kind", JOINT)
@pytest.mark.parametrize("idx", FAST[:2])
def test_grad_joint(kind, idx):
    c = _case(kind, idx)
    _check_jacobian(kind, c, [c["r"], 0.0])


def test_envelope_theorem_joint_wasserstein():
    # d f*/d rho = 2 rho gamma* (A.4), gamma* from the closed-form LMO at the solution.
    c = _case("joint_wasserstein", 0)
    S, n, r = c["S"], c["n"], c["r"]
    cov = np.asarray(_wmmse_joint(S, n, r).cov)
    _, gamma = O.wasserstein_lmo_closed_form(O.joint_gradient(cov, n), S, r)
    np.testing.assert_allclose(_jacobian("joint_wasserstein", c, [r, 0.0])[0, 0], 2 * r * gamma, rtol=1e-8)


def test_grad_at_radius_zero_is_finite():
    # The Wasserstein worst case grows linearly in the radius: one-sided derivative at 0.
    c = _case("wasserstein", 3)
    _check_jacobian("wasserstein", c, [0.0, c["r2"], 0.0, 0.0], one_sided=(0,))
    _check_jacobian("wasserstein", c, [0.0, 0.0, 0.0, 0.0], one_sided=(0, 1))
    _check_jacobian("joint_wasserstein", _case("joint_wasserstein", 3), [0.0, 0.0], one_sided=(0,))


# ============================================================================ jit / vmap


def _batch(rng, n, m, size=8):
    Ms, Hs, Rs = zip(*(O.random_instance(rng, n, m) for _ in range(size)), strict=True)
    return np.stack(Ms), np.stack(Hs), np.stack(Rs)


def test_jit_and_vmap_decoupled(rng):
    Ms, Hs, Rs = _batch(rng, 2, 1)
    tx, tv = rng.uniform(0.05, 2.0, size=(2, 8))
    tx[3] = 0.0  # a nominal block inside the batch
    i_min = np.where(np.arange(8) % 2 == 0, 1.0, 0.8)
    batched = jax.jit(jax.vmap(lambda *a: wasserstein_mmse(*a[:5], i_min=a[5])))(Ms, Hs, Rs, tx, tv, i_min)
    for k in range(8):
        one = _wmmse(Ms[k], Hs[k], Rs[k], tx[k], tv[k], i_min=i_min[k])
        assert bool(batched.converged[k])
        np.testing.assert_allclose(batched.state_cov[k], one.state_cov, rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(batched.noise_cov[k], one.noise_cov, rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(batched.value[k], one.value, rtol=1e-12)
    np.testing.assert_array_equal(batched.state_cov[3], Ms[3])


def test_jit_and_vmap_joint_kl(rng):
    Ss = np.stack([O.random_joint(rng, 2, 1) for _ in range(8)])
    c = rng.uniform(0.05, 2.0, size=8)
    batched = jax.jit(jax.vmap(lambda S, c: worst_case_joint(KL(c), S, 2)))(Ss, c)
    for k in range(8):
        one = _worst_case_joint(KL(c[k]), Ss[k], 2)
        assert bool(batched.converged[k])
        np.testing.assert_allclose(batched.cov[k], one.cov, rtol=1e-10, atol=1e-12)
        np.testing.assert_allclose(batched.value[k], one.value, rtol=1e-12)


def test_vmap_of_grad(rng):
    Ms, Hs, Rs = _batch(rng, 2, 1)
    tx = rng.uniform(0.05, 2.0, size=8)
    value = lambda M, H, R, t: wasserstein_mmse(M, H, R, t, 0.3).value
    grads = jax.jit(jax.vmap(jax.grad(value, argnums=3)))(Ms, Hs, Rs, tx)
    for k in range(8):
        c = {"M": Ms[k], "H": Hs[k], "R": Rs[k], "i_min": 1.0}
        np.testing.assert_allclose(grads[k], _jacobian("wasserstein", c, [tx[k], 0.3, 0.0, 0.0])[0, 0], rtol=1e-9)


# ============================================================================ properties


@st.composite
def _problems(draw):
    # small sizes only: every further size costs several seconds of XLA compilation
    n, m = draw(st.sampled_from([(1, 1), (2, 1)]))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    M, H, R = O.random_instance(rng, n, m)
    scale = draw(st.sampled_from([0.1, 1.0, 10.0]))
    tx = draw(st.floats(0.0, 2.0))
    tv = draw(st.floats(0.0, 2.0))
    i_min = draw(st.sampled_from([1.0, 0.8]))
    return scale * M, H, scale * R, np.sqrt(scale) * tx, np.sqrt(scale) * tv, i_min


def _assert_sym_psd(a, tol):
    a = np.asarray(a)
    size = max(1.0, float(np.max(np.abs(a))))
    assert np.max(np.abs(a - a.T)) <= tol * size
    assert np.linalg.eigvalsh(0.5 * (a + a.T))[0] >= -tol * size


def _assert_in_bures_ball(cov, nominal, radius):
    # Bures(Σ*, Σ̂) <= θ + 1e-8, except that at θ ≈ 0 the distance itself carries a
    # round-off of √(eps Tr) ~ 3e-8 (the square root of the squared distance).
    d2 = float(bures_distance_squared(cov, nominal))
    assert np.sqrt(d2) <= radius + 1e-8 or d2 <= radius**2 + 1e-14 * float(np.trace(nominal))


@hypothesis.settings(max_examples=25, deadline=None, derandomize=True)
@hypothesis.given(_problems())
def test_property_decoupled_wasserstein(problem):
    M, H, R, tx, tv, i_min = problem
    sol = _wmmse(M, H, R, tx, tv, i_min=i_min)
    assert bool(sol.converged)
    _assert_sym_psd(sol.state_cov, 1e-12)
    _assert_sym_psd(sol.noise_cov, 1e-12)
    _assert_in_bures_ball(sol.state_cov, M, tx)
    _assert_in_bures_ball(sol.noise_cov, R, tv)
    kf = _kf_value(M, H, R, i_min)
    assert float(sol.value) >= kf - 1e-12 * abs(kf)
    np.testing.assert_allclose(sol.value, O.posterior_trace(sol.state_cov, H, sol.noise_cov, i_min), rtol=1e-12)


@hypothesis.settings(max_examples=25, deadline=None, derandomize=True)
@hypothesis.given(_problems())
def test_property_joint_wasserstein_and_kl(problem):
    M, H, R, tx, tv, i_min = problem
    n = M.shape[0]
    S = np.block([[M, M @ H.T], [H @ M, H @ M @ H.T + R]])
    sol = _wmmse_joint(S, n, tx)
    assert bool(sol.converged)
    _assert_sym_psd(sol.cov, 1e-12)
    _assert_in_bures_ball(sol.cov, S, tx)
    assert float(sol.value) >= O.schur_trace(S, n) * (1 - 1e-12)
    sol = _worst_case(KL(tx), KL(tv), M, H, R, i_min=i_min)
    assert bool(sol.converged)
    _assert_sym_psd(sol.state_cov, 1e-12)
    _assert_sym_psd(sol.noise_cov, 1e-12)
    assert O.kl_divergence(sol.state_cov, M) <= tx + 1e-8
    assert O.kl_divergence(sol.noise_cov, R) <= tv + 1e-8
    kf = _kf_value(M, H, R, i_min)
    assert float(sol.value) >= kf - 1e-12 * abs(kf)


# ============================================================================ bad input


_M, _H, _R = O.random_instance(np.random.default_rng(7), 3, 2)
_S = O.random_joint(np.random.default_rng(8), 2, 1)


@pytest.mark.parametrize(
    "call, match",
    [
        (lambda: wasserstein_mmse(_M, _H, _R, -0.1, 0.5), "radius_x"),
        (lambda: wasserstein_mmse(_M, _H, _R, 0.5, -0.1), "radius_v"),
        (lambda: Wasserstein(-1.0), "radius"),
        (lambda: KL(-1.0), "radius"),
        (lambda: Moment(0.5), "theta2"),
        (lambda: wasserstein_mmse_joint(_S, 2, -0.1), "radius"),
        (lambda: wasserstein_mmse(_M[:, :2], _H, _R, 0.5, 0.5), "prior_cov"),
        (lambda: wasserstein_mmse(_M, _H, _R[:1], 0.5, 0.5), "noise_cov"),
        (lambda: wasserstein_mmse(_M, _H[:, :2], _R, 0.5, 0.5), r"\bH\b"),
        (lambda: worst_case(KL(0.1), KL(0.1), _M, _H.T, _R), r"\bH\b"),
        (lambda: wasserstein_mmse_joint(_S[:, :2], 2, 0.5), r"\bcov\b"),
        (lambda: wasserstein_mmse_joint(_S, 3, 0.5), r"\bn\b"),
        (lambda: worst_case_joint(KL(0.1), _S, 0), r"\bn\b"),
        (lambda: worst_case(0.5, KL(0.1), _M, _H, _R), "state_set"),
        (lambda: worst_case_joint(KL(0.1), _S, 2.0), r"\bn\b"),
    ],
    ids=["radius_x<0", "radius_v<0", "Wasserstein<0", "KL<0", "Moment<1", "radius<0", "prior_cov non-square",
         "noise_cov non-square", "H mismatch", "H transposed", "cov non-square", "n=d", "n=0", "set type",
         "n float"],
)
def test_bad_input(call, match):
    with pytest.raises(ValueError, match=match):
        call()


@pytest.mark.parametrize("kind", ["wasserstein", "kl"])
def test_oracle_warm_start_gives_the_cold_start_answer(rng, kind):
    """`oracle(..., guess=g)` starts the multiplier's root search at `g` (Frank–Wolfe passes the
    previous iterate's): any guess, inside the bracket or not, gives the same maximizer."""
    d = 4
    nom, direction = O.random_spd(rng, d), O.random_spd(rng, d, 0.0)
    ball = Wasserstein(0.7) if kind == "wasserstein" else KL(0.3)
    cov, mult = ball.oracle(jnp.asarray(direction), jnp.asarray(nom))
    for guess in (0.5 * mult, 0.99 * mult, 1.01 * mult, 2.0 * mult, -1.0, 0.0, 1e6, jnp.nan):
        cov_g, mult_g = ball.oracle(jnp.asarray(direction), jnp.asarray(nom), guess=jnp.asarray(guess))
        np.testing.assert_allclose(mult_g, mult, rtol=1e-13)
        np.testing.assert_allclose(cov_g, cov, rtol=1e-12, atol=1e-13)
