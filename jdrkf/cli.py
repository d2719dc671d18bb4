"""Command line: `jdrkf list`, `jdrkf reproduce NAME [--runs N] [--seed S] [--json PATH] [--plots DIR]`."""

from __future__ import annotations

import argparse
import json
import pathlib
import sys
import time


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="jdrkf", description="Robust and distributionally robust state estimation in JAX.")
    sub = p.add_subparsers(dest="command", required=True)
    sub.add_parser("list", help="list the registered paper reproductions")
    r = sub.add_parser("reproduce", help="run a paper reproduction and print paper vs ours")
    r.add_argument("name", help="experiment name (see `jdrkf list`)")
    r.add_argument("--runs", type=int, default=None, help="Monte Carlo runs (default: the experiment's)")
    r.add_argument("--seed", type=int, default=0, help="PRNG seed of the simulation (default 0)")
    r.add_argument("--json", type=pathlib.Path, default=None, help="write the table as JSON to this path")
    r.add_argument("--plots", type=pathlib.Path, default=None, help="write figures into this directory (needs matplotlib)")
    r.add_argument(
        "--precision", choices=("float64", "float32"), default="float64",
        help="floating-point precision of the whole run (default float64; this CLI process sets jax_enable_x64)",
    )
    r.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    return p


def main(argv: list[str] | None = None) -> int:
    args = _parser().parse_args(argv)
    if args.command == "reproduce":
        # The CLI is an application: it may choose the precision of its own process.
        # The library itself never changes jax_enable_x64.
        import jax

        jax.config.update("jax_enable_x64", args.precision == "float64")

    from . import experiments

    if args.command == "list":
        for name, exp in sorted(experiments.EXPERIMENTS.items()):
            print(f"{name:24s} {exp.description}")
        return 0

    try:
        exp = experiments.get(args.name)
    except ValueError as e:
        print(f"jdrkf: {e}", file=sys.stderr)
        return 2
    runs = exp.default_runs if args.runs is None else args.runs
    if runs < 2:
        print("jdrkf: --runs must be at least 2 (confidence intervals need two runs)", file=sys.stderr)
        return 2
    progress = not args.no_progress
    if progress:
        try:
            import tqdm  # noqa: F401
        except ImportError:
            print("(progress bar disabled: install tqdm, e.g. pip install 'jdrkf[cli]')", file=sys.stderr)
            progress = False
    t0 = time.perf_counter()
    report = exp.run(runs=runs, seed=args.seed, progress=progress, curves=args.plots is not None)
    elapsed = time.perf_counter() - t0
    print(report.table())
    print(f"\n({runs} runs, seed {args.seed}, {args.precision}, {elapsed:.1f} s)")
    if args.json is not None:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(report.to_json(), indent=2))
    if args.plots is not None:
        from .plotting import plot_error_curves, plot_sweeps

        if report.curves:
            print(f"figure: {plot_error_curves(report, args.plots / f'{report.experiment}.png')}")
        if report.sweeps:
            print(f"figure: {plot_sweeps(report, args.plots / f'{report.experiment}-sweeps.png')}")
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
