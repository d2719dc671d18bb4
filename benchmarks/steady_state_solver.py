#!/usr/bin/env python
"""Steady-state DR solver (Jang, Hakobyan & Yang 2025, problem (14)): jdrkf vs cvxpy + Clarabel.

For (n, m) ∈ {(2, 1), (4, 2), (10, 5)} and `--instances` random systems per size
(seeded; `A` Gaussian scaled to spectral radius uniform in [0.5, 1.2], `C` Gaussian,
Σ̂w = BBᵀ/n + 0.1 I, Σ̂v = DDᵀ/m + 0.2 I with Gaussian B, D, θx, θv uniform in
[0.1, 1]) the script solves the steady-state distributionally robust problem (14) of
Jang, Hakobyan & Yang with

1. jdrkf: `eqx.filter_jit(lambda f, m: f.solve(m).value)` with
   `f = jdrkf.SteadyStateDRKF(θx, θv)` (Newton on the KKT system of (14), continued
   in the radii). Compile time = first call − median call; ms/solve = median over up
   to `--repeats` rounds over all instances (`jax.block_until_ready`; a round budget
   `--cell-budget-s` stops repeating early). Newton iterations, `converged` and the
   residual come from an untimed jitted `f.solve(m)`. Traces and XLA compilations
   during the timed rounds are counted (`jax.monitoring`): they must be 0.
2. jdrkf gradient: `eqx.filter_jit(jax.value_and_grad(θx ↦ value))` (implicit
   function theorem on the same KKT system); timed the same way and checked against
   central finite differences of jdrkf's value (h = 1e-5) and of the SDP value
   (h = `--fd-h-sdp`, first instance; Clarabel's ~1e-9 value accuracy limits this
   check to ~1e-5).
3. cvxpy + Clarabel, plain: `tests/stationary_oracle.stationary_sdp` as the tests call
   it (problem built and canonicalized at every call; Clarabel tolerance ladder 1e-10,
   1e-9, 1e-8; `optimal_inaccurate` after the last rung is accepted and flagged). Wall
   time of the whole call and Clarabel's own `solver_stats.solve_time` (summed over
   rungs).
4. cvxpy DPP: the same SDP with `A`, `C`, Σ̂w, Σ̂v, λmin(Σ̂v) and θ² as `cp.Parameter`s.
   `A X Aᵀ` and `C X⁻ Cᵀ` are not DPP (parameter · variable · parameter), so the
   auxiliary variables `P = A X` and `G = C X⁻` are tied by linear equalities and
   `X̂⁻ = P Aᵀ + Σ̂w`, `C X⁻ Cᵀ = G Cᵀ`. Canonicalized once (reported separately),
   then re-solved with new parameter values, (a) with the tolerance ladder and (b)
   once with Clarabel's default tolerances (1e-8), the cheapest cvxpy path.

5. jdrkf, many radii (the goal row): `--radius-batch` (default 1000) radius pairs
   (θx, θv) uniform in [0.1, 1] (NumPy RNG seeded by `--seed` and the size) on the
   first system of the size, solved in ONE call of
   `eqx.filter_jit(jax.vmap(lambda tx, tv, m: SteadyStateDRKF(tx, tv).solve(m).value,
   in_axes=(0, 0, None)))`; compile = first call − median call, time per solve =
   median call / B. Untimed: the same vmapped `solve` reports `converged` and the
   Newton iterations of every pair, and the values of the first `--radius-checks`
   pairs (default all) are compared with single solves (`jdrkf` row's function),
   tolerance 1e-8 relative.

Agreement: |jdrkf − SDP| / SDP over the solves Clarabel reports `optimal` (inaccurate
ones are counted and listed separately). Speed ratio: cvxpy time / jdrkf median time,
for each cvxpy variant.

Goal (per size): the vmapped many-radii solve, per solve (call time / 1000), ≥ 100×
faster than the cvxpy-DPP re-solve per solve (median over the size's systems; the
faster DPP variant whose values agree with jdrkf's single solves to 1e-6), with every
pair converged and the values equal to the single solves (1e-8). Informative (the
former goal, out of reach for one jitted CPU call, see `call_floor.py`): the single
solve ≥ 100× faster than the fastest cvxpy variant that agrees to 1e-6.

`--platform gpu` runs the jdrkf children on a GPU (cvxpy stays on the CPU; the
OPENBLAS_NUM_THREADS=1 row is dropped there); the device is recorded.

Processes: per size, jdrkf and cvxpy run in separate child processes (in one process,
jdrkf's n = 10 solve was 25× slower after cvxpy had run). jdrkf runs twice: with the
environment as it is (the goal's number) and, timings only, with
OPENBLAS_NUM_THREADS=1. jaxlib's CPU LAPACK kernels call SciPy's OpenBLAS, whose worker
threads compete with XLA's on few cores: on a loaded 2-core machine the n = 10 solve
took 2.2 s with the default thread count and 31 ms with one thread.
`--openblas-threads N` sets OPENBLAS_NUM_THREADS=N in every child instead (and drops
the extra row); `--no-openblas-1-row` drops it. A faulthandler watchdog aborts a child
whose phase runs longer than `--watchdog-s` (jaxlib 0.10's batched-LAPACK deadlock, see
`wasserstein_solver.py`); the parent re-runs it (`--retries`).

Usage:

    python benchmarks/steady_state_solver.py                          # full run
    python benchmarks/steady_state_solver.py --quick --out smoke/ssb   # smoke run (~1-2 min)
    python benchmarks/steady_state_solver.py --platform gpu           # jdrkf on a GPU (writes *_gpu.*)
    python benchmarks/steady_state_solver.py --sizes 2x1 4x2 --instances 20 --openblas-threads 1
"""

from __future__ import annotations

import argparse
import datetime
import faulthandler
import json
import os
import platform
import statistics
import subprocess
import sys
import tempfile
import time
import warnings

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, os.path.join(ROOT, "tests"))

DEFAULT_SIZES = ["2x1", "4x2", "10x5"]
GOAL_REL = 1e-6
GOAL_RATIO = 100.0
GOAL_RADII = 1000  # radius pairs per vmapped call in the goal
GOAL_RADII_REL = 1e-8  # vmapped values vs single solves
TOLERANCES = (1e-10, 1e-9, 1e-8)  # as tests/stationary_oracle.py


# --------------------------------------------------------------------------- helpers


from _provenance import (  # noqa: E402
    check_platform, cpu_model, device_summary, git_info, loadavg, package_source_hash, parse_size, set_platform, versions,
)


def log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def rel(a, b) -> float:
    return abs(float(a) - float(b)) / max(abs(float(b)), 1e-300)


def med(xs):
    xs = [x for x in xs if x is not None]
    return statistics.median(xs) if xs else None


def maxn(xs):
    xs = [x for x in xs if x is not None]
    return max(xs) if xs else None


