"""Packaging: one version, a typed package, citation metadata.

The version lives in `jdrkf/_version.py` only; pyproject.toml declares it dynamic and
hatchling reads it from there. The oracles are the build backend (hatchling builds a
wheel here, when it is installed) and the installed distribution's metadata.
"""

from __future__ import annotations

import importlib.metadata
import re
import zipfile
from pathlib import Path

import pytest

import jdrkf

ROOT = Path(__file__).resolve().parent.parent


def test_pyproject_reads_the_version_from_the_package():
    tomllib = pytest.importorskip("tomllib")
    project = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))
    assert "version" not in project["project"] and project["project"]["dynamic"] == ["version"]
    assert project["tool"]["hatch"]["version"]["path"] == "jdrkf/_version.py"
    assert re.fullmatch(r"\d+\.\d+\.\d+([.-]?(a|b|rc|dev|post)\d+)?", jdrkf.__version__)


def test_installed_metadata_has_the_package_version():
    try:
        installed = importlib.metadata.version("jdrkf")
    except importlib.metadata.PackageNotFoundError:
        pytest.skip("jdrkf is not installed (running from a source tree)")
    assert installed == jdrkf.__version__, "reinstall (pip install -e .) after changing jdrkf/_version.py"


def test_wheel_is_typed_and_carries_the_version(tmp_path):
    pytest.importorskip("hatchling")
    from hatchling.builders.wheel import WheelBuilder

    (wheel,) = WheelBuilder(str(ROOT)).build(directory=str(tmp_path), versions=["standard"])
    with zipfile.ZipFile(wheel) as zf:
        names = set(zf.namelist())
        (meta,) = [n for n in names if n.endswith(".dist-info/METADATA")]
        metadata = zf.read(meta).decode()
    assert "jdrkf/py.typed" in names and "jdrkf/_version.py" in names
    assert re.search(r"^Version: (.+)$", metadata, re.MULTILINE).group(1) == jdrkf.__version__
    assert Path(wheel).name.startswith(f"jdrkf-{jdrkf.__version__}-")


def test_citation_file_is_valid_and_carries_no_second_version():
    yaml = pytest.importorskip("yaml")
    tomllib = pytest.importorskip("tomllib")
    cff = yaml.safe_load((ROOT / "CITATION.cff").read_text(encoding="utf-8"))
    project = tomllib.loads((ROOT / "pyproject.toml").read_text(encoding="utf-8"))["project"]
    assert cff["cff-version"] == "1.2.0" and cff["type"] == "software" and cff["message"]
    assert cff["license"] == project["license"]["text"]
    assert "version" not in cff  # the version lives in jdrkf/_version.py only
    assert all(a.get("name") or a.get("family-names") for a in cff["authors"])
    refs = cff["references"]
    assert len(refs) == 5  # the five papers whose estimators jdrkf implements
    for ref in refs:
        assert ref["type"] == "article" and ref["title"] and isinstance(ref["year"], int)
        assert all(a["family-names"] and a["given-names"] for a in ref["authors"])


def test_changelog_has_an_unreleased_section():
    changelog = (ROOT / "CHANGELOG.md").read_text(encoding="utf-8")
    assert changelog.startswith("# Changelog") and "\n## [Unreleased]\n" in changelog
