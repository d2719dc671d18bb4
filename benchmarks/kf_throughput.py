#!/usr/bin/env python
"""Kalman-filter throughput: jdrkf vs dynamax `lgssm_filter` vs a batched NumPy KF.

Seed 000's system (n = 2 states, m = 1 observation), B independent runs of
length T simulated once with NumPy (fixed seed) and fed to every
implementation. For each dtype (float32, float64) and each B the script

1. checks that the filtered means (and covariances, log-likelihoods) of all
   implementations agree and prints the max abs differences;
2. times each implementation: compile time = first call − median steady-state
   call; run time = median of `--repeats` calls (`jax.block_until_ready`);
   steps/s = B·T / run time;
3. prints a markdown table with ratios and writes JSON + markdown.

Every implementation does the full per-run computation: the covariance recursion
of a time-invariant model does not depend on the data, but no implementation is
allowed to share it across runs (see "dynamax (shared cov)" below for what
happens when it is).

Implementations (rows of the table):

- `jdrkf`: `jax.jit(jax.vmap(jdrkf.KalmanFilter(), in_axes=(None, None, 0)))`,
  the library as it is. Its NaN (missing-data) masking makes the observation
  matrix depend on `y`, so the covariance recursion is per run.
- `dynamax`: `lgssm_filter` vmapped over the runs *and* over a per-run copy of
  the initial covariance, so that its covariance recursion is per run as well.
- `numpy`: a batched NumPy KF (loop over time, vectorized over runs with
  einsum, batch axis last; Joseph-form update, Cholesky unrolled over the m×m
  innovation covariance), per-run covariances.
- `dynamax (shared cov)` — *reference only, not a fair comparison*:
  `jax.vmap(lgssm_filter, in_axes=(None, 0))`. Since nothing in dynamax's
  covariance recursion depends on the data, `vmap` leaves it unbatched: it is
  computed once per time step for all B runs. This is the usual way to call
  dynamax and is how a ~4e7 steps/s figure is obtained; it is excluded from the
  goal ratio.

Precision: each dtype runs in its own child process (the parent re-invokes this
script with `--child --dtype ...`); the float64 child enables `jax_enable_x64`
before any array is created, and every output's dtype is asserted.

`--variants` additionally times prototype variants of the jdrkf step (written
here, not in the library) at the largest B, to explain what bounds the library.

Usage:

    python benchmarks/kf_throughput.py                 # full run, B ∈ {1e3, 1e4}, T = 1000
    python benchmarks/kf_throughput.py --variants      # + prototype variants at the largest B
    python benchmarks/kf_throughput.py --quick --out /tmp/kfb   # smoke run, B = 100, T = 100
"""

from __future__ import annotations

import argparse
import datetime
import json
import math
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time

import numpy as np

# --------------------------------------------------------------------------- system / data

# Seed 000's system: x_k = F x_{k-1} + w_k, y_k = H x_k + v_k, x_0 ~ N(0, I2).
SYSTEM = {
    "F": [[0.9802, 0.0196], [0.0, 0.9802]],
    "H": [[1.0, -1.0]],
    "Q": [[1.9608, 0.0195], [0.0195, 1.9605]],
    "R": [[1.0]],
    "m0": [0.0, 0.0],
    "P0": [[1.0, 0.0], [0.0, 1.0]],
}
DATA_SEED = 0


from _provenance import cpu_model, loadavg, package_source_hash  # noqa: E402


def system_arrays(dtype="float64"):
    return {k: np.asarray(v, dtype=dtype) for k, v in SYSTEM.items()}


def simulate(num_runs: int, num_steps: int, seed: int = DATA_SEED) -> np.ndarray:
    """`ys` of shape (num_runs, num_steps, m), float64, simulated with NumPy."""
    s = system_arrays()
    F, H, Q, R, m0, P0 = s["F"], s["H"], s["Q"], s["R"], s["m0"], s["P0"]
    n, m = F.shape[0], H.shape[0]
    rng = np.random.default_rng(seed)
    lq, lr, lp = np.linalg.cholesky(Q), np.linalg.cholesky(R), np.linalg.cholesky(P0)
    x = m0 + rng.standard_normal((num_runs, n)) @ lp.T
    ys = np.empty((num_runs, num_steps, m))
    for t in range(num_steps):
        x = x @ F.T + rng.standard_normal((num_runs, n)) @ lq.T
        ys[:, t] = x @ H.T + rng.standard_normal((num_runs, m)) @ lr.T
    return ys


# --------------------------------------------------------------------------- NumPy KF


