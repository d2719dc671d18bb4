#!/usr/bin/env python
"""Kalman-filter throughput on the path users type: jdrkf vs dynamax vs a minimal JAX KF vs NumPy.

Wang & Ye's (2022) system (n = 2 states, m = 1 observation), B independent runs of length T
simulated once with NumPy (fixed seed) and fed to every implementation, in float32 and
float64 (each dtype in its own child process). Every row is timed in the same process:
compile time = first call − median call; run time = median of `--repeats` calls, made in
interleaved rounds (each row once per round, so that a drifting load hits every row alike)
(`jax.block_until_ready`); steps/s = B·T / run time.

Goal rows (issue "Fast by default"), each a ratio of two rows of the same run:

1. **README tour vs dynamax**: `jax.jit(jax.vmap(jdrkf.KalmanFilter(outputs="filtered_means"),
   in_axes=(None, None, 0)))` — the README's tour, which asks for the filtered means it
   uses — against dynamax as its users call it, `jax.jit(jax.vmap(lgssm_filter,
   in_axes=(None, 0)))` (which returns filtered means, covariances and the marginal
   log-likelihood; its data-independent covariance recursion is unbatched, as jdrkf's). Goal ≥ 2×.
2. **README tour vs a minimal JAX KF**: a 15-line `lax.scan` + `vmap` Kalman filter
   (written below, the textbook recursion) returning the same output, the filtered means.
   Goal ≥ 1×.
3. **Per-run path vs NumPy**: every run has its own missing entries (5 %, seeded), so
   each run's covariance recursion is its own: `jax.vmap(lambda y, o: KalmanFilter()(model,
   prior, y, observed=o))` against a batched NumPy KF that masks the same entries
   (loop over time, vectorized over runs, batch axis last). Both return filtered means,
   covariances and log-likelihoods. Goal ≥ 1×.

Extra rows (labelled, not goals): jdrkf with dynamax's outputs (the default
`outputs`: filtered means, covariances, marginal log-likelihood) and with
`outputs="all"`.

DR rows (`--dr`, on by default; `--no-dr` skips them): the cost of the run-time range check
of traced hyper-parameters. Two shared-covariance DR filters, `DRKF(Wasserstein(θ),
Wasserstein(θ))` and `WassersteinKF(θ)` (θ = 0.1), through `jax.jit(jax.vmap(flt, in_axes=(None,
None, 0)))` on the same system, B = 2000 runs of T = 200 steps (`--dr-B`, `--dr-T`), each in
three builds compiled ahead of time: (a) the radii as Python floats (checked once, eagerly,
when the set is built; constants in the program), (b) the radii as traced arguments of the
jitted function, so that the range check (`Wasserstein.valid()`, reported as
`RESULTS.invalid_hyperparameter`) is in the compiled program, and (c) measurement only: (b)
compiled with `Wasserstein.valid` patched to return `True` inside this script, i.e. without
the check. The three are called interleaved (`--repeats` rounds); the check's cost is the
ratio of medians (b)/(c). Before timing: (a), (b), (c) agree on the filtered means, and with
θ = −0.1, (b) raises the invalid-hyper-parameter error while (c) does not (so (c) really
lacks the check). `--dr-dtypes` picks the dtypes (default float64 only, to keep the section
under a minute on 2 cores).

Before timing, outputs are compared: tour vs dynamax and vs the minimal KF (filtered
means), the per-run path vs NumPy (means, covariances, log-likelihoods); tolerances
1e-8 (float64) and 1e-3 (float32). The script exits with status 1 if a check fails.

`--platform gpu` runs the JAX rows on a GPU (the device is recorded; B defaults to
1e4, 1e5, 1e6 there). At that scale NumPy would need minutes to simulate 10⁹ steps, so
the data are simulated on the device (`--simulate device`, the default on a GPU: the same
model, `jax.random` with key `--seed`, products at `Precision.HIGHEST`); the per-run
mask and the NumPy rows use the first `--numpy-max-runs` runs. Agreement checks compare
the first `CHECK_RUNS` runs of each output; only that slice is kept, so a row's memory is
one output. A row that runs out of device memory is recorded as such (no steps/s) instead
of ending the run. Usage:

    python benchmarks/kf_throughput.py                  # B = 1e4, T = 1000, float32 + float64
    python benchmarks/kf_throughput.py --platform gpu   # on a GPU
    python benchmarks/kf_throughput.py --quick --out smoke/kfb   # smoke run, B = 100, T = 100
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

from _provenance import cpu_model, device_summary, loadavg, package_source_hash, set_platform

# Wang & Ye's (2022) system: x_k = F x_{k-1} + w_k, y_k = H x_k + v_k, x_0 ~ N(0, I2).
SYSTEM = {
    "F": [[0.9802, 0.0196], [0.0, 0.9802]],
    "H": [[1.0, -1.0]],
    "Q": [[1.9608, 0.0195], [0.0195, 1.9605]],
    "R": [[1.0]],
    "m0": [0.0, 0.0],
    "P0": [[1.0, 0.0], [0.0, 1.0]],
}
DATA_SEED = 0
MISSING_FRACTION = 0.05
CHECK_RUNS = 10_000  # runs compared in the agreement checks


def system_arrays(dtype="float64"):
    return {k: np.asarray(v, dtype=dtype) for k, v in SYSTEM.items()}


def simulate(num_runs: int, num_steps: int, seed: int = DATA_SEED) -> tuple[np.ndarray, np.ndarray]:
    """`ys` (num_runs, num_steps, m), float64, and a per-run mask of observed entries."""
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
    observed = rng.random(ys.shape) >= MISSING_FRACTION
    return ys, observed


def simulate_device(num_runs: int, num_steps: int, seed: int, dtype: str, mask_runs: int):
    """As `simulate`, on the JAX device with `jax.random` (key `seed`), in `dtype`: `ys`
    (num_runs, num_steps, m) on the device and a NumPy mask of the first `mask_runs` runs."""
    import jax
    import jax.numpy as jnp
    from jax import lax

    s = system_arrays(dtype)
    F, H, m0 = (jnp.asarray(s[k]) for k in ("F", "H", "m0"))
    lq, lr, lp = (jnp.asarray(np.linalg.cholesky(system_arrays()[k]).astype(dtype)) for k in ("Q", "R", "P0"))
    n, m = F.shape[0], H.shape[0]
    hi = lax.Precision.HIGHEST

    @jax.jit
    def run(key):
        k0, kt = jax.random.split(key)
        x0 = m0 + jnp.matmul(jax.random.normal(k0, (num_runs, n), dtype), lp.T, precision=hi)

        def step(x, k):
            kw, kv = jax.random.split(k)
            x = jnp.matmul(x, F.T, precision=hi) + jnp.matmul(jax.random.normal(kw, (num_runs, n), dtype), lq.T, precision=hi)
            y = jnp.matmul(x, H.T, precision=hi) + jnp.matmul(jax.random.normal(kv, (num_runs, m), dtype), lr.T, precision=hi)
            return x, y

        return jnp.swapaxes(lax.scan(step, x0, jax.random.split(kt, num_steps))[1], 0, 1)

    ys = jax.block_until_ready(run(jax.random.key(seed)))
    observed = np.random.default_rng(seed).random((min(mask_runs, num_runs), num_steps, m)) >= MISSING_FRACTION
    return ys, observed


def numpy_kf(F, H, Q, R, m0, P0, ys, observed):
    """Batched Kalman filter in NumPy with missing entries (per-run covariances, Joseph form).

    `ys`, `observed`: (B, T, m). Loops over time; every step is vectorized over the B
    runs with the batch axis last. Missing rows are decoupled as in jdrkf (zero `H` row
    and residual, unit noise variance). Returns filtered means (B, T, n), covariances
    (B, T, n, n) and marginal log-likelihoods (B,).
    """
    dtype = ys.dtype
    num_runs, num_steps, m = ys.shape
    n = F.shape[0]
    F, H, Q, R, m0, P0 = (np.asarray(a, dtype) for a in (F, H, Q, R, m0, P0))
    Y = np.ascontiguousarray(np.moveaxis(ys, 0, -1))  # (T, m, B)
    O = np.ascontiguousarray(np.moveaxis(observed, 0, -1)).astype(dtype)  # (T, m, B)
    mean = np.repeat(m0[:, None], num_runs, 1)  # (n, B)
    P = np.repeat(P0[:, :, None], num_runs, 2)  # (n, n, B)
    out_m = np.empty((num_steps, n, num_runs), dtype)
    out_P = np.empty((num_steps, n, n, num_runs), dtype)
    ll = np.zeros(num_runs, dtype)
    Qb, eye = Q[:, :, None], np.eye(n, dtype=dtype)[:, :, None]
    eye_m = np.eye(m, dtype=dtype)[:, :, None]
    log2pi = dtype.type(math.log(2 * math.pi))

    def cho_solve(L, b):  # L (m, m, B) lower, b (m, p, B) -> (L Lᵀ)⁻¹ b
        z = np.empty_like(b)
        for i in range(m):
            z[i] = (b[i] - np.einsum("kb,kpb->pb", L[i, :i], z[:i])) / L[i, i]
        x = np.empty_like(b)
        for i in reversed(range(m)):
            x[i] = (z[i] - np.einsum("kb,kpb->pb", L[i + 1:, i], x[i + 1:])) / L[i, i]
        return x

    for t in range(num_steps):
        o = O[t]  # (m, B)
        mp = F @ mean
        Pp = np.einsum("ilb,jl->ijb", np.einsum("ik,klb->ilb", F, P), F) + Qb
        Pp = 0.5 * (Pp + Pp.transpose(1, 0, 2))
        h = H[:, :, None] * o[:, None, :]  # (m, n, B)
        r = R[:, :, None] * (o[:, None, :] * o[None, :, :]) + eye_m * (1.0 - o)[None, :, :]
        innov = np.where(o > 0, Y[t] - np.einsum("ijb,jb->ib", h, mp), 0.0)
        HP = np.einsum("ikb,kjb->ijb", h, Pp)
        S = np.einsum("ijb,ljb->ilb", HP, h) + r
        S = 0.5 * (S + S.transpose(1, 0, 2))
        L = np.zeros_like(S)
        for j in range(m):
            L[j, j] = np.sqrt(S[j, j] - np.sum(L[j, :j] ** 2, axis=0))
            for i in range(j + 1, m):
                L[i, j] = (S[i, j] - np.sum(L[i, :j] * L[j, :j], axis=0)) / L[j, j]
        KT = cho_solve(L, HP)  # (m, n, B): Kᵀ = S⁻¹ H P
        z = cho_solve(L, innov[:, None, :])[:, 0]
        mean = mp + np.einsum("kib,kb->ib", KT, innov)
        A = eye - np.einsum("kib,kjb->ijb", KT, h)
        P = np.einsum("ilb,jlb->ijb", np.einsum("ikb,klb->ilb", A, Pp), A) + np.einsum("kib,klb,ljb->ijb", KT, r, KT)
        P = 0.5 * (P + P.transpose(1, 0, 2))
        logdet = 2 * np.sum(np.log(np.einsum("iib->ib", L)), axis=0)
        ll += -0.5 * (np.sum(innov * z, axis=0) + logdet + np.sum(o, axis=0) * log2pi)
        out_m[t] = mean
        out_P[t] = P
    return np.moveaxis(out_m, -1, 0), np.moveaxis(out_P, -1, 0), ll


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

    source_hash = package_source_hash(jdrkf)
    s = system_arrays(dtype)
    c = lambda a: jnp.asarray(a, dtype=dtype)  # noqa: E731
    F, H, Q, R, m0, P0 = (c(s[k]) for k in ("F", "H", "Q", "R", "m0", "P0"))
    n, m = F.shape[0], H.shape[0]
    model = jdrkf.LinearModel(F=F, H=H, Q=Q, R=R)
    prior = jdrkf.Gaussian(mean=m0, cov=P0)

    # The README tour and its variants.
    tour = jax.jit(jax.vmap(jdrkf.KalmanFilter(outputs="filtered_means"), in_axes=(None, None, 0)))
    default_outputs = jax.jit(jax.vmap(jdrkf.KalmanFilter(), in_axes=(None, None, 0)))
    all_outputs = jax.jit(jax.vmap(jdrkf.KalmanFilter(outputs="all"), in_axes=(None, None, 0)))
    kf = jdrkf.KalmanFilter()
    per_run = jax.jit(jax.vmap(lambda y, o: kf(model, prior, y, observed=o)))

    # dynamax conditions on y_1 first: its `initial` is the predicted law of x_1.
    s64 = system_arrays()
    params = ParamsLGSSM(
        initial=ParamsLGSSMInitial(mean=c(s64["F"] @ s64["m0"]), cov=c(s64["F"] @ s64["P0"] @ s64["F"].T + s64["Q"])),
        dynamics=ParamsLGSSMDynamics(weights=F, bias=c(np.zeros(n)), input_weights=c(np.zeros((n, 0))), cov=Q),
        emissions=ParamsLGSSMEmissions(weights=H, bias=c(np.zeros(m)), input_weights=c(np.zeros((m, 0))), cov=R),
    )
    dyn = jax.jit(jax.vmap(lgssm_filter, in_axes=(None, 0)))

    # A minimal JAX Kalman filter, as a user would write it in 15 lines.
    def minimal_kf(ys):
        def step(carry, y):
            mu, P = carry
            mu, P = F @ mu, F @ P @ F.T + Q  # predict
            S = H @ P @ H.T + R
            K = jnp.linalg.solve(S, H @ P).T  # gain
            mu, P = mu + K @ (y - H @ mu), P - K @ S @ K.T  # update
            return (mu, P), mu

        return lax.scan(step, (m0, P0), ys)[1]

    minimal = jax.jit(jax.vmap(minimal_kf))

    def first_call(impl, kind, B, fn, *fargs, keep=lambda out: out):
        """First call (compile + run) of a row. Returns `(keep(output) as NumPy, first-call
        seconds)`, or `None` after recording a row that ran out of device memory."""
        try:
            t0 = time.perf_counter()
            out = jax.block_until_ready(fn(*fargs))
            first = time.perf_counter() - t0
        except Exception as e:  # noqa: BLE001 (XLA's error class differs between jax versions)
            if "RESOURCE_EXHAUSTED" not in str(e) and "out of memory" not in str(e).lower():
                raise
            log(f"[{dtype}] B={B} {impl}: out of device memory")
            rows.append({"impl": impl, "kind": kind, "dtype": dtype, "B": B, "T": args.T, "out_of_memory": True,
                         "first_call_s": None, "compile_s": None, "run_s": None, "run_min_s": None,
                         "run_times_s": [], "steps_per_s": None})
            return None
        kept = jax.tree.map(np.asarray, keep(out))
        del out
        return kept, first

    rows, checks = [], []
    tol = 1e-8 if dtype == "float64" else 1e-3

    def record(impl, kind, B, first, times, compiled=True):
        med = statistics.median(times)
        rows.append({
            "impl": impl, "kind": kind, "dtype": dtype, "B": B, "T": args.T, "first_call_s": first,
            "compile_s": (first - med) if compiled else None, "run_s": med, "run_min_s": min(times),
            "run_times_s": times, "steps_per_s": B * args.T / med,
        })

    def timed_rows(B, specs):
        """Every row's first call, then `args.repeats` rounds in which each row is called
        once, in order: slow drifts of a shared machine's load then hit every row alike.
        `specs`: `(impl, kind, fn, fargs, keep, compiled)`. Returns `{impl: kept output}`."""
        kept, firsts = {}, {}
        for impl, kind, fn, fargs, keep, compiled in specs:
            got = first_call(impl, kind, B, fn, *fargs, keep=keep)
            if got is not None:
                kept[impl], firsts[impl] = got
        times = {impl: [] for impl in firsts}
        for _ in range(args.repeats):
            for impl, _kind, fn, fargs, _keep, _compiled in specs:
                if impl in firsts:
                    t0 = time.perf_counter()
                    jax.block_until_ready(fn(*fargs))
                    times[impl].append(time.perf_counter() - t0)
        for impl, kind, _fn, _fargs, _keep, compiled in specs:
            if impl in firsts:
                record(impl, kind, B, firsts[impl], times[impl], compiled)
        return kept

    def check(B, what, pairs):
        ok = True
        entry = {"B": B, "dtype": dtype, "vs": what, "runs_compared": min(B, CHECK_RUNS)}
        for key, (a, b) in pairs.items():
            entry[f"max_abs_diff_{key}"] = d = maxabs(a, b)
            ok &= d <= tol * (1.0 if key != "loglik" else max(1.0, float(np.max(np.abs(np.asarray(b, np.float64))))))
        entry["ok"] = bool(ok)
        checks.append(entry)
        log(f"[{dtype}] B={B} check {what}: " + " ".join(f"{k}={v:.3g}" for k, v in entry.items()
                                                           if k.startswith("max_abs")) + (" ok" if ok else " FAIL"))

    B_max = max(args.batch_sizes)
    if args.simulate == "device":
        ys_all, observed_all = simulate_device(B_max, args.T, args.seed, dtype, args.numpy_max_runs)
    else:
        ys_np_all, observed_all = simulate(B_max, args.T, args.seed)
        ys_all = jnp.asarray(ys_np_all.astype(dtype))
        del ys_np_all
    head = lambda out: out[:CHECK_RUNS]  # noqa: E731
    means = lambda out: out.filtered_means[:CHECK_RUNS]  # noqa: E731
    for B in args.batch_sizes:
        ys = ys_all if B == B_max else ys_all[:B]
        log(f"[{dtype}] B={B} T={args.T}")
        specs = [
            ("jdrkf README tour", "goal", tour, (model, prior, ys), means, True),
            ("dynamax", "peer", dyn, (params, ys), means, True),
            ("minimal scan+vmap KF", "peer", minimal, (ys,), head, True),
            ("jdrkf, default outputs (dynamax's set)", "extra", default_outputs, (model, prior, ys), means, True),
            ('jdrkf, outputs="all"', "extra", all_outputs, (model, prior, ys), means, True),
        ]
        if B <= args.numpy_max_runs:
            ys_np, obs_np = np.asarray(ys), np.ascontiguousarray(observed_all[:B])
            specs += [
                ("jdrkf per-run (5% missing)", "goal", per_run, (ys, jnp.asarray(obs_np)),
                 lambda out: (out.filtered_means, out.filtered_covariances, out.marginal_loglik), True),
                ("numpy per-run (5% missing)", "peer",
                 lambda y, o: numpy_kf(s["F"], s["H"], s["Q"], s["R"], s["m0"], s["P0"], y, o), (ys_np, obs_np),
                 lambda out: out, False),
            ]
        kept = timed_rows(B, specs)
        if "jdrkf README tour" in kept and "dynamax" in kept:
            check(B, "README tour vs dynamax", {"means": (kept["jdrkf README tour"], kept["dynamax"])})
        if "jdrkf README tour" in kept and "minimal scan+vmap KF" in kept:
            check(B, "README tour vs minimal KF", {"means": (kept["jdrkf README tour"], kept["minimal scan+vmap KF"])})
        r_run, r_np = kept.get("jdrkf per-run (5% missing)"), kept.get("numpy per-run (5% missing)")
        if r_run is not None and r_np is not None:
            check(B, "jdrkf per-run vs numpy", {"means": (r_run[0], r_np[0]), "covs": (r_run[1], r_np[1]),
                                                "loglik": (r_run[2], r_np[2])})
        del kept, r_run, r_np
        del ys
    del ys_all

    dr = run_dr(args, dtype, model, prior, tol) if args.dr and dtype in args.dr_dtypes else None
    return {
        "dtype": dtype,
        "rows": rows,
        "checks": checks,
        "checks_ok": all(ck["ok"] for ck in checks) and (dr is None or dr["checks_ok"]),
        "dr": dr,
        "jdrkf_source_sha256": {"start": source_hash, "end": package_source_hash(jdrkf)},
        "versions": {
            "python": platform.python_version(), "jax": jax.__version__, "jaxlib": __import__("jaxlib").__version__,
            "dynamax": getattr(dynamax, "__version__", "unknown"), "numpy": np.__version__,
            "jdrkf": getattr(jdrkf, "__version__", "unknown"),
        },
        "device": device_summary(jax),
    }


DR_THETA = 0.1


def run_dr(args, dtype, model, prior, tol) -> dict:
    """DR rows: builds (a) concrete radii, (b) traced radii, (c) traced radii without the
    run-time check (module docstring); interleaved timing, checks, cost ratios."""
    import jax
    import jax.numpy as jnp
    import jdrkf
    from jdrkf.sets import Wasserstein

    ys_np, _ = simulate(args.dr_B, args.dr_T, args.seed)
    ys = jnp.asarray(ys_np.astype(dtype))
    filters = {  # name -> filter from radii (two for DRKF, one for WassersteinKF)
        "DRKF(Wasserstein, Wasserstein)": (lambda tx, tv: jdrkf.DRKF(state_set=Wasserstein(tx), noise_set=Wasserstein(tv)), 2),
        "WassersteinKF": (lambda rho: jdrkf.WassersteinKF(rho), 1),
    }
    valid = Wasserstein.valid

    def build(make, k, variant, thetas):
        """Lower and compile one build; returns (callable, its radii arguments, compile seconds)."""
        if variant == "a":
            flt = make(*(DR_THETA,) * k)
            fn, radii = (lambda ys: jax.vmap(flt, in_axes=(None, None, 0))(model, prior, ys)), ()
        else:
            fn = lambda radii, ys: jax.vmap(make(*radii), in_axes=(None, None, 0))(model, prior, ys)
            radii = thetas
        t0 = time.perf_counter()
        # Compiled ahead of time; inner jit caches are cleared before each build so that no
        # build reuses another's traced functions (the patched (c) is built first, and no
        # cache is cleared after (b), the build whose run-time check is tested).
        jax.clear_caches()
        if variant == "c":
            Wasserstein.valid = lambda self: jnp.asarray(True)
        try:
            compiled = jax.jit(fn).lower(*((radii,) if radii else ()), ys).compile()
        finally:
            Wasserstein.valid = valid
        return compiled, radii, time.perf_counter() - t0

    rows, checks, cost = [], [], []
    for name, (make, k) in filters.items():
        thetas = tuple(jnp.asarray(DR_THETA, dtype) for _ in range(k))
        builds = {v: build(make, k, v, thetas) for v in "cab"}

        def call(v, radii=None, builds=builds):
            compiled, default, _ = builds[v]
            r = default if radii is None else radii
            return compiled(r, ys) if v != "a" else compiled(ys)

        outs = {v: jax.block_until_ready(call(v)) for v in "abc"}
        entry = {"B": args.dr_B, "dtype": dtype, "vs": f"{name}: (a), (b), (c) filtered means"}
        entry["max_abs_diff_means"] = max(maxabs(outs[v].filtered_means, outs["a"].filtered_means) for v in "bc")
        entry["ok"] = entry["max_abs_diff_means"] <= tol * max(1.0, float(np.max(np.abs(np.asarray(outs["a"].filtered_means)))))
        del outs
        bad = tuple(jnp.asarray(-DR_THETA, dtype) for _ in range(k))
        plain_fn = jax.jit(lambda r, ys: jax.vmap(make(*r), in_axes=(None, None, 0))(model, prior, ys))
        raised, outcome = {}, {}
        # (b) and (c) are the ahead-of-time builds; a plain jitted call of the same bad radii
        # (no ahead-of-time build) is a diagnostic. Each outcome is recorded: the exception
        # (its class, and the end of its message unless it carries the check's) or, when none was raised, the run's result
        # codes and whether its means are finite (a swallowed raise leaves NaN means).
        for v, fn in (("b", lambda: call("b", bad)), ("c", lambda: call("c", bad)), ("plain_jit", lambda: plain_fn(bad, ys))):
            try:
                out = jax.block_until_ready(fn())
                raised[v] = ""
                outcome[v] = (f"no exception; result codes {sorted(set(np.asarray(out.result._value).ravel().tolist()))}, "
                              f"means finite {bool(np.isfinite(np.asarray(out.filtered_means)).all())}")
                del out
            except Exception as e:  # noqa: BLE001 (the filter's error, whatever its class)
                raised[v] = str(e)
                text = " ".join(str(e).split())
                outcome[v] = type(e).__name__ + (" carrying the invalid-hyper-parameter message" if "hyper-parameter" in text
                                                 else f" ending: ...{text[-200:]}")
        b_flags = "hyper-parameter" in raised["b"]
        c_flags = "hyper-parameter" in raised["c"]
        entry["negative_radius_flagged"] = {"b": b_flags, "c": c_flags, "plain_jit": "hyper-parameter" in raised["plain_jit"]}
        entry["negative_radius_outcome"] = outcome
        entry["ok"] = bool(entry["ok"] and b_flags and not c_flags)
        checks.append(entry)
        log(f"[{dtype}] DR {name}: means diff {entry['max_abs_diff_means']:.3g}, θ<0 flagged by (b) {b_flags}, "
            f"by (c) {c_flags}, by a plain jit call {entry['negative_radius_flagged']['plain_jit']}" + (" ok" if entry["ok"] else " FAIL"))

        times = {v: [] for v in "abc"}
        for _ in range(args.repeats):
            for v in "abc":
                t0 = time.perf_counter()
                jax.block_until_ready(call(v))
                times[v].append(time.perf_counter() - t0)
        labels = {"a": "(a) concrete radii", "b": "(b) traced radii, run-time check",
                  "c": "(c) traced radii, check removed (measurement only)"}
        med = {v: statistics.median(times[v]) for v in "abc"}
        for v in "abc":
            rows.append({"impl": f"{name} {labels[v]}", "filter": name, "variant": v, "kind": "dr", "dtype": dtype,
                         "B": args.dr_B, "T": args.dr_T, "compile_s": builds[v][2], "run_s": med[v],
                         "run_min_s": min(times[v]), "run_times_s": times[v], "steps_per_s": args.dr_B * args.dr_T / med[v]})
        cost.append({"filter": name, "dtype": dtype, "B": args.dr_B, "T": args.dr_T,
                     "check_cost_b_over_c": med["b"] / med["c"], "traced_over_concrete_b_over_a": med["b"] / med["a"],
                     "pairwise_median_b_over_c": statistics.median(b / c for b, c in zip(times["b"], times["c"]))})
        log(f"[{dtype}] DR {name}: (b)/(c) = {cost[-1]['check_cost_b_over_c']:.3f}, (b)/(a) = {cost[-1]['traced_over_concrete_b_over_a']:.3f}")
    return {"theta": DR_THETA, "rows": rows, "checks": checks, "check_cost": cost, "checks_ok": all(c["ok"] for c in checks)}


# --------------------------------------------------------------------------- parent


GOALS = [  # (name, numerator row, denominator row, target)
    ("README tour / dynamax", "jdrkf README tour", "dynamax", 2.0),
    ("README tour / minimal scan+vmap KF", "jdrkf README tour", "minimal scan+vmap KF", 1.0),
    ("per-run (missing data) / NumPy", "jdrkf per-run (5% missing)", "numpy per-run (5% missing)", 1.0),
]


def goal_table(rows):
    out = []
    for dtype in sorted({r["dtype"] for r in rows}):
        for B in sorted({r["B"] for r in rows if r["dtype"] == dtype}):
            get = {r["impl"]: r for r in rows if r["dtype"] == dtype and r["B"] == B}
            for name, num, den, target in GOALS:
                if num in get and den in get and get[num]["steps_per_s"] and get[den]["steps_per_s"]:
                    ratio = get[num]["steps_per_s"] / get[den]["steps_per_s"]
                    out.append({"goal": name, "dtype": dtype, "B": B, "ratio": ratio, "target": target, "met": ratio >= target,
                                "ratio_best_of": get[den]["run_min_s"] / get[num]["run_min_s"]})
    return out


def build_markdown(result) -> str:
    meta, cfg = result["meta"], result["config"]
    lines = [
        f"# Kalman-filter throughput ({meta['platform_tag']}): jdrkf vs dynamax vs a minimal JAX KF vs NumPy",
        "",
        f"- Wang & Ye's (2022) system (n=2, m=1), T={cfg['T']}, data seed {cfg['seed']} (simulated with "
        f"{'jax.random on the device' if cfg.get('simulate') == 'device' else 'NumPy'}), {cfg['repeats']} interleaved rounds of timed calls per cell "
        "(median; best in the goal table), compile = first call − median.",
        f"- Machine: {meta['cpu_model']}, {meta['cpu_count']} cores; JAX device: {meta['device']}; "
        f"jax {meta['versions']['jax']}, dynamax {meta['versions']['dynamax']}, numpy {meta['versions']['numpy']}; "
        f"jdrkf source sha256 {next(iter(meta['jdrkf_source_sha256'].values()))['start']}.",
        "- `README tour`: `jax.jit(jax.vmap(KalmanFilter(outputs=\"filtered_means\"), in_axes=(None, None, 0)))`; "
        "`dynamax`: `jax.jit(jax.vmap(lgssm_filter, in_axes=(None, 0)))` (filtered means, covariances, marginal "
        "log-likelihood); `minimal scan+vmap KF`: the 15-line textbook filter in the script, filtered means; "
        "`per-run`: 5% of entries missing, a different mask per run, `observed=` mask (jdrkf) or the same "
        "decoupling in the batched NumPy KF; both return means, covariances, log-likelihoods.",
        "",
        "## Goals",
        "",
        "| goal | dtype | B | ratio (median) | ratio (best) | target | met |",
        "|---|---|---:|---:|---:|---:|---|",
    ]
    for g in result["goal"]:
        lines.append(f"| {g['goal']} | {g['dtype']} | {g['B']} | **{g['ratio']:.2f}** | {g['ratio_best_of']:.2f} | "
                     f"{g['target']:g} | {'yes' if g['met'] else 'no'} |")
    lines += ["", "## All rows", "",
              "| impl | kind | dtype | B | compile s | run s (median) | run s (best) | steps/s |",
              "|---|---|---|---:|---:|---:|---:|---:|"]
    for r in result["rows"]:
        if r.get("out_of_memory"):
            lines.append(f"| {r['impl']} | {r['kind']} | {r['dtype']} | {r['B']} | – | out of device memory | – | – |")
            continue
        comp = "n/a" if r["compile_s"] is None else f"{r['compile_s']:.2f}"
        lines.append(f"| {r['impl']} | {r['kind']} | {r['dtype']} | {r['B']} | {comp} | {r['run_s']:.4g} | "
                     f"{r['run_min_s']:.4g} | {r['steps_per_s']:.3g} |")
    lines += ["", "`kind`: `goal` rows are jdrkf as the README shows it; `peer` rows are the baselines as their users "
              "call them; `extra` rows are other jdrkf output settings, not goals.", "",
              "## Agreement checks (max abs differences)", "", "| dtype | B | vs | differences | ok |", "|---|---:|---|---|---|"]
    for ck in result["checks"]:
        diffs = ", ".join(f"{k.removeprefix('max_abs_diff_')} {v:.2e}" for k, v in ck.items() if k.startswith("max_abs"))
        lines.append(f"| {ck['dtype']} | {ck['B']} | {ck['vs']} | {diffs} | {'yes' if ck['ok'] else 'no'} |")
    dr = result.get("dr")
    if dr and dr["rows"]:
        lines += ["", "## DR rows: cost of the run-time hyper-parameter check", "",
                  (f"θ = {dr['theta']}, B = {dr['B']}, T = {dr['T']}; `jax.jit(jax.vmap(flt, in_axes=(None, None, 0)))`, "
                   "compiled ahead of time; (a) radii as Python floats (checked eagerly), (b) radii traced (range check "
                   "in the program), (c) as (b) with `Wasserstein.valid` patched to `True` in this script (measurement "
                   f"only); {cfg['repeats']} interleaved rounds, medians."), "",
                  "| filter | dtype | check cost (b)/(c) | pairwise median (b)/(c) | traced/concrete (b)/(a) |",
                  "|---|---|---:|---:|---:|"]
        for c in dr["check_cost"]:
            lines.append(f"| {c['filter']} | {c['dtype']} | **{c['check_cost_b_over_c']:.3f}** | "
                         f"{c['pairwise_median_b_over_c']:.3f} | {c['traced_over_concrete_b_over_a']:.3f} |")
        lines += ["", "| impl | dtype | compile s | run s (median) | run s (best) | steps/s |", "|---|---|---:|---:|---:|---:|"]
        for r in dr["rows"]:
            lines.append(f"| {r['impl']} | {r['dtype']} | {r['compile_s']:.2f} | {r['run_s']:.4g} | {r['run_min_s']:.4g} | "
                         f"{r['steps_per_s']:.3g} |")
        lines += ["", "| dtype | filter: (a), (b), (c) means agree | θ = −0.1 flagged by (b) / (c) | by a plain jit call | ok |",
                  "|---|---|---|---|---|"]
        yn = lambda x: "–" if x is None else ("yes" if x else "no")  # noqa: E731
        for ck in dr["checks"]:
            flags = ck["negative_radius_flagged"]
            lines.append(f"| {ck['dtype']} | {ck['vs']}: max abs diff {ck['max_abs_diff_means']:.2e} | "
                         f"{yn(flags['b'])} / {yn(flags['c'])} | {yn(flags.get('plain_jit'))} | {yn(ck['ok'])} |")
        outcomes = [(ck["vs"].split(":")[0], v, o) for ck in dr["checks"] for v, o in ck.get("negative_radius_outcome", {}).items()]
        if outcomes:
            lines += ["", "What the θ = −0.1 calls returned (build: outcome):", ""]
            lines += [f"- {name}, {v}: {o.replace('|', '/')}" for name, v, o in outcomes]
    return "\n".join(lines) + "\n"


def run_parent(args) -> int:
    t_start = time.perf_counter()
    out_dir = os.path.abspath(args.out)
    os.makedirs(out_dir, exist_ok=True)
    children = []
    with tempfile.TemporaryDirectory() as tmp:
        for dtype in args.dtypes:
            path = os.path.join(tmp, f"{dtype}.json")
            cmd = [sys.executable, os.path.abspath(__file__), "--child", "--dtype", dtype, "--child-out", path,
                   "--T", str(args.T), "--repeats", str(args.repeats), "--seed", str(args.seed),
                   "--platform", args.platform, "--simulate", args.simulate, "--numpy-max-runs", str(args.numpy_max_runs),
                   "--batch-sizes", *map(str, args.batch_sizes),
                   "--dr" if args.dr else "--no-dr", "--dr-B", str(args.dr_B), "--dr-T", str(args.dr_T),
                   "--dr-dtypes", *args.dr_dtypes]
            before = loadavg()
            proc = subprocess.run(cmd)
            if proc.returncode != 0:
                log(f"child for {dtype} failed with exit code {proc.returncode}")
                return proc.returncode
            with open(path) as f:
                res = json.load(f)
            res["loadavg"] = {"before": before, "after": loadavg()}
            children.append(res)
    rows = [r for c in children for r in c["rows"]]
    first = children[0]
    result = {
        "benchmark": "kf_throughput",
        "created": datetime.datetime.now(datetime.timezone.utc).isoformat(timespec="seconds"),
        "command": " ".join(["python", "benchmarks/kf_throughput.py", *sys.argv[1:]]),
        "wall_s": time.perf_counter() - t_start,
        "config": {"batch_sizes": args.batch_sizes, "T": args.T, "repeats": args.repeats, "seed": args.seed,
                   "dtypes": args.dtypes, "platform": args.platform, "simulate": args.simulate, "missing_fraction": MISSING_FRACTION,
                   "dr": args.dr, "dr_B": args.dr_B, "dr_T": args.dr_T, "dr_dtypes": args.dr_dtypes},
        "system": SYSTEM,
        "meta": {
            "cpu_model": cpu_model(), "cpu_count": os.cpu_count(), "platform": platform.platform(),
            "platform_tag": args.tag, "device": first["device"], "versions": first["versions"],
            "loadavg": {c["dtype"]: c["loadavg"] for c in children},
            "jdrkf_source_sha256": {c["dtype"]: c["jdrkf_source_sha256"] for c in children},
        },
        "rows": rows,
        "goal": goal_table(rows),
        "checks": [k for c in children for k in c["checks"]],
        "checks_ok": all(c["checks_ok"] for c in children),
        "dr": {"theta": DR_THETA, "B": args.dr_B, "T": args.dr_T,
               "rows": [r for c in children if c["dr"] for r in c["dr"]["rows"]],
               "checks": [k for c in children if c["dr"] for k in c["dr"]["checks"]],
               "check_cost": [k for c in children if c["dr"] for k in c["dr"]["check_cost"]]} if args.dr else None,
    }
    stem = os.path.join(out_dir, f"kf_throughput_{args.tag}")
    with open(stem + ".json", "w") as f:
        json.dump(result, f, indent=2)
    md = build_markdown(result)
    with open(stem + ".md", "w") as f:
        f.write(md)
    print(md)
    log(f"wrote {stem}.json and {stem}.md ({result['wall_s']:.0f} s)")
    if not result["checks_ok"]:
        failed = [f"{c['dtype']}: {ck['vs']}" for c in children for ck in c["checks"] if not ck["ok"]]
        failed += [f"{c['dtype']}: DR rows, {ck['vs']} and the θ < 0 calls"
                   for c in children if c.get("dr") for ck in c["dr"]["checks"] if not ck["ok"]]
        log("ERROR: checks failed (see the checks tables): " + "; ".join(failed))
        return 1
    return 0


def main(argv=None) -> int:
    here = os.path.dirname(os.path.abspath(__file__))
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--quick", action="store_true", help="smoke run: B=100, T=100")
    p.add_argument("--platform", choices=["cpu", "gpu"], default="cpu", help="JAX platform of the timed rows")
    p.add_argument("--batch-sizes", type=int, nargs="+", default=None, help="B values (default 1e4 on CPU, 1e4 1e5 1e6 on GPU)")
    p.add_argument("--T", type=int, default=None, help="time steps (default 1000)")
    p.add_argument("--repeats", type=int, default=7, help="timed rounds: every row called once per round (median reported)")
    p.add_argument("--numpy-max-runs", type=int, default=10_000, help="largest B for the per-run/NumPy rows")
    p.add_argument("--simulate", choices=["numpy", "device"], default=None,
                   help="where the data are simulated (default numpy on the CPU, device on a GPU)")
    p.add_argument("--seed", type=int, default=DATA_SEED, help="NumPy seed of the simulated data")
    p.add_argument("--dtypes", nargs="+", default=["float32", "float64"], choices=["float32", "float64"])
    p.add_argument("--dr", action=argparse.BooleanOptionalAction, default=True,
                   help="DR rows: cost of the run-time hyper-parameter check (default on)")
    p.add_argument("--dr-B", type=int, default=None, help="runs of the DR rows (default 2000; --quick 100)")
    p.add_argument("--dr-T", type=int, default=None, help="time steps of the DR rows (default 200; --quick 50)")
    p.add_argument("--dr-dtypes", nargs="+", default=["float64"], choices=["float32", "float64"],
                   help="dtypes of the DR rows (among --dtypes; default float64)")
    p.add_argument("--out", default=os.path.join(here, "results"), help="output directory")
    p.add_argument("--tag", default=None, help="output file stem suffix (default the platform, '_quick' appended)")
    p.add_argument("--child", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--dtype", choices=["float32", "float64"], help=argparse.SUPPRESS)
    p.add_argument("--child-out", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.batch_sizes is None:
        args.batch_sizes = [100] if args.quick else ([10_000, 100_000, 1_000_000] if args.platform == "gpu" else [10_000])
    if args.T is None:
        args.T = 100 if args.quick else 1000
    if args.simulate is None:
        args.simulate = "device" if args.platform == "gpu" else "numpy"
    if args.dr_B is None:
        args.dr_B = 100 if args.quick else 2000
    if args.dr_T is None:
        args.dr_T = 50 if args.quick else 200
    if args.tag is None:
        args.tag = args.platform + ("_quick" if args.quick else "")
    if args.child:
        set_platform(args.platform)
        with open(args.child_out, "w") as f:
            json.dump(run_child(args), f)
        return 0
    return run_parent(args)


if __name__ == "__main__":
    sys.exit(main())
