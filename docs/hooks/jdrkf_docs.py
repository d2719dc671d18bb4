"""MkDocs hook of the jdrkf site: pages that reuse the repository's own files instead of copies.

- Every `notebooks/*.ipynb` becomes a page `notebooks/<name>/` (rendered by mkdocs-jupyter from its
  stored outputs), and every `benchmarks/results/*_cpu.md` a page `benchmarks/<name>/`, so new
  notebooks and benchmark results appear without editing the site's configuration.
- In a page, a line `<!-- readme: Heading -->` is replaced by the body of the README section
  `## Heading` (`<!-- readme: (top) -->`: the text before the first section), and a line
  `<!-- report: name -->` by the stored report `docs/reproductions/<name>.md` of
  `jdrkf reproduce name`. A missing section or report fails the build.
- `<!-- api: package -->` expands to one mkdocstrings block per public name that the package's
  `__init__.py` re-exports (for `jdrkf`: its lazy export table, less the filters, which have their
  own page), so the API pages follow the exports.
"""

from __future__ import annotations

import ast
import pathlib
import re

from mkdocs.exceptions import PluginError
from mkdocs.plugins import event_priority
from mkdocs.structure.files import File, Files

ROOT = pathlib.Path(__file__).resolve().parents[2]
_DIRECTIVE = re.compile(r"^<!-- (readme|report|api): (.+?) -->[ \t]*$", re.M)


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
