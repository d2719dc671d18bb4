#!/usr/bin/env python
"""Li, Shi, Yu, Shi, "Variational Robust Kalman Filters": the paper numbers of `jdrkf reproduce
li-identity` (Table III) and `li-torsion` (Table IV) that lie outside our 95% intervals and were
not explained, examined with an independent NumPy oracle of the authors' MATLAB code
(`lsl-zsj/Variational-Robust-Kalman-Filters`).

Gaps examined (paper vs our stored reports, seed 0, 200 runs, when the experiments ran jdrkf's
VBKF with its default covariance; they now run `VBKF(covariance="nominal")`, the authors' form
found here):

- li-torsion y2 (Table IV Case 1), VBKF x2/x3 (θ_m, θ_t): paper 2.609 / 2.717, ours 1.61 / 1.85
  (now 2.63 / 2.81).
- li-identity y2 (Table III Case 2): VBKF x2 0.086, STKF-AR1 x1/x2 0.092/0.086, KF x2 0.143; ours
  0.115, 0.129/0.118, 0.166 (and the paper's VBKF = STKF-AR1 tie, which ours did not show; it
  now does).
- li-torsion y3 (Table IV Case 3), KF x3 (θ_t): paper 0.524, ours 0.723.

What the script does (the oracles are written from the authors' `akf_forward_vb.m`,
`student_forward_adap.m` and `kf_dob_forward.m`, not from jdrkf; they run all episodes at once,
batched over the run axis):

1. Agreement on identical episodes (simulated by `jdrkf.experiments.li_variational`): the
   oracle's KF against `KalmanFilter`; the oracle's `akf_forward_vb` *with jdrkf's choices*
   (posterior covariance with the adapted R_t, first VB pass at β⁻ = ρβ) against jdrkf's `VBKF`
   with its default covariance, and with the nominal R in the covariance against the
   experiment's `VBKF(covariance="nominal")`; the oracle's `student_forward_adap` (nominal-covariance Joseph form, as written) against
   jdrkf's `STKF_AR1(covariance="nominal")`. Maximum absolute state difference.
2. The authors' VBKF as written: their `akf_forward_vb.m` (both the identity and the torsion
   version) updates the posterior covariance with the Joseph form using the *nominal* R,
   `P = (I − KH)P⁻(I − KH)ᵀ + K R Kᵀ`, although the gain uses the adapted `R_t = diag(λ)`, and
   its first VB pass uses the previous step's posterior β (not ρβ). jdrkf's `VBKF` uses `R_t` in
   the Joseph form (the VB posterior) and ρβ by default; the experiments now run
   `VBKF(covariance="nominal")`, the first switch. One switch at a time, on the
   report's episodes (same seeds, 200 runs): every torsion case (y2, y3, y4: the quirk must not
   break the rows that agree) and identity y2.
3. Identity y2 levels: where the paper's single run lies among our per-run RMSEs with the
   authors' filters (KF, VBKF as written, STKF-AR1), the fraction of runs at or below all of the
   paper's y2 numbers at once, and the KF (which has no hyper-parameter or quirk) under the two
   noise laws on record (the code's std × ((2 sin(2π·0.02 t))² + 1), the paper's printed
   variance × (2 sin²(0.04π t) + 1)) and the code law applied to the variance.
4. Torsion y3 KF x3: the KF's θ_t error is driven by the measurement outliers (p = 0.01,
   N(0, 900R), whole vector). Per run, the outlier energy of channel 2 (θ_t) recovered from the
   episode, `Σ_k v²_{k,2}/(a_k² r)` over steps whose whitened |v_{k,2}| > 6 (a nominal draw exceeds
   6 with probability 2e-9), its correlation with the KF x3 RMSE, and the KF's means over the 5% of
   runs with the least channel-2 outlier energy against the paper's five KF numbers.

A paper value is "inside the spread" when it lies in the central 95% of the per-run values (the
paper's tables are single runs). Every mean has a 95% Student-t interval.

Usage: `python benchmarks/li_gaps.py [--quick] [--seed 0] [--runs 200] [--out benchmarks/results]`.
"""

from __future__ import annotations

import argparse
import os
import sys
import time

import numpy as np