class Watchdog:
    """Abort the process (exit status 1, tracebacks on stderr) when a phase runs longer
    than its limit; the parent then re-runs the cell."""

    def __init__(self, seconds: float):
        self.seconds = seconds

    def arm(self, phase: str, seconds: float | None = None):
        log(f"== {phase} (load {loadavg()})")
        if self.seconds > 0:
            faulthandler.dump_traceback_later(seconds or self.seconds, exit=True)

    def disarm(self):
        faulthandler.cancel_dump_traceback_later()


# --------------------------------------------------------------------------- instances


def make_instances(n: int, m: int, count: int, seed: int):
    """`count` systems (A, C, Σ̂w, Σ̂v, θx, θv), float64 NumPy; instance i does not depend
    on `count`."""
    rng = np.random.default_rng([seed, n, m])
    out = []
    for _ in range(count):
        a = rng.normal(size=(n, n))
        a = a / np.max(np.abs(np.linalg.eigvals(a))) * rng.uniform(0.5, 1.2)
        c = rng.normal(size=(m, n))
        b = rng.normal(size=(n, n))
        d = rng.normal(size=(m, m))
        w = b @ b.T / n + 0.1 * np.eye(n)
        v = d @ d.T / m + 0.2 * np.eye(m)
        tx, tv = rng.uniform(0.1, 1.0, 2)
        out.append((a, c, 0.5 * (w + w.T), 0.5 * (v + v.T), float(tx), float(tv)))
    return out


# --------------------------------------------------------------------------- jdrkf child


def bench_jdrkf(args, n, m, wd, radii=True):
    import equinox as eqx
    import jax
    import jax.numpy as jnp
    from jax import monitoring

    import jdrkf

    compiles, traces = [], []

    def listener(name, secs, **kw):
        if name.endswith("backend_compile_duration"):
            compiles.append(secs)
        elif name.endswith("jaxpr_trace_duration"):
            traces.append(secs)

    monitoring.register_event_duration_secs_listener(listener)

    count = args.instances_large if n >= args.large_n else args.instances
    inst = make_instances(n, m, count, args.seed)

    def f64(x):
        return jnp.asarray(x, dtype=jnp.float64)

    models = [jdrkf.LinearModel(F=f64(a), H=f64(c), Q=f64(w), R=f64(v)) for a, c, w, v, _, _ in inst]
    filters = [jdrkf.SteadyStateDRKF(f64(tx), f64(tv)) for *_, tx, tv in inst]
    row = {"n": n, "m": m, "instances": count}

    value_fn = eqx.filter_jit(lambda f, mdl: f.solve(mdl).value)
    solve_fn = eqx.filter_jit(lambda f, mdl: f.solve(mdl))

    def value_theta(tx, f, mdl):
        return eqx.tree_at(lambda g: g.radius_x, f, tx).solve(mdl).value

    grad_fn = eqx.filter_jit(jax.value_and_grad(value_theta))

    def timed(fn, make_args, phase):
        """First call (compile) on instance 0, then rounds over all instances."""
        wd.arm(f"{n}x{m}: {phase} first call", args.watchdog_first_call_s)
        c0, r0 = len(compiles), len(traces)
        t0 = time.perf_counter()
        jax.block_until_ready(fn(*make_args(0)))
        first = time.perf_counter() - t0
        n_compiles, n_traces = len(compiles), len(traces)
        wd.arm(f"{n}x{m}: {phase} timed rounds")
        per = [[] for _ in range(count)]
        start = time.perf_counter()
        for _ in range(args.repeats):
            for i in range(count):
                a = make_args(i)
                t0 = time.perf_counter()
                jax.block_until_ready(fn(*a))
                per[i].append(time.perf_counter() - t0)
            if time.perf_counter() - start > args.cell_budget_s:
                break
        wd.disarm()
        flat = [t for ts in per for t in ts]
        return {"first_s": first, "compile_s": first - med(flat), "median_ms": med(flat) * 1e3, "min_ms": min(flat) * 1e3,
                "per_instance_median_ms": [med(ts) * 1e3 for ts in per], "rounds": len(per[0]),
                "compiles_first_call": n_compiles - c0, "traces_first_call": n_traces - r0,
                "compiles_during_timing": len(compiles) - n_compiles, "traces_during_timing": len(traces) - n_traces}

    t = timed(value_fn, lambda i: (filters[i], models[i]), "value")
    row["jdrkf"] = t
    log(f"   {n}x{m}: jdrkf {t['median_ms']:.3g} ms/solve (compile {t['compile_s']:.1f} s, {t['rounds']} rounds)")

    wd.arm(f"{n}x{m}: diagnostics")
    per = []
    for i in range(count):
        s = solve_fn(filters[i], models[i])
        per.append({"value": float(s.value), "iterations": int(s.iterations), "converged": bool(s.converged),
                    "residual": float(s.residual), "theta_x": inst[i][4], "theta_v": inst[i][5],
                    "spectral_radius": float(np.max(np.abs(np.linalg.eigvals(inst[i][0]))))})
    wd.disarm()
    row["per_instance"] = per

    if radii and args.radius_batch:  # not in the OPENBLAS_NUM_THREADS=1 child
        row["radii"] = bench_radii(args, n, m, wd, models[0], value_fn, jax, jnp, eqx, jdrkf)

    if not args.no_grad:
        g = timed(grad_fn, lambda i: (filters[i].radius_x, filters[i], models[i]), "value_and_grad wrt theta_x")
        row["grad"] = g
        wd.arm(f"{n}x{m}: gradient check (finite differences of jdrkf's value)")
        h = 1e-5
        checks = []
        for i in range(min(count, args.grad_checks)):
            _, gi = grad_fn(filters[i].radius_x, filters[i], models[i])
            tx = inst[i][4]
            up = value_fn(eqx.tree_at(lambda f: f.radius_x, filters[i], f64(tx + h)), models[i])
            dn = value_fn(eqx.tree_at(lambda f: f.radius_x, filters[i], f64(tx - h)), models[i])
            fd = (float(up) - float(dn)) / (2 * h)
            per[i]["grad_theta_x"] = float(gi)
            per[i]["grad_theta_x_fd_jdrkf"] = fd
            checks.append(rel(gi, fd))
        wd.disarm()
        g["max_rel_diff_vs_fd_jdrkf"] = maxn(checks)
        log(f"   {n}x{m}: value_and_grad {g['median_ms']:.3g} ms (compile {g['compile_s']:.1f} s); "
            f"vs FD {g['max_rel_diff_vs_fd_jdrkf']}")
    return row


