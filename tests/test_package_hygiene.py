"""The package, its docs and benchmark records stand alone: no text points to files outside
the repository (development notes, paper seeds) or to a machine's directories.

Scanned: text files (`.py`, `.md`, `.json`, `.ipynb`, `.txt`) under `jdrkf/`, `docs/`,
`benchmarks/`, plus `README.md`, and the cell sources (not the outputs) of
`notebooks/*.ipynb`. The forbidden strings are assembled from parts below, so this file
does not match itself.
"""

from __future__ import annotations

import json
import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
SCANNED_DIRS = ("jdrkf", "docs", "benchmarks")
SCANNED_FILES = ("README.md",)
SUFFIXES = {".py", ".md", ".json", ".ipynb", ".txt"}
SKIPPED_DIRS = {"__pycache__", ".ipynb_checkpoints"}

# References to material that users of the package never see.
_FORBIDDEN = (
    ".." + "/shared",
    "algorithms" + ".md",
    "reference-" + "settings",
    "ARCHITECTURE" + ".md",
    "architecture-" + "notes",
)
# The paper seeds of the development set-up: "seed 003", "seed-004", "Seed 000's".
_SEED = re.compile(r"(?i)\b" + "se" + r"ed[ _-]?00\d")
# Absolute directories of some machine: /work/…, /home/…, /tmp/…, /Users/…, C:\Users\….
_MACHINE_PATH = re.compile("(?<![A-Za-z0-9_.~-])/(?:" + "|".join(["wo" + "rk", "ho" + "me", "t" + "mp", "Us" + "ers"]) + ")/"
                           r"|[A-Za-z]:\\" + "Us" + r"ers\\")


def _text_files():
    files = [ROOT / f for f in SCANNED_FILES if (ROOT / f).is_file()]
    for d in SCANNED_DIRS:
        for path in sorted((ROOT / d).rglob("*")):
            if path.is_file() and path.suffix in SUFFIXES and not SKIPPED_DIRS & set(path.relative_to(ROOT).parts):
                files.append(path)
    return files


def _notebook_sources():
    for path in sorted((ROOT / "notebooks").glob("*.ipynb")):
        cells = json.loads(path.read_text(encoding="utf-8"))["cells"]
        text = "\n".join("".join(c["source"]) if isinstance(c["source"], list) else c["source"] for c in cells)
        yield path, text


def _offences(text):
    out = []
    for lineno, line in enumerate(text.splitlines(), start=1):
        hits = [s for s in _FORBIDDEN if s in line]
        hits += [m.group(0) for pattern in (_SEED, _MACHINE_PATH) for m in pattern.finditer(line)]
        out.extend(f"{lineno}: {h!r} in {line.strip()[:120]!r}" for h in hits)
    return out


def _scan():
    found = {}
    for path in _text_files():
        if path == Path(__file__).resolve():
            continue
        bad = _offences(path.read_text(encoding="utf-8", errors="replace"))
        if bad:
            found[str(path.relative_to(ROOT))] = bad
    for path, text in _notebook_sources():
        bad = _offences(text)
        if bad:
            found[str(path.relative_to(ROOT))] = bad
    return found


def test_scan_covers_the_package():
    names = {p.relative_to(ROOT).as_posix() for p in _text_files()}
    assert "jdrkf/__init__.py" in names and "README.md" in names
    assert any(n.startswith("jdrkf/filters/") for n in names)
    assert any(n.startswith("benchmarks/") for n in names)


@pytest.mark.parametrize(
    "line",
    [
        "see " + "seed" + " 003, Sec. V",
        "the " + "Seed" + "-004 experiments",
        "`.." + "/shared/docs/x`",
        "(algorithms" + ".md §A.1)",
        "the reference-" + "settings notes",
        '"out": "/' + 'work/main/benchmarks/results"',
        "python x.py --out /" + "tmp/ws",
        "/" + "home/user/jdrkf",
        "C:\\" + "Users\\me\\jdrkf",
    ],
)
def test_detector_flags(line):
    assert _offences(line)


@pytest.mark.parametrize(
    "line",
    [
        "Wang & Ye (2022), Eq. (14); see `docs/math/wasserstein.md`",
        "benchmarks/results/marginal_solver_cpu.json",
        "python benchmarks/kf_throughput.py --quick --out smoke/kf",
        "a network/work/queue; seed 1, seed 10",
        "https://github.com/owner/repo/tree/main/work/x",
    ],
)
def test_detector_passes(line):
    assert not _offences(line)


def test_no_outside_references_or_machine_paths():
    found = _scan()
    assert not found, "references outside the repository or machine paths:\n" + "\n".join(
        f"{f}:{hit}" for f, hits in found.items() for hit in hits
    )
