#!/usr/bin/env python
"""Tuning three or more filter hyper-parameters jointly: gradient (optax Adam through
`jdrkf.tuning.fit`) vs a full grid (`jdrkf.tuning.grid_search`) vs random search, one
scenario per paper, tuned on training runs and scored on held-out runs.

Scenarios (each tunes three parameters jointly; the systems are the experiments' own):

- `wang-ye`: `DRKF(Wasserstein(θx), Wasserstein(θv), EpsContamination(ε))` on Wang & Ye's
  system with model uncertainty (α = 1) and 5 % outliers of magnitude 100; mean RMSE.
- `li`: `STKF_AR1` (Li et al., Algorithm 2) with the measurement channels' initial `ν`,
  `τ²` and forgetting `ρ` on the torsion system, case y3 (replacement outliers on a
  slowly varying noise level); mean RMSE.
- `chen`: `MarginalDRKF(MarginalKL(c))` with one KL radius per sensor (3 sensors) on
  Chen et al.'s correlated-sensor fusion problem (text settings); mean squared error.
- `wang2022`: `DRParticleFilter` (Wang 2022) on the growth model with the mismatched
  measurement: Wasserstein prior radius (Method 1), likelihood inflation θ (Method 3) and
  the outlier threshold ε (Method 6, "drop"); mean RMSE, common random numbers (fixed
  key per run; resampling differentiated by the stop-gradient score estimator).
- `jang`: `SteadyStateDRKF(θx, θv)` on Jang et al.'s closed-loop LQR tracking problem
  (Gaussian setting) with per-run EM nominal covariances multiplied by a tuned scale `s`;
  mean closed-loop LQR cost.

Methods, all from the same start (the filter's default values) and on the same training runs:

(a) gradient: `tuning.fit` with Adam, a convergence test and a few jittered restarts;
(b) grid: `tuning.grid_search` over `k` points per axis (`k³` evaluations), for each `k`
    in `--grid-k` (the largest grid is the reference);
(c) random search: uniform (log-uniform for scale parameters) samples in the grid's box,
    as many forward evaluations as (a) costs.

Cost unit: forward-filter-equivalents = one evaluation of the training objective. A
value-and-gradient counts as its measured time over the forward time (median of 3 calls
each, after compilation). Wall times include compilation. The held-out error of each
method is the objective on runs simulated with another key. Goal (issue 20): gradient's
held-out error ≤ 1.02 × the largest grid's, at ≥ 10× fewer forward-equivalents, in ≥ 4
of 5 scenarios. Diagnostics per scenario (always reported, to explain a miss): the
gradient at the start vs central finite differences, the number of strict local minima
of the training loss on the grid, the relative spread of the grid's training losses,
and the spread of the restarts' final losses.

Usage:

    python benchmarks/tuning.py            # full run (~15 min on 2 cores)
    python benchmarks/tuning.py --quick    # smoke run (< 2 min): small data, k ∈ {2, 3}, few steps
    python benchmarks/tuning.py --scenarios wang-ye chen
"""

from __future__ import annotations

import argparse
import dataclasses
import datetime
import json
import os
import platform
import sys
import time
from collections.abc import Callable

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
sys.path.insert(0, HERE)

from _provenance import (
    cpu_model,
    device_summary,
    git_info,
    loadavg,
    package_source_hash,
    portable_path,
    set_platform,
    versions,
)

GOAL_RATIO = 1.02
GOAL_COST = 10.0


def log(msg: str) -> None:
    print(msg, file=sys.stderr, flush=True)


@dataclasses.dataclass
class Scenario:
    name: str
    paper: str
    description: str
    names: tuple[str, ...]
    start: tuple[float, ...]
    bounds: list[tuple[float, float | None]]
    axes: list[tuple[float, float, bool]]  # grid box per axis: (low, high, log-spaced)
    loss: Callable  # loss(values_tuple, data) -> scalar
    data: Callable  # data(key, runs) -> pytree
    lr: float
    metric: str


# --------------------------------------------------------------------------- scenarios


