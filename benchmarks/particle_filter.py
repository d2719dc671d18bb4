#!/usr/bin/env python
"""Bootstrap particle filter (Wang 2022, Sec. V growth model): jdrkf vs vectorized NumPy.

Model (Wang 2022, Sec. V; the authors' `[1] Time Series Example`):
`x_k = x/2 + 25x/(1 + x²) + 8 cos(1.2k) + w`, `y_k = x_k²/20 + v`, `Q = 10`, `R = 1`,
`x_0 ~ N(0, 1)`. `--runs` independent trajectories of `--steps` steps are simulated once
with NumPy (`--seed`) and fed to every implementation, in each `--dtype` (default: both
float64 and float32; the NumPy PF runs in the same dtype as the jdrkf rows it is compared to).

Rows:

1. `jdrkf <scheme>`: `jax.jit(jax.vmap(BootstrapPF(N, resampling=scheme), in_axes=(None, None, 0, 0)))`
   over runs and keys, for each resampling scheme (systematic = the default and the
   goal row; stratified, residual, multinomial). ESS threshold 0.5, weighted-mean estimate.
2. `numpy systematic`: the same algorithm in NumPy, vectorized over particles AND runs
   (arrays `(runs, N)`; systematic resampling of the rows whose ESS < 0.5 N by one flat
   `np.searchsorted` over row-offset cumulative weights).

3. `--sis` adds `jdrkf none (SIS)`: `ess_threshold=0` (no resampling code at all), to show
   what the resampling costs (under `vmap` it runs for every run and step, as a select).

Timing: compile s = first call − median call; run s = median wall time of `--repeats`
calls (`jax.block_until_ready`); NumPy: median of `--repeats` calls. On a shared machine
the wall time depends on the load, so the process CPU time of each call is recorded too
(`cpu s`, median; all threads of the process counted) and the speed-up is reported both
ways. Accuracy: RMSE over time
of each run vs the true states, mean and 95% CI over runs (`jdrkf.metrics.mean_ci`):
the rows must agree statistically (different random numbers).

Goal (CPU, `--platform cpu`, N = 1000, T = 100, 1000 runs, per dtype): jdrkf systematic
uses ≥ 2.5× less process CPU time than the NumPy PF (NumPy CPU s / jdrkf CPU s, both
measured with `time.process_time()` around the timed calls, in the same run). The
wall-time ratio is reported as an informative row (it also counts the second core
XLA uses, and the machine's load).

`--platform gpu` runs the jdrkf rows on a GPU (NumPy stays on the CPU; the CPU-time
goal is then not evaluated) and adds a GPU-scale row: systematic resampling with
`--gpu-particles` (default 1e4) particles × `--gpu-runs` (default 1e3) runs, T steps,
reported in particle-steps/s.

Usage:

    python benchmarks/particle_filter.py            # full run (N = 1000, T = 100, 1000 runs, both dtypes)
    python benchmarks/particle_filter.py --quick    # smoke run (a few seconds)
    python benchmarks/particle_filter.py --platform gpu --sis   # on a GPU, + the N = 1e4 x 1e3 runs row
    python benchmarks/particle_filter.py --dtype float32 --schemes systematic --sis
"""

from __future__ import annotations

import argparse
import datetime
import json
import math
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

Q, R, P0 = 10.0, 1.0, 1.0
GOAL_CPU_RATIO = 2.5  # NumPy process CPU s / jdrkf process CPU s
SCHEMES = ("systematic", "stratified", "residual", "multinomial")


def log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


def growth_f(x, k, cos):
    return x / 2 + 25 * x / (1 + x**2) + 8 * cos(1.2 * k)


def simulate(runs: int, steps: int, seed: int):
    rng = np.random.default_rng(seed)
    x = math.sqrt(P0) * rng.normal(size=runs)
    xs, ys = [], []
    for t in range(steps):
        x = growth_f(x, t + 1, np.cos) + math.sqrt(Q) * rng.normal(size=runs)
        xs.append(x)
        ys.append(x**2 / 20 + math.sqrt(R) * rng.normal(size=runs))
    return np.stack(xs, 1), np.stack(ys, 1)  # (runs, T)


