#!/usr/bin/env python
"""What a jitted JAX call costs on this CPU, against the single-solve budget of issue 4's former goal.

Issue 4 asked the steady-state solve (`SteadyStateDRKF.solve`) to be ≥ 100× faster than
cvxpy + Clarabel on problem (14), one solve per call: that is now an informative row of
`steady_state_solver.py` (whose goal is 1000 radius pairs in one vmapped call), and
this script shows why one call cannot meet it. `steady_state_solver.py` records the fastest cvxpy
time per size; this script measures, in the same setting as that benchmark's
`--sync-dispatch` run (float64, CPU async dispatch off: the latency of one call),

1. `trivial`: `jax.jit(lambda a: a + 1)` on a 2×2 array: the cost of any jitted call;
2. `newton k`: a jitted `lax.while_loop` of `k` Newton iterations (`jax.jacfwd` Jacobian
   and a dense LU solve) on a toy smooth system `F(z) = A z + tanh(z) − b` with as many
   unknowns as problem (14) has in `SteadyStateDRKF.solve` (`n(n+1) + m(m+1)/2 + 2`);
   a lower bound for one Newton iteration of any JAX solver of that size, whose
   residual needs matrix inverses, square roots and a line search besides;
3. `KKT Newton k`: the same loop on jdrkf's own optimality system of (14)
   (`_stationary_residual` from `_initial_guess`, no line search, no sweeps), on the
   first random system of `steady_state_solver.py` (seed 0) of each size: what `k`
   bare Newton iterations of the real solver cost (the recorded solves take a median
   of 4-5 after 8 fixed-point sweeps);

and prints them next to the 100× budget (fastest cvxpy time / 100) and jdrkf's solve
time read from `results/steady_state_solver_<platform>.json` (`--ss-results`; the CPU
file when there is none for the platform).

`--platform gpu` times the JAX calls on a GPU (the device is recorded; the output stem is
`call_floor_<platform>`).

Usage:

    python benchmarks/call_floor.py                 # writes results/call_floor_cpu.{json,md}
    python benchmarks/call_floor.py --out smoke/cf
    python benchmarks/call_floor.py --platform gpu  # writes results/call_floor_gpu.{json,md}
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import statistics
import sys
import time

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)

from _provenance import cpu_model, device_summary, git_info, loadavg, package_source_hash, set_platform, versions  # noqa: E402

ITERS = (1, 4, 8)


def unknowns(n: int, m: int) -> int:
    return n * (n + 1) + m * (m + 1) // 2 + 2


def time_us(fn, arg, repeats: int) -> dict:
    import jax

    jax.block_until_ready(fn(arg))
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        jax.block_until_ready(fn(arg))
        ts.append(time.perf_counter() - t0)
    return {"median_us": 1e6 * statistics.median(ts), "min_us": 1e6 * min(ts)}


def newton_loop(residual, x0, iters):
    """`iters` bare Newton steps (`jacfwd` Jacobian, dense LU solve) in a `lax.while_loop`."""
    import jax
    import jax.numpy as jnp
    from jax import lax

    def body(c):
        z, k = c
        return z - jnp.linalg.solve(jax.jacfwd(residual)(z), residual(z)), k + 1

    return lax.while_loop(lambda c: c[1] < iters, body, (x0, 0))[0]


def toy_newton(d: int, iters: int):
    """A jittable `a ↦ z` running `iters` Newton steps on `A z + tanh(z) − b` with `d` unknowns."""
    import jax.numpy as jnp
    import numpy as np

    b = jnp.asarray(np.random.default_rng(d).normal(size=d))
    return lambda a: newton_loop(lambda z: a @ z + jnp.tanh(z) - b, jnp.zeros(d), iters)


def kkt_newton(c, w, v, tx, tv, iters: int):
    """A jittable `A ↦ z` running `iters` Newton steps on jdrkf's optimality system of (14)."""
    from jdrkf.sets._steady_state import _initial_guess, _stationary_residual

    return lambda a: newton_loop(_stationary_residual(a, c, w, v, tx, tv), _initial_guess(a, c, w, v), iters)


def measure(sizes, repeats: int) -> dict:
    import jax
    import jax.numpy as jnp
    import numpy as np
    from steady_state_solver import make_instances

    jax.config.update("jax_enable_x64", True)
    jax.config.update("jax_cpu_enable_async_dispatch", False)
    out = {"trivial": time_us(jax.jit(lambda a: a + 1), jnp.eye(2), repeats), "newton": {}, "kkt_newton": {}}
    for n, m in sizes:
        d = unknowns(n, m)
        rng = np.random.default_rng(d)
        a_toy = jnp.asarray(rng.normal(size=(d, d)) / np.sqrt(d) + 2 * np.eye(d))
        out["newton"][f"{n}x{m}"] = {"unknowns": d, **{
            str(k): time_us(jax.jit(toy_newton(d, k)), a_toy, repeats) for k in ITERS}}
        a, c, w, v, tx, tv = (jnp.asarray(x) for x in make_instances(n, m, 1, 0)[0])
        out["kkt_newton"][f"{n}x{m}"] = {
            str(k): time_us(jax.jit(kkt_newton(c, w, v, tx, tv, k)), a, repeats) for k in ITERS}
    return out