def _scenarios(quick: bool) -> dict[str, Scenario]:
    import jax
    import jax.numpy as jnp

    import jdrkf
    from jdrkf.experiments import (
        chen_fusion,
        jang,
        li_variational,
        wang_nonlinear,
        wang_ye,
    )
    from jdrkf.sets import EpsContamination, MarginalKL, Wasserstein

    def rmse(states, means):
        return jnp.mean(jdrkf.metrics.rmse(states, means))

    # Wang & Ye (2022): Wasserstein DR filter with ε-contamination outliers.
    wy_model, wy_prior = wang_ye.nominal_model(), wang_ye.prior()

    def wy_loss(v, tr):
        flt = jdrkf.DRKF(state_set=Wasserstein(v[0]), noise_set=Wasserstein(v[1]), outliers=EpsContamination(v[2]), throw=False)
        return rmse(tr.states, jax.vmap(lambda y: flt(wy_model, wy_prior, y).filtered_means)(tr.observations))

    def wy_data(key, runs):
        return wang_ye.scenario(key, runs, 1.0, True, 100 if quick else 200)

    # Li et al.: STKF-AR1, measurement channels' initial ν, τ² and forgetting ρ.
    li_model, li_prior = li_variational.torsion_model(), li_variational.torsion_prior()

    def li_loss(v, tr):
        flt = jdrkf.STKF_AR1(nu_y=v[0], tau2_y=v[1], rho_y=v[2], throw=False)
        return rmse(tr.states, jax.vmap(lambda y: flt(li_model, li_prior, y).filtered_means)(tr.observations))

    def li_data(key, runs):
        return li_variational.torsion_scenario(key, "y3", runs, 100 if quick else 400)

    # Chen et al.: marginal KL DR filter, one radius per sensor.
    ch_model, ch_true, ch_prior = chen_fusion.scenario("paper")
    ch_x0 = jdrkf.Gaussian(jnp.zeros(3), jnp.zeros((3, 3)))

    def ch_loss(v, tr):
        flt = jdrkf.MarginalDRKF(MarginalKL(jnp.stack(v)), throw=False)
        means = jax.vmap(lambda y: flt(ch_model, ch_prior, y).filtered_means)(tr.observations)
        return jnp.mean(jnp.sum((tr.states - means) ** 2, axis=-1))

    def ch_data(key, runs):
        return jdrkf.simulate(key, ch_true, ch_x0, 30 if quick else 100, runs)

    # Wang (2022): DR particle filter on the growth model with the mismatched measurement.
    gm = wang_nonlinear.growth_models()
    g_prior = jdrkf.Gaussian(jnp.zeros(1), jnp.eye(1))
    particles = 32 if quick else 100

    def pf_loss(v, data):
        tr, keys = data
        flt = jdrkf.DRParticleFilter(particles, prior="wasserstein", prior_radius=v[0], likelihood="inflate", theta=v[1],
                                     outlier="drop", outlier_threshold=v[2], throw=False)
        means = jax.vmap(lambda y, k: flt(gm["nominal"], g_prior, y, k).filtered_means)(tr.observations, keys)
        return rmse(tr.states, means)

    def pf_data(key, runs):
        ks, kf = jax.random.split(key)
        return jdrkf.simulate(ks, gm["true"], g_prior, 30 if quick else 100, runs), jax.random.split(kf, runs)

    # Jang et al.: steady-state DR filter in closed loop; EM nominals (5 outputs per run) scaled by s.
    a, b, c = jang.lqr_system()
    x0_law, _, _, qv, rv = jang.noise_laws("gaussian")
    true_model = jdrkf.LinearModel(F=a, H=c, Q=qv * np.eye(4), R=rv * np.eye(2), B=b)
    controller = jdrkf.LQRController.design(a, b, jang.LQR_Q, jang.LQR_R)
    reference = jnp.asarray(jang.reference_trajectory())
    j_prior = jdrkf.Gaussian(jnp.zeros(4), qv * jnp.eye(4))
    w_law, v_law = jdrkf.GaussianNoise(qv * jnp.eye(4)), jdrkf.GaussianNoise(rv * jnp.eye(2))

    def j_loss(v, data):
        qs, rs, keys = data
        flt = jdrkf.SteadyStateDRKF(v[0], v[1], throw=False)

        def one(args):
            q, r, key = args
            model = jdrkf.LinearModel(F=a, H=c, Q=v[2] * q, R=v[2] * r, B=b)
            res = jdrkf.closed_loop(key, flt, model, j_prior, controller, reference, true_model=true_model,
                                    initial_state=x0_law, process_noise=w_law, measurement_noise=v_law)
            return res.cost(jang.LQR_Q, jang.LQR_R)

        return jnp.mean(jax.lax.map(one, (qs, rs, keys)))  # lax.map: one steady-state solve per run

    @jax.jit
    def j_em(key):
        kx, kw, kv = jax.random.split(key, 3)
        x = x0_law.sample(kx)
        ws = jnp.sqrt(qv) * jax.random.normal(kw, (jang.NUM_EM_OUTPUTS, 4))
        vs = jnp.sqrt(rv) * jax.random.normal(kv, (jang.NUM_EM_OUTPUTS, 2))
        _, ys = jax.lax.scan(lambda x, wv: (a @ x + wv[0], c @ x + wv[1]), x, (ws, vs))
        em = jdrkf.em_noise_covariances(a, c, ys, jnp.zeros(4), qv * jnp.eye(4))
        return em.Q, em.R

    def j_data(key, runs):
        kem, kloop = jax.random.split(key)
        qs, rs = jax.vmap(j_em)(jax.random.split(kem, runs))
        return qs, rs, jax.random.split(kloop, runs)

    return {
        "wang-ye": Scenario(
            "wang-ye", "Wang & Ye (2022)", "DRKF(Wasserstein(θx), Wasserstein(θv), EpsContamination(ε)), α = 1, 5 % outliers",
            ("θx", "θv", "ε"), (0.1, 0.1, 0.05), [(0.0, None), (0.0, None), (0.0, 0.5)],
            [(0.005, 2.0, True), (0.005, 2.0, True), (0.005, 0.3, True)], wy_loss, wy_data, 0.1, "mean RMSE"),
        "li": Scenario(
            "li", "Li et al.", "STKF_AR1 measurement channels: initial ν, τ², forgetting ρ; torsion case y3",
            ("ν_y", "τ²_y", "ρ_y"), (100.0, 1.0, 0.99), [(0.0, None), (0.0, None), (0.0, 1.0)],
            [(1.0, 300.0, True), (0.1, 10.0, True), (0.9, 0.999, False)], li_loss, li_data, 0.1, "mean RMSE"),
        "chen": Scenario(
            "chen", "Chen et al. (2025)", "MarginalDRKF(MarginalKL(c₁, c₂, c₃)), one KL radius per sensor",
            ("c₁", "c₂", "c₃"), (0.05, 0.05, 0.05), [(0.0, None)] * 3,
            [(1e-3, 0.5, True)] * 3, ch_loss, ch_data, 0.1, "mean squared error"),
        "wang2022": Scenario(
            "wang2022", "Wang (2022)", f"DRParticleFilter({particles}): Wasserstein prior radius, inflation θ, outlier threshold ε (drop)",
            ("prior radius", "θ", "ε"), (0.1, 5.0, 1e-6), [(0.0, None), (0.0, None), (0.0, None)],
            [(0.01, 3.0, True), (1.0, 20.0, True), (1e-9, 1e-2, True)], pf_loss, pf_data, 0.1, "mean RMSE"),
        "jang": Scenario(
            "jang", "Jang et al. (2025)", "SteadyStateDRKF(θx, θv) with EM nominals scaled by s; closed-loop LQR tracking",
            ("θx", "θv", "s"), (0.1, 0.1, 1.0), [(0.0, None), (0.0, None), (0.0, None)],
            [(0.01, 2.0, True), (0.01, 2.0, True), (0.3, 3.0, True)], j_loss, j_data, 0.1, "mean LQR cost"),
    }


