#!/usr/bin/env python
"""Regression check: representative `jax.jit(jax.vmap(filter))` calls timed at two git revisions
of jdrkf, side by side on the same machine.

Each revision is checked out into a temporary `git worktree`; a child process imports jdrkf from
it (`PYTHONPATH`) and times every case (compile excluded, median of `--repeats` calls). The two
revisions alternate for `--rounds` rounds, so slow drifts of a shared machine's load hit both;
the table gives per case the median over rounds, the range, and head / base. The cases cover the
filter families whose code paths a library change may touch: the shared-covariance Wasserstein
filters (decoupled DRKF, WKF, steady-state DRKF), the per-run DRKF (an `observed` mask), the
square-root KF, the Huber KF, the UKF and the bootstrap PF (systematic resampling).

Usage: `python benchmarks/compare_revisions.py --base REV [--head HEAD] [--rounds 3] [--repeats 7]
[--out benchmarks/results]` → `results/compare_revisions_cpu.{md,json}`.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)


def child(repeats: int) -> dict:
    """Time the cases with the jdrkf on `sys.path` (float64); seconds per call, medians."""
    import jax
    import jax.numpy as jnp
    import numpy as np

    jax.config.update("jax_enable_x64", True)  # the benchmark process, not the library
    import jdrkf
    from jdrkf.experiments import wang_nonlinear as wn
    from jdrkf.experiments import wang_ye as wy

    def timed(f, *args):
        jax.block_until_ready(f(*args))
        ts = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            jax.block_until_ready(f(*args))
            ts.append(time.perf_counter() - t0)
        return float(np.median(ts))

    def vmapped(flt, model, prior, **kw):
        return jax.jit(jax.vmap(lambda *a: flt(model, prior, a[0], **{k: a[i + 1] for i, k in enumerate(kw)}).filtered_means))

    key = jax.random.key(0)
    model, p0 = wy.nominal_model(), wy.prior()
    ys = wy.scenario(key, 2000, 1.0, False, 200).observations
    ys_long = wy.scenario(key, 10_000, 0.0, False, 100).observations
    growth = wn.growth_models()["true"]
    gp = jdrkf.Gaussian(jnp.zeros(1), 5.0 * jnp.eye(1))
    gys = jdrkf.simulate(key, growth, gp, 100, 1000).observations
    drkf = jdrkf.DRKF(jdrkf.sets.Wasserstein(0.1), jdrkf.sets.Wasserstein(0.1), throw=False)
    pf = jdrkf.BootstrapPF(1000, resampling="systematic", throw=False)
    cases = {
        "DRKF(Wasserstein, Wasserstein), shared, 2000 runs × 200 steps": lambda: timed(vmapped(drkf, model, p0), ys),
        "DRKF(Wasserstein, Wasserstein), per-run `observed` mask, 200 × 200": lambda: timed(
            jax.jit(jax.vmap(lambda y, o: drkf(model, p0, y, observed=o).filtered_means)), ys[:200], jnp.ones(ys[:200].shape, bool)),
        "WassersteinKF(0.1), shared, 2000 × 200": lambda: timed(vmapped(jdrkf.WassersteinKF(0.1, throw=False), model, p0), ys),
        "SteadyStateDRKF(0.1, 0.1), 10⁴ × 100": lambda: timed(vmapped(jdrkf.SteadyStateDRKF(0.1, 0.1, throw=False), model, p0), ys_long),
        "KalmanFilter(square_root=True), 10⁴ × 100": lambda: timed(vmapped(jdrkf.KalmanFilter(square_root=True, throw=False), model, p0), ys_long),
        "HuberKF(0.05, 1.4), 10⁴ × 100": lambda: timed(vmapped(jdrkf.HuberKF(0.05, 1.4, throw=False), model, p0), ys_long),
        "UnscentedKF, growth model, 1000 × 100": lambda: timed(vmapped(jdrkf.UnscentedKF(throw=False), growth, gp), gys),
        "BootstrapPF(1000, systematic), growth model, 200 × 100": lambda: timed(
            jax.jit(jax.vmap(lambda y, k: pf(growth, gp, y, key=k).filtered_means)), gys[:200], jax.random.split(key, 200)),
    }
    return {name: case() for name, case in cases.items()}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--base", help="the earlier revision (any git revision name; required)")
    ap.add_argument("--head", default="HEAD")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--out", default=os.path.join(HERE, "results"))
    ap.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        print(json.dumps(child(args.repeats)))
        return None
    if args.base is None:
        ap.error("--base is required")

    sys.path.insert(0, HERE)
    from _provenance import cpu_model, loadavg, portable_path

    def rev(name):
        return subprocess.run(["git", "rev-parse", "--verify", f"{name}^{{commit}}"], cwd=ROOT, capture_output=True,
                              text=True, check=True).stdout.strip()

    revs = {"base": rev(args.base), "head": rev(args.head)}
    t0 = time.time()
    res = {"revisions": revs, "rounds": args.rounds, "repeats": args.repeats, "cpu": f"{cpu_model()}, {os.cpu_count()} cores",
           "loadavg_start": loadavg(), "times": {"base": [], "head": []}}
    with tempfile.TemporaryDirectory() as tmp:
        trees = {}
        for label, commit in revs.items():
            trees[label] = os.path.join(tmp, label)
            subprocess.run(["git", "worktree", "add", "--detach", "-f", trees[label], commit], cwd=ROOT, check=True,
                           capture_output=True)
        try:
            for r in range(args.rounds):
                for label in ("base", "head"):
                    env = dict(os.environ, PYTHONPATH=trees[label])
                    out = subprocess.run([sys.executable, os.path.abspath(__file__), "--child", "--repeats", str(args.repeats)],
                                         env=env, capture_output=True, text=True, check=True)
                    res["times"][label].append(json.loads(out.stdout.strip().splitlines()[-1]))
                    print(f"[{time.time() - t0:6.0f}s] round {r + 1} {label} done", flush=True)
        finally:
            for path in trees.values():
                subprocess.run(["git", "worktree", "remove", "--force", path], cwd=ROOT, capture_output=True)
    res["loadavg_end"] = loadavg()
    res["wall_s"] = time.time() - t0
    res["cases"] = {}
    for name in res["times"]["head"][0]:
        b = [t[name] for t in res["times"]["base"]]
        h = [t[name] for t in res["times"]["head"]]
        res["cases"][name] = {"base_median_s": statistics.median(b), "head_median_s": statistics.median(h),
                              "base_range_s": [min(b), max(b)], "head_range_s": [min(h), max(h)],
                              "head_over_base": statistics.median(h) / statistics.median(b)}
    os.makedirs(args.out, exist_ok=True)
    stem = os.path.join(args.out, "compare_revisions_cpu")
    with open(stem + ".json", "w") as f:
        json.dump(res, f, indent=1)
    with open(stem + ".md", "w") as f:
        f.write(render(res))
    print(f"wrote {portable_path(stem)}.md/.json")
    return res


def render(res) -> str:
    revs = res["revisions"]
    lines = [f"# Regression check: jdrkf at {revs['head'][:7]} (head) vs {revs['base'][:7]} (base), CPU", "",
             f"- Machine: {res['cpu']}; load average at start {res['loadavg_start']}, at end {res['loadavg_end']}; "
             f"wall {res['wall_s']:.0f} s.",
             f"- Each revision in its own process, alternating for {res['rounds']} rounds; per case the median of "
             f"{res['repeats']} calls after compilation, float64. Generated by `benchmarks/compare_revisions.py "
             f"--base {revs['base'][:7]} --head {revs['head'][:7]}`.", "",
             "| case | base ms (median over rounds, range) | head ms | head / base |", "|---|---:|---:|---:|"]
    for name, c in res["cases"].items():
        lines.append(f"| {name} | {c['base_median_s'] * 1e3:.2f} ({c['base_range_s'][0] * 1e3:.2f}–{c['base_range_s'][1] * 1e3:.2f}) | "
                     f"{c['head_median_s'] * 1e3:.2f} ({c['head_range_s'][0] * 1e3:.2f}–{c['head_range_s'][1] * 1e3:.2f}) | "
                     f"{c['head_over_base']:.2f} |")
    worse = [n for n, c in res["cases"].items() if c["head_over_base"] > 1.0 and c["head_range_s"][0] > c["base_range_s"][1]]
    lines += ["", "Slower at head beyond the round-to-round range (head's fastest round slower than base's slowest): "
              + ("; ".join(worse) if worse else "none") + "."]
    return "\n".join(lines) + "\n"


if __name__ == "__main__":
    main()