def bench_radii(args, n, m, wd, model, value_fn, jax, jnp, eqx, jdrkf) -> dict:
    """`--radius-batch` radius pairs on one system, solved in one vmapped call (the goal row)."""
    B = args.radius_batch
    radii = np.random.default_rng([args.seed, n, m, 1]).uniform(0.1, 1.0, (B, 2))
    txs, tvs = jnp.asarray(radii[:, 0], jnp.float64), jnp.asarray(radii[:, 1], jnp.float64)
    vm_value = eqx.filter_jit(jax.vmap(lambda tx, tv, mdl: jdrkf.SteadyStateDRKF(tx, tv).solve(mdl).value,
                                       in_axes=(0, 0, None)))
    wd.arm(f"{n}x{m}: {B} radius pairs, vmapped, first call", args.watchdog_first_call_s)
    t0 = time.perf_counter()
    values = np.asarray(jax.block_until_ready(vm_value(txs, tvs, model)))
    first = time.perf_counter() - t0
    wd.arm(f"{n}x{m}: {B} radius pairs, vmapped, timed calls")
    times, start = [], time.perf_counter()
    for _ in range(args.repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(vm_value(txs, tvs, model))
        times.append(time.perf_counter() - t0)
        if time.perf_counter() - start > args.cell_budget_s:
            break
    wd.arm(f"{n}x{m}: {B} radius pairs, diagnostics and single-solve check")
    vm_solve = eqx.filter_jit(jax.vmap(lambda tx, tv, mdl: (lambda s: (s.converged, s.iterations))(
        jdrkf.SteadyStateDRKF(tx, tv).solve(mdl)), in_axes=(0, 0, None)))
    conv, its = (np.asarray(x) for x in vm_solve(txs, tvs, model))
    k = B if args.radius_checks is None else min(B, args.radius_checks)
    single = [float(value_fn(jdrkf.SteadyStateDRKF(txs[i], tvs[i]), model)) for i in range(k)]
    wd.disarm()
    rels = [rel(values[i], single[i]) for i in range(k)]
    out = {"B": B, "system": 0, "radii_range": [0.1, 1.0], "first_s": first, "compile_s": first - med(times),
           "call_s": med(times), "call_min_s": min(times), "calls": len(times),
           "per_solve_ms": med(times) / B * 1e3, "per_solve_min_ms": min(times) / B * 1e3,
           "converged": int(conv.sum()), "iterations_median": float(np.median(its)), "iterations_max": int(its.max()),
           "checked": k, "max_rel_diff_vs_single": maxn(rels) if rels else None,
           "values_finite": bool(np.all(np.isfinite(values)))}
    out["check_ok"] = out["max_rel_diff_vs_single"] is not None and out["max_rel_diff_vs_single"] <= GOAL_RADII_REL
    log(f"   {n}x{m}: {B} radius pairs vmapped: {out['call_s']:.3g} s/call = {out['per_solve_ms'] * 1e3:.3g} µs/solve "
        f"(compile {out['compile_s']:.1f} s); converged {out['converged']}/{B}, chord steps med/max "
        f"{out['iterations_median']:.0f}/{out['iterations_max']}; max rel Δ vs {k} single solves {out['max_rel_diff_vs_single']}")
    return out


# --------------------------------------------------------------------------- cvxpy child


class Recorder:
    """The tolerance ladder of `stationary_oracle._solve`, recording status, Clarabel's
    time and iterations; accepts `optimal_inaccurate` after the last rung (flagged)."""

    def __init__(self, cp, tolerances=TOLERANCES):
        self.cp, self.tolerances, self.last = cp, tolerances, None

    def __call__(self, prob):
        cp = self.cp
        tries = []
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)
            for tol in self.tolerances:
                opts = {} if tol is None else {"tol_gap_abs": tol, "tol_gap_rel": tol, "tol_feas": tol}
                try:
                    prob.solve(solver=cp.CLARABEL, max_iter=500, **opts)
                except cp.SolverError as e:
                    tries.append({"tol": tol, "status": f"SolverError: {e}", "solver_s": None, "iters": None})
                    continue
                st = prob.solver_stats
                tries.append({"tol": tol, "status": prob.status, "solver_s": st.solve_time, "iters": st.num_iters})
                if prob.status == cp.OPTIMAL:
                    break
        ok = prob.status == cp.OPTIMAL
        usable = prob.status in (cp.OPTIMAL, cp.OPTIMAL_INACCURATE)
        self.last = {
            "value": float(prob.value) if usable else None, "status": prob.status, "optimal": ok,
            "tol": tries[-1]["tol"], "solver_s": sum(t["solver_s"] or 0.0 for t in tries),
            "iters": sum(t["iters"] or 0 for t in tries), "tries": len(tries),
        }
        return self.last["tol"] if ok else None


def build_stationary_dpp(cp, n: int, m: int):
    """Problem (14) in DPP form (see the module docstring); returns (problem, setter)."""
    p = {"A": cp.Parameter((n, n)), "C": cp.Parameter((m, n)), "W": cp.Parameter((n, n), symmetric=True),
         "V": cp.Parameter((m, m), symmetric=True), "vmin": cp.Parameter(nonneg=True),
         "t2x": cp.Parameter(nonneg=True), "t2v": cp.Parameter(nonneg=True)}
    X = cp.Variable((n, n), symmetric=True)
    Xm = cp.Variable((n, n), symmetric=True)
    Sv = cp.Variable((m, m), symmetric=True)
    P = cp.Variable((n, n))  # A X
    G = cp.Variable((m, n))  # C X⁻
    Yx = cp.Variable((n, n))
    Yv = cp.Variable((m, m))
    xhat = P @ p["A"].T + p["W"]
    schur = cp.bmat([[Xm - X, G.T], [G, G @ p["C"].T + Sv]])
    bx = cp.bmat([[xhat, Yx], [Yx.T, Xm]])
    bv = cp.bmat([[p["V"], Yv], [Yv.T, Sv]])
    cons = [
        P == p["A"] @ X, G == p["C"] @ Xm,
        0.5 * (schur + schur.T) >> 0, X >> 0, Xm >> 0, Sv >> p["vmin"] * np.eye(m),
        0.5 * (bx + bx.T) >> 0, cp.trace(xhat + Xm - 2 * Yx) <= p["t2x"],
        0.5 * (bv + bv.T) >> 0, cp.trace(p["V"] + Sv - 2 * Yv) <= p["t2v"],
    ]
    prob = cp.Problem(cp.Maximize(cp.trace(X)), cons)
    if not prob.is_dcp(dpp=True):
        raise RuntimeError("the stationary problem is not DPP")

    def set_params(a, c, w, v, tx, tv):
        p["A"].value, p["C"].value, p["W"].value, p["V"].value = a, c, w, v
        p["vmin"].value = float(np.min(np.linalg.eigvalsh(v)))
        p["t2x"].value, p["t2v"].value = tx**2, tv**2

    return prob, set_params