def numpy_kf(F, H, Q, R, m0, P0, ys):
    """Batched Kalman filter in NumPy (per-run covariances, Joseph form).

    `ys`: (B, T, m). Loops over time; every step is vectorized over the B runs
    with the batch axis last (so the inner loops run over B, not over n = 2).
    Returns filtered means (B, T, n), filtered covariances (B, T, n, n) (both as
    transposed views of time-major buffers) and the marginal log-likelihoods (B,).
    """
    dtype = ys.dtype
    num_runs, num_steps, m = ys.shape
    n = F.shape[0]
    F, H, Q, R, m0, P0 = (np.asarray(a, dtype) for a in (F, H, Q, R, m0, P0))
    Y = np.ascontiguousarray(np.moveaxis(ys, 0, -1))  # (T, m, B)
    mean = np.repeat(m0[:, None], num_runs, 1)  # (n, B)
    P = np.repeat(P0[:, :, None], num_runs, 2)  # (n, n, B): one covariance per run
    out_m = np.empty((num_steps, n, num_runs), dtype)
    out_P = np.empty((num_steps, n, n, num_runs), dtype)
    ll = np.zeros(num_runs, dtype)
    Rb, Qb, eye = R[:, :, None], Q[:, :, None], np.eye(n, dtype=dtype)[:, :, None]
    log2pi = dtype.type(m * math.log(2 * math.pi))

    def cho_solve(L, b):  # L (m, m, B) lower, b (m, p, B) -> (L Lᵀ)⁻¹ b
        z = np.empty_like(b)
        for i in range(m):
            z[i] = (b[i] - np.einsum("kb,kpb->pb", L[i, :i], z[:i])) / L[i, i]
        x = np.empty_like(b)
        for i in reversed(range(m)):
            x[i] = (z[i] - np.einsum("kb,kpb->pb", L[i + 1:, i], x[i + 1:])) / L[i, i]
        return x

    for t in range(num_steps):
        # predict
        mp = F @ mean
        Pp = np.einsum("ilb,jl->ijb", np.einsum("ik,klb->ilb", F, P), F) + Qb
        Pp = 0.5 * (Pp + Pp.transpose(1, 0, 2))
        # update
        innov = Y[t] - H @ mp
        HP = np.einsum("ik,kjb->ijb", H, Pp)
        S = np.einsum("ijb,lj->ilb", HP, H) + Rb
        S = 0.5 * (S + S.transpose(1, 0, 2))
        L = np.zeros_like(S)
        for j in range(m):
            L[j, j] = np.sqrt(S[j, j] - np.sum(L[j, :j] ** 2, axis=0))
            for i in range(j + 1, m):
                L[i, j] = (S[i, j] - np.sum(L[i, :j] * L[j, :j], axis=0)) / L[j, j]
        KT = cho_solve(L, HP)  # (m, n, B): Kᵀ = S⁻¹ H P
        z = cho_solve(L, innov[:, None, :])[:, 0]
        mean = mp + np.einsum("kib,kb->ib", KT, innov)
        A = eye - np.einsum("kib,kj->ijb", KT, H)
        P = np.einsum("ilb,jlb->ijb", np.einsum("ikb,klb->ilb", A, Pp), A) + np.einsum("kib,kl,ljb->ijb", KT, R, KT)
        P = 0.5 * (P + P.transpose(1, 0, 2))
        logdet = 2 * np.sum(np.log(np.einsum("iib->ib", L)), axis=0)
        ll += -0.5 * (np.sum(innov * z, axis=0) + logdet + log2pi)
        out_m[t] = mean
        out_P[t] = P
    return np.moveaxis(out_m, -1, 0), np.moveaxis(out_P, -1, 0), ll


# --------------------------------------------------------------------------- helpers


def maxabs(a, b) -> float:
    return float(np.max(np.abs(np.asarray(a, np.float64) - np.asarray(b, np.float64))))


def log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


# --------------------------------------------------------------------------- child (one dtype)


