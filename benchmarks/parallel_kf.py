#!/usr/bin/env python
"""Parallel-in-time (associative scan) vs sequential (lax.scan) Kalman filter and RTS smoother.

One series of T steps (no batch of runs: parallel-in-time is for one long series), for
T ∈ {10, 100, 1e3, 1e4, 1e5} and state dimensions n = 2 (m = 1) and n = 8 (m = 4), on a
seeded random stable system (F = 0.97 × an orthogonal matrix). Four jitted rows per cell,
each returning filtered means, covariances and the marginal log-likelihood (the default
`outputs`), the smoothers also the smoothed moments and cross-covariances:

- `sequential filter`: `jdrkf.KalmanFilter()(model, prior, ys)`;
- `parallel filter`: `jdrkf.ParallelKalmanFilter()(model, prior, ys)`;
- `sequential smoother`: `jdrkf.smooth(jdrkf.KalmanFilter(), model, prior, ys)`;
- `parallel smoother`: `jdrkf.parallel_smooth(model, prior, ys)`.

Timing: after a first (compiling) call of every row, `--repeats` rounds each call every row
once in turn (interleaved, so that load changes hit all rows alike); a row's time is its
median over the rounds. The crossover T of a pair (filter, smoother) at a given n is the
smallest measured T from which on the parallel row is faster at every larger T (none when
it is slower at the largest T). Before timing, the parallel outputs are compared with the
sequential ones (max abs difference relative to the largest entry; 1e-8 in float64, 1e-3 in
float32); the script exits with status 1 if a check fails.

Usage:

    python benchmarks/parallel_kf.py                   # CPU, float64: results/parallel_kf_cpu.{json,md}
    python benchmarks/parallel_kf.py --platform gpu    # on a GPU: results/parallel_kf_gpu.{json,md}
    python benchmarks/parallel_kf.py --quick --out smoke/pkf   # smoke run: n = 2, T ≤ 1000
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import platform
import statistics
import sys
import time

import numpy as np
from _provenance import (
    cpu_model,
    device_summary,
    git_info,
    loadavg,
    package_source_hash,
    set_platform,
    versions,
)

SEED = 0
DIMS = {2: 1, 8: 4}  # n -> m
ROWS = ("sequential filter", "parallel filter", "sequential smoother", "parallel smoother")


def log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def system(n: int, m: int, seed: int = SEED) -> dict:
    rng = np.random.default_rng(seed + n)
    F = 0.97 * np.linalg.qr(rng.standard_normal((n, n)))[0]
    c = rng.standard_normal((n, n))
    return {
        "F": F, "H": rng.standard_normal((m, n)), "Q": c @ c.T / n + 0.1 * np.eye(n), "R": np.eye(m),
        "m0": np.zeros(n), "P0": np.eye(n),
    }


def run(args) -> dict:
    import jax
    import jax.numpy as jnp

    jax.config.update("jax_enable_x64", args.dtype == "float64")
    import jdrkf

    source_hash = package_source_hash(jdrkf)
    kf, pkf = jdrkf.KalmanFilter(), jdrkf.ParallelKalmanFilter()
    smooth_fields = lambda s: (s.smoothed_means, s.smoothed_covariances, s.smoothed_cross_covariances,
                               s.filter_result.filtered_means, s.marginal_loglik)
    fns = {
        "sequential filter": jax.jit(lambda mdl, pr, y: kf(mdl, pr, y)),
        "parallel filter": jax.jit(lambda mdl, pr, y: pkf(mdl, pr, y)),
        "sequential smoother": jax.jit(lambda mdl, pr, y: smooth_fields(jdrkf.smooth(kf, mdl, pr, y))),
        "parallel smoother": jax.jit(lambda mdl, pr, y: smooth_fields(jdrkf.parallel_smooth(mdl, pr, y))),
    }
    tol = 1e-8 if args.dtype == "float64" else 1e-3
    cells, checks = [], []
    for n in args.dims:
        m = DIMS[n]
        s = {k: jnp.asarray(v, dtype=args.dtype) for k, v in system(n, m, args.seed).items()}
        model = jdrkf.LinearModel(s["F"], s["H"], s["Q"], s["R"])
        prior = jdrkf.Gaussian(s["m0"], s["P0"])
        ys_all = jdrkf.simulate(jax.random.key(args.seed), model, prior, max(args.T), 1).observations[0]
        for T in args.T:
            ys = ys_all[:T]
            repeats = args.repeats if T < 10**5 else max(3, args.repeats // 2)
            first, outs = {}, {}
            for name, fn in fns.items():
                t0 = time.perf_counter()
                outs[name] = jax.block_until_ready(fn(model, prior, ys))
                first[name] = time.perf_counter() - t0
            for kind, seq, par in (("filter", outs["sequential filter"], outs["parallel filter"]),
                                   ("smoother", outs["sequential smoother"], outs["parallel smoother"])):
                a, b = jax.tree.leaves(seq), jax.tree.leaves(par)
                diff = max(float(jnp.max(jnp.abs(x - y)) / jnp.maximum(1.0, jnp.max(jnp.abs(x)))) for x, y in zip(a, b))
                checks.append({"n": n, "T": T, "what": kind, "max_rel_diff": diff, "ok": diff <= tol})
            del outs
            times = {name: [] for name in fns}
            for _ in range(repeats):
                for name, fn in fns.items():
                    t0 = time.perf_counter()
                    jax.block_until_ready(fn(model, prior, ys))
                    times[name].append(time.perf_counter() - t0)
            for name in fns:
                med = statistics.median(times[name])
                cells.append({"row": name, "n": n, "m": m, "T": T, "median_s": med, "min_s": min(times[name]),
                              "first_call_s": first[name], "compile_s": first[name] - med, "times_s": times[name],
                              "us_per_step": 1e6 * med / T})
            log(f"n={n} T={T}: " + ", ".join(f"{r} {statistics.median(times[r]) * 1e3:.3g} ms" for r in fns))
    return {"cells": cells, "checks": checks, "device": device_summary(jax), "jax": jax.__version__,
            "jdrkf_source_sha256": {"start": source_hash, "end": package_source_hash(jdrkf)}}


def crossovers(cells) -> list[dict]:
    def medians(n, row):
        return {c["T"]: c["median_s"] for c in cells if c["n"] == n and c["row"] == row}

    out = []
    for n in sorted({c["n"] for c in cells}):
        for kind in ("filter", "smoother"):
            seq, par = medians(n, f"sequential {kind}"), medians(n, f"parallel {kind}")
            ts = sorted(seq)
            cross = None
            for i, T in enumerate(ts):
                if all(par[u] < seq[u] for u in ts[i:]):
                    cross = T
                    break
            out.append({"n": n, "what": kind, "crossover_T": cross,
                        "speedup_at_largest_T": seq[ts[-1]] / par[ts[-1]], "largest_T": ts[-1]})
    return out


def build_markdown(result) -> str:
    meta, cfg = result["meta"], result["config"]
    lines = [
        f"# Parallel-in-time vs sequential Kalman filter and RTS smoother ({meta['tag']})",
        "",
        (
            f"- One series per call, random stable system (seed {cfg['seed']}), {cfg['dtype']}; "
            + " and ".join(f"n = {n} (m = {m})" for n, m in cfg["dims"].items())
            + f". Median of {cfg['repeats']} interleaved rounds ({max(3, cfg['repeats'] // 2)} at T = 1e5); "
            "every row returns filtered means, covariances and the log-likelihood (smoothers: also the smoothed "
            "moments and cross-covariances)."
        ),
        (
            f"- Machine: {meta['cpu_model']}, {meta['cpu_count']} cores; JAX device: {meta['device']}; "
            f"jax {meta['versions']['jax']}; jdrkf source sha256 {meta['jdrkf_source_sha256']['start']}; "
            f"load average at start {meta['loadavg']['before']}, at end {meta['loadavg']['after']}."
        ),
        "",
        "## Crossover",
        "",
        "| n | pair | crossover T | sequential / parallel time at the largest T |",
        "|---:|---|---:|---:|",
    ]
    for c in result["crossover"]:
        cross = "none (sequential faster)" if c["crossover_T"] is None else f"{c['crossover_T']:g}"
        lines.append(f"| {c['n']} | {c['what']} | {cross} | {c['speedup_at_largest_T']:.2f}× (T = {c['largest_T']:g}) |")
    lines += ["", "## Times (median ms per call; µs per step in parentheses)", "",
              "| n | T | " + " | ".join(ROWS) + " | parallel / sequential (filter, smoother) |",
              "|---:|---:|" + "---:|" * (len(ROWS) + 1)]
    for n in sorted({c["n"] for c in result["cells"]}):
        for T in sorted({c["T"] for c in result["cells"] if c["n"] == n}):
            get = {c["row"]: c for c in result["cells"] if c["n"] == n and c["T"] == T}
            vals = " | ".join(f"{get[r]['median_s'] * 1e3:.3g} ({get[r]['us_per_step']:.3g})" for r in ROWS)
            ratio_f = get["parallel filter"]["median_s"] / get["sequential filter"]["median_s"]
            ratio_s = get["parallel smoother"]["median_s"] / get["sequential smoother"]["median_s"]
            lines.append(f"| {n} | {T:g} | {vals} | {ratio_f:.2f}, {ratio_s:.2f} |")
    lines += ["", "Compile times (first call − median, s): " + "; ".join(
        f"n={c['n']} T={c['T']:g} {c['row']} {c['compile_s']:.2f}" for c in result["cells"] if c["T"] == max(cfg["T"])),
        "", "## Agreement checks (parallel vs sequential, max abs difference / max(1, max abs entry))", "",
        "| n | T | pair | difference | ok |", "|---:|---:|---|---:|---|"]
    for ck in result["checks"]:
        lines.append(f"| {ck['n']} | {ck['T']:g} | {ck['what']} | {ck['max_rel_diff']:.2e} | {'yes' if ck['ok'] else 'no'} |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    here = os.path.dirname(os.path.abspath(__file__))
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--platform", choices=["cpu", "gpu"], default="cpu", help="JAX platform")
    p.add_argument("--quick", action="store_true", help="smoke run: n = 2, T in {10, 100, 1000}, 3 rounds")
    p.add_argument("--T", type=int, nargs="+", default=None, help="series lengths (default 10 100 1e3 1e4 1e5)")
    p.add_argument("--dims", type=int, nargs="+", default=None, choices=sorted(DIMS), help="state dimensions")
    p.add_argument("--repeats", type=int, default=None, help="interleaved timing rounds (default 7)")
    p.add_argument("--dtype", choices=["float32", "float64"], default="float64")
    p.add_argument("--seed", type=int, default=SEED)
    p.add_argument("--out", default=os.path.join(here, "results"), help="output directory")
    p.add_argument("--tag", default=None, help="output file stem suffix (default the platform, '_quick' appended)")
    args = p.parse_args(argv)
    args.T = args.T or ([10, 100, 1000] if args.quick else [10, 100, 1000, 10_000, 100_000])
    args.dims = args.dims or ([2] if args.quick else sorted(DIMS))
    args.repeats = args.repeats or (3 if args.quick else 7)
    args.tag = args.tag or (args.platform + ("_quick" if args.quick else ""))
    set_platform(args.platform)
    t_start, before = time.perf_counter(), loadavg()
    res = run(args)
    result = {
        "benchmark": "parallel_kf",
        "created": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "command": " ".join(["python", "benchmarks/parallel_kf.py", *sys.argv[1:]]),
        "wall_s": time.perf_counter() - t_start,
        "config": {"T": args.T, "dims": {n: DIMS[n] for n in args.dims}, "repeats": args.repeats, "dtype": args.dtype,
                   "seed": args.seed, "platform": args.platform},
        "meta": {"tag": args.tag, "cpu_model": cpu_model(), "cpu_count": os.cpu_count(), "platform": platform.platform(),
                 "device": res["device"], "versions": versions(("jax", "jaxlib", "equinox", "numpy", "jdrkf")),
                 "git": git_info(), "loadavg": {"before": before, "after": loadavg()},
                 "jdrkf_source_sha256": res["jdrkf_source_sha256"]},
        "crossover": crossovers(res["cells"]),
        "cells": res["cells"],
        "checks": res["checks"],
        "checks_ok": all(c["ok"] for c in res["checks"]),
    }
    os.makedirs(args.out, exist_ok=True)
    stem = os.path.join(args.out, f"parallel_kf_{args.tag}")
    with open(stem + ".json", "w") as f:
        json.dump(result, f, indent=2)
    md = build_markdown(result)
    with open(stem + ".md", "w") as f:
        f.write(md)
    print(md)
    log(f"wrote {stem}.json and {stem}.md ({result['wall_s']:.0f} s)")
    if not result["checks_ok"]:
        log("ERROR: parallel and sequential outputs disagree beyond tolerance (see checks)")
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