def bench_cvxpy(args, n, m, wd):
    import cvxpy as cp
    import stationary_oracle as so

    count = args.instances_large if n >= args.large_n else args.instances
    inst = make_instances(n, m, count, args.seed)
    row = {"n": n, "m": m, "instances": count}
    per = [{} for _ in range(count)]

    # -- plain: the oracle as the tests call it
    wd.arm(f"{n}x{m}: cvxpy plain x{count}")
    rec = Recorder(cp)
    orig = so._solve
    so._solve = rec
    try:
        wall = []
        for i, x in enumerate(inst):
            t0 = time.perf_counter()
            so.stationary_sdp(*x)
            wall.append(time.perf_counter() - t0)
            per[i]["plain"] = dict(rec.last, wall_s=wall[-1])
        # finite-difference derivative of the SDP value in θx, first instance
        if not args.no_grad:
            h = args.fd_h_sdp
            a, c, w, v, tx, tv = inst[0]
            so.stationary_sdp(a, c, w, v, tx + h, tv)
            up = rec.last
            so.stationary_sdp(a, c, w, v, tx - h, tv)
            dn = rec.last
            if up["value"] is not None and dn["value"] is not None:
                per[0]["grad_theta_x_fd_sdp"] = (up["value"] - dn["value"]) / (2 * h)
                per[0]["grad_fd_sdp_optimal"] = up["optimal"] and dn["optimal"]
    finally:
        so._solve = orig
    wd.disarm()
    row["plain_ms"] = med(wall) * 1e3
    row["plain_clarabel_ms"] = med([p["plain"]["solver_s"] for p in per]) * 1e3

    # -- DPP
    if not args.no_dpp:
        wd.arm(f"{n}x{m}: cvxpy DPP x{count}")
        try:
            t0 = time.perf_counter()
            prob, setp = build_stationary_dpp(cp, n, m)
            row["dpp_build_s"] = time.perf_counter() - t0
            for key, tols in [("dpp", TOLERANCES), ("dpp_default", (None,))]:
                rec = Recorder(cp, tols)
                order = list(range(count)) + ([0] if count == 1 else [])
                wall, first = [], None
                for j, i in enumerate(order):
                    t0 = time.perf_counter()
                    setp(*inst[i])
                    rec(prob)
                    dt = time.perf_counter() - t0
                    if j == 0 and key == "dpp":
                        first = dt  # includes the one-time canonicalization
                    else:
                        wall.append(dt)
                    per[i][key] = dict(rec.last, wall_s=dt)
                row[f"{key}_ms"] = med(wall) * 1e3
                row[f"{key}_clarabel_ms"] = med([p[key]["solver_s"] for p in per]) * 1e3
                if key == "dpp":
                    row["dpp_first_s"] = first
                    row["dpp_canonicalize_s"] = first - med(wall) if wall else None
        except Exception as e:  # noqa: BLE001 - recorded, the rest of the row stands
            row["dpp_error"] = f"{type(e).__name__}: {e}"
            log(f"   {n}x{m}: DPP failed: {row['dpp_error']}")
        wd.disarm()
    row["per_instance"] = per
    log(f"   {n}x{m}: cvxpy plain {row['plain_ms']:.3g} ms (Clarabel {row['plain_clarabel_ms']:.3g} ms), "
        f"DPP {row.get('dpp_ms')} ms, DPP default tol {row.get('dpp_default_ms')} ms")
    return row


# --------------------------------------------------------------------------- merge


VARIANTS = [("plain", "cvxpy plain (oracle, rebuilt per solve)"), ("dpp", "cvxpy DPP, tolerance ladder"),
            ("dpp_default", "cvxpy DPP, Clarabel default tolerances")]


def merge(jrow: dict | None, crow: dict | None, n: int, m: int, j1row: dict | None = None) -> dict:
    """Combine the children of a size (jdrkf; jdrkf with OPENBLAS_NUM_THREADS=1, timings
    only; cvxpy): agreement, ratios, per-size goals."""
    row = {"n": n, "m": m, "jdrkf_failed": jrow is None, "cvxpy_failed": crow is None}
    if j1row:
        row["jdrkf_ob1"] = j1row.get("jdrkf")
        row["grad_ob1"] = j1row.get("grad")
        if jrow:
            row["max_rel_diff_ob1_vs_default"] = maxn(
                [rel(a["value"], b["value"]) for a, b in zip(j1row["per_instance"], jrow["per_instance"], strict=True)])
    if jrow:
        row.update({k: v for k, v in jrow.items() if k != "per_instance"})
    if crow:
        row.update({k: v for k, v in crow.items() if k not in ("per_instance", "instances")})
        row.setdefault("instances", crow["instances"])
    count = row.get("instances", 0)
    per = [{} for _ in range(count)]
    for src in (jrow, crow):
        for i, p in enumerate((src or {}).get("per_instance", [])):
            per[i].update(p)
    row["per_instance"] = per
    if jrow:
        its = [p["iterations"] for p in per]
        row["iterations_median"], row["iterations_max"] = float(np.median(its)), int(np.max(its))
        row["converged"] = sum(p["converged"] for p in per)
        row["max_residual"] = maxn([p["residual"] for p in per])
    jms = (row.get("jdrkf") or {}).get("median_ms")
    jms1 = (row.get("jdrkf_ob1") or {}).get("median_ms")
    for key, _ in VARIANTS:
        ok = [p for p in per if key in p and "value" in p]
        if not ok:
            continue
        acc = [rel(p["value"], p[key]["value"]) for p in ok if p[key]["optimal"]]
        row[f"max_rel_diff_vs_{key}"] = maxn(acc)
        row[f"inaccurate_{key}"] = [i for i, p in enumerate(per) if key in p and not p[key]["optimal"]]
        row[f"max_rel_diff_vs_{key}_inaccurate"] = maxn(
            [rel(p["value"], p[key]["value"]) for p in ok if not p[key]["optimal"] and p[key]["value"] is not None])
        row[f"fallbacks_{key}"] = sum(1 for p in per if key in p and p[key]["tries"] > 1)
        t = row.get(f"{key}_ms")
        row[f"ratio_{key}"] = t / jms if t and jms else None
        tc = row.get(f"{key}_clarabel_ms")
        row[f"ratio_{key}_clarabel_only"] = tc / jms if tc and jms else None
        row[f"ratio_{key}_ob1"] = t / jms1 if t and jms1 else None
    if jrow and crow and "grad" in row:
        p0 = per[0]
        if "grad_theta_x" in p0 and "grad_theta_x_fd_sdp" in p0:
            row["grad"]["rel_diff_vs_fd_sdp_instance0"] = rel(p0["grad_theta_x"], p0["grad_theta_x_fd_sdp"])
    row["goal"] = size_goal(row, "jdrkf")
    row["radii_goal"] = radii_goal(row)
    if row.get("jdrkf_ob1"):
        row["goal_ob1"] = size_goal(row, "jdrkf_ob1")
    return row