# --------------------------------------------------------------------------- NumPy PF


def numpy_pf(ys: np.ndarray, n: int, seed: int, threshold: float = 0.5, dtype=np.float64) -> np.ndarray:
    """Bootstrap PF over all runs at once; returns the weighted-mean estimates `(runs, T)`."""
    rng = np.random.default_rng(seed)
    runs, steps = ys.shape
    ys = ys.astype(dtype)
    x = (math.sqrt(P0) * rng.standard_normal((runs, n))).astype(dtype)
    lw = np.full((runs, n), -math.log(n), dtype)
    ar = np.arange(n, dtype=dtype)
    log_norm = dtype(0.5 * math.log(2 * math.pi * R))
    est = np.empty((runs, steps), dtype)
    for t in range(steps):
        x = growth_f(x, dtype(t + 1), np.cos) + dtype(math.sqrt(Q)) * rng.standard_normal((runs, n), dtype=dtype)
        resid = ys[:, t, None] - x * x / 20
        a = lw - 0.5 * resid * resid / dtype(R) - log_norm
        amax = a.max(axis=1, keepdims=True)
        inc = amax + np.log(np.exp(a - amax).sum(axis=1, keepdims=True))
        lw = a - inc
        w = np.exp(lw)
        est[:, t] = (w * x).sum(axis=1)
        ess = 1.0 / (w * w).sum(axis=1)
        rows = np.nonzero(ess < threshold * n)[0]
        if rows.size:
            c = np.minimum(np.cumsum(w[rows], axis=1), 1.0)
            c[:, -1] = 1.0
            off = 2.0 * np.arange(rows.size, dtype=dtype)[:, None]  # keeps the flat array sorted
            u = (ar[None, :] + rng.random((rows.size, 1), dtype=dtype)) / n
            pos = np.searchsorted((c + off).ravel(), (u + off).ravel(), side="right").reshape(rows.size, n)
            idx = np.clip(pos - np.arange(rows.size)[:, None] * n, 0, n - 1)
            x[rows] = np.take_along_axis(x[rows], idx, axis=1)
            lw[rows] = -math.log(n)
    return est


# --------------------------------------------------------------------------- jdrkf


def _time_calls(fn, repeats):
    """Median/min wall and median process-CPU seconds of `repeats` calls of `fn()`."""
    wall, cpu = [], []
    for _ in range(repeats):
        t0, c0 = time.perf_counter(), time.process_time()
        fn()
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return statistics.median(wall), min(wall), statistics.median(cpu)


def bench_jdrkf(args, ys, states, dtype_name, particles=None, configs=None, label="jdrkf"):
    import equinox as eqx
    import jax
    import jax.numpy as jnp

    import jdrkf
    from jdrkf._nonlinear import NonlinearModel
    from jdrkf.filters._particle import BootstrapPF

    dtype = jnp.float64 if dtype_name == "float64" else jnp.float32

    def f(x, t):
        return x / 2 + 25 * x / (1 + x**2) + 8 * jnp.cos(1.2 * (t + 1).astype(x.dtype))

    def h(x, t):
        return x**2 / 20

    model = NonlinearModel(f, h, jnp.array([[Q]], dtype), jnp.array([[R]], dtype))
    prior = jdrkf.Gaussian(jnp.zeros(1, dtype), jnp.full((1, 1), P0, dtype))
    ys_j = jnp.asarray(ys[..., None], dtype)
    keys = jax.random.split(jax.random.key(args.seed + 1), ys.shape[0])
    rows = []
    particles = particles or args.particles
    if configs is None:
        configs = [(scheme, 0.5) for scheme in args.schemes] + ([("none (SIS)", 0.0)] if args.sis else [])
    for scheme, threshold in configs:
        opts = {"resampling": scheme} if threshold > 0 else {}
        pf = BootstrapPF(particles, ess_threshold=threshold, throw=False, **opts)
        fn = eqx.filter_jit(jax.vmap(lambda m, p, y, k, pf=pf: pf(m, p, y, k).filtered_means[..., 0],
                                     in_axes=(None, None, 0, 0)))
        t0 = time.perf_counter()
        est = np.asarray(jax.block_until_ready(fn(model, prior, ys_j, keys)))
        first = time.perf_counter() - t0
        run_s, min_s, cpu_s = _time_calls(lambda fn=fn: jax.block_until_ready(fn(model, prior, ys_j, keys)), args.repeats)
        row = {"impl": label, "scheme": scheme, "dtype": dtype_name, "particles": particles, "runs": ys.shape[0],
               "steps": ys.shape[1], "run_s": run_s, "min_s": min_s, "cpu_s": cpu_s,
               "compile_s": first - run_s, "particle_steps_per_s": particles * ys.size / run_s, **accuracy(states, est)}
        log(f"  {label} {scheme} {dtype_name} (N={particles}, {ys.shape[0]} runs): {run_s:.3g} s wall, {cpu_s:.3g} s CPU "
            f"(compile {first - run_s:.2g} s), {row['particle_steps_per_s']:.3g} particle-steps/s, "
            f"RMSE {row['rmse_mean']:.3f}")
        rows.append(row)
    return rows