def build_markdown(r) -> str:
    meta = r["meta"]
    L = [f"# Cost of a jitted JAX call ({r['config'].get('platform', 'cpu').upper()}) vs the 100× single-solve budget "
         "of the steady-state solver (issue 4's former goal)", "",
         f"- CPU: {meta['cpu_model']}, {meta['cpu_count']} cores; JAX device: {meta.get('device')}; float64; "
         "JAX CPU async dispatch off. "
         f"Versions: {', '.join(f'{k} {v}' for k, v in meta['versions'].items() if v)}.",
         f"- Git commit {meta['git'].get('commit')}; load average at start {meta['loadavg']['start']}, "
         f"at end {meta['loadavg']['end']}. Medians (min) of {r['config']['repeats']} calls.",
         f"- cvxpy and jdrkf solve times: `{r['ss_results']}` ({r['ss_created']}, commit {r['ss_commit']}).", "",
         f"A jitted call that adds 1 to a 2×2 array: **{r['floor']['trivial']['median_us']:.1f} µs** "
         f"({r['floor']['trivial']['min_us']:.1f}).", "",
         "| n | m | unknowns | fastest cvxpy (ms) | 100× budget (µs) | Clarabel alone / 100 (µs) | jdrkf solve (µs) | "
         + " | ".join(f"toy Newton, {k} it. (µs)" for k in ITERS) + " | "
         + " | ".join(f"KKT Newton, {k} it. (µs)" for k in ITERS) + " |",
         "|---:|---:|---:|---:|---:|---:|---:|" + "---:|" * (2 * len(ITERS))]
    for row in r["rows"]:
        nw = r["floor"]["newton"][f"{row['n']}x{row['m']}"]
        kk = r["floor"]["kkt_newton"][f"{row['n']}x{row['m']}"]
        L.append(f"| {row['n']} | {row['m']} | {nw['unknowns']} | {row['cvxpy_ms']:.3g} ({row['baseline']}) | "
                 f"{row['budget_us']:.0f} | {row['clarabel_budget_us']:.1f} | {row['jdrkf_us']:.0f} | "
                 + " | ".join(f"{nw[str(k)]['median_us']:.1f}" for k in ITERS) + " | "
                 + " | ".join(f"{kk[str(k)]['median_us']:.1f}" for k in ITERS) + " |")
    L += ["", "Reading: the budget is the fastest cvxpy time / 100. The KKT columns time bare Newton "
          "iterations of jdrkf's own optimality system from its zero-radius start (the start's DARE and "
          "Lyapunov solves are in the 1 it. column); the solver needs several after its fixed-point "
          "sweeps. The toy columns are the floor of a JAX Newton loop with that many unknowns, whatever "
          "the residual. Clarabel's own solve time (no cvxpy overhead) gives a smaller budget at n = 2 "
          "and 4. A GPU adds kernel-launch latency to these serial, tiny problems.", ""]
    return "\n".join(L)


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--platform", choices=["cpu", "gpu"], default="cpu", help="JAX platform of the timed calls")
    p.add_argument("--ss-results", default=None,
                   help="steady_state_solver JSON (default results/steady_state_solver_<platform>.json, else the CPU one)")
    p.add_argument("--repeats", type=int, default=None, help="timed calls per row (default 500; 50 with --quick)")
    p.add_argument("--quick", action="store_true", help="smoke run: 50 calls per row")
    p.add_argument("--out", default=os.path.join(HERE, "results"))
    p.add_argument("--tag", default=None, help="output file stem suffix (default the platform, '_quick' appended with --quick)")
    args = p.parse_args(argv)
    args.repeats = args.repeats or (50 if args.quick else 500)
    if args.tag is None:
        args.tag = args.platform + ("_quick" if args.quick else "")
    if args.ss_results is None:
        args.ss_results = os.path.join(HERE, "results", f"steady_state_solver_{args.platform}.json")
        if not os.path.exists(args.ss_results):
            args.ss_results = os.path.join(HERE, "results", "steady_state_solver_cpu.json")
    set_platform(args.platform)
    with open(args.ss_results) as f:
        ss = json.load(f)
    rows = []
    for s in ss["sizes"]:
        if "baseline" not in s["goal"]:  # a part of this size failed: no cvxpy time to compare with
            continue
        base = s["goal"]["baseline"]
        rows.append({"n": s["n"], "m": s["m"], "baseline": base, "cvxpy_ms": s[f"{base}_ms"],
                     "budget_us": 1e3 * s[f"{base}_ms"] / 100, "clarabel_budget_us": 1e3 * s[f"{base}_clarabel_ms"] / 100,
                     "jdrkf_us": 1e3 * s["jdrkf"]["median_ms"]})
    meta = {"cpu_model": cpu_model(), "cpu_count": os.cpu_count(), "versions": versions(), "git": git_info(),
            "jdrkf_source_sha256": package_source_hash(), "loadavg": {"start": loadavg()}}
    floor = measure([(r["n"], r["m"]) for r in rows], args.repeats)
    import jax

    meta["device"] = device_summary(jax)
    meta["loadavg"]["end"] = loadavg()
    result = {"benchmark": "call_floor",
              "created": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
              "config": {"repeats": args.repeats, "iterations": list(ITERS), "platform": args.platform}, "meta": meta,
              "ss_results": os.path.relpath(args.ss_results, os.path.dirname(HERE)), "ss_created": ss.get("created"),
              "ss_commit": ss.get("meta", {}).get("git", {}).get("commit"), "rows": rows, "floor": floor}
    md = build_markdown(result)
    os.makedirs(args.out, exist_ok=True)
    stem = os.path.join(args.out, f"call_floor_{args.tag}")
    with open(stem + ".json", "w") as f:
        json.dump(result, f, indent=2)
    with open(stem + ".md", "w") as f:
        f.write(md)
    print(md)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