def run_child(args) -> dict:
    dtype = args.dtype
    import jax

    jax.config.update("jax_enable_x64", dtype == "float64")
    import dynamax
    import jax.numpy as jnp
    import jdrkf
    from dynamax.linear_gaussian_ssm import (
        ParamsLGSSM,
        ParamsLGSSMDynamics,
        ParamsLGSSMEmissions,
        ParamsLGSSMInitial,
        lgssm_filter,
    )
    from jax import lax

    jdrkf_hash_start = package_source_hash(jdrkf)
    np_dtype = np.dtype(dtype)
    s = system_arrays(dtype)
    F, H, Q, R, m0, P0 = s["F"], s["H"], s["Q"], s["R"], s["m0"], s["P0"]
    n, m = F.shape[0], H.shape[0]
    c = lambda a: jnp.asarray(a, dtype=dtype)

    # jdrkf model/prior (x_0 ~ N(m0, P0); jdrkf predicts first).
    model = jdrkf.LinearModel(F=c(F), H=c(H), Q=c(Q), R=c(R))
    prior = jdrkf.Gaussian(mean=c(m0), cov=c(P0))
    assert model.F.dtype == np_dtype and prior.cov.dtype == np_dtype, (model.F.dtype, prior.cov.dtype)
    kf_jdrkf = jax.jit(jax.vmap(jdrkf.KalmanFilter(), in_axes=(None, None, 0)))
    # nan_as_missing=False: no NaN masking, so vmap shares the covariance recursion (like dynamax shared).
    kf_jdrkf_shared = jax.jit(jax.vmap(jdrkf.KalmanFilter(nan_as_missing=False), in_axes=(None, None, 0)))

    # dynamax conditions on y_1 first: its `initial` is the predicted law of x_1.
    s64 = system_arrays()
    m1 = s64["F"] @ s64["m0"]
    P1 = s64["F"] @ s64["P0"] @ s64["F"].T + s64["Q"]

    def dyn_params(initial_cov):
        return ParamsLGSSM(
            initial=ParamsLGSSMInitial(mean=c(m1), cov=initial_cov),
            dynamics=ParamsLGSSMDynamics(weights=c(F), bias=c(np.zeros(n)), input_weights=c(np.zeros((n, 0))), cov=c(Q)),
            emissions=ParamsLGSSMEmissions(weights=c(H), bias=c(np.zeros(m)), input_weights=c(np.zeros((m, 0))), cov=c(R)),
        )

    # Per-run: the initial covariance is batched, so the whole covariance recursion is.
    per_run_axes = ParamsLGSSM(initial=ParamsLGSSMInitial(mean=None, cov=0), dynamics=None, emissions=None)
    kf_dyn = jax.jit(jax.vmap(lgssm_filter, in_axes=(per_run_axes, 0)))
    kf_dyn_shared = jax.jit(jax.vmap(lgssm_filter, in_axes=(None, 0)))

    ys_all = simulate(max(args.batch_sizes), args.T, args.seed)
    data_checksum = float(np.sum(ys_all))

    def time_jax(fn, *fargs):
        t0 = time.perf_counter()
        out = jax.block_until_ready(fn(*fargs))
        first = time.perf_counter() - t0
        times = []
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            o = jax.block_until_ready(fn(*fargs))
            times.append(time.perf_counter() - t0)
            del o
        return out, first, times

    def time_numpy(fn, *fargs):
        t0 = time.perf_counter()
        out = fn(*fargs)
        first = time.perf_counter() - t0
        times = []
        for _ in range(args.repeats):
            t0 = time.perf_counter()
            o = fn(*fargs)
            times.append(time.perf_counter() - t0)
            del o
        return out, first, times

    def record(impl, B, first, times, compiled=True, note=""):
        med = statistics.median(times)
        return {
            "impl": impl,
            "dtype": dtype,
            "B": B,
            "T": args.T,
            "first_call_s": first,
            "compile_s": (first - med) if compiled else None,
            "run_s": med,
            "run_min_s": min(times),
            "run_times_s": times,
            "steps_per_s": B * args.T / med,
            "note": note,
        }

    rows, checks, variants = [], [], []
    tol = 1e-8 if dtype == "float64" else 1e-3
    all_ok = True
    for B in args.batch_sizes:
        ys_np = np.ascontiguousarray(ys_all[:B]).astype(dtype)
        ys = jnp.asarray(ys_np)
        assert ys.dtype == np_dtype
        log(f"[{dtype}] B={B} T={args.T}: jdrkf ...")
        r_j, first, times = time_jax(kf_jdrkf, model, prior, ys)
        rows.append(record("jdrkf", B, first, times))
        log(f"[{dtype}] B={B}: dynamax (per-run cov) ...")
        p_run = dyn_params(jnp.broadcast_to(c(P1), (B, n, n)))
        r_d, first, times = time_jax(kf_dyn, p_run, ys)
        rows.append(record("dynamax", B, first, times))
        log(f"[{dtype}] B={B}: numpy ...")
        r_n, first, times = time_numpy(numpy_kf, F, H, Q, R, m0, P0, ys_np)
        rows.append(record("numpy", B, first, times, compiled=False))
        log(f"[{dtype}] B={B}: dynamax (shared cov, reference) ...")
        r_s, first, times = time_jax(kf_dyn_shared, dyn_params(c(P1)), ys)
        rows.append(record("dynamax (shared cov)", B, first, times,
                           note="reference only: vmap leaves the data-independent covariance recursion unbatched"))
        log(f"[{dtype}] B={B}: jdrkf (shared cov, nan_as_missing=False) ...")
        r_js, first, times = time_jax(kf_jdrkf_shared, model, prior, ys)
        rows.append(record("jdrkf (shared cov)", B, first, times,
                           note="KalmanFilter(nan_as_missing=False): vmap shares the covariance recursion"))

        # dtypes really are what was asked for
        for name, arrs in {
            "jdrkf": (r_j.filtered_means, r_j.filtered_covariances, r_j.marginal_loglik),
            "dynamax": (r_d.filtered_means, r_d.filtered_covariances, r_d.marginal_loglik),
            "dynamax (shared cov)": (r_s.filtered_means, r_s.filtered_covariances, r_s.marginal_loglik),
            "jdrkf (shared cov)": (r_js.filtered_means, r_js.filtered_covariances, r_js.marginal_loglik),
            "numpy": r_n,
        }.items():
            for a in arrs:
                assert a.dtype == np_dtype, f"{name} output has dtype {a.dtype}, expected {dtype}"
        assert r_j.filtered_means.shape == (B, args.T, n)

        ref_m, ref_P, ref_ll = r_j.filtered_means, r_j.filtered_covariances, r_j.marginal_loglik
        for name, (fm, fP, ll) in {
            "dynamax": (r_d.filtered_means, r_d.filtered_covariances, r_d.marginal_loglik),
            "numpy": r_n,
            "dynamax (shared cov)": (r_s.filtered_means, r_s.filtered_covariances, r_s.marginal_loglik),
            "jdrkf (shared cov)": (r_js.filtered_means, r_js.filtered_covariances, r_js.marginal_loglik),
        }.items():
            ck = {
                "B": B,
                "dtype": dtype,
                "vs": f"jdrkf vs {name}",
                "max_abs_diff_filtered_means": maxabs(ref_m, fm),
                "max_abs_diff_filtered_covs": maxabs(ref_P, fP),
                "max_rel_diff_marginal_loglik": float(
                    np.max(np.abs(np.asarray(ref_ll, np.float64) - np.asarray(ll, np.float64))
                           / np.abs(np.asarray(ref_ll, np.float64)))),
                "tolerance_means": tol,
            }
            ck["ok"] = ck["max_abs_diff_filtered_means"] <= tol and ck["max_abs_diff_filtered_covs"] <= tol
            all_ok &= ck["ok"]
            checks.append(ck)
            log(f"[{dtype}] B={B} check jdrkf vs {name}: max|Δmean|={ck['max_abs_diff_filtered_means']:.3g} "
                f"max|Δcov|={ck['max_abs_diff_filtered_covs']:.3g} "
                f"max rel|Δloglik|={ck['max_rel_diff_marginal_loglik']:.3g} -> {'ok' if ck['ok'] else 'FAIL'}")
        if B == max(args.batch_sizes) and args.variants:
            variants = run_variants(args, jax, jnp, lax, jdrkf, model, prior, ys, r_j, time_jax, record)
        del r_j, r_d, r_n, r_s

    return {
        "dtype": dtype,
        "jax_enable_x64": bool(jax.config.jax_enable_x64),
        "rows": rows,
        "checks": checks,
        "checks_ok": all_ok,
        "variants": variants,
        "data_checksum": data_checksum,
        "jdrkf_source_sha256": {"start": jdrkf_hash_start, "end": package_source_hash(jdrkf)},
        "versions": {
            "python": platform.python_version(),
            "jax": jax.__version__,
            "jaxlib": __import__("jaxlib").__version__,
            "dynamax": getattr(dynamax, "__version__", "unknown"),
            "numpy": np.__version__,
            "jdrkf": getattr(jdrkf, "__version__", "unknown"),
        },
        "jax_devices": [f"{d.platform}:{d.device_kind}:{d.id}" for d in jax.devices()],
        "jax_backend": jax.default_backend(),
    }