# ----------------------------------------------------------------------------------------------
# NumPy oracle of the authors' MATLAB filters, batched over runs: z is (B, T, m), states (B, T, n)
# ----------------------------------------------------------------------------------------------


def oracle_kf(F, H, Q, R, x0, P0, z):
    """`kf_dob_forward.m` / `kf_forward.m`: predict, K = P⁻Hᵀ(HP⁻Hᵀ + R)⁻¹, P = (I − KH)P⁻."""
    B, T, _ = z.shape
    n = F.shape[0]
    x, P = np.broadcast_to(x0, (B, n)).copy(), P0.copy()
    out = np.empty((B, T, n))
    for k in range(T):
        x, P = x @ F.T, F @ P @ F.T + Q
        K = np.linalg.solve(H @ P @ H.T + R, H @ P).T
        x = x + (z[:, k] - x @ H.T) @ K.T
        P = (np.eye(n) - K @ H) @ P
        out[:, k] = x
    return out


def oracle_vbkf(F, H, Q, R, x0, P0, z, alpha0, beta0, rho, num_iter=4, cov="nominal", first="previous"):
    """`akf_forward_vb.m` for a diagonal R, β in units of R (the identity version whitens by
    chol(R); the torsion version uses absolute variances with β₀ = 2.03 = 20.3·0.1, the same).

    Per step: α⁻ = ρα, β⁻ = ρβ, α = α⁻ + ½; `num_iter` times: λ = β/α, R_t = diag(λ r),
    K from P⁻ and R_t, x = x⁻ + K(z − Hx⁻), P = (I − KH)P⁻(I − KH)ᵀ + K R_c Kᵀ, then
    β = β⁻ + ½e² + ½ diag(HPHᵀ)/r with e = (z − Hx)/√r.
    `cov="nominal"`: R_c = R (the authors' code); `"adapted"`: R_c = R_t (jdrkf).
    `first="previous"`: the first pass uses the previous posterior β (the authors' code, which
    sets β⁻ but reads β); `"forgotten"`: β⁻ (jdrkf's `start="scale"`)."""
    B, T, m = z.shape
    n = F.shape[0]
    r = np.diag(R)
    x, P = np.broadcast_to(x0, (B, n)).copy(), np.broadcast_to(P0, (B, n, n)).copy()
    alpha, beta = np.full((B, m), float(alpha0)), np.full((B, m), float(beta0))
    eye, out = np.eye(n), np.empty((B, T, n))
    for k in range(T):
        alpha_m, beta_m = rho * alpha, rho * beta
        alpha = alpha_m + 0.5
        xp, Pp = x @ F.T, F @ P @ F.T + Q
        if first == "forgotten":
            beta = beta_m.copy()
        for _ in range(num_iter):
            rt = (beta / alpha) * r  # (B, m)
            S = H @ Pp @ H.T + rt[:, :, None] * np.eye(m)
            K = np.swapaxes(np.linalg.solve(S, H @ Pp), 1, 2)
            x = xp + np.einsum("bnm,bm->bn", K, z[:, k] - xp @ H.T)
            A = eye - K @ H
            rc = np.broadcast_to(R, (B, m, m)) if cov == "nominal" else rt[:, :, None] * np.eye(m)
            P = A @ Pp @ np.swapaxes(A, 1, 2) + K @ rc @ np.swapaxes(K, 1, 2)
            e = (z[:, k] - x @ H.T) / np.sqrt(r)
            beta = beta_m + 0.5 * e**2 + 0.5 * np.einsum("ij,bjk,ik->bi", H, P, H) / r
        out[:, k] = x
    return out