def size_goal(row, jkey: str) -> dict:
    """≥ 100× faster than the fastest cvxpy variant whose values agree to 1e-6 (jdrkf
    timings from `row[jkey]`)."""
    if row["jdrkf_failed"] or row["cvxpy_failed"] or not row.get(jkey):
        return {"met": None, "detail": "not evaluated (a part failed)"}
    if row.get("converged", 0) < row["instances"]:
        return {"met": False, "detail": f"jdrkf converged on {row['converged']}/{row['instances']} instances"}
    cands = []
    for key, label in VARIANTS:
        if row.get(f"{key}_ms") is None:
            continue
        d = row.get(f"max_rel_diff_vs_{key}")
        agree = d is not None and d <= GOAL_REL
        cands.append((row[f"{key}_ms"], key, label, agree, d))
    equal = [c for c in cands if c[3]]
    if not equal:
        return {"met": False, "detail": "no cvxpy variant agrees with jdrkf to 1e-6: "
                + ", ".join(f"{c[2]} {c[4]:.1e}" if c[4] is not None else f"{c[2]} n/a" for c in cands)}
    ms, key, label, _, d = min(equal)
    ratio = ms / row[jkey]["median_ms"]
    return {"met": ratio >= GOAL_RATIO, "ratio": ratio, "baseline": key,
            "detail": (f"{ratio:.3g}× vs {label} ({ms:.3g} ms vs jdrkf {row[jkey]['median_ms']:.3g} ms; "
                       f"max rel Δvalue {d:.1e})")}


def radii_goal(row) -> dict | None:
    """The goal: B = 1000 radius pairs in one vmapped call, per solve ≥ 100× faster than
    the cvxpy-DPP re-solve per solve (the faster DPP variant whose values agree to 1e-6)."""
    rb = row.get("radii")
    if not rb:
        return None
    if rb["B"] != GOAL_RADII:
        return {"met": None, "detail": f"not evaluated (B = {rb['B']}, the goal's is {GOAL_RADII})"}
    if row["cvxpy_failed"]:
        return {"met": None, "detail": "not evaluated (no cvxpy-DPP time)"}
    cands = [(row[f"{k}_ms"], k, label, row.get(f"max_rel_diff_vs_{k}")) for k, label in VARIANTS
             if k in ("dpp", "dpp_default") and row.get(f"{k}_ms") is not None]
    equal = [c for c in cands if c[3] is not None and c[3] <= GOAL_REL]
    if not equal:
        return {"met": False if cands else None, "detail": "no cvxpy-DPP variant agrees with jdrkf to 1e-6"
                if cands else "not evaluated (no cvxpy-DPP time)"}
    ms, key, label, d = min(equal)
    ratio = ms / rb["per_solve_ms"]
    bad = []
    if rb["converged"] < rb["B"]:
        bad.append(f"converged {rb['converged']}/{rb['B']}")
    if not rb["check_ok"]:
        bad.append(f"vmapped vs single values {fmt(rb['max_rel_diff_vs_single'], '.1e')} > {GOAL_RADII_REL:g}")
    return {"met": ratio >= GOAL_RATIO and not bad, "ratio": ratio, "baseline": key,
            "detail": (f"{ratio:.3g}× ({rb['per_solve_ms'] * 1e3:.3g} µs per solve = {rb['call_s']:.3g} s / {rb['B']} vs "
                       f"{label} {ms:.3g} ms per solve)" + ("; " + "; ".join(bad) if bad else ""))}


# --------------------------------------------------------------------------- markdown


def fmt(x, spec, na="n/a"):
    return na if x is None else format(x, spec)


