"""Provenance helpers shared by the benchmark scripts: what machine, which versions and
which source produced a result."""

from __future__ import annotations

import hashlib
import importlib.metadata as md
import os
import platform
import subprocess

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def cpu_model() -> str:
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def loadavg():
    try:
        return list(os.getloadavg())
    except OSError:
        return None


def package_source_hash(pkg=None) -> str:
    """sha256 over a package's .py files (default jdrkf; the library may be edited between runs)."""
    root = os.path.join(ROOT, "jdrkf") if pkg is None else os.path.dirname(os.path.abspath(pkg.__file__))
    h = hashlib.sha256()
    for dirpath, dirnames, filenames in sorted(os.walk(root)):
        dirnames.sort()
        for fn in sorted(filenames):
            if fn.endswith(".py"):
                path = os.path.join(dirpath, fn)
                h.update(os.path.relpath(path, root).encode())
                with open(path, "rb") as f:
                    h.update(f.read())
    return h.hexdigest()[:16]


def git_info() -> dict:
    def run(*cmd):
        try:
            return subprocess.run(["git", *cmd], cwd=ROOT, capture_output=True, text=True, check=True).stdout.strip()
        except (OSError, subprocess.CalledProcessError):
            return None

    status = run("status", "--porcelain", "--", "jdrkf")
    return {"commit": run("rev-parse", "HEAD"), "jdrkf_dirty": bool(status) if status is not None else None}


def versions(packages=("jax", "jaxlib", "equinox", "cvxpy", "clarabel", "numpy", "scipy", "jdrkf")) -> dict:
    out = {"python": platform.python_version()}
    for pkg in packages:
        try:
            out[pkg] = md.version(pkg)
        except md.PackageNotFoundError:
            out[pkg] = None
    return out


def parse_size(s: str) -> tuple[int, int]:
    n, m = s.lower().split("x")
    return int(n), int(m)