def oracle_stkf_ar(F, H, Q, R, x0, P0, z, nu_p, nu_r, rho_p, rho_r, max_iter=4, tol=1e-5):
    """`student_forward_adap.m` (identity version) for a diagonal R: per step ν ← ρν + 1,
    τ² ← ρτ²; fixed point on x with P₁ = L_P C_x⁻¹ L_Pᵀ, R₁ = L_R C_y⁻¹ L_Rᵀ,
    C = diag(ν/(τ²ν + e²)), at most `max_iter` passes, stop when ‖x_j − x_{j−1}‖/(‖x_{j−1}‖ + 1e-5)
    < tol; P = (I − KH)P⁻(I − KH)ᵀ + K R Kᵀ (nominal R, P⁻); then λ ← ρλ + e²/ν + v/ν, τ² = λ
    (scale frozen where ρ = 1). Runs whose loop stops at different passes are masked per run."""
    B, T, m = z.shape
    n = F.shape[0]
    br = np.sqrt(np.diag(R))
    nu_p, nu_r = np.full((B, n), float(nu_p)), np.full((B, m), float(nu_r))
    rho_p, rho_r = np.broadcast_to(np.asarray(rho_p, float), (n,)), np.broadcast_to(np.asarray(rho_r, float), (m,))
    tau_p, tau_r, lam_p, lam_r = np.ones((B, n)), np.ones((B, m)), np.ones((B, n)), np.ones((B, m))
    x, P = np.broadcast_to(x0, (B, n)).copy(), np.broadcast_to(P0, (B, n, n)).copy()
    eye, out = np.eye(n), np.empty((B, T, n))
    for k in range(T):
        xp, Pp = x @ F.T, F @ P @ F.T + Q
        nu_p, nu_r = rho_p * nu_p + 1.0, rho_r * nu_r + 1.0
        tau_p, tau_r = rho_p * tau_p, rho_r * tau_r
        Lp = np.linalg.cholesky(Pp)
        dp = np.linalg.solve(Lp, xp[..., None])[..., 0]
        dr = z[:, k] / br
        x_last, active = xp.copy(), np.ones(B, bool)
        xt, K1 = xp.copy(), np.zeros((B, n, m))
        ep, er = np.zeros((B, n)), np.zeros((B, m))
        for _ in range(max_iter):
            ep_j = dp - np.linalg.solve(Lp, x_last[..., None])[..., 0]
            er_j = dr - (x_last @ H.T) / br
            cx = nu_p / (tau_p * nu_p + ep_j**2)
            cy = nu_r / (tau_r * nu_r + er_j**2)
            P1 = Lp @ (Lp / cx[:, None, :]).swapaxes(1, 2)  # L_P diag(1/C_x) L_Pᵀ
            R1 = (br**2) / cy  # diagonal
            S = H @ P1 @ H.T + R1[:, :, None] * np.eye(m)
            K_j = np.swapaxes(np.linalg.solve(S, H @ P1), 1, 2)
            x_j = xp + np.einsum("bnm,bm->bn", K_j, z[:, k] - xp @ H.T)
            a = active[:, None]
            ep, er = np.where(a, ep_j, ep), np.where(a, er_j, er)
            K1 = np.where(active[:, None, None], K_j, K1)
            xt = np.where(a, x_j, xt)
            rel = np.linalg.norm(x_j - x_last, axis=1) / (np.linalg.norm(x_last, axis=1) + 1e-5)
            x_last = np.where(a, x_j, x_last)
            active = active & ~(rel < tol)
            if not active.any():
                break
        x = xt
        A = eye - K1 @ H
        P = A @ Pp @ np.swapaxes(A, 1, 2) + K1 @ R @ np.swapaxes(K1, 1, 2)
        Lp_inv = np.linalg.inv(Lp)
        vp = np.einsum("bij,bjk,bik->bi", Lp_inv, P, Lp_inv)
        vr = np.einsum("ij,bjk,ik->bi", H, P, H) / br**2
        lam_p = np.where(rho_p == 1, lam_p, rho_p * lam_p + ep**2 / nu_p + vp / nu_p)
        lam_r = np.where(rho_r == 1, lam_r, rho_r * lam_r + er**2 / nu_r + vr / nu_r)
        tau_p, tau_r = lam_p.copy(), lam_r.copy()
        out[:, k] = x
    return out


def rmse(states, est):
    """Per-run, per-state RMSE over the horizon: (B, n)."""
    return np.sqrt(np.mean((states - est) ** 2, axis=1))


# ----------------------------------------------------------------------------------------------
# summaries
# ----------------------------------------------------------------------------------------------