def build_markdown(r) -> str:
    meta, cfg = r.get("meta", {}), r.get("config", {})

    def g(d, k, spec, na="n/a"):
        return fmt((d or {}).get(k), spec, na)

    L = [f"# Steady-state DR solver (Jang, Hakobyan & Yang 2025, problem (14)) on {cfg.get('platform', 'cpu').upper()}: "
         "jdrkf vs cvxpy + Clarabel", ""]
    if meta:
        L += [
            (f"- CPU: {meta.get('cpu_model')}, {meta.get('cpu_count')} cores; JAX device: {meta.get('device')} "
             f"({', '.join(meta.get('jax_devices') or ['?'])}); float64; OPENBLAS_NUM_THREADS="
             f"{meta.get('openblas_num_threads') or 'unset'} in the children; JAX CPU async dispatch "
             f"{'on (JAX default: a call returns before its result is ready, adding thread hand-off latency to one small solve)' if meta.get('async_dispatch', True) else 'off (`--sync-dispatch`: the latency of one call)'}."),
            "- Versions: " + ", ".join(f"{k} {v}" for k, v in (meta.get("versions") or {}).items()) + ".",
            (f"- Git commit {(meta.get('git') or {}).get('commit')}"
             f"{' (jdrkf/ has uncommitted changes)' if (meta.get('git') or {}).get('jdrkf_dirty') else ''}; jdrkf source "
             f"sha256 {meta.get('jdrkf_source_sha256_start')}"
             f"{'' if meta.get('jdrkf_source_consistent', True) else ' — WARNING: the library changed during the run'}."),
            (f"- Load average (1, 5, 15 min) at start {(meta.get('loadavg') or {}).get('start')}, at end "
             f"{(meta.get('loadavg') or {}).get('end')}: on a shared machine other processes compete for the cores. "
             f"Wall time {fmt(r.get('wall_s'), '.0f')} s. Hangs re-run: {meta.get('hangs', 0)}"
             f"{'; FAILED cells: ' + ', '.join(meta['failed_cells']) if meta.get('failed_cells') else ''}."),
        ]
    L += [
        (f"- Instances: seed {cfg.get('seed')}, {cfg.get('instances')} per size ({cfg.get('instances_large')} for "
         f"n ≥ {cfg.get('large_n')}); A scaled to spectral radius U[0.5, 1.2], θx, θv ~ U[0.1, 1]. jdrkf: median over up to "
         f"{cfg.get('repeats')} rounds over the instances (after compilation). cvxpy: one solve per instance (median)."),
        "",
        "## Solve: times (medians, ms per solve)",
        "",
        "| n | m | inst. | jdrkf (min) | jdrkf, OPENBLAS_NUM_THREADS=1 (min) | compile s | Newton iters med/max | "
        "converged | cvxpy plain (Clarabel) | cvxpy DPP (Clarabel) | cvxpy DPP, default tol. (Clarabel) | DPP canon. s |",
        "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|",
    ]
    notes, ratio_rows = [], []
    for x in r.get("sizes", []):
        j, j1 = x.get("jdrkf"), x.get("jdrkf_ob1")
        jf = "failed" if x.get("jdrkf_failed") else "n/a"
        cf = "failed" if x.get("cvxpy_failed") else "n/a"
        L.append(
            f"| {x['n']} | {x['m']} | {x.get('instances', '?')} | {g(j, 'median_ms', '.3g', jf)} ({g(j, 'min_ms', '.3g', '–')}) | "
            f"{g(j1, 'median_ms', '.3g', '–')} ({g(j1, 'min_ms', '.3g', '–')}) | "
            f"{g(j, 'compile_s', '.1f', '–')} | {g(x, 'iterations_median', '.0f', '–')}/{g(x, 'iterations_max', 'd', '–')} | "
            f"{x.get('converged', '–')}/{x.get('instances', '?')} | "
            f"{g(x, 'plain_ms', '.3g', cf)} ({g(x, 'plain_clarabel_ms', '.3g', '–')}) | "
            f"{g(x, 'dpp_ms', '.3g', cf)} ({g(x, 'dpp_clarabel_ms', '.3g', '–')}) | "
            f"{g(x, 'dpp_default_ms', '.3g', cf)} ({g(x, 'dpp_default_clarabel_ms', '.3g', '–')}) | "
            f"{g(x, 'dpp_canonicalize_s', '.2f', '–')} |")
        inacc = "/".join(str(len(x[f"inaccurate_{k}"])) if f"inaccurate_{k}" in x else "–" for k, _ in VARIANTS)

        def gstat(goal):
            if not goal:
                return "–"
            return "not evaluated" if goal.get("met") is None else ("**met**" if goal["met"] else "**not met**")

        goal, goal1 = x.get("goal") or {}, x.get("goal_ob1")
        ratio_rows.append(
            f"| {x['n']} | {x['m']} | {g(x, 'ratio_plain', '.3g', '–')} | {g(x, 'ratio_dpp', '.3g', '–')} | "
            f"{g(x, 'ratio_dpp_default', '.3g', '–')} | {g(x, 'ratio_dpp_default_clarabel_only', '.3g', '–')} | "
            f"{g(x, 'ratio_dpp_default_ob1', '.3g', '–')} | "
            f"{g(x, 'max_rel_diff_vs_plain', '.1e', '–')} | {g(x, 'max_rel_diff_vs_dpp', '.1e', '–')} | "
            f"{g(x, 'max_rel_diff_vs_dpp_default', '.1e', '–')} | {inacc} | {gstat(goal)} | {gstat(goal1)} |")
        tag = f"{x['n']}x{x['m']}"
        for jj, lab in ((j, ""), (j1, " (OPENBLAS_NUM_THREADS=1)")):
            if jj and (jj.get("compiles_during_timing") or jj.get("traces_during_timing")):
                notes.append(f"{tag}: {jj.get('compiles_during_timing')} XLA compilation(s), {jj.get('traces_during_timing')} "
                             f"trace(s) during the timed jdrkf rounds{lab}: the timings include recompilation")
        if x.get("converged") is not None and x["converged"] < x.get("instances", 0):
            bad = [i for i, p in enumerate(x.get("per_instance", [])) if not p.get("converged", True)]
            notes.append(f"{tag}: jdrkf did not converge on instance(s) {bad}")
        for k, label in VARIANTS:
            if x.get(f"inaccurate_{k}"):
                notes.append(f"{tag}: {label}: Clarabel ended `optimal_inaccurate` on instance(s) {x[f'inaccurate_{k}']} "
                             f"(left out of Δ; their max rel Δ {fmt(x.get(f'max_rel_diff_vs_{k}_inaccurate'), '.1e')})")
            if x.get(f"fallbacks_{k}"):
                notes.append(f"{tag}: {label}: {x[f'fallbacks_{k}']} solve(s) needed a looser rung of the tolerance ladder "
                             "(their time includes every rung)")
        if x.get("dpp_error"):
            notes.append(f"{tag}: DPP failed: {x['dpp_error']}")
        if goal.get("detail"):
            notes.append(f"{tag} single solve (informative): {goal['detail']}")
        if goal1 and goal1.get("detail"):
            notes.append(f"{tag} single solve with OPENBLAS_NUM_THREADS=1: {goal1['detail']}")
        if j and j.get("per_instance_median_ms"):
            pm = j["per_instance_median_ms"]
            notes.append(f"{tag}: jdrkf per-instance medians {min(pm):.3g}–{max(pm):.3g} ms")
        if x.get("max_rel_diff_ob1_vs_default") is not None and x["max_rel_diff_ob1_vs_default"] > 1e-12:
            notes.append(f"{tag}: jdrkf values with 1 and default OpenBLAS threads differ by {x['max_rel_diff_ob1_vs_default']:.1e}")
    L += ["", "## Solve: speed ratios (cvxpy time / jdrkf time) and value agreement", "",
          "| n | m | plain / jdrkf | DPP / jdrkf | DPP default tol. / jdrkf | Clarabel-only (DPP default tol.) / jdrkf | "
          "DPP default tol. / jdrkf with 1 OpenBLAS thread | max rel Δ vs plain | vs DPP | vs DPP default tol. | "
          "`optimal_inaccurate` (plain/DPP/default) | single solve ≥ 100× at 1e-6 (informative) | same, 1 OpenBLAS thread |",
          "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|---|---|"] + ratio_rows
    L += [""] + [f"- {s}" for s in notes] + [""]
    L += [
        "Ratios are time ratios (cvxpy time / jdrkf median time: how many times faster jdrkf is). "
        "\"Clarabel-only\" uses Clarabel's own `solve_time` (no cvxpy overhead), the hardest baseline. "
        "Δ = |jdrkf − SDP| / SDP of the optimal value Tr Σ*, over solves Clarabel reports `optimal`. "
        "The single-solve comparison (informative) uses the fastest cvxpy variant whose values agree with jdrkf to 1e-6. The OPENBLAS_NUM_THREADS=1 "
        "column is a separate child process (timings only): jaxlib's CPU LAPACK calls go to SciPy's OpenBLAS, whose "
        "threads compete with XLA's on few cores.",
        "",
    ]
    rrows = [x for x in r.get("sizes", []) if x.get("radii")]
    if rrows:
        L += [f"## Many radii in one vmapped call (the goal): `eqx.filter_jit(jax.vmap(lambda tx, tv, m: "
              f"SteadyStateDRKF(tx, tv).solve(m).value, in_axes=(0, 0, None)))`", "",
              f"B radius pairs (θx, θv) ~ U[0.1, 1] (seed {cfg.get('seed')}) on the size's first system, one call; "
              "µs per solve = median call / B. The cvxpy-DPP time per solve is the median re-solve over the size's "
              "systems (the faster DPP variant whose values agree with jdrkf to 1e-6). The single solve is the "
              "`jdrkf` column above (informative).", "",
              "| n | m | B | compile s | call s (min) | µs per solve (min) | jdrkf single solve µs | cvxpy DPP ms per solve | "
              "ratio DPP / vmapped | converged | chord steps med/max | max rel Δ vs single solves (checked) | goal ≥ 100× |",
              "|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---:|---|"]
        for x in rrows:
            rb, gl = x["radii"], x.get("radii_goal") or {}
            status = ("not evaluated" if gl.get("met") is None else ("**met**" if gl["met"] else "**not met**"))
            base, jms = gl.get("baseline"), (x.get("jdrkf") or {}).get("median_ms")
            L.append(f"| {x['n']} | {x['m']} | {rb['B']} | {rb['compile_s']:.1f} | {rb['call_s']:.3g} ({rb['call_min_s']:.3g}) | "
                     f"{rb['per_solve_ms'] * 1e3:.3g} ({rb['per_solve_min_ms'] * 1e3:.3g}) | "
                     f"{fmt(jms * 1e3 if jms is not None else None, '.3g')} | "
                     f"{fmt(x.get(f'{base}_ms') if base else None, '.3g')}{' (' + base + ')' if base else ''} | "
                     f"{fmt(gl.get('ratio'), '.3g', '–')} | {rb['converged']}/{rb['B']} | "
                     f"{rb['iterations_median']:.0f}/{rb['iterations_max']} | "
                     f"{fmt(rb['max_rel_diff_vs_single'], '.1e')} ({rb['checked']}) | {status} |")
        L.append("")
    grows = [x for x in r.get("sizes", []) if x.get("grad")]
    if grows:
        L += ["## Gradient of the value with respect to θx (`jax.value_and_grad`, implicit function theorem)", "",
              "| n | m | ms/call (min) | ms/call, OPENBLAS_NUM_THREADS=1 | compile s | ratio grad/value | "
              "max rel Δ vs FD of jdrkf (h = 1e-5) | rel Δ vs FD of the SDP (instance 0) |",
              "|---:|---:|---:|---:|---:|---:|---:|---:|"]
        for x in grows:
            gr, j = x["grad"], x.get("jdrkf") or {}
            ratio = gr["median_ms"] / j["median_ms"] if j.get("median_ms") else None
            L.append(f"| {x['n']} | {x['m']} | {gr['median_ms']:.3g} ({gr['min_ms']:.3g}) | "
                     f"{g(x.get('grad_ob1'), 'median_ms', '.3g', '–')} | {gr['compile_s']:.1f} | "
                     f"{fmt(ratio, '.3g')} | {g(gr, 'max_rel_diff_vs_fd_jdrkf', '.1e')} | "
                     f"{g(gr, 'rel_diff_vs_fd_sdp_instance0', '.1e')} |")
        L += ["", (f"cvxpy has no derivative of the optimal value here (the SDP FD needs two more solves; h = "
                   f"{cfg.get('fd_h_sdp')}, limited by Clarabel's ~1e-9 value accuracy)."), ""]
    L += ["## Goals", ""]
    for informative in (False, True):
        if informative and any(gl.get("informative") for gl in r.get("goals", [])):
            L += ["", "Informative (not goals):", ""]
        for goal in r.get("goals", []):
            if bool(goal.get("informative")) != informative:
                continue
            status = "met" if goal["met"] else ("not met" if goal["met"] is not None else "not evaluated")
            L.append(f"- {goal['goal']}: **{status}** — {goal['detail']}")
    L.append("")
    return "\n".join(L)


