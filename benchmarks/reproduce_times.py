"""Run time of every `jdrkf reproduce NAME` at its defaults (issue goal: ≤ 5 min on 2 cores).

Each experiment runs as its own process, `python -m jdrkf.cli reproduce NAME --no-progress`
(import, compilation, tuning and Monte Carlo included), one after the other. The table
records the wall time and the CPU time (user + system of the child) of each; on a quiet
2-core machine the wall time is what a user waits. `--store-reports` also writes each
printed report to `docs/reproductions/NAME.md` (and `NAME.json`), where the paper pages and
the differences table of the documentation include them.

    python benchmarks/reproduce_times.py                       # every experiment, defaults
    python benchmarks/reproduce_times.py chen-fusion jang-lqr  # some of them
    python benchmarks/reproduce_times.py --quick --out smoke/rt  # --quick runs (smoke test)

Writes `results/reproduce_times_cpu.{md,json}` (or `--out` + `.md`/`.json`).
"""

from __future__ import annotations

import argparse
import datetime
import json
import os
import pathlib
import resource
import subprocess
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import _provenance  # noqa: E402

ROOT = pathlib.Path(_provenance.ROOT)
GOAL_S = 300.0


def run_one(name: str, quick: bool, timeout: float, json_path: pathlib.Path | None = None) -> dict:
    """Run one reproduction in a child process; its wall and CPU seconds and report
    (`json_path`: the child also writes its JSON report there)."""
    cmd = [sys.executable, "-m", "jdrkf.cli", "reproduce", name, "--no-progress", *(["--quick"] if quick else []),
           *(["--json", str(json_path)] if json_path is not None else [])]
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    t0 = time.perf_counter()
    try:
        proc = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=timeout)
        status, stdout, stderr = proc.returncode, proc.stdout, proc.stderr
    except subprocess.TimeoutExpired as e:
        status, stdout, stderr = "timeout", e.stdout or "", e.stderr or ""
        stdout = stdout.decode() if isinstance(stdout, bytes) else stdout
        stderr = stderr.decode() if isinstance(stderr, bytes) else stderr
    wall = time.perf_counter() - t0
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return {"name": name, "status": status, "wall_s": wall, "cpu_s": cpu, "report": stdout,
            "stderr_tail": stderr[-2000:] if status != 0 else ""}


def _load(avg) -> str:
    return "n/a" if avg is None else " / ".join(f"{a:.1f}" for a in avg)


def markdown(result: dict) -> str:
    meta = result["meta"]
    lines = [
        f"# Run time of jdrkf reproduce at {'--quick' if meta['quick'] else 'the defaults'} ({meta['platform']})",
        "",
        f"- Machine: {meta['cpu']}, {meta['cores']} cores; load average at start {_load(meta['loadavg_start'])}, at end "
        f"{_load(meta['loadavg_end'])}; {meta['date']}; jax {meta['versions'].get('jax')}; commit {meta['git']['commit']}"
        f"{' (jdrkf modified)' if meta['git']['jdrkf_dirty'] else ''}.",
        "- Each experiment ran as its own process (`python -m jdrkf.cli reproduce NAME --no-progress"
        f"{' --quick' if meta['quick'] else ''}`), one after the other: import, compilation, tuning and Monte "
        "Carlo included. CPU = user + system time of the process.",
        f"- Goal: every default run within {GOAL_S:.0f} s on 2 cores; \"within goal\" checks the CPU time, which bounds "
        "the wall time of the same run on an otherwise idle machine (wall times measured while other jobs shared the "
        "cores are longer).",
        *([f"- Rows timed at different times (`--update`): each row gives its start and commit."] if "updated_from" in meta else []),
        "",
        "| experiment | runs | wall s | CPU s | status | within goal | timed |",
        "|---|---:|---:|---:|---|---|---|",
    ]
    for r in result["rows"]:
        ok = r["status"] == 0 and r["cpu_s"] <= GOAL_S
        lines.append(f"| {r['name']} | {r['runs']} | {r['wall_s']:.1f} | {r['cpu_s']:.1f} | "
                     f"{'ok' if r['status'] == 0 else r['status']} | {'yes' if ok else '**no**'} | "
                     f"{r['date']} ({r['commit'][:7]}) |")
    n_ok = sum(r["status"] == 0 and r["cpu_s"] <= GOAL_S for r in result["rows"])
    lines += ["", f"{n_ok} of {len(result['rows'])} within the goal; total wall time "
                  f"{sum(r['wall_s'] for r in result['rows']) / 60:.1f} min."]
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("names", nargs="*", help="experiments to time (default: all registered)")
    p.add_argument("--quick", action="store_true", help="time the --quick runs instead of the defaults")
    p.add_argument("--timeout", type=float, default=1800.0, help="seconds before a run is stopped (default 1800)")
    p.add_argument("--store-reports", action="store_true", help="write each report to docs/reproductions/NAME.md and .json")
    p.add_argument("--update", action="store_true",
                   help="keep the other experiments' rows of the existing results file (re-time some after a change)")
    p.add_argument("--out", type=pathlib.Path, default=None,
                   help="output path without suffix (default benchmarks/results/reproduce_times_cpu)")
    args = p.parse_args(argv)

    sys.path.insert(0, str(ROOT))
    from jdrkf import experiments

    names = args.names or sorted(experiments.EXPERIMENTS)
    for name in names:
        experiments.get(name)  # unknown names fail before anything runs
    meta = {"date": datetime.datetime.now().isoformat(timespec="seconds"), "platform": "cpu", "cpu": _provenance.cpu_model(),
            "cores": os.cpu_count(), "loadavg_start": _provenance.loadavg(), "quick": args.quick,
            "versions": _provenance.versions(), "git": _provenance.git_info()}
    rows = []
    for name in names:
        exp = experiments.get(name)
        store = ROOT / "docs" / "reproductions" / name if args.store_reports else None
        row = run_one(name, args.quick, args.timeout, None if store is None else store.with_suffix(".json"))
        row["runs"] = exp.options(quick=args.quick)["runs"]
        print(f"{name}: {row['status']}, wall {row['wall_s']:.1f} s, CPU {row['cpu_s']:.1f} s", flush=True)
        if row["status"] != 0:
            print(row["stderr_tail"], file=sys.stderr)
        elif args.store_reports:
            report = row["report"]
            store.with_suffix(".md").write_text(report[:report.rindex("\nreport: ")].rstrip() + "\n")  # less the CLI's "report: PATH" line
        rows.append(row)
    meta["loadavg_end"] = _provenance.loadavg()
    rows = [{**{k: v for k, v in r.items() if k != "report"}, "date": meta["date"], "commit": meta["git"]["commit"]} for r in rows]
    out = args.out or ROOT / "benchmarks" / "results" / "reproduce_times_cpu"
    if args.update and out.with_suffix(".json").is_file():
        old = json.loads(out.with_suffix(".json").read_text())
        if old["meta"]["quick"] != args.quick:
            raise SystemExit("--update: the existing results were timed in the other mode (--quick or not)")
        rows += [r for r in old["rows"] if r["name"] not in names]
        rows.sort(key=lambda r: r["name"])
        meta["updated_from"] = old["meta"]["date"]
    result = {"meta": meta, "goal_s": GOAL_S, "rows": rows}
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".json").write_text(json.dumps(result, indent=2))
    out.with_suffix(".md").write_text(markdown(result))
    print(f"wrote {out.with_suffix('.md')}")
    return 0 if all(r["status"] == 0 for r in rows) else 1


if __name__ == "__main__":
    sys.exit(main())