def summarize(values, paper=None) -> dict:
    from jdrkf import metrics

    v = np.asarray(values, float)
    mean, (lo, hi) = metrics.mean_ci(v)
    out = {"mean": mean, "ci95": [lo, hi], "p2.5": float(np.percentile(v, 2.5)), "p97.5": float(np.percentile(v, 97.5)), "n": int(v.size)}
    if paper is not None:
        out["paper"] = float(paper)
        out["paper_percentile"] = 100.0 * float(np.mean(v <= paper))
        out["paper_inside_ci"] = bool(lo <= paper <= hi)
        out["paper_inside_spread"] = bool(out["p2.5"] <= paper <= out["p97.5"])
    return out


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--quick", action="store_true", help="fewer runs and a shorter agreement check (smoke test)")
    ap.add_argument("--seed", type=int, default=0, help="the reports' seed (jdrkf reproduce … --seed)")
    ap.add_argument("--runs", type=int, default=None, help="runs per case (default 200, the reports'; quick 24)")
    ap.add_argument("--out", default=os.path.join(os.path.dirname(os.path.abspath(__file__)), "results"))
    args = ap.parse_args(argv)

    import jax

    jax.config.update("jax_enable_x64", True)  # the benchmark process, not the library
    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

    from _provenance import write_results
    from jdrkf.experiments import li_variational as lv

    quick = args.quick
    runs = args.runs or (24 if quick else 200)
    agree_runs = 6 if quick else 20
    t_start, cpu_start = time.time(), time.process_time()
    res = {"seed": args.seed, "quick": quick, "runs": runs, "agreement_runs": agree_runs}
    key = jax.random.key(args.seed)

    def log(msg):
        print(f"[{time.time() - t_start:6.1f}s, CPU {time.process_time() - cpu_start:6.1f}s] {msg}", flush=True)

    def jd(flt, model, prior, tr):
        return np.asarray(jax.vmap(lambda y: flt(model, prior, y).filtered_means)(tr.observations))

    # models as numpy
    im, ip = lv.identity_model(), lv.identity_prior()
    iF, iH, iR = (np.asarray(a) for a in (im.F, im.H, im.R))
    iQ = np.asarray(im.G) @ np.asarray(im.Q) @ np.asarray(im.G).T
    ix0, iP0 = np.asarray(ip.mean), np.asarray(ip.cov)
    tm, tp = lv.torsion_model(), lv.torsion_prior()
    tF, tH, tQ, tR = (np.asarray(a) for a in (tm.F, tm.H, tm.Q, tm.R))
    tx0, tP0 = np.asarray(tp.mean), np.asarray(tp.cov)
    TV = dict(alpha0=20.0, beta0=2.03 / lv.V_VN, rho=0.98)  # torsion VBKF (the authors' scripts)
    IV = dict(alpha0=50.0, beta0=50.0, rho=0.99)  # identity VBKF

    # the reports' episodes: run_identity uses fold_in(key, 1) for y2, run_torsion fold_in(key, j)
    def identity_data(case, n, key_index=1):
        tr = lv.identity_scenario(jax.random.fold_in(key, key_index), case, n)
        return tr, np.asarray(tr.states), np.asarray(tr.observations)

    def torsion_data(case, n):
        tr = lv.torsion_scenario(jax.random.fold_in(key, lv.TORSION_CASES.index(case)), case, n)
        return tr, np.asarray(tr.states), np.asarray(tr.observations)

    # ---- 1. agreement --------------------------------------------------------------------------
    agree = {}
    tr, xs, z = identity_data("y2", agree_runs)
    fl, default = lv.identity_filters("y2"), lv.identity_filters("y2", "reweighted")
    agree["identity y2 KF"] = np.abs(oracle_kf(iF, iH, iQ, iR, ix0, iP0, z) - jd(fl["KF"], im, ip, tr)).max()
    agree["identity y2 VBKF (oracle with jdrkf's default covariance)"] = np.abs(
        oracle_vbkf(iF, iH, iQ, iR, ix0, iP0, z, **IV, cov="adapted", first="forgotten") - jd(default["VBKF"], im, ip, tr)).max()
    agree["identity y2 VBKF (the experiment's covariance='nominal' vs the oracle's nominal-R form)"] = np.abs(
        oracle_vbkf(iF, iH, iQ, iR, ix0, iP0, z, **IV, cov="nominal", first="forgotten") - jd(fl["VBKF"], im, ip, tr)).max()
    agree["identity y2 STKF-AR1 (authors' student_forward_adap vs covariance='nominal')"] = np.abs(
        oracle_stkf_ar(iF, iH, iQ, iR, ix0, iP0, z, 1e8, 100.0, 1.0, 0.99) - jd(fl["STKF-AR1"], im, ip, tr)).max()
    scale = {"identity": float(np.abs(xs).max())}
    tr, xs, z = torsion_data("y2", agree_runs)
    fl, default = lv.torsion_filters("y2"), lv.torsion_filters("y2", "reweighted")
    agree["torsion y2 KF"] = np.abs(oracle_kf(tF, tH, tQ, tR, tx0, tP0, z) - jd(fl["KF"], tm, tp, tr)).max()
    agree["torsion y2 VBKF (oracle with jdrkf's default covariance)"] = np.abs(
        oracle_vbkf(tF, tH, tQ, tR, tx0, tP0, z, **TV, cov="adapted", first="forgotten") - jd(default["VBKF"], tm, tp, tr)).max()
    agree["torsion y2 VBKF (the experiment's covariance='nominal' vs the oracle's nominal-R form)"] = np.abs(
        oracle_vbkf(tF, tH, tQ, tR, tx0, tP0, z, **TV, cov="nominal", first="forgotten") - jd(fl["VBKF"], tm, tp, tr)).max()
    scale["torsion"] = float(np.abs(xs).max())
    res["agreement"] = {"max_abs_state_diff": {k: float(v) for k, v in agree.items()}, "max_abs_state": scale,
                        "steps": {"identity": lv.IDENTITY_STEPS, "torsion": lv.NUM_STEPS}}
    log("agreement: " + ", ".join(f"{k}: {v:.1e}" for k, v in agree.items()))

    # ---- 2. the authors' VBKF as written, torsion y2/y3/y4 -----------------------------------------
    variants = {"jdrkf VBKF (adapted R_t, ρβ first)": dict(cov="adapted", first="forgotten"),
                "first pass at previous β only": dict(cov="adapted", first="previous"),
                "nominal-R Joseph covariance only": dict(cov="nominal", first="forgotten"),
                "authors' code (both)": dict(cov="nominal", first="previous")}
    tors, ydata = {}, {}
    for case in lv.TORSION_CASES:
        tr, xs, z = torsion_data(case, runs)
        ydata[case] = (tr, xs, z)
        paper = lv.PAPER_TORSION[case]["VBKF"]
        per = {}
        for name, kw in variants.items():
            r = rmse(xs, oracle_vbkf(tF, tH, tQ, tR, tx0, tP0, z, **TV, **kw))
            per[name] = {f"x{i + 1}": summarize(r[:, i], paper[i]) for i in range(5)}
        kf = rmse(xs, oracle_kf(tF, tH, tQ, tR, tx0, tP0, z))
        per["KF (oracle)"] = {f"x{i + 1}": summarize(kf[:, i], lv.PAPER_TORSION[case]["KF"][i]) for i in range(5)}
        if case == "y4":  # the mild-draw explanation of y4: the 5% of runs with the least process-outlier energy
            _, energy = lv.process_outliers(tr)
            low = np.argsort(energy, kind="stable")[: max(2, runs // 20)]
            for name in (next(iter(variants)), list(variants)[-1]):
                r = rmse(xs[low], oracle_vbkf(tF, tH, tQ, tR, tx0, tP0, z[low], **TV, **variants[name]))
                per[f"{name}, {len(low)} runs with least process-outlier energy"] = {
                    f"x{i + 1}": summarize(r[:, i], paper[i]) for i in range(5)}
        tors[case] = per
        log(f"torsion {case}: VBKF x2 jdrkf {per[next(iter(variants))]['x2']['mean']:.3f}, "
            f"authors {per[list(variants)[-1]]['x2']['mean']:.3f} (paper {paper[1]})")
    res["torsion_vbkf"] = tors

    # ---- 3. identity y2 ------------------------------------------------------------------------
    tr, xs, z = identity_data("y2", runs)
    paper = lv.PAPER_IDENTITY["y2"]
    est = {"KF": oracle_kf(iF, iH, iQ, iR, ix0, iP0, z),
           "VBKF (jdrkf)": oracle_vbkf(iF, iH, iQ, iR, ix0, iP0, z, **IV, cov="adapted", first="forgotten"),
           "VBKF (as written)": oracle_vbkf(iF, iH, iQ, iR, ix0, iP0, z, **IV, cov="nominal", first="previous"),
           "STKF-AR1 (as written)": oracle_stkf_ar(iF, iH, iQ, iR, ix0, iP0, z, 1e8, 100.0, 1.0, 0.99)}
    paper_of = {"KF": paper["KF"], "VBKF (jdrkf)": paper["VBKF"], "VBKF (as written)": paper["VBKF"],
                "STKF-AR1 (as written)": paper["STKF-AR1"]}
    rm = {f: rmse(xs, e) for f, e in est.items()}
    ident = {"filters": {f: {f"x{i + 1}": summarize(rm[f][:, i], paper_of[f][i]) for i in range(2)} for f in rm}}
    d = rm["VBKF (as written)"] - rm["STKF-AR1 (as written)"]
    dj = rm["VBKF (jdrkf)"] - rm["STKF-AR1 (as written)"]
    ident["tie"] = {"authors' VBKF − STKF-AR1": {f"x{i + 1}": summarize(d[:, i]) for i in range(2)},
                    "jdrkf VBKF − STKF-AR1": {f"x{i + 1}": summarize(dj[:, i]) for i in range(2)},
                    "max_abs_state_diff_authors_vbkf_vs_stkf_ar1": float(np.abs(est["VBKF (as written)"] - est["STKF-AR1 (as written)"]).max())}
    joint = ((rm["KF"][:, 0] <= paper["KF"][0]) & (rm["KF"][:, 1] <= paper["KF"][1])
             & (rm["VBKF (as written)"][:, 0] <= paper["VBKF"][0]) & (rm["VBKF (as written)"][:, 1] <= paper["VBKF"][1]))
    ident["joint_fraction_at_or_below_all_four"] = float(joint.mean())
    ident["fraction_KF_x2_at_or_below"] = float(np.mean(rm["KF"][:, 1] <= paper["KF"][1]))
    corr = np.corrcoef(rm["KF"][:, 1], rm["VBKF (as written)"][:, 1])[0, 1]
    ident["corr_KF_x2_VBKF_x2"] = float(corr)
    # VBKF/KF paired ratio (as written) against the forgetting factor ρ (the code: 0.99; its default 0.98)
    sweep = {}
    for rho in (0.9, 0.95, 0.98, 0.99, 0.995):
        r = rmse(xs, oracle_vbkf(iF, iH, iQ, iR, ix0, iP0, z, 50.0, 50.0, rho, cov="nominal", first="previous"))
        sweep[f"{rho:g}"] = {f"x{i + 1}": summarize(r[:, i] / rm["KF"][:, i], paper["VBKF"][i] / paper["KF"][i]) for i in range(2)}
    ident["rho_sweep_vbkf_over_kf"] = sweep
    # KF under the other laws on record (fresh episodes, same count)
    laws = {}
    import jax.numpy as jnp
    from jdrkf import GaussianNoise, ScaledNoise
    from jdrkf import simulate
    from jdrkf import Gaussian

    def kf_law(factor, k):
        meas = ScaledNoise(GaussianNoise(im.R), factor)
        trl = simulate(jax.random.fold_in(key, k), im, Gaussian(jnp.zeros(2), jnp.zeros((2, 2))), lv.IDENTITY_STEPS, runs, measurement_noise=meas)
        r = rmse(np.asarray(trl.states), oracle_kf(iF, iH, iQ, iR, ix0, iP0, np.asarray(trl.observations)))
        return {f"x{i + 1}": summarize(r[:, i], paper["KF"][i]) for i in range(2)}

    laws["code: std × ((2 sin(2π·0.02 t))² + 1)"] = ident["filters"]["KF"]
    laws["printed: variance × (2 sin²(0.04π t) + 1)"] = kf_law(lv._printed_variance_factor, 2)
    laws["code law on the variance: variance × ((2 sin(2π·0.02 t))² + 1)"] = kf_law(lv._identity_amp, 3)
    ident["kf_laws"] = laws
    res["identity_y2"] = ident
    log(f"identity y2: authors' VBKF {ident['filters']['VBKF (as written)']['x1']['mean']:.4f}/"
        f"{ident['filters']['VBKF (as written)']['x2']['mean']:.4f}, joint {joint.mean():.3f}")

    # ---- 4. torsion y3 KF x3 vs the measurement-outlier draw ------------------------------------------
    tr, xs, z = ydata["y3"]
    kf = rmse(xs, oracle_kf(tF, tH, tQ, tR, tx0, tP0, z))
    v = z - xs @ tH.T  # (B, T, 2) measurement noise
    t = np.arange(z.shape[1])
    a = np.asarray(lv._slow_amp(t))
    w = v / (a[None, :, None] * np.sqrt(lv.V_VN))
    hit = np.abs(w) > 6.0
    energy = np.where(hit, w**2, 0.0).sum(axis=1)  # (B, 2) per channel
    count = hit.any(axis=2).sum(axis=1)
    low = np.argsort(energy[:, 1], kind="stable")[: max(2, runs // 20)]
    kpaper = lv.PAPER_TORSION["y3"]["KF"]
    y3 = {"outliers_per_run": summarize(count), "corr_energy_ch2_KF_x3": float(np.corrcoef(energy[:, 1], kf[:, 2])[0, 1]),
          "corr_energy_ch1_KF_x2": float(np.corrcoef(energy[:, 0], kf[:, 1])[0, 1]),
          "corr_energy_ch2_KF_x2": float(np.corrcoef(energy[:, 1], kf[:, 1])[0, 1]),
          "all_runs": {f"x{i + 1}": summarize(kf[:, i], kpaper[i]) for i in range(5)},
          "low_ch2_energy_runs": {f"x{i + 1}": summarize(kf[low, i], kpaper[i]) for i in range(5)},
          "low_ch2_energy_count": int(len(low)),
          "channel2_energy_percentile_needed": None}
    # the channel-2 outlier energy of runs whose KF x3 is within ±5% of the paper's
    near = np.abs(kf[:, 2] / kpaper[2] - 1.0) < 0.05
    y3["runs_with_KF_x3_within_5pct"] = int(near.sum())
    if near.any():
        y3["channel2_energy_percentile_needed"] = float(np.mean(energy[:, 1] <= np.median(energy[near, 1])) * 100)
    res["torsion_y3_kf"] = y3
    log(f"torsion y3: KF x3 all {kf[:, 2].mean():.3f}, low-energy runs {kf[low, 2].mean():.3f} (paper {kpaper[2]})")

    stem = os.path.join(args.out, "li_gaps" + ("_quick" if quick else ""))
    log(f"wrote {write_results(res, stem, render, (t_start, cpu_start))}.md/.json")
    return res


def _ci(s, digits=3):
    return f"{s['mean']:.{digits}f} [{s['ci95'][0]:.{digits}f}, {s['ci95'][1]:.{digits}f}]"


def _pct(s):
    return f"{s['paper_percentile']:.1f}"


def render(res) -> str:
    lines = ["# Li et al. (Variational Robust KFs): the li-identity / li-torsion gaps", "",
             f"Seed {res['seed']} (the reports' episodes), {res['runs']} runs per case; wall {res['wall_s']:.0f} s, "
             f"CPU (user + sys) {res['cpu_s']:.0f} s. Means with 95% Student-t intervals; 'pct' is the percentile of the "
             "paper's single-run number among our per-run values. Generated by `benchmarks/li_gaps.py`"
             + (" --quick" if res["quick"] else "") + ".", "",
             f"## 1. NumPy oracle of the authors' code vs jdrkf, identical episodes ({res['agreement_runs']} runs)", "",
             "| check | max abs state difference |", "|---|---|"]
    for k, v in res["agreement"]["max_abs_state_diff"].items():
        lines.append(f"| {k} | {v:.1e} |")
    lines += ["", f"(largest |state|: identity {res['agreement']['max_abs_state']['identity']:.3g}, torsion "
              f"{res['agreement']['max_abs_state']['torsion']:.3g}.)", "",
              "## 2. The authors' VBKF as written (`akf_forward_vb.m`): torsion, all cases", "",
              "Their VBKF updates P with the Joseph form and the *nominal* R (the gain uses the adapted R_t); jdrkf's "
              "VBKF uses R_t. One switch at a time on the reports' episodes.", "",
              "| case | variant | x1 (d) | x2 (θ_m) | x3 (θ_t) | x4 (ω_m) | x5 (ω_t) |", "|---|---|---|---|---|---|---|"]
    for case, per in res["torsion_vbkf"].items():
        first = next(iter(per.values()))
        lines.append(f"| {case} | paper (one run) | " + " | ".join(f"{first[f'x{i}']['paper']:g}" for i in range(1, 6)) + " |")
        for name, s in per.items():
            lines.append(f"| {case} | {name} | " + " | ".join(f"{_ci(s[f'x{i}'])} (pct {_pct(s[f'x{i}'])})" for i in range(1, 6)) + " |")
    ident = res["identity_y2"]
    lines += ["", "## 3. Identity y2 (Table III Case 2)", "",
              "| filter | x1 (position) | pct | x2 (velocity) | pct |", "|---|---|---|---|---|"]
    for f, s in ident["filters"].items():
        lines.append(f"| {f} (paper {s['x1']['paper']:g} / {s['x2']['paper']:g}) | {_ci(s['x1'], 4)} | {_pct(s['x1'])} | {_ci(s['x2'], 4)} | {_pct(s['x2'])} |")
    tie = ident["tie"]
    lines += ["", "Paired differences (same runs): authors' VBKF − STKF-AR1 "
              + ", ".join(f"{k} {_ci(v, 5)}" for k, v in tie["authors' VBKF − STKF-AR1"].items())
              + f" (max state difference {tie['max_abs_state_diff_authors_vbkf_vs_stkf_ar1']:.2g}); jdrkf VBKF − STKF-AR1 "
              + ", ".join(f"{k} {_ci(v, 5)}" for k, v in tie["jdrkf VBKF − STKF-AR1"].items()) + ".", "",
              f"Fraction of runs at or below all four of the paper's KF and VBKF numbers: {ident['joint_fraction_at_or_below_all_four']:.3f}; "
              f"KF x2 ≤ 0.143: {ident['fraction_KF_x2_at_or_below']:.3f}; correlation of KF x2 and VBKF x2 over runs "
              f"{ident['corr_KF_x2_VBKF_x2']:.2f}.", "",
              "VBKF (as written) / KF RMSE ratio per run against the forgetting factor ρ (the code uses 0.99):", "",
              "| ρ | x1 ratio (paper 0.708) | pct | x2 ratio (paper 0.601) | pct |", "|---|---|---|---|---|"]
    for rho, s in ident["rho_sweep_vbkf_over_kf"].items():
        lines.append(f"| {rho} | {_ci(s['x1'])} | {_pct(s['x1'])} | {_ci(s['x2'])} | {_pct(s['x2'])} |")
    lines += ["",
              "KF (no hyper-parameters, no quirk) under the measurement-noise laws on record:", "",
              "| law | KF x1 (paper 0.130) | pct | KF x2 (paper 0.143) | pct |", "|---|---|---|---|---|"]
    for law, s in ident["kf_laws"].items():
        lines.append(f"| {law} | {_ci(s['x1'], 4)} | {_pct(s['x1'])} | {_ci(s['x2'], 4)} | {_pct(s['x2'])} |")
    y3 = res["torsion_y3_kf"]
    lines += ["", "## 4. Torsion y3 (Table IV Case 3): the KF and the measurement-outlier draw", "",
              f"Outlier steps per run {_ci(y3['outliers_per_run'], 1)}; correlation over runs of channel-2 (θ_t) outlier energy "
              f"with KF x3: {y3['corr_energy_ch2_KF_x3']:.2f}; of channel-1 energy with KF x2: {y3['corr_energy_ch1_KF_x2']:.2f}; "
              f"of channel-2 energy with KF x2: {y3['corr_energy_ch2_KF_x2']:.2f}.", "",
              f"| KF state | paper | all runs | pct | {y3['low_ch2_energy_count']} runs with the least channel-2 outlier energy | pct |",
              "|---|---|---|---|---|---|"]
    for i in range(1, 6):
        a, b = y3["all_runs"][f"x{i}"], y3["low_ch2_energy_runs"][f"x{i}"]
        lines.append(f"| x{i} | {a['paper']:g} | {_ci(a)} | {_pct(a)} | {_ci(b)} | {_pct(b)} |")
    if y3["channel2_energy_percentile_needed"] is not None:
        lines += ["", f"{y3['runs_with_KF_x3_within_5pct']} runs have KF x3 within ±5% of the paper's; their median channel-2 "
                  f"outlier energy is at percentile {y3['channel2_energy_percentile_needed']:.0f} of all runs."]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