# --------------------------------------------------------------------------- methods


def _axis(lo, hi, logscale, k):
    return np.geomspace(lo, hi, k) if logscale else np.linspace(lo, hi, k)


def _median_time(fn, *args, repeats=3):
    import jax

    jax.block_until_ready(fn(*args))
    times = []
    for _ in range(repeats):
        t = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - t)
    return float(np.median(times))


def _local_minima(losses, k, dims):
    cube = losses.reshape((k,) * dims)
    count = 0
    for idx in np.ndindex(cube.shape):
        val, better = cube[idx], True
        for d in range(dims):
            for step in (-1, 1):
                j = list(idx)
                j[d] += step
                if 0 <= j[d] < k and not cube[tuple(j)] > val:
                    better = False
        count += better and np.isfinite(val)
    return int(count)


def run_scenario(sc: Scenario, args, seed: int) -> dict:
    import equinox as eqx
    import jax
    import jax.numpy as jnp
    import optax

    from jdrkf import tuning

    class Params(eqx.Module):
        values: tuple

    where = lambda p: p.values
    key = jax.random.key(seed)
    t0 = time.perf_counter()
    # Held-out runs: `test_chunks` data sets of the training size from other keys (one compiled program for both).
    train = sc.data(jax.random.fold_in(key, 0), args.train_runs)
    tests = [sc.data(jax.random.fold_in(key, 1 + i), args.train_runs) for i in range(args.test_chunks)]
    train_obj = lambda p: sc.loss(p.values, train)
    loss_at = eqx.filter_jit(sc.loss)
    vg_at = eqx.filter_jit(jax.value_and_grad(sc.loss))
    start = tuple(jnp.asarray(x) for x in sc.start)
    t_fwd = _median_time(loss_at, start, train)
    t_vg = _median_time(vg_at, start, train)
    ratio = t_vg / t_fwd
    log(f"[{sc.name}] data + compile {time.perf_counter() - t0:.1f} s; forward {t_fwd * 1e3:.1f} ms, value-and-grad {t_vg * 1e3:.1f} ms ({ratio:.2f}×)")

    def fwd(values):
        return float(loss_at(tuple(jnp.asarray(x) for x in values), train))

    def test_error(values):
        return float(np.mean([loss_at(tuple(jnp.asarray(x) for x in values), test) for test in tests]))

    # Diagnostics at the start: gradient vs central finite differences (relative step 1e-4).
    _, g0 = vg_at(start, train)
    fd = []
    for i, x in enumerate(sc.start):
        h = 1e-4 * x
        up = [x + h if j == i else y for j, y in enumerate(sc.start)]
        dn = [x - h if j == i else y for j, y in enumerate(sc.start)]
        fd.append((fwd(up) - fwd(dn)) / (2 * h))
    g0 = np.asarray([float(g) for g in g0])
    fd = np.asarray(fd)
    fd_err = (np.abs(g0 - fd) / np.maximum(np.abs(fd), 1e-300)).tolist()

    # (a) gradient
    t = time.perf_counter()
    res = tuning.fit(Params(start), train_obj, where=where, bounds=sc.bounds, optimizer=optax.adam(sc.lr), steps=args.steps,
                     tol=args.tol, patience=3, restarts=args.restarts, jitter=0.5, key=jax.random.fold_in(key, 2))
    wall_grad = time.perf_counter() - t
    costs, cum = [], 0.0  # per recorded iterate, in forward-equivalents
    seq_params, seq_losses = [], []
    for run in res.runs:
        for i in range(len(run.losses)):
            last_unconverged = (not run.converged) and i == len(run.losses) - 1
            cum += 1.0 if last_unconverged else ratio
            costs.append(cum)
            seq_params.append(run.params[i])
            seq_losses.append(run.losses[i])
    cost_grad = cum
    best_so_far = np.minimum.accumulate(np.where(np.isnan(seq_losses), np.inf, seq_losses))
    change = [i for i in range(len(best_so_far)) if i == 0 or best_so_far[i] < best_so_far[i - 1]]
    marks = sorted(set(change[:: max(1, len(change) // 10)]) | {change[-1]})
    grad_curve = [(costs[i], test_error(seq_params[i])) for i in marks]  # at a change, iterate i is the best so far
    grad_curve.append((costs[-1], grad_curve[-1][1]))
    best_params = [float(x) for x in res.params[res.best_step]]
    grad = {
        "train": res.loss, "test": test_error(best_params), "params": best_params, "cost": cost_grad, "wall_s": wall_grad,
        "steps": [len(r.losses) - 1 for r in res.runs], "converged": [r.converged for r in res.runs],
        "start_losses": [float(r.losses[r.best_step]) for r in res.runs], "best_start": res.start, "best_step": res.best_step,
        "curve": grad_curve,
    }
    log(f"[{sc.name}] gradient: train {res.loss:.5g}, held-out {grad['test']:.5g}, cost {cost_grad:.1f} fwd-eq, wall {wall_grad:.1f} s, params {best_params}")

    # (b) grids
    # Grid sizes: those of --grid-k whose k³ forward passes fit in --grid-budget seconds (at least the smallest).
    ks = [k for k in args.grid_k if k**3 * t_fwd <= args.grid_budget] or [min(args.grid_k)]
    grids = []
    for k in ks:
        axes = [_axis(lo, hi, lg, k) for lo, hi, lg in sc.axes]
        rows = np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, len(axes))
        t = time.perf_counter()
        gr = tuning.grid_search(Params(start), train_obj, where=where, grid=rows)
        wall = time.perf_counter() - t
        best = [float(x) for x in gr.grid[int(np.nanargmin(gr.losses))]]
        finite = gr.losses[np.isfinite(gr.losses)]
        grids.append({
            "k": k, "evaluations": len(rows), "train": gr.loss, "test": test_error(best), "params": best, "wall_s": wall,
            "local_minima": _local_minima(np.where(np.isfinite(gr.losses), gr.losses, np.inf), k, len(axes)),
            "spread": float(finite.max() / finite.min() - 1) if finite.size else float("nan"),
            "failed": int(np.sum(~np.isfinite(gr.losses))),
        })
        log(f"[{sc.name}] grid k={k}: train {gr.loss:.5g}, held-out {grids[-1]['test']:.5g}, wall {wall:.1f} s, params {best}")

    # (c) random search with the gradient's budget
    rng = np.random.default_rng(seed)
    count = max(1, round(cost_grad))
    samples = np.stack([np.exp(rng.uniform(np.log(lo), np.log(hi), count)) if lg else rng.uniform(lo, hi, count)
                        for lo, hi, lg in sc.axes], -1)
    t = time.perf_counter()
    r_losses = np.asarray([fwd(row) for row in samples])
    wall_rand = time.perf_counter() - t
    r_best = np.minimum.accumulate(np.where(np.isnan(r_losses), np.inf, r_losses))
    r_change = [i for i in range(count) if i == 0 or r_best[i] < r_best[i - 1]]
    rand_curve = [(i + 1, test_error(samples[i])) for i in r_change]
    rand_curve.append((count, rand_curve[-1][1]))
    ib = r_change[-1]
    rand = {"train": float(r_losses[ib]), "test": rand_curve[-1][1], "params": samples[ib].tolist(), "cost": count, "wall_s": wall_rand, "curve": rand_curve}
    log(f"[{sc.name}] random ({count}): train {rand['train']:.5g}, held-out {rand['test']:.5g}, wall {wall_rand:.1f} s")

    ref = grids[-1]
    ok_err = grad["test"] <= GOAL_RATIO * ref["test"]
    ok_cost = ref["evaluations"] / cost_grad >= GOAL_COST
    return {
        "name": sc.name, "paper": sc.paper, "description": sc.description, "parameters": list(sc.names), "metric": sc.metric,
        "start": list(sc.start), "bounds": [list(b) for b in sc.bounds], "grid_box": [list(a) for a in sc.axes],
        "forward_s": t_fwd, "value_and_grad_s": t_vg, "vg_over_forward": ratio,
        "start_gradient": g0.tolist(), "start_fd": fd.tolist(), "start_gradient_rel_err": fd_err,
        "gradient": grad, "grids": grids, "random": rand,
        "goal": {"error_ratio": grad["test"] / ref["test"], "cost_ratio": ref["evaluations"] / cost_grad, "met": bool(ok_err and ok_cost)},
        "wall_s": time.perf_counter() - t0,
    }


# --------------------------------------------------------------------------- output


def _why(r) -> list[str]:
    out = []
    g, ref = r["gradient"], r["grids"][-1]
    if r["goal"]["error_ratio"] > GOAL_RATIO:
        if g["train"] > ref["train"]:
            out.append(f"gradient's training loss {g['train']:.5g} is above the grid's {ref['train']:.5g} (an optimisation miss)")
        else:
            out.append(f"gradient's training loss {g['train']:.5g} ≤ the grid's {ref['train']:.5g}, but its held-out error is higher (overfitting the training runs)")
    if r["goal"]["cost_ratio"] < GOAL_COST:
        out.append(f"gradient cost {g['cost']:.0f} forward-equivalents is only {r['goal']['cost_ratio']:.1f}× below the grid's {ref['evaluations']}")
    if max(r["start_gradient_rel_err"]) > 1e-2:
        bad = [f"{n}: {e:.1e}" for n, e in zip(r["parameters"], r["start_gradient_rel_err"]) if e > 1e-2]
        out.append("gradient ≠ finite differences at the start (" + ", ".join(bad) + "): non-smooth objective or biased gradient")
    if any(abs(x) == 0.0 for x in r["start_gradient"]):
        zero = [n for n, x in zip(r["parameters"], r["start_gradient"]) if x == 0.0]
        out.append("zero gradient w.r.t. " + ", ".join(zero) + " (a hard decision: flat almost everywhere)")
    if ref["local_minima"] > 1:
        out.append(f"{ref['local_minima']} strict local minima of the training loss on the k = {ref['k']} grid")
    if ref["spread"] < 0.01:
        out.append(f"flat objective: the grid's training losses differ by {100 * ref['spread']:.2f} % at most")
    return out


def write_markdown(path, results, meta) -> None:
    lines = [
        "# Tuning three parameters jointly: gradient vs grid vs random search",
        "",
        (f"{meta['date']} · {meta['device']} · {meta['cpu']} · jax {meta['versions'].get('jax')} · "
        f"{'quick' if meta['quick'] else 'full'} run: {meta['train_runs']} training runs, {meta['test_runs']} held-out runs (another key), "
        f"Adam ≤ {meta['steps']} steps × {1 + meta['restarts']} starts (tol {meta['tol']}), grids k ∈ {meta['grid_k']} "
        f"(those whose k³ forward passes take ≤ {meta['grid_budget_s']:.0f} s); total wall {meta['wall_s']:.0f} s."),
        "",
        ("Cost in forward-filter-equivalents (one evaluation of the training objective; a value-and-gradient counts "
        "as its measured time over the forward time). Wall times include compilation. Goal: gradient's held-out error "
        f"≤ {GOAL_RATIO} × the largest grid's, at ≥ {GOAL_COST:.0f}× fewer forward-equivalents."),
        "",
        f"**Goal met in {sum(r['goal']['met'] for r in results)} of {len(results)} scenarios.**",
        "",
    ]
    for r in results:
        g, rd = r["gradient"], r["random"]
        fmt = lambda v: ", ".join(f"{x:.4g}" for x in v)
        lines += [
            f"## {r['name']} — {r['paper']}",
            "",
            (f"{r['description']}. Parameters ({', '.join(r['parameters'])}), start ({fmt(r['start'])}); metric: {r['metric']}. "
            f"Forward {1e3 * r['forward_s']:.1f} ms, value-and-grad {1e3 * r['value_and_grad_s']:.1f} ms ({r['vg_over_forward']:.2f} forward-equivalents)."),
            "",
            "| method | evaluations | cost (fwd-eq) | wall s | training | held-out | parameters |",
            "|---|---:|---:|---:|---:|---:|---|",
            f"| gradient (Adam, {len(g['steps'])} starts, steps {g['steps']}) | {sum(g['steps']) + len(g['steps'])} | {g['cost']:.1f} | {g['wall_s']:.1f} | {g['train']:.5g} | {g['test']:.5g} | {fmt(g['params'])} |",
        ]
        for gr in r["grids"]:
            lines.append(f"| grid k = {gr['k']} | {gr['evaluations']} | {gr['evaluations']} | {gr['wall_s']:.1f} | {gr['train']:.5g} | {gr['test']:.5g} | {fmt(gr['params'])} |")
        lines.append(f"| random search | {rd['cost']} | {rd['cost']} | {rd['wall_s']:.1f} | {rd['train']:.5g} | {rd['test']:.5g} | {fmt(rd['params'])} |")
        ref = r["grids"][-1]
        lines += [
            "",
            (f"Held-out error gradient / grid k = {ref['k']}: **{r['goal']['error_ratio']:.4f}** (goal ≤ {GOAL_RATIO}); "
            f"grid cost / gradient cost: **{r['goal']['cost_ratio']:.1f}×** (goal ≥ {GOAL_COST:.0f}) — goal {'met' if r['goal']['met'] else 'NOT met'}."),
            "",
            f"Diagnostics: gradient at the start ({fmt(r['start_gradient'])}) vs central differences ({fmt(r['start_fd'])}), "
            f"relative error {', '.join(f'{e:.1e}' for e in r['start_gradient_rel_err'])}; restarts' best training losses ({fmt(g['start_losses'])}), "
            f"converged {g['converged']}; k = {ref['k']} grid: {ref['local_minima']} strict local minima, training losses spread {100 * ref['spread']:.1f} %"
            + (f", {ref['failed']} failed (NaN)" if ref["failed"] else "") + ".",
        ]
        why = _why(r)
        if why:
            lines += ["", "Measured: " + "; ".join(why) + "."]
        lines += ["", f"![{r['name']}](tuning_cpu_{r['name']}.png)", ""]
    with open(path, "w") as f:
        f.write("\n".join(lines))


def plot(path, r) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 4))
    gx, gy = zip(*r["gradient"]["curve"])
    ax.step(gx, gy, where="post", label="gradient (Adam)", color="C0")
    rx, ry = zip(*r["random"]["curve"])
    ax.step(rx, ry, where="post", label="random search", color="C1")
    ax.plot([g["evaluations"] for g in r["grids"]], [g["test"] for g in r["grids"]], "s--", color="C2", label="grid (k³ points)")
    for g in r["grids"]:
        ax.annotate(f"k={g['k']}", (g["evaluations"], g["test"]), textcoords="offset points", xytext=(4, 4), fontsize=8)
    ax.axhline(GOAL_RATIO * r["grids"][-1]["test"], color="0.5", lw=0.8, ls=":", label=f"{GOAL_RATIO} × largest grid")
    ax.set_xscale("log")
    ax.set_xlabel("cost (forward-filter-equivalents)")
    ax.set_ylabel(f"held-out {r['metric']}")
    ax.set_title(f"{r['name']}: {', '.join(r['parameters'])}")
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--quick", action="store_true", help="smoke run: small data, k ∈ {2, 3}, 6 steps, no restarts")
    p.add_argument("--scenarios", nargs="+", default=["wang-ye", "li", "chen", "wang2022", "jang"])
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--restarts", type=int, default=None, help="gradient restarts (default: 0 quick, 1 full)")
    p.add_argument("--grid-budget", type=float, default=None, help="seconds of forward passes allowed per grid (default 20 quick, 150 full)")
    p.add_argument("--out", default=os.path.join(HERE, "results", "tuning_cpu"), help="output prefix (.md, .json, _<scenario>.png)")
    args = p.parse_args(argv)
    args.train_runs, args.test_chunks = (4, 1) if args.quick else (16, 2)
    args.test_runs = args.train_runs * args.test_chunks
    args.steps, args.tol = (6, 1e-4) if args.quick else (25, 1e-4)
    args.restarts = (0 if args.quick else 1) if args.restarts is None else args.restarts
    args.grid_k = (2, 3) if args.quick else (3, 6, 10)
    args.grid_budget = (20.0 if args.quick else 150.0) if args.grid_budget is None else args.grid_budget
    set_platform("cpu")
    import jax

    jax.config.update("jax_enable_x64", True)  # the benchmark process, not the library
    t0 = time.perf_counter()
    scenarios = _scenarios(args.quick)
    unknown = set(args.scenarios) - set(scenarios)
    if unknown:
        raise SystemExit(f"unknown scenarios {sorted(unknown)}; choose from {list(scenarios)}")
    results = []
    for i, name in enumerate(args.scenarios):
        results.append(run_scenario(scenarios[name], args, args.seed + i))
    meta = {
        "date": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"), "device": device_summary(jax),
        "cpu": cpu_model(), "cores": os.cpu_count(), "machine": platform.machine(), "loadavg": loadavg(), "versions": versions(),
        "jdrkf_source": package_source_hash(), "git": git_info(), "quick": args.quick, "train_runs": args.train_runs,
        "test_runs": args.test_runs, "steps": args.steps, "restarts": args.restarts, "tol": args.tol, "grid_k": list(args.grid_k), "grid_budget_s": args.grid_budget,
        "seed": args.seed, "dtype": "float64", "wall_s": time.perf_counter() - t0, "out": portable_path(args.out),
    }
    os.makedirs(os.path.dirname(os.path.abspath(args.out)), exist_ok=True)
    for r in results:
        plot(f"{args.out}_{r['name']}.png", r)
    with open(args.out + ".json", "w") as f:
        json.dump({"meta": meta, "scenarios": results}, f, indent=1)
    write_markdown(args.out + ".md", results, meta)
    log(f"wrote {args.out}.md/.json and {len(results)} plots in {meta['wall_s']:.0f} s; goal met in {sum(r['goal']['met'] for r in results)}/{len(results)}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
