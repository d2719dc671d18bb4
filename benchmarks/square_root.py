#!/usr/bin/env python
"""Square-root vs covariance form in float32 on ill-conditioned systems (issue 21, item 3).

Systems (NumPy RNG seeded by `--seed` + system index): state dimension `n`, one
measurement with `R = 1e-2`, prior `N(0, I)`, process noise `Q = diag(1, …, 1/c)`
(log-spaced, `cond(Q) = c`) in noise coordinates, mapped by `G`, and two families:

- `rotated`: `G` a random rotation and `F = G diag(0.99 … 0.999) Gᵀ` (the least
  excited direction is the slowest): the ill-conditioning of `G Q Gᵀ` and of the
  covariances is not aligned with the coordinates.
- `aligned` (control): `G = I`, `F = diag(0.99 … 0.999)`: graded, axis-aligned
  ill-conditioning, which floating point represents entry by entry.

All entries are rounded to float32 first, so float32 and float64 runs filter the same
model. Data: one simulated run of `--steps` steps (float64, rounded to float32).

Filters, each in the covariance form and with `square_root=True`: `KalmanFilter` and
`DRKF(Moment(1.001), Moment(1.1))` (moment sets: the worst case is a factor in closed
form). Reference: the float64 covariance form of the same filter (the KF's is tested
against a NumPy Kalman filter); the float64 square-root form is compared with it too.

Errors of the float32 runs against the reference, maxima over the `T` steps:

- `cov`: `‖P̂ − P‖_F / ‖P‖_F` (normwise relative error of the filtered covariance);
- `dir`: `‖P^{-½}(P̂ − P)P^{-½}‖₂`, the relative error of the filtered variance in the
  worst direction (what an ill-conditioned covariance loses first);
- `mean`: `‖m̂ − m‖ / max_t ‖m‖` (filtered means).

Timing: `µs/step` of one jitted float32 run (median of `--repeats` calls after the
compiling one, `jax.block_until_ready`); on a loaded machine, indicative only.

Goals (rotated family, `cond(Q)` up to 1e8, `T = 1e5`): the square-root KF's `cov` and
`mean` errors ≤ 1e-3 on every system; per `cond(Q)`, the covariance form's `cov` and `dir`
errors larger than the square-root form's on every system (with the counts of systems
where they are, and where the covariance form's `cov` exceeds 1e-3).

Usage:

    python benchmarks/square_root.py                        # full run: results/square_root_cpu.{md,json}
    python benchmarks/square_root.py --quick --out smoke/sr  # smoke run (T = 2000, one system per cell)
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

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(HERE)
sys.path.insert(0, HERE)

from _provenance import cpu_model, device_summary, git_info, loadavg, package_source_hash, set_platform, versions  # noqa: E402

GOAL_REL = 1e-3
GOAL_COND = 1e8
GOAL_STEPS = 100_000


def log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def system(family: str, n: int, cond: float, seed: int):
    """`(F, H, Q, R, G)` of the module docstring, rounded to float32 (as float64 arrays)."""
    rng = np.random.default_rng(seed)
    g = np.linalg.qr(rng.normal(size=(n, n)))[0] if family == "rotated" else np.eye(n)
    f = g @ np.diag(np.linspace(0.99, 0.999, n)) @ g.T
    q = np.diag(np.logspace(0.0, -np.log10(cond), n))
    h, r = rng.normal(size=(1, n)), np.array([[1e-2]])
    return tuple(np.asarray(x, np.float32).astype(np.float64) for x in (f, h, q, r, g))


def errors(p, m, p_ref, m_ref) -> dict:
    """`cov`, `dir` and `mean` of the module docstring (`dir` is NaN when a reference
    covariance is not numerically positive definite)."""
    try:
        whiten = np.linalg.inv(np.linalg.cholesky(p_ref))
        rel_dir = float(np.max(np.linalg.norm(whiten @ (p - p_ref) @ np.swapaxes(whiten, 1, 2), ord=2, axis=(1, 2))))
    except np.linalg.LinAlgError:
        rel_dir = float("nan")
    with np.errstate(invalid="ignore"):
        return {
            "cov": float(np.max(np.linalg.norm(p - p_ref, axis=(1, 2)) / np.linalg.norm(p_ref, axis=(1, 2)))),
            "dir": rel_dir,
            "mean": float(np.max(np.linalg.norm(m - m_ref, axis=1)) / np.max(np.linalg.norm(m_ref, axis=1))),
        }


_COMPILED = {}


def run_case(jax, jnp, jdrkf, sysm, ys, args) -> list[dict]:
    from jdrkf.sets import Moment

    f, h, q, r, g = sysm
    n = f.shape[0]
    makers = {  # fading memory on the prior (√θ₂ · 0.999 < 1 keeps the slowest mode stable), moment noise set
        "KF": lambda sq: jdrkf.KalmanFilter(square_root=sq, throw=False),
        "DRKF-moment": lambda sq: jdrkf.DRKF(Moment(1.001), Moment(1.1), square_root=sq, throw=False),
    }

    def filt(name, sq, dtype):
        """The jitted run (compiled once per filter, form and shapes) and its arguments."""
        c = lambda a: jnp.asarray(a, dtype)  # noqa: E731
        model = jdrkf.LinearModel(c(f), c(h), c(q), c(r), G=c(g))
        prior = jdrkf.Gaussian(c(np.zeros(n)), c(np.eye(n)))
        if (name, sq) not in _COMPILED:
            flt = makers[name](sq)
            _COMPILED[name, sq] = jax.jit(lambda mdl, pr, y: flt(mdl, pr, y))
        fn = _COMPILED[name, sq]
        return lambda y: fn(model, prior, y), c(ys)

    rows = []
    for name in makers:
        ref_fn, ys64 = filt(name, False, jnp.float64)
        ref = ref_fn(ys64)
        p_ref, m_ref = np.asarray(ref.filtered_covariances), np.asarray(ref.filtered_means)
        sq64 = filt(name, True, jnp.float64)[0](ys64)
        f64_diff = float(np.max(np.abs(np.asarray(sq64.filtered_covariances) - p_ref)) / np.max(np.abs(p_ref)))
        for form, sq in (("covariance", False), ("square_root", True)):
            fn, ys32 = filt(name, sq, jnp.float32)
            res = jax.block_until_ready(fn(ys32))
            times = []
            for _ in range(args.repeats):
                t0 = time.perf_counter()
                jax.block_until_ready(fn(ys32))
                times.append(time.perf_counter() - t0)
            err = errors(np.asarray(res.filtered_covariances, np.float64), np.asarray(res.filtered_means, np.float64), p_ref, m_ref)
            rows.append({"filter": name, "form": form, **err, "result": str(res.result).split("<")[-1].rstrip(">") or "successful",
                         "us_per_step": 1e6 * statistics.median(times) / ys.shape[0], "float64_sqrt_vs_cov": f64_diff})
    return rows


def build_markdown(result) -> str:
    c, m = result["config"], result["meta"]
    L = ["# Square-root vs covariance form, float32 (benchmarks/square_root.py)", "",
         f"`{result['command']}` — {result['created']}, {m['device']}, {m['cpu_model']} ({m['cpu_count']} CPUs), "
         f"load {m['loadavg']['start']}, jax {m['versions'].get('jax')}, commit {m['git']['commit']} "
         f"(jdrkf dirty: {m['git']['jdrkf_dirty']}), source sha {m['jdrkf_source_sha256']}.", "",
         f"T = {c['steps']} steps, seeds {c['seed']}…{c['seed'] + c['systems'] - 1} per cell. Errors of the float32 run "
         "against the float64 covariance form (maxima over the steps): `cov` = ‖P̂ − P‖_F/‖P‖_F, `dir` = "
         "‖P^{-½}(P̂ − P)P^{-½}‖₂ (relative variance error in the worst direction), `mean` = ‖m̂ − m‖/max‖m‖. "
         "`f64` = max |P_sqrt − P_cov| / max |P| of the two float64 forms.", "",
         "| family | n | cond(Q) | seed | filter | form | cov | dir | mean | result | µs/step | f64 |",
         "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for row in result["rows"]:
        L.append(f"| {row['family']} | {row['n']} | {row['cond']:.0e} | {row['seed']} | {row['filter']} | {row['form']} | "
                 f"{row['cov']:.2e} | {row['dir']:.2e} | {row['mean']:.2e} | {row['result']} | {row['us_per_step']:.2f} | "
                 f"{row['float64_sqrt_vs_cov']:.1e} |")
    L += ["", "## Summary (maxima over the systems of each cell)", "",
          "| family | filter | cond(Q) | form | max cov | max dir | max mean |", "|---|---|---|---|---|---|---|"]
    for s in result["summary"]:
        L.append(f"| {s['family']} | {s['filter']} | {s['cond']:.0e} | {s['form']} | {s['cov']:.2e} | {s['dir']:.2e} | {s['mean']:.2e} |")
    L += ["", "## Goals", ""]
    for g in result["goals"]:
        verdict = "not evaluated" if g["met"] is None else ("met" if g["met"] else "not met")
        L.append(f"- {g['goal']}: **{verdict}** — {g['detail']}")
    L.append("")
    return "\n".join(L)


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--quick", action="store_true", help="smoke run: T = 2000, one system per cell, one repeat")
    p.add_argument("--steps", type=int, default=None, help=f"T (default {GOAL_STEPS}; 2000 with --quick)")
    p.add_argument("--systems", type=int, default=None, help="systems per (family, n, cond) cell (default 3; 1 with --quick)")
    p.add_argument("--sizes", type=int, nargs="+", default=[2, 4], help="state dimensions n")
    p.add_argument("--conds", type=float, nargs="+", default=[1e4, 1e6, 1e8], help="cond(Q) values")
    p.add_argument("--families", nargs="+", default=["rotated", "aligned"], choices=["rotated", "aligned"])
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--platform", choices=["cpu", "gpu"], default="cpu")
    p.add_argument("--out", default=os.path.join(HERE, "results"))
    p.add_argument("--tag", default=None, help="output file stem suffix (default the platform, '_quick' appended with --quick)")
    args = p.parse_args(argv)
    args.steps = args.steps or (2000 if args.quick else GOAL_STEPS)
    args.systems = args.systems or (1 if args.quick else 3)
    if args.quick:
        args.repeats = 1
    if args.tag is None:
        args.tag = args.platform + ("_quick" if args.quick else "")

    set_platform(args.platform)
    import jax
    import jax.numpy as jnp

    import jdrkf

    jax.config.update("jax_enable_x64", True)  # float64 references; the compared runs are float32
    t_start = time.perf_counter()
    meta = {"cpu_model": cpu_model(), "cpu_count": os.cpu_count(), "platform": platform.platform(), "versions": versions(),
            "git": git_info(), "jdrkf_source_sha256": package_source_hash(), "device": device_summary(jax),
            "loadavg": {"start": loadavg()}}
    rows = []
    for family in args.families:
        for n in args.sizes:
            for cond in args.conds:
                for i in range(args.systems):
                    seed = args.seed + i
                    sysm = system(family, n, cond, seed)
                    f, h, q, r, g = sysm
                    model = jdrkf.LinearModel(f, h, q, r, G=g)
                    prior = jdrkf.Gaussian(np.zeros(n), np.eye(n))
                    ys = np.asarray(jdrkf.simulate(jax.random.key(seed), model, prior, args.steps, 1).observations[0], np.float32)
                    for row in run_case(jax, jnp, jdrkf, sysm, ys.astype(np.float64), args):
                        rows.append({"family": family, "n": n, "cond": cond, "seed": seed, **row})
                        log(f"{family} n={n} cond={cond:.0e} seed={seed} {row['filter']:11s} {row['form']:11s} "
                            f"cov {row['cov']:.2e} dir {row['dir']:.2e} mean {row['mean']:.2e} {row['result']} "
                            f"{row['us_per_step']:.2f} us/step")
    summary = []
    for family in args.families:
        for name in ("KF", "DRKF-moment"):
            for cond in args.conds:
                for form in ("covariance", "square_root"):
                    sel = [x for x in rows if (x["family"], x["filter"], x["cond"], x["form"]) == (family, name, cond, form)]
                    if sel:
                        summary.append({"family": family, "filter": name, "cond": cond, "form": form,
                                        **{k: max(x[k] for x in sel) for k in ("cov", "dir", "mean")}})
    goals = []
    kf = [x for x in rows if x["family"] == "rotated" and x["filter"] == "KF" and x["cond"] <= GOAL_COND]
    if kf:
        pairs = {}
        for x in kf:
            pairs.setdefault((x["n"], x["cond"], x["seed"]), {})[x["form"]] = x
        why = "quick run, not the goal's horizon" if args.steps < GOAL_STEPS else None
        sq_ok = all(v["square_root"]["cov"] <= GOAL_REL and v["square_root"]["mean"] <= GOAL_REL
                    and v["square_root"]["result"] == "successful" for v in pairs.values())
        worst = max(max(v["square_root"]["cov"], v["square_root"]["mean"]) for v in pairs.values())
        goals.append({"goal": f"rotated family, cond(Q) ≤ {GOAL_COND:.0e}: the square-root KF in float32 within {GOAL_REL:g} "
                              "of float64 (`cov` and `mean`) on every system",
                      "met": None if why else bool(sq_ok),
                      "detail": f"worst square-root `cov`/`mean` error {worst:.2e} over {len(pairs)} systems"
                                + (f" — {why}" if why else "")})
        for cond in sorted({k[1] for k in pairs}):
            cell = [v for k, v in pairs.items() if k[1] == cond]
            count = lambda key, cell=cell: sum(v["covariance"][key] > v["square_root"][key] for v in cell)  # noqa: E731
            over = sum(v["covariance"]["cov"] > GOAL_REL for v in cell)
            further = count("cov") == len(cell) and count("dir") == len(cell)
            goals.append({"goal": f"rotated family, cond(Q) = {cond:.0e}: the covariance form's float32 errors larger than the "
                                  "square-root form's (`cov` and `dir`) on every system",
                          "met": None if why else bool(further),
                          "detail": f"larger on {count('cov')}/{len(cell)} systems in `cov`, {count('dir')}/{len(cell)} in `dir`, "
                                    f"{count('mean')}/{len(cell)} in `mean`; covariance-form `cov` above {GOAL_REL:g} on "
                                    f"{over}/{len(cell)}; max `dir`: covariance {max(v['covariance']['dir'] for v in cell):.2e}, "
                                    f"square root {max(v['square_root']['dir'] for v in cell):.2e}" + (f" — {why}" if why else "")})
    meta["loadavg"]["end"] = loadavg()
    config = {k: v for k, v in vars(args).items() if k != "out"}
    result = {"benchmark": "square_root", "created": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
              "command": " ".join([os.path.basename(sys.executable), os.path.relpath(os.path.abspath(__file__), ROOT)] + argv),
              "wall_s": time.perf_counter() - t_start, "config": config, "meta": meta, "rows": rows, "summary": summary,
              "goals": goals}
    md = build_markdown(result)
    os.makedirs(args.out, exist_ok=True)
    stem = os.path.join(args.out, f"square_root_{args.tag}")
    with open(stem + ".json", "w") as f:
        json.dump(result, f, indent=2, default=float)
    with open(stem + ".md", "w") as f:
        f.write(md)
    print(md)
    log(f"wrote {stem}.json and {stem}.md ({result['wall_s']:.0f} s)")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
