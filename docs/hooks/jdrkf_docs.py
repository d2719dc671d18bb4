"""MkDocs hook of the jdrkf site: pages that reuse the repository's own files instead of copies.

- Every `notebooks/*.ipynb` becomes a page `notebooks/<name>/` (rendered by mkdocs-jupyter from its
  stored outputs), and every `benchmarks/results/*_cpu.md` a page `benchmarks/<name>/`, so new
  notebooks and benchmark results appear without editing the site's configuration.
- In a page, a line `<!-- readme: Heading -->` is replaced by the body of the README section
  `## Heading` (`<!-- readme: (top) -->`: the text before the first section), and a line
  `<!-- report: name -->` by the stored report `docs/reproductions/<name>.md` of
  `jdrkf reproduce name`. A missing section or report fails the build.
- `<!-- differences: all -->` expands to the table of every paper number outside our 95% interval
  in the stored JSON reports (`docs/reproductions/<name>.json`, written by
  `benchmarks/reproduce_times.py --store-reports`), with the cause from
  `docs/reproductions/differences.toml` or, where the paper's number is one episode (or a small
  average) and lies inside the spread of our runs, that computed explanation.
- `<!-- api: package -->` expands to one mkdocstrings block per public name that the package's
  `__init__.py` re-exports (for `jdrkf`: its lazy export table, less the filters, which have their
  own page), so the API pages follow the exports.
"""

from __future__ import annotations

import ast
import json
import math
import pathlib
import re
import tomllib

from mkdocs.exceptions import PluginError
from mkdocs.plugins import event_priority
from mkdocs.structure.files import File, Files

ROOT = pathlib.Path(__file__).resolve().parents[2]
_DIRECTIVE = re.compile(r"^<!-- (readme|report|api|differences): (.+?) -->[ \t]*$", re.M)


def _readme_section(heading: str) -> str:
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    # Split on level-2 headings outside code blocks (README code blocks hold only `# comments`).
    parts = re.split(r"^## (.+)\n", text, flags=re.M)
    if heading == "(top)":
        return re.sub(r"\A# .*\n", "", parts[0]).strip()
    sections = dict(zip(parts[1::2], parts[2::2]))
    if heading not in sections:
        raise PluginError(f"README.md has no section '## {heading}' (sections: {', '.join(sections)})")
    return sections[heading].strip()


def _report(name: str) -> str:
    path = ROOT / "docs" / "reproductions" / f"{name}.md"
    if not path.is_file():
        raise PluginError(f"no stored report {path.relative_to(ROOT)}: run `jdrkf reproduce {name} > {path.relative_to(ROOT)}`")
    # A report is plain text, one statement a line ("Scenario: …", "Metric: …", list items, a
    # table): each line is its own paragraph, except within a table and within a list.
    lines = path.read_text(encoding="utf-8").strip().splitlines()
    out = lines[:1]
    for prev, line in zip(lines, lines[1:]):
        together = (prev.startswith("|") and line.startswith("|")) or (prev.startswith("- ") and line.startswith("- "))
        if prev.strip() and line.strip() and not together:
            out.append("")
        out.append(line)
    return "\n".join(out)


def _fmt(x: float) -> str:
    return f"{x:.4g}"


def _spread_cause(row: dict, paper_runs: int) -> str | None:
    """The computed explanation of a paper number outside our interval, if the spread of our
    runs covers it: a single episode inside the central 95% of our per-run values, or an
    average of `paper_runs` episodes within 1.96 sd/√paper_runs of our mean."""
    if paper_runs == 1 and row.get("paper_percentile") is not None:
        pct = row["paper_percentile"]
        if 2.5 <= pct <= 97.5:
            return f"one random episode in the paper; {pct:.0f}% of our per-run values lie at or below its number"
    elif paper_runs > 1 and row.get("sd") is not None:
        z = abs(row["paper"] - row["mean"]) / (row["sd"] / math.sqrt(paper_runs))
        if z <= 1.96:
            return (f"the paper averages {paper_runs} episodes; its number is {z:.1f} standard errors of a "
                    f"{paper_runs}-episode mean from ours")
    return None