def accuracy(states, est) -> dict:
    import jdrkf

    r = np.sqrt(np.mean((states - est) ** 2, axis=1))
    mean, (lo, hi) = jdrkf.metrics.mean_ci(r, 0.95)
    return {"rmse_mean": float(mean), "rmse_ci95": [float(lo), float(hi)], "finite": bool(np.all(np.isfinite(est)))}


# --------------------------------------------------------------------------- report


def build_markdown(r) -> str:
    c, m = r["config"], r["meta"]
    L = [f"# Bootstrap particle filter ({c.get('platform', 'cpu').upper()}): jdrkf vs NumPy "
         f"({'quick' if c['quick'] else 'full'} run)", "",
         f"Growth model of Wang 2022 (Q = {Q:g}, R = {R:g}), N = {c['particles']} particles, T = {c['steps']}, "
         f"{c['runs']} runs, dtypes {', '.join(c['dtype'])}. JAX device: {m.get('device')} ({', '.join(m['jax_devices'])}, "
         f"backend {m['jax_backend']}); NumPy on the CPU. CPU: {m['cpu_model']} ({m['cpu_affinity']} usable cores), "
         f"load {m['loadavg']['start']} → {m['loadavg']['end']}. jax {m['versions'].get('jax')}, "
         f"numpy {m['versions'].get('numpy')}. Source {m['jdrkf_source_sha256']} (git {m['git']['commit']}, "
         f"dirty {m['git']['jdrkf_dirty']}).", "",
         "Wall times depend on the machine's load (shared machine); `CPU s` is the process CPU time of a call "
         "(median), less sensitive to it.", "",
         "| implementation | resampling | dtype | run s (median) | CPU s | compile s | particle-steps/s | "
         "speed-up vs NumPy (wall) | speed-up (CPU) | RMSE (mean, 95% CI) |",
         "|---|---|---|---|---|---|---|---|---|---|"]
    for x in r["rows"]:
        work = x.get("particles", c["particles"]) * x.get("steps", c["steps"]) * x.get("runs", c["runs"])
        np_row = next((y for y in r["rows"] if y["impl"] == "numpy" and y["dtype"] == x["dtype"]), None)
        if x.get("particles", c["particles"]) != c["particles"] or x.get("runs", c["runs"]) != c["runs"]:
            np_row = None  # the GPU-scale row: another problem size
        sp = f"{np_row['run_s'] / x['run_s']:.2f}×" if np_row else "–"
        sp_cpu = f"{np_row['cpu_s'] / x['cpu_s']:.2f}×" if np_row else "–"
        comp = f"{x['compile_s']:.2f}" if x.get("compile_s") is not None else "–"
        impl = x["impl"] if np_row or x["impl"] == "numpy" else f"{x['impl']} (N = {x['particles']}, {x['runs']} runs)"
        L.append(f"| {impl} | {x['scheme']} | {x['dtype']} | {x['run_s']:.3g} | {x['cpu_s']:.3g} | {comp} | "
                 f"{work / x['run_s']:.3g} | {sp} | {sp_cpu} | "
                 f"{x['rmse_mean']:.3f} [{x['rmse_ci95'][0]:.3f}, {x['rmse_ci95'][1]:.3f}] |")
    L += ["", "## Goals", ""]
    for informative in (False, True):
        if informative and any(g.get("informative") for g in r["goals"]):
            L += ["", "Informative (not goals):", ""]
        for g in r["goals"]:
            if bool(g.get("informative")) != informative:
                continue
            verdict = "not evaluated" if g["met"] is None else ("met" if g["met"] else "not met")
            L.append(f"- {g['goal']}: {g['detail']}" if informative else f"- {g['goal']}: **{verdict}** — {g['detail']}")
    L.append("")
    return "\n".join(L)


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--quick", action="store_true", help="smoke run: 50 runs, T = 50, 2 repeats")
    p.add_argument("--particles", type=int, default=1000)
    p.add_argument("--steps", type=int, default=None, help="T (default 100; 50 with --quick)")
    p.add_argument("--runs", type=int, default=None, help="independent runs (default 1000; 50 with --quick)")
    p.add_argument("--repeats", type=int, default=3)
    p.add_argument("--schemes", nargs="+", default=list(SCHEMES), choices=SCHEMES)
    p.add_argument("--dtype", nargs="+", choices=("float64", "float32"), default=["float64", "float32"],
                   help="dtype(s) of the jdrkf and NumPy rows (default: both)")
    p.add_argument("--sis", action="store_true", help="add a jdrkf row without resampling (ess_threshold=0)")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--platform", choices=["cpu", "gpu"], default="cpu", help="JAX platform of the jdrkf rows (NumPy: CPU)")
    p.add_argument("--gpu-particles", type=int, default=None, help="N of the GPU-scale row (default 1e4; 1e3 with --quick)")
    p.add_argument("--gpu-runs", type=int, default=None, help="runs of the GPU-scale row (default 1e3; 100 with --quick)")
    p.add_argument("--out", default=os.path.join(HERE, "results"))
    p.add_argument("--tag", default=None, help="output file stem suffix (default the platform, '_quick' appended with --quick)")
    args = p.parse_args(argv)
    args.steps = args.steps or (50 if args.quick else 100)
    args.runs = args.runs or (50 if args.quick else 1000)
    if args.quick:
        args.repeats = min(args.repeats, 2)
    args.gpu_particles = args.gpu_particles or (1000 if args.quick else 10_000)
    args.gpu_runs = args.gpu_runs or (100 if args.quick else 1000)
    if args.tag is None:
        args.tag = args.platform + ("_quick" if args.quick else "")

    set_platform(args.platform)
    import jax

    if "float64" in args.dtype:
        jax.config.update("jax_enable_x64", True)
    t_start = time.perf_counter()
    meta = {"cpu_model": cpu_model(), "cpu_count": os.cpu_count(),
            "cpu_affinity": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None,
            "platform": platform.platform(), "versions": versions(), "git": git_info(),
            "jdrkf_source_sha256": package_source_hash(), "jax_devices": [str(d) for d in jax.devices()],
            "device": device_summary(jax),
            "jax_backend": jax.default_backend(), "XLA_FLAGS": os.environ.get("XLA_FLAGS"),
            "PJRT_NPROC": os.environ.get("PJRT_NPROC"),
            "loadavg": {"start": loadavg()}}
    log(f"particle_filter: N={args.particles} T={args.steps} runs={args.runs} {args.dtype}, load {meta['loadavg']['start']}")
    states, ys = simulate(args.runs, args.steps, args.seed)
    rows, goals = [], []
    for dtype_name in args.dtype:
        jrows = bench_jdrkf(args, ys, states, dtype_name)
        dtype = np.float64 if dtype_name == "float64" else np.float32
        est = None

        def call(dtype=dtype):
            nonlocal est
            est = numpy_pf(ys, args.particles, args.seed + 2, dtype=dtype)

        run_s, min_s, cpu_s = _time_calls(call, args.repeats)
        np_row = {"impl": "numpy", "scheme": "systematic", "dtype": dtype_name, "run_s": run_s, "min_s": min_s,
                  "cpu_s": cpu_s, "compile_s": None, **accuracy(states, est)}
        log(f"  numpy systematic {dtype_name}: {run_s:.3g} s wall, {cpu_s:.3g} s CPU, RMSE {np_row['rmse_mean']:.3f}")
        rows += jrows + [np_row]
        sys_row = next((x for x in jrows if x["scheme"] == "systematic"), None)
        if sys_row is not None:
            ratio = np_row["run_s"] / sys_row["run_s"]
            ratio_cpu = np_row["cpu_s"] / sys_row["cpu_s"]
            # a quick run (50 runs, T = 50) is not the goal's setting, and the goal is the CPU's: not evaluated
            why = ("quick run, not the goal's setting" if args.quick
                   else "GPU run: the goal is for --platform cpu" if args.platform != "cpu" else None)
            goals.append({"goal": f"jdrkf systematic uses ≥ {GOAL_CPU_RATIO:g}× less process CPU time than the vectorized "
                                  f"NumPy PF ({dtype_name})",
                          "met": None if why else ratio_cpu >= GOAL_CPU_RATIO,
                          "ratio_cpu": ratio_cpu, "ratio": ratio, "dtype": dtype_name,
                          "detail": f"{ratio_cpu:.2f}× (NumPy {np_row['cpu_s']:.3g} CPU s / jdrkf {sys_row['cpu_s']:.3g} CPU s "
                                    "per call, median)" + (f" — {why}" if why else "")})
            goals.append({"goal": f"wall time, jdrkf systematic vs the vectorized NumPy PF ({dtype_name})", "met": None,
                          "informative": True, "ratio": ratio, "dtype": dtype_name,
                          "detail": f"{ratio:.2f}× ({sys_row['run_s']:.3g} s vs {np_row['run_s']:.3g} s, medians)"})
            lo = max(sys_row["rmse_ci95"][0], np_row["rmse_ci95"][0])
            hi = min(sys_row["rmse_ci95"][1], np_row["rmse_ci95"][1])
            goals.append({"goal": f"jdrkf and NumPy RMSE agree (95% CIs overlap, {dtype_name})", "met": lo <= hi,
                          "dtype": dtype_name,
                          "detail": f"jdrkf {sys_row['rmse_mean']:.3f}, NumPy {np_row['rmse_mean']:.3f}"})
    if args.platform == "gpu":  # the GPU-scale row: N = 1e4 particles x 1e3 runs (no NumPy counterpart)
        g_states, g_ys = simulate(args.gpu_runs, args.steps, args.seed)
        for dtype_name in args.dtype:
            grow = bench_jdrkf(args, g_ys, g_states, dtype_name, particles=args.gpu_particles,
                               configs=[("systematic", 0.5)], label="jdrkf GPU scale")[0]
            rows.append(grow)
            goals.append({"goal": f"GPU scale: systematic, N = {args.gpu_particles}, {args.gpu_runs} runs, T = {args.steps} "
                                  f"({dtype_name})", "met": None, "informative": True, "dtype": dtype_name,
                          "particle_steps_per_s": grow["particle_steps_per_s"],
                          "detail": f"{grow['particle_steps_per_s']:.3g} particle-steps/s ({grow['run_s']:.3g} s per call, "
                                    f"compile {grow['compile_s']:.2g} s; RMSE {grow['rmse_mean']:.3f})"})
    meta["loadavg"]["end"] = loadavg()

    config = {k: v for k, v in vars(args).items() if k != "out"}
    result = {"benchmark": "particle_filter",
              "created": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
              "command": " ".join([os.path.basename(sys.executable), os.path.relpath(os.path.abspath(__file__), ROOT)] + argv),
              "wall_s": time.perf_counter() - t_start, "config": config, "meta": meta, "rows": rows, "goals": goals}
    md = build_markdown(result)
    os.makedirs(args.out, exist_ok=True)
    stem = os.path.join(args.out, f"particle_filter_{args.tag}")
    with open(stem + ".json", "w") as f:
        json.dump(result, f, indent=2, default=float)
    with open(stem + ".md", "w") as f:
        f.write(md)
    print(md)
    log(f"wrote {stem}.json and {stem}.md ({result['wall_s']:.0f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