# --------------------------------------------------------------------------- prototype variants


def run_variants(args, jax, jnp, lax, jdrkf, model, prior, ys, r_lib, time_jax, record):
    """Prototype variants of the jdrkf KF step, all per-run (the prior is batched
    so nothing can be shared across runs). Used only to explain what bounds the
    library; the main table uses `jdrkf.KalmanFilter` as it is."""
    B = ys.shape[0]
    dtype = str(ys.dtype)
    n = model.state_dim
    bmean = jnp.broadcast_to(prior.mean, (B, n))
    bcov = jnp.broadcast_to(prior.cov, (B, n, n))
    sym = lambda a: 0.5 * (a + jnp.swapaxes(a, -1, -2))
    out = []

    def add(name, description, fn, fargs, get_means):
        log(f"[{dtype}] variant B={B}: {name} ...")
        res, first, times = time_jax(fn, *fargs)
        row = record(name, B, first, times, note=description)
        fm = get_means(res)
        if fm is not None:
            assert fm.dtype == ys.dtype, (name, fm.dtype)
        row["max_abs_diff_filtered_means_vs_lib"] = maxabs(fm, r_lib.filtered_means) if fm is not None else None
        out.append(row)
        del res

    lib_row_means = lambda r: r.filtered_means

    # -- the library, called differently
    add("lib throw=False", "jdrkf.KalmanFilter(throw=False): no eqx.error_if check",
        jax.jit(jax.vmap(jdrkf.KalmanFilter(throw=False), in_axes=(None, None, 0))), (model, prior, ys), lib_row_means)

    def lib_filtered_only(model, prior, ys):
        r = jax.vmap(jdrkf.KalmanFilter(), in_axes=(None, None, 0))(model, prior, ys)
        return r.filtered_means, r.filtered_covariances, r.marginal_loglik

    add("lib, filtered outputs only", "library; jit returns only filtered means/covs/loglik (XLA may drop the rest)",
        jax.jit(lib_filtered_only), (model, prior, ys), lambda r: r[0])

    # -- matrix-form re-implementations of the library step
    def chol_lapack(S):
        return jnp.linalg.cholesky(S)

    def cho_solve_lapack(L, b):
        b2 = b[:, None] if b.ndim == 1 else b
        z = jax.scipy.linalg.solve_triangular(L, b2, lower=True)
        x = jax.scipy.linalg.solve_triangular(L, z, lower=True, trans="T")
        return x[:, 0] if b.ndim == 1 else x

    def chol_unrolled(S):
        """Cholesky of a small static-size matrix with elementwise ops (no LAPACK call)."""
        k = S.shape[-1]
        zero = jnp.zeros_like(S[0, 0])
        L = [[zero] * k for _ in range(k)]
        for j in range(k):
            L[j][j] = jnp.sqrt(S[j, j] - sum((L[j][i] ** 2 for i in range(j)), zero))
            for i in range(j + 1, k):
                L[i][j] = (S[i, j] - sum((L[i][q] * L[j][q] for q in range(j)), zero)) / L[j][j]
        return jnp.stack([jnp.stack(row) for row in L])

    def cho_solve_unrolled(L, b):
        k = L.shape[0]
        zero = jnp.zeros_like(b[0])
        z = [None] * k
        for i in range(k):
            z[i] = (b[i] - sum((L[i, q] * z[q] for q in range(i)), zero)) / L[i, i]
        x = [None] * k
        for i in reversed(range(k)):
            x[i] = (z[i] - sum((L[q, i] * x[q] for q in range(i + 1, k)), zero)) / L[i, i]
        return jnp.stack(x)

    def make_matrix(mask=True, la="lapack", unroll=1):
        chol = chol_unrolled if la == "unrolled" else chol_lapack
        solve = cho_solve_unrolled if la == "unrolled" else cho_solve_lapack

        def run(mdl, mean0, cov0, ys1):
            Fm, Hm, Qm, Rm = mdl.F, mdl.H, mdl.Q, mdl.R

            def body(state, y):
                mean, P = state
                mp = Fm @ mean
                Pp = sym(Fm @ P @ Fm.T + Qm)
                if mask:
                    obs = ~jnp.isnan(y)
                    o = obs.astype(y.dtype)
                    h = Hm * o[:, None]
                    r = Rm * (o[:, None] * o[None, :]) + jnp.diag(1.0 - o)
                    res = jnp.where(obs, y, 0.0)
                    nobs = jnp.sum(o)
                else:
                    h, r, res, nobs = Hm, Rm, y, y.shape[0]
                innov = res - h @ mp
                S = sym(h @ Pp @ h.T + r)
                L = chol(S)
                failed = ~jnp.all(jnp.isfinite(L))
                if la == "lapack_combined":  # one solve for [H P⁻ | innov]: 2 triangular solves instead of 4
                    X = solve(L, jnp.concatenate([h @ Pp, innov[:, None]], axis=1))
                    K, z = X[:, :-1].T, X[:, -1]
                else:
                    K = solve(L, h @ Pp).T
                    z = solve(L, innov)
                mf = mp + K @ innov
                A = jnp.eye(Fm.shape[0], dtype=S.dtype) - K @ h
                Pf = sym(A @ Pp @ A.T + K @ r @ K.T)
                ll = -0.5 * (innov @ z + 2.0 * jnp.sum(jnp.log(jnp.diagonal(L))) + nobs * math.log(2 * math.pi))
                return (mf, Pf), (mp, Pp, mf, Pf, ll, failed)

            return lax.scan(body, (mean0, cov0), ys1, unroll=unroll)[1]

        return jax.jit(jax.vmap(run, in_axes=(None, 0, 0, 0)))

    fargs = (model, bmean, bcov, ys)
    add("proto matrix, LAPACK Cholesky", "the KF step as jdrkf wrote it before linalg.cholesky was unrolled: NaN mask, jnp.linalg.cholesky + 4 solve_triangular (LAPACK potrf/trsm custom calls), Joseph form, all outputs",
        make_matrix(), fargs, lambda r: r[2])
    add("proto matrix, LAPACK, no NaN mask", "as above without the NaN masking (still per-run: batched prior)",
        make_matrix(mask=False), fargs, lambda r: r[2])
    add("proto matrix, LAPACK, one combined solve", "LAPACK as above, but K and the loglik solve share one cho_solve on [H P⁻ | innov] (1 potrf + 2 trsm per step instead of 1 + 4)",
        make_matrix(la="lapack_combined"), fargs, lambda r: r[2])
    add("proto matrix, unrolled Cholesky", "NaN mask kept; Cholesky / triangular solves of the m×m S unrolled into elementwise ops, no LAPACK custom calls (what jdrkf.linalg.cholesky/cho_solve now do for size <= 6)",
        make_matrix(la="unrolled"), fargs, lambda r: r[2])
    add("proto matrix, unrolled Cholesky, scan unroll=4", "as above with lax.scan(..., unroll=4)",
        make_matrix(la="unrolled", unroll=4), fargs, lambda r: r[2])

    # -- fully scalarized step: every matrix entry is its own (B,) array
    def make_scalar(outputs="all"):
        def mm(a, b):
            return [[sum(a[i][k] * b[k][j] for k in range(len(b))) for j in range(len(b[0]))] for i in range(len(a))]

        def mv(a, x):
            return [sum(a[i][k] * x[k] for k in range(len(x))) for i in range(len(a))]

        def tr(a):
            return [list(r) for r in zip(*a)]

        def madd(a, b):
            return [[x + y for x, y in zip(r, s)] for r, s in zip(a, b)]

        def msym(a):
            return [[0.5 * (a[i][j] + a[j][i]) for j in range(len(a))] for i in range(len(a))]

        def entries(a):
            return [[a[i, j] for j in range(a.shape[1])] for i in range(a.shape[0])]

        def chol(S):
            k = len(S)
            L = [[0.0] * k for _ in range(k)]
            for j in range(k):
                L[j][j] = jnp.sqrt(S[j][j] - sum(L[j][q] ** 2 for q in range(j)))
                for i in range(j + 1, k):
                    L[i][j] = (S[i][j] - sum(L[i][q] * L[j][q] for q in range(j))) / L[j][j]
            return L

        def cho_solve(L, b):  # b: k rows of p entries
            k, p = len(L), len(b[0])
            z = [None] * k
            for i in range(k):
                z[i] = [(b[i][col] - sum(L[i][q] * z[q][col] for q in range(i))) / L[i][i] for col in range(p)]
            x = [None] * k
            for i in reversed(range(k)):
                x[i] = [(z[i][col] - sum(L[q][i] * x[q][col] for q in range(i + 1, k))) / L[i][i] for col in range(p)]
            return x

        def run(mdl, mean0, cov0, ys1):
            Fm, Hm, Qm, Rm = entries(mdl.F), entries(mdl.H), entries(mdl.Q), entries(mdl.R)
            nn, mm_ = len(Fm), len(Hm)

            def body(state, y):
                mean = [state[0][i] for i in range(nn)]
                P = entries(state[1])
                mp = mv(Fm, mean)
                Pp = msym(madd(mm(mm(Fm, P), tr(Fm)), Qm))
                yl = [y[i] for i in range(mm_)]
                obs = [~jnp.isnan(v) for v in yl]
                o = [ob.astype(y.dtype) for ob in obs]
                h = [[Hm[i][j] * o[i] for j in range(nn)] for i in range(mm_)]
                r = [[Rm[i][j] * o[i] * o[j] + ((1.0 - o[i]) if i == j else 0.0) for j in range(mm_)] for i in range(mm_)]
                hm = mv(h, mp)
                innov = [jnp.where(obs[i], yl[i], 0.0) - hm[i] for i in range(mm_)]
                hP = mm(h, Pp)
                S = msym(madd(mm(hP, tr(h)), r))
                L = chol(S)
                failed = ~jnp.all(jnp.isfinite(jnp.stack([L[i][i] for i in range(mm_)])))
                K = tr(cho_solve(L, hP))
                z = cho_solve(L, [[v] for v in innov])
                Kin = mv(K, innov)
                mf = [mp[i] + Kin[i] for i in range(nn)]
                KH = mm(K, h)
                A = [[(1.0 if i == j else 0.0) - KH[i][j] for j in range(nn)] for i in range(nn)]
                Pf = msym(madd(mm(mm(A, Pp), tr(A)), mm(mm(K, r), tr(K))))
                logdet = 2.0 * sum(jnp.log(L[i][i]) for i in range(mm_))
                ll = -0.5 * (sum(innov[i] * z[i][0] for i in range(mm_)) + logdet + sum(o) * math.log(2 * math.pi))
                vec = jnp.stack
                mat = lambda a: jnp.stack([jnp.stack(row) for row in a])
                carry = (vec(mf), mat(Pf))
                if outputs == "all":
                    return carry, (vec(mp), mat(Pp), carry[0], carry[1], ll, failed)
                return carry, (carry[0], carry[1], ll)

            return lax.scan(body, (mean0, cov0), ys1)[1]

        return jax.jit(jax.vmap(run, in_axes=(None, 0, 0, 0)))

    add("proto scalarized", "whole step written entry by entry (each entry a (B,) array under vmap); NaN mask, Joseph form, all outputs",
        make_scalar(), fargs, lambda r: r[2])
    add("proto scalarized, filtered outputs only", "as above, emitting only filtered mean/cov/loglik increment (dynamax's output volume)",
        make_scalar("filtered"), fargs, lambda r: r[0])

    # -- output floors: a trivial scan that only writes k floats per run and step
    def make_floor(k):
        def run(ys1):
            def body(s, y):
                s = s * 0.99 + y[0]
                return s, tuple(s * (i + 1) for i in range(k))
            return lax.scan(body, jnp.zeros((), ys1.dtype), ys1)[1]
        return jax.jit(jax.vmap(run))

    add("floor: write 13 floats/step", "trivial scan emitting as many floats per run-step as jdrkf's FilterResult (n=2: 2+4+2+4+1)",
        make_floor(13), (ys,), lambda r: None)
    add("floor: write 6 floats/step", "trivial scan emitting as many floats per run-step as dynamax (filtered mean + cov)",
        make_floor(6), (ys,), lambda r: None)
    return out


