"""Command line: `jdrkf list`, `jdrkf reproduce NAME [--runs N] [--quick | --full] [--seed S] [--json PATH] [--plots DIR]
[--params FILE] [--distributed [--coordinator HOST:PORT --num-processes N --process-id I]]`,
`jdrkf tune NAME [--method grad|grid|random] [--budget B] [--runs N] [--seed S] [--quick] [--out DIR]`.

Everything that can be checked without computing is checked first — argument ranges,
that the output paths are writable, that the optional dependencies are importable —
and a failure is one line on stderr with exit status 2. JAX and the experiments are
imported only after these checks, inside `reproduce`/`list`.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import sys
import tempfile
import time

SEED_LIMIT = 2**32


class _Parser(argparse.ArgumentParser):
    def error(self, message):  # one line instead of argparse's usage block
        self.exit(2, f"jdrkf: error: {message} (see `{self.prog} --help`)\n")


def _int_at_least(lo: int, hi: int | None = None):
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
        if value < lo or (hi is not None and value >= hi):
            raise argparse.ArgumentTypeError(f"must be {'at least ' + str(lo) if hi is None else f'in [{lo}, {hi})'}, got {value}")
        return value

    return parse


def _number_at_least(lo: float):
    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
        if not value >= lo or value == float("inf"):
            raise argparse.ArgumentTypeError(f"must be a finite number at least {lo:g}, got {text}")
        return value

    return parse


def _parser() -> argparse.ArgumentParser:
    p = _Parser(prog="jdrkf", description="Robust and distributionally robust state estimation in JAX.")
    sub = p.add_subparsers(dest="command", required=True)
    sub.add_parser("list", help="list the registered paper reproductions with their default run counts")
    r = sub.add_parser("reproduce", help="run a paper reproduction and print paper vs ours")
    r.add_argument("name", help="experiment name (see `jdrkf list`)")
    r.add_argument("--runs", type=_int_at_least(2), default=None,
                   help="Monte Carlo runs, at least 2 (default: the experiment's; see `jdrkf list`)")
    mode = r.add_mutually_exclusive_group()
    mode.add_argument("--quick", action="store_true",
                      help="a small run count and problem size: a smoke test, not a reproduction")
    mode.add_argument("--full", action="store_true",
                      help="the paper's scale (run count, particles, horizons) where the default is cut to fit minutes; "
                           "see `jdrkf list`")
    r.add_argument("--seed", type=_int_at_least(0, SEED_LIMIT), default=0, help="PRNG seed of the simulation (default 0)")
    r.add_argument("--json", type=pathlib.Path, default=None, help="write the report as JSON to this file")
    r.add_argument("--plots", type=pathlib.Path, default=None, help="write figures into this directory (needs matplotlib)")
    r.add_argument(
        "--precision", choices=("float64", "float32"), default="float64",
        help="floating-point precision of the whole run (default float64; this CLI process sets jax_enable_x64)",
    )
    r.add_argument("--progress", action=argparse.BooleanOptionalAction, default=None,
                   help="progress bars on stderr (default: only when stderr is a terminal)")
    r.add_argument("--params", type=pathlib.Path, default=None,
                   help="also evaluate the filters with the parameters tuned by `jdrkf tune NAME` (its JSON file)")
    r.add_argument("--distributed", action="store_true",
                   help="start JAX's distributed runtime first (jax.distributed.initialize(), which reads a cluster's "
                        "layout, e.g. SLURM's): Monte Carlo runs are split over the devices of all processes, and only "
                        "process 0 prints and writes files")
    r.add_argument("--coordinator", metavar="HOST:PORT", default=None,
                   help="with --distributed, a manual launch: process 0's address (needs --num-processes and --process-id)")
    r.add_argument("--num-processes", type=_int_at_least(1), default=None, help="with --coordinator: the number of processes")
    r.add_argument("--process-id", type=_int_at_least(0), default=None, help="with --coordinator: this process's index")
    t = sub.add_parser("tune", help="tune the filters of an experiment on training runs, score them on held-out runs")
    t.add_argument("name", help="experiment name with a tuning problem: wang-ye-table1/2/3, chen-fusion, li-torsion, wang-growth, jang-lqr")
    t.add_argument("--method", choices=("grad", "grid", "random"), default="grad",
                   help="gradient (Adam through the filters), a full grid, or random search (default grad)")
    t.add_argument("--budget", type=_number_at_least(1.0), default=None,
                   help="cost in forward-filter-equivalents (default 100, 20 with --quick); grid: ⌊budget^(1/d)⌋ points per axis")
    t.add_argument("--runs", type=_int_at_least(2), default=None,
                   help="training runs, and as many held-out runs from another key (default 16, 4 with --quick)")
    t.add_argument("--seed", type=_int_at_least(0, SEED_LIMIT), default=0, help="PRNG seed of the simulation (default 0)")
    t.add_argument("--quick", action="store_true", help="shorter runs and a small default budget: a smoke test")
    t.add_argument("--out", type=pathlib.Path, default=None,
                   help="write tune-NAME-METHOD.json and a convergence plot (.png) into this directory (needs matplotlib)")
    t.add_argument("--progress", action=argparse.BooleanOptionalAction, default=None,
                   help="progress bars on stderr (default: only when stderr is a terminal)")
    return p


def _fail(message: str) -> int:
    print(f"jdrkf: error: {message}", file=sys.stderr)
    return 2


def _check_file(path: pathlib.Path) -> str | None:
    """Why `path` cannot be written as a file (None if it can): creates missing parent
    directories and opens the file for appending; a file that did not exist is removed again."""
    if path.is_dir():
        return "it is a directory"
    existed = path.exists()
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with open(path, "a"):
            pass
    except OSError as e:
        return e.strerror or str(e)
    if not existed:
        path.unlink(missing_ok=True)  # with --distributed, every process checks the same path
    return None


def _check_dir(path: pathlib.Path) -> str | None:
    """Why no file can be written into directory `path` (None if it can); creates it."""
    try:
        path.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=path):
            pass
    except OSError as e:
        return e.strerror or str(e)
    return None


def _validate(args) -> str | None:
    """The first problem of a `reproduce` command line that shows before computing."""
    if args.json is not None and (why := _check_file(args.json)):
        return f"cannot write --json {args.json}: {why}"
    if args.plots is not None:
        if (why := _check_dir(args.plots)):
            return f"cannot write --plots into {args.plots}: {why}"
        try:
            import matplotlib.figure  # noqa: F401
        except ImportError as e:
            return f"--plots needs matplotlib ({e}); install it with pip install 'jdrkf[cli]'"
    if args.progress:
        try:
            import tqdm  # noqa: F401
        except ImportError as e:
            return f"--progress needs tqdm ({e}); install it with pip install 'jdrkf[cli]'"
    return None


def _progress_wanted(flag: bool | None) -> bool:
    if flag is not None:
        return flag
    if not sys.stderr.isatty():
        return False
    try:
        import tqdm  # noqa: F401
    except ImportError:
        return False
    return True


def _tune(args) -> int:
    """`jdrkf tune`: checks, then `jdrkf.experiments._tune.command` under a progress reporter."""
    if args.out is not None:
        if (why := _check_dir(args.out)):
            return _fail(f"cannot write --out into {args.out}: {why}")
        try:
            import matplotlib.figure  # noqa: F401
        except ImportError as e:
            return _fail(f"--out needs matplotlib ({e}); install it with pip install 'jdrkf[cli]'")
    if args.progress:
        try:
            import tqdm  # noqa: F401
        except ImportError as e:
            return _fail(f"--progress needs tqdm ({e}); install it with pip install 'jdrkf[cli]'")
    import jax

    jax.config.update("jax_enable_x64", True)  # the CLI's own process (gradients are checked in float64)
    from ._progress import Quiet, TqdmReporter, reporting
    from .experiments import _tune

    try:
        _tune.problems(args.name, args.quick)
    except ValueError as e:
        return _fail(str(e))
    with reporting(TqdmReporter() if _progress_wanted(args.progress) else Quiet()):
        _tune.command(args.name, method=args.method, budget=args.budget, runs=args.runs, seed=args.seed,
                      quick=args.quick, out=args.out)
    return 0


def _distributed_problem(args) -> str | None:
    """What is wrong with the `--distributed` options of a `reproduce` command line."""
    manual = {"--coordinator": args.coordinator, "--num-processes": args.num_processes, "--process-id": args.process_id}
    given = [k for k, v in manual.items() if v is not None]
    if given and not args.distributed:
        return f"{', '.join(given)} only apply with --distributed"
    if given and len(given) < len(manual):
        return f"{' and '.join(k for k in manual if k not in given)} must be given with {', '.join(given)} (a manual launch)"
    if given and args.process_id >= args.num_processes:
        return f"--process-id must be below --num-processes ({args.num_processes}), got {args.process_id}"
    return None


def _start_distributed(args) -> str | None:
    """`jax.distributed.initialize` (before any JAX computation); why it failed, or None."""
    import jax

    manual = {} if args.coordinator is None else {
        "coordinator_address": args.coordinator, "num_processes": args.num_processes, "process_id": args.process_id}
    try:
        jax.distributed.initialize(**manual)
    except Exception as e:  # noqa: BLE001 - whatever stops the runtime from starting is reported in one line
        hint = "" if manual else ("; outside a cluster that JAX detects (e.g. SLURM), pass --coordinator HOST:PORT "
                                  "--num-processes N --process-id I")
        return f"--distributed: jax.distributed.initialize() failed: {' '.join(str(e).split()).rstrip('.')}{hint}"
    return None


def main(argv: list[str] | None = None) -> int:
    from ._cpu_pool import use_large_cpu_pool

    use_large_cpu_pool()  # an application may size its CPU pool; before any JAX computation (jaxlib 0.10 deadlock)
    parser = _parser()
    args = parser.parse_args(argv)
    if args.command == "reproduce" and (problem := _distributed_problem(args)):
        parser.error(problem)
    if args.command == "tune":
        return _tune(args)
    if args.command == "reproduce" and (problem := _validate(args)):
        return _fail(problem)
    if args.command == "reproduce":
        # The CLI is an application: it may choose the precision of its own process.
        # The library itself never changes jax_enable_x64.
        import jax

        jax.config.update("jax_enable_x64", args.precision == "float64")
        if args.distributed and (problem := _start_distributed(args)):
            return _fail(problem)

    from . import experiments

    if args.command == "list":
        print(f"{'name':24s} {'runs':>5s} {'time':>10s} {'quick':>5s} {'time':>6s} {'full':>5s} {'time':>11s}  description")
        for name, exp in sorted(experiments.EXPERIMENTS.items()):
            full = ("—", "") if exp.full is None else (exp.full["runs"], exp.time_estimate(full=True))
            print(f"{name:24s} {exp.default_runs:5d} {exp.time_estimate():>10s} {exp.options(quick=True)['runs']:5d} "
                  f"{exp.time_estimate(quick=True):>6s} {full[0]:>5} {full[1]:>11s}  {exp.description}")
        print(f"\nruns: default Monte Carlo runs; quick: the runs of --quick (which also shrinks horizons and grids); "
              "full: the runs of --full, the paper's scale where the default is cut to fit minutes (—: the default is "
              f"the paper's scale); time: CPU time of the whole command on a {experiments.MEASURED_ON}, roughly an upper "
              "bound of its wall time on an otherwise idle machine (est.: scaled up from smaller runs; —: not measured).")
        return 0

    from .experiments._tune import load_params

    try:
        exp = experiments.get(args.name)
        exp.options(quick=args.quick, full=args.full)  # --full on an experiment without a paper-scale mode
        params = None if args.params is None else load_params(args.params, args.name)
    except ValueError as e:
        return _fail(str(e))
    from ._progress import Quiet, TqdmReporter, reporting

    lead = jax.process_index() == 0  # with --distributed, only process 0 reports
    show = lead and _progress_wanted(args.progress)
    if show and args.runs is None and (expected := exp.time_estimate(quick=args.quick, full=args.full)) != "—":
        print(f"{exp.name}: expect about {expected} (CPU time measured on a {experiments.MEASURED_ON})", file=sys.stderr)
    with reporting(TqdmReporter() if show else Quiet()) as reporter:
        t0 = time.perf_counter()
        report = exp.reproduce(args.runs, args.seed, quick=args.quick, full=args.full, curves=args.plots is not None,
                               settings={"precision": args.precision},
                               params=params)
        report.settings["wall time"] = f"{time.perf_counter() - t0:.1f} s"
        if not lead:
            return 0
        print(report.table(), flush=True)
        if args.json is not None:
            args.json.write_text(json.dumps(report.to_json(), indent=2))
            print(f"\nreport: {args.json}")
        if args.plots is not None:
            from .plotting import plot_error_curves, plot_sweeps

            figures = [(plot_error_curves, f"{report.experiment}.png")] * bool(report.curves)
            figures += [(plot_sweeps, f"{report.experiment}-sweeps.png")] * bool(report.sweeps)
            paths = []
            with reporter.phase("plotting", total=len(figures), unit="figure") as bar:
                for plot, filename in figures:
                    paths.append(plot(report, args.plots / filename))
                    bar.update()
            for path in paths:
                print(f"figure: {path}")
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