def evaluate_goals(r) -> list:
    goals = []
    rows = [x for x in r.get("sizes", []) if x.get("radii_goal")]
    if rows:
        evaluated = [x["radii_goal"]["met"] for x in rows if x["radii_goal"]["met"] is not None]
        goals.append({"goal": f"{GOAL_RADII} radius pairs in one vmapped call: per solve ≥ {GOAL_RATIO:g}× faster than the "
                              "cvxpy-DPP re-solve per solve, all converged, values = single solves "
                              f"({GOAL_RADII_REL:g} relative), per size",
                      "met": all(evaluated) if evaluated else None,
                      "ratios": {f"{x['n']}x{x['m']}": x["radii_goal"].get("ratio") for x in rows},
                      "detail": "; ".join(f"{x['n']}x{x['m']}: " + ("met" if x["radii_goal"]["met"] else (
                          "not met" if x["radii_goal"]["met"] is not None else "n/a")) + f", {x['radii_goal']['detail']}"
                          for x in rows)})
    for key, lab in (("goal", ""), ("goal_ob1", ", jdrkf with OPENBLAS_NUM_THREADS=1")):
        rows = [x for x in r.get("sizes", []) if x.get(key)]
        if not rows:
            continue
        per = [f"{x['n']}x{x['m']}: {'met' if x[key]['met'] else ('not met' if x[key]['met'] is not None else 'n/a')}"
               f" ({x[key].get('ratio', float('nan')):.3g}×)" for x in rows]
        evaluated = [x[key]["met"] for x in rows if x[key]["met"] is not None]
        goals.append({"goal": f"single solve ≥ {GOAL_RATIO:g}× faster than cvxpy + Clarabel at equal value "
                              f"({GOAL_REL:g} relative), per size{lab} (the former goal)", "informative": True,
                      "met": all(evaluated) if evaluated else None, "detail": "; ".join(per)})
    diffs = [(x.get(f"max_rel_diff_vs_{k}"), f"{x['n']}x{x['m']} {k}") for x in r.get("sizes", []) for k, _ in VARIANTS
             if x.get(f"max_rel_diff_vs_{k}") is not None]
    if diffs:
        worst = max(diffs)
        goals.append({"goal": f"value agreement |jdrkf − SDP|/SDP ≤ {GOAL_REL:g} (Clarabel `optimal` solves)",
                      "met": worst[0] <= GOAL_REL, "detail": f"worst {worst[0]:.1e} ({worst[1]})"})
    return goals


# --------------------------------------------------------------------------- processes


def run_child(args, cell: str) -> dict:
    size, part = cell.split("/")
    n, m = parse_size(size)
    wd = Watchdog(args.watchdog_s)
    out = {"cell": cell, "jdrkf_source_sha256_start": package_source_hash(), "loadavg_start": loadavg()}
    if part in ("jdrkf", "jdrkf_ob1"):
        set_platform(args.platform)
        import jax

        jax.config.update("jax_enable_x64", True)
        jax.config.update("jax_cpu_enable_async_dispatch", not args.sync_dispatch)
        out["jax_devices"] = [str(d) for d in jax.devices()]
        out["device"] = device_summary(jax)
        out["result"] = bench_jdrkf(args, n, m, wd, radii=part == "jdrkf")
    else:
        out["result"] = bench_cvxpy(args, n, m, wd)
    wd.disarm()
    out["jdrkf_source_sha256_end"] = package_source_hash()
    out["loadavg_end"] = loadavg()
    return out