def _differences(_: str) -> str:
    """Markdown table: every row of the stored JSON reports whose paper number lies outside
    our 95% interval, with its cause (curated, or computed by `_spread_cause`)."""
    folder = ROOT / "docs" / "reproductions"
    spec = tomllib.loads((folder / "differences.toml").read_text(encoding="utf-8"))
    runs_of, causes = spec["paper_runs"], spec.get("cause", [])
    reports = sorted(folder.glob("*.json"))
    if not reports:
        raise PluginError("differences: no stored JSON report in docs/reproductions/ (benchmarks/reproduce_times.py --store-reports)")
    lines = ["| experiment | filter | metric | paper | ours (95% CI) | cause | evidence |", "|---|---|---|---:|---|---|---|"]
    for path in reports:
        report = json.loads(path.read_text(encoding="utf-8"))
        name = report["experiment"]
        if name not in runs_of:
            raise PluginError(f"differences.toml: no paper_runs entry for {name!r}")
        for row in report["rows"]:
            if not row.get("outside_ci"):
                continue
            curated = [c for c in causes if c["experiment"] == name and c.get("filter", row["filter"]) == row["filter"]
                       and c.get("metric", "") in row["metric"]]
            if curated:
                cause, evidence = curated[0]["cause"], curated[0]["evidence"]
            else:
                computed = _spread_cause(row, runs_of[name])
                cause, evidence = (computed, "this table (the stored run)") if computed else ("**not explained**", "—")
            lo, hi = row["ci95"]
            lines.append(f"| {name} | {row['filter']} | {row['metric']} | {_fmt(row['paper'])} | {_fmt(row['mean'])} "
                         f"[{_fmt(lo)}, {_fmt(hi)}] | {cause} | {evidence} |")
    return "\n".join(lines)


def _api(module: str) -> str:
    """One mkdocstrings block per public name of package `module`, in the order of its
    `__init__.py`: the names it re-exports (`from ._x import Y as Y`), or for `jdrkf` the
    non-filter names of its lazy export table."""
    init = ROOT.joinpath(*module.split("."), "__init__.py")
    if not init.is_file():
        raise PluginError(f"api directive: no package {module!r}")
    tree = ast.parse(init.read_text(encoding="utf-8"))
    if module == "jdrkf":
        exports = next(
            ast.literal_eval(node.value)
            for node in tree.body
            if isinstance(node, ast.AnnAssign) and getattr(node.target, "id", None) == "_EXPORTS"
        )
        names = [name for name, origin in exports.items() if origin != ".filters"]
    else:
        names = [
            alias.asname
            for node in tree.body
            if isinstance(node, ast.ImportFrom)
            for alias in node.names
            if alias.asname and not alias.asname.startswith("_")
        ]
    return "\n\n".join(f"::: {module}.{name}" for name in names)


def _expand(match: re.Match) -> str:
    kind, arg = match.group(1), match.group(2).strip()
    if kind == "readme":
        return _readme_section(arg)
    if kind == "report":
        return _report(arg)
    if kind == "differences":
        return _differences(arg)
    return _api(arg)


def result_page(filename: str) -> str:
    """The site page of a stored result: `NAME_cpu.md` -> `NAME`, `NAME_gpu.md` -> `NAME-gpu`."""
    return filename.removesuffix("_cpu.md") if filename.endswith("_cpu.md") else filename.removesuffix("_gpu.md") + "-gpu"


@event_priority(100)  # before mkdocs-jupyter, which turns .ipynb files into pages
def on_files(files: Files, config) -> Files:
    for nb in sorted((ROOT / "notebooks").glob("*.ipynb")):
        files.append(File(f"notebooks/{nb.name}", str(ROOT), config["site_dir"], config["use_directory_urls"]))
    for result in sorted((ROOT / "benchmarks" / "results").glob("*_[cg]pu.md")):
        files.append(File.generated(config, f"benchmarks/{result_page(result.name)}.md", abs_src_path=str(result)))
    for figure in sorted((ROOT / "benchmarks" / "results").glob("*_cpu_*.png")):  # plots the pages show
        files.append(File.generated(config, f"benchmarks/{figure.name}", abs_src_path=str(figure)))
    return files


def on_page_markdown(markdown: str, page, config, files) -> str:
    return _DIRECTIVE.sub(_expand, markdown)