# --------------------------------------------------------------------------- parent


def fmt(x, spec):
    return "n/a" if x is None else format(x, spec)


def build_markdown(result) -> str:
    rows = result["rows"]
    dyn = {(r["dtype"], r["B"]): r["steps_per_s"] for r in rows if r["impl"] == "dynamax"}
    npy = {(r["dtype"], r["B"]): r["steps_per_s"] for r in rows if r["impl"] == "numpy"}
    meta = result["meta"]
    lines = [
        "# Kalman-filter throughput (CPU): jdrkf vs dynamax vs NumPy",
        "",
        (f"- System: seed 000 (n=2, m=1), T={result['config']['T']}, data seed {result['config']['seed']}, "
         f"{result['config']['repeats']} timed calls per cell (median), compile = first call − median."),
        (f"- CPU: {meta['cpu_model']}, {meta['cpu_count']} cores; JAX device: {', '.join(meta['jax_devices'])}; "
         f"jax {meta['versions']['jax']}, jaxlib {meta['versions']['jaxlib']}, dynamax {meta['versions']['dynamax']}, "
         f"numpy {meta['versions']['numpy']}, jdrkf {meta['versions']['jdrkf']} "
         f"(source sha256 {', '.join(sorted({h for v in meta['jdrkf_source_sha256'].values() for h in v.values()}))}"
         f"{'' if meta['jdrkf_source_consistent'] else ' — WARNING: the library changed during the run'})."),
        ("- Every implementation computes one covariance recursion per run (none shares it across runs), "
         "except the two `(shared cov)` rows: plain `vmap` over the data computes the data-independent "
         "covariance recursion once for all runs (jdrkf does this with `KalmanFilter(nan_as_missing=False)`)."),
        "",
        "| impl | dtype | B | compile s | run s (median) | run s (best) | steps/s | ratio vs dynamax | ratio vs numpy |",
        "|---|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        key = (r["dtype"], r["B"])
        lines.append(
            f"| {r['impl']} | {r['dtype']} | {r['B']} | {fmt(r['compile_s'], '.2f')} | {r['run_s']:.3f} | {r['run_min_s']:.3f} | "
            f"{r['steps_per_s']:.3g} | {r['steps_per_s'] / dyn[key]:.2f} | {r['steps_per_s'] / npy[key]:.2f} |"
        )
    lines += ["", ("steps/s = B·T / median run time; ratios use steps/s. `compile s` = first call − median "
                   "(it also absorbs first-call page faults and timing noise, so it can be slightly negative). "
                   "`dynamax (shared cov)` is a reference row that shares the covariance recursion across runs.")]
    lines += ["", "## Goal: jdrkf ≥ 2× dynamax steps/s at the largest B", ""]
    for g in result["goal"]:
        lines.append(
            f"- {g['dtype']}, B={g['B']}: jdrkf/dynamax = **{g['ratio_jdrkf_vs_dynamax']:.2f}** "
            f"({'met' if g['met'] else 'not met'}); jdrkf/numpy = {g['ratio_jdrkf_vs_numpy']:.2f}; "
            f"jdrkf/dynamax(shared cov) = {g['ratio_jdrkf_vs_dynamax_shared']:.2f}; "
            f"best-of-{result['config']['repeats']} jdrkf/dynamax = {g['ratio_jdrkf_vs_dynamax_best']:.2f}; "
            f"shared-covariance modes, jdrkf (nan_as_missing=False) / dynamax (shared cov) = "
            f"**{g['ratio_jdrkf_shared_vs_dynamax_shared']:.2f}**"
        )
    lines += ["", "## Agreement checks (max abs differences vs jdrkf)", "",
              "| dtype | B | vs | filtered means | filtered covs | rel. loglik | ok |", "|---|---:|---|---:|---:|---:|---|"]
    for ck in result["checks"]:
        lines.append(
            f"| {ck['dtype']} | {ck['B']} | {ck['vs'].replace('jdrkf vs ', '')} | {ck['max_abs_diff_filtered_means']:.2e} | "
            f"{ck['max_abs_diff_filtered_covs']:.2e} | {ck['max_rel_diff_marginal_loglik']:.2e} | {'yes' if ck['ok'] else 'NO'} |"
        )
    if result["variants"]:
        lib = {(r["dtype"], r["B"]): r["run_s"] for r in rows if r["impl"] == "jdrkf"}
        lines += ["", "## Prototype variants of the jdrkf step (benchmark-only code, per-run, largest B)", "",
                  "| variant | dtype | B | compile s | run s | steps/s | speed-up vs LAPACK proto | speed-up vs lib | ratio vs dynamax | max abs Δmean vs lib |",
                  "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
        base = {(v["dtype"], v["B"]): v["run_s"] for v in result["variants"] if v["impl"] == "proto matrix, LAPACK Cholesky"}
        for v in result["variants"]:
            key = (v["dtype"], v["B"])
            lines.append(
                f"| {v['impl']} | {v['dtype']} | {v['B']} | {fmt(v['compile_s'], '.2f')} | {v['run_s']:.3f} | {v['steps_per_s']:.3g} | "
                f"{fmt(base[key] / v['run_s'] if key in base else None, '.2f')} | {lib[key] / v['run_s']:.2f} | {v['steps_per_s'] / dyn[key]:.2f} | {fmt(v['max_abs_diff_filtered_means_vs_lib'], '.1e')} |"
            )
        lines += ["", "Variant descriptions:", ""]
        seen = set()
        for v in result["variants"]:
            if v["impl"] not in seen:
                seen.add(v["impl"])
                lines.append(f"- **{v['impl']}**: {v['note']}")
    lines.append("")
    return "\n".join(lines)


def run_parent(args) -> int:
    out_dir = args.out
    os.makedirs(out_dir, exist_ok=True)
    child_results = []
    t_start = time.perf_counter()
    for dtype in args.dtypes:
        with tempfile.TemporaryDirectory() as tmp:
            path = os.path.join(tmp, "child.json")
            cmd = [sys.executable, os.path.abspath(__file__), "--child", "--dtype", dtype, "--child-out", path,
                   "--T", str(args.T), "--repeats", str(args.repeats), "--seed", str(args.seed),
                   "--batch-sizes", *map(str, args.batch_sizes)]
            if args.variants:
                cmd.append("--variants")
            load_before = loadavg()
            log(f"running: {' '.join(cmd)}")
            proc = subprocess.run(cmd, check=False)
            if proc.returncode != 0:
                log(f"child for {dtype} failed with exit code {proc.returncode}")
                return proc.returncode
            with open(path) as f:
                res = json.load(f)
            res["loadavg_before"], res["loadavg_after"] = load_before, loadavg()
            child_results.append(res)

    rows = [r for c in child_results for r in c["rows"]]
    checks = [k for c in child_results for k in c["checks"]]
    variants = [v for c in child_results for v in c["variants"]]
    for v in variants:
        same = {r["impl"]: r for r in rows if r["dtype"] == v["dtype"] and r["B"] == v["B"]}
        v["speedup_vs_lib"] = same["jdrkf"]["run_s"] / v["run_s"]
        v["ratio_vs_dynamax"] = v["steps_per_s"] / same["dynamax"]["steps_per_s"]
    bmax = max(args.batch_sizes)
    goal = []
    for c in child_results:
        get = {r["impl"]: r for r in c["rows"] if r["B"] == bmax}
        ratio = get["jdrkf"]["steps_per_s"] / get["dynamax"]["steps_per_s"]
        goal.append({
            "dtype": c["dtype"], "B": bmax,
            "ratio_jdrkf_vs_dynamax": ratio,
            "ratio_jdrkf_vs_numpy": get["jdrkf"]["steps_per_s"] / get["numpy"]["steps_per_s"],
            "ratio_jdrkf_vs_dynamax_shared": get["jdrkf"]["steps_per_s"] / get["dynamax (shared cov)"]["steps_per_s"],
            "ratio_jdrkf_vs_dynamax_best": get["dynamax"]["run_min_s"] / get["jdrkf"]["run_min_s"],
            "ratio_jdrkf_shared_vs_dynamax_shared": get["jdrkf (shared cov)"]["steps_per_s"] / get["dynamax (shared cov)"]["steps_per_s"],
            "target": 2.0, "met": ratio >= 2.0,
        })
    hashes = {h for c in child_results for h in c["jdrkf_source_sha256"].values()}
    consistent = len(hashes) == 1
    if not consistent:
        log("WARNING: jdrkf's source changed during the run; the dtypes may have timed different library versions")
    first = child_results[0]
    result = {
        "benchmark": "kf_throughput",
        "created": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "command": " ".join([os.path.basename(sys.executable)] + sys.argv),
        "wall_s": time.perf_counter() - t_start,
        "config": {"batch_sizes": args.batch_sizes, "T": args.T, "repeats": args.repeats, "seed": args.seed,
                   "dtypes": args.dtypes, "quick": args.quick, "variants": args.variants},
        "system": SYSTEM,
        "meta": {
            "cpu_model": cpu_model(),
            "cpu_count": os.cpu_count(),
            "cpu_affinity": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None,
            "platform": platform.platform(),
            "versions": first["versions"],
            "jax_devices": first["jax_devices"],
            "jax_backend": first["jax_backend"],
            "loadavg": {c["dtype"]: {"before": c["loadavg_before"], "after": c["loadavg_after"]} for c in child_results},
            "x64_per_child": {c["dtype"]: c["jax_enable_x64"] for c in child_results},
            "data_checksum": {c["dtype"]: c["data_checksum"] for c in child_results},
            "jdrkf_source_sha256": {c["dtype"]: c["jdrkf_source_sha256"] for c in child_results},
            "jdrkf_source_consistent": consistent,
        },
        "rows": rows,
        "ratios": [
            {"dtype": r["dtype"], "B": r["B"], "impl": r["impl"],
             "vs_dynamax": r["steps_per_s"] / next(x["steps_per_s"] for x in rows
                                                    if x["impl"] == "dynamax" and x["dtype"] == r["dtype"] and x["B"] == r["B"]),
             "vs_numpy": r["steps_per_s"] / next(x["steps_per_s"] for x in rows
                                                  if x["impl"] == "numpy" and x["dtype"] == r["dtype"] and x["B"] == r["B"])}
            for r in rows
        ],
        "goal": goal,
        "checks": checks,
        "checks_ok": all(c["checks_ok"] for c in child_results),
        "variants": variants,
    }
    md = build_markdown(result)
    stem = os.path.join(out_dir, f"kf_throughput_{args.tag}")
    with open(stem + ".json", "w") as f:
        json.dump(result, f, indent=2)
    with open(stem + ".md", "w") as f:
        f.write(md)
    print(md)
    log(f"wrote {stem}.json and {stem}.md ({result['wall_s']:.0f} s)")
    if not result["checks_ok"]:
        log("ERROR: implementations disagree beyond tolerance (see checks)")
        return 1
    return 0


def main(argv=None) -> int:
    here = os.path.dirname(os.path.abspath(__file__))
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--quick", action="store_true", help="smoke run: B=100, T=100")
    p.add_argument("--batch-sizes", type=int, nargs="+", default=None, help="B values (default 1000 10000)")
    p.add_argument("--T", type=int, default=None, help="time steps (default 1000)")
    p.add_argument("--repeats", type=int, default=5, help="timed calls per cell (median reported; >= 5)")
    p.add_argument("--seed", type=int, default=DATA_SEED, help="NumPy seed of the simulated data")
    p.add_argument("--dtypes", nargs="+", default=["float32", "float64"], choices=["float32", "float64"])
    p.add_argument("--variants", action="store_true", help="also time prototype variants of the jdrkf step at the largest B")
    p.add_argument("--out", default=os.path.join(here, "results"), help="output directory")
    p.add_argument("--tag", default=None, help="output file stem suffix (default 'cpu', 'cpu_quick' with --quick)")
    # internal: one dtype per child process
    p.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--dtype", choices=["float32", "float64"], help=argparse.SUPPRESS)
    p.add_argument("--child-out", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.batch_sizes is None:
        args.batch_sizes = [100] if args.quick else [1000, 10000]
    if args.T is None:
        args.T = 100 if args.quick else 1000
    if args.tag is None:
        args.tag = "cpu_quick" if args.quick else "cpu"
    if args.child:
        res = run_child(args)
        with open(args.child_out, "w") as f:
            json.dump(res, f)
        return 0
    return run_parent(args)


if __name__ == "__main__":
    sys.exit(main())