def spawn(args, cell: str) -> tuple[dict | None, list]:
    attempts = []
    env = dict(os.environ)
    threads = "1" if cell.endswith("/jdrkf_ob1") else args.openblas_threads
    if threads is not None:
        env["OPENBLAS_NUM_THREADS"] = str(threads)
    for attempt in range(args.retries + 1):
        with tempfile.TemporaryDirectory() as tmp:
            path = os.path.join(tmp, "cell.json")
            cmd = [sys.executable, os.path.abspath(__file__), *args.argv, "--child-cell", cell, "--child-out", path]
            t0 = time.perf_counter()
            proc = subprocess.run(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, env=env)
            sys.stderr.write(proc.stderr)
            hang = "Timeout (" in proc.stderr
            attempts.append({"cell": cell, "attempt": attempt + 1, "returncode": proc.returncode, "hang": hang,
                             "wall_s": time.perf_counter() - t0, "loadavg_after": loadavg()})
            if proc.returncode == 0:
                with open(path) as f:
                    return json.load(f), attempts
            log(f"cell {cell}: child exited with {proc.returncode}{' (watchdog: hang)' if hang else ''}")
            if not hang:
                break
    return None, attempts


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--quick", action="store_true", help="smoke run: 2 instances (1 at n >= 10), 2 rounds")
    p.add_argument("--sizes", nargs="+", default=None, help=f"NxM sizes (default {' '.join(DEFAULT_SIZES)})")
    p.add_argument("--instances", type=int, default=None, help="random systems per size (default 10)")
    p.add_argument("--instances-large", type=int, default=None, help="systems for n >= --large-n (default 10)")
    p.add_argument("--large-n", type=int, default=10)
    p.add_argument("--repeats", type=int, default=5, help="timed rounds over the instances (median)")
    p.add_argument("--cell-budget-s", type=float, default=60.0, help="stop starting new rounds after this many seconds")
    p.add_argument("--grad-checks", type=int, default=3, help="instances whose gradient is checked by finite differences")
    p.add_argument("--fd-h-sdp", type=float, default=1e-3, help="step of the SDP finite difference in θx")
    p.add_argument("--no-grad", action="store_true", help="skip the gradient rows")
    p.add_argument("--no-dpp", action="store_true", help="skip the cvxpy DPP variants")
    p.add_argument("--no-cvxpy", action="store_true", help="skip cvxpy altogether")
    p.add_argument("--openblas-threads", type=int, default=None,
                   help="set OPENBLAS_NUM_THREADS in all children (default: unchanged) and drop the extra 1-thread jdrkf row")
    p.add_argument("--no-openblas-1-row", action="store_true",
                   help="skip the extra jdrkf child run with OPENBLAS_NUM_THREADS=1")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--platform", choices=["cpu", "gpu"], default="cpu", help="JAX platform of the jdrkf children (cvxpy: CPU)")
    p.add_argument("--radius-batch", type=int, default=GOAL_RADII,
                   help=f"radius pairs in the vmapped many-radii row (the goal's {GOAL_RADII}; 0 skips it)")
    p.add_argument("--radius-checks", type=int, default=None,
                   help="pairs whose vmapped value is checked against a single solve (default all; 50 with --quick)")
    p.add_argument("--sync-dispatch", action="store_true",
                   help="turn JAX's CPU async dispatch off in the jdrkf children (latency of one call; default: on, JAX's default)")
    p.add_argument("--watchdog-s", type=float, default=600.0, help="a child aborts when a phase runs longer than this")
    p.add_argument("--watchdog-first-call-s", type=float, default=180.0, help="limit for a first (compiling) call")
    p.add_argument("--retries", type=int, default=1, help="re-runs of a cell whose child hung")
    p.add_argument("--out", default=os.path.join(HERE, "results"), help="output directory")
    p.add_argument("--tag", default=None, help="output file stem suffix (default the platform, '_quick' appended with --quick)")
    p.add_argument("--child-cell", help=argparse.SUPPRESS)
    p.add_argument("--child-out", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    args.argv = list(argv)
    sizes = args.sizes or DEFAULT_SIZES
    args.instances = args.instances or (2 if args.quick else 10)
    args.instances_large = args.instances_large or (1 if args.quick else 10)
    if args.quick:
        args.repeats = min(args.repeats, 2)
        args.grad_checks = min(args.grad_checks, 1)
        if args.radius_checks is None:
            args.radius_checks = 50
    if args.tag is None:
        args.tag = args.platform + ("_quick" if args.quick else "")

    if args.child_cell:
        res = run_child(args, args.child_cell)
        with open(args.child_out, "w") as f:
            json.dump(res, f, default=float)
        return 0

    check_platform(args.platform)
    t_start = time.perf_counter()
    meta = {
        "cpu_model": cpu_model(), "cpu_count": os.cpu_count(),
        "cpu_affinity": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None,
        "platform": platform.platform(), "versions": versions(), "git": git_info(),
        "openblas_num_threads": (str(args.openblas_threads) if args.openblas_threads is not None
                                 else os.environ.get("OPENBLAS_NUM_THREADS")),
        "jdrkf_source_sha256_start": package_source_hash(), "loadavg": {"start": loadavg()},
        "async_dispatch": not args.sync_dispatch,
    }
    log(f"steady_state_solver: sizes {sizes}, load {meta['loadavg']['start']}")
    children, attempts, failed = {}, [], []
    parts = ["jdrkf"] + ([] if args.openblas_threads is not None or args.no_openblas_1_row or args.platform == "gpu"
                         else ["jdrkf_ob1"])
    parts += [] if args.no_cvxpy else ["cvxpy"]
    for sz in sizes:
        for part in parts:
            cell = f"{sz}/{part}"
            res, att = spawn(args, cell)
            attempts += att
            meta["loadavg"][f"after {cell}"] = loadavg()
            if res is None:
                failed.append(cell)
            else:
                children[cell] = res
    if not children:
        log("ERROR: every cell failed")
        return 1
    meta["jax_devices"] = next((c["jax_devices"] for c in children.values() if "jax_devices" in c), None)
    meta["device"] = next((c["device"] for c in children.values() if "device" in c), None)
    meta["loadavg"]["end"] = loadavg()
    hashes = {meta["jdrkf_source_sha256_start"], package_source_hash()}
    for c in children.values():
        hashes |= {c["jdrkf_source_sha256_start"], c["jdrkf_source_sha256_end"]}
    meta["jdrkf_source_sha256_all_seen"] = sorted(hashes)
    meta["jdrkf_source_consistent"] = len(hashes) == 1
    meta["cells"], meta["hangs"], meta["failed_cells"] = attempts, sum(a["hang"] for a in attempts), failed

    rows = []
    for sz in sizes:
        n, m = parse_size(sz)
        j = children.get(f"{sz}/jdrkf", {}).get("result")
        j1 = children.get(f"{sz}/jdrkf_ob1", {}).get("result")
        c = children.get(f"{sz}/cvxpy", {}).get("result")
        if j is None and c is None and j1 is None:
            continue
        row = merge(j, c, n, m, j1)
        row["cvxpy_failed"] = row["cvxpy_failed"] and not args.no_cvxpy
        rows.append(row)
    config = {k: v for k, v in vars(args).items() if k not in ("child_cell", "child_out", "out", "argv")}
    config["sizes"] = sizes
    result = {
        "benchmark": "steady_state_solver",
        "created": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "command": " ".join([os.path.basename(sys.executable), os.path.relpath(os.path.abspath(__file__), ROOT)] + argv),
        "wall_s": time.perf_counter() - t_start,
        "config": config, "meta": meta, "sizes": rows,
    }
    result["goals"] = evaluate_goals(result)
    md = build_markdown(result)
    os.makedirs(args.out, exist_ok=True)
    stem = os.path.join(args.out, f"steady_state_solver_{args.tag}")
    with open(stem + ".json", "w") as f:
        json.dump(result, f, indent=2, default=float)
    with open(stem + ".md", "w") as f:
        f.write(md)
    print(md)
    log(f"wrote {stem}.json and {stem}.md ({result['wall_s']:.0f} s)")
    if failed:
        log(f"ERROR: cells failed: {failed}")
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
