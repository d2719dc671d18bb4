"""Provenance helpers shared by the benchmark scripts: what machine, which versions and
which source produced a result."""

from __future__ import annotations

import hashlib
import importlib.metadata as md
import os
import platform
import subprocess
import sys

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


def portable_path(path: str) -> str:
    """`path` as recorded in a result file: relative to the repository root when inside it,
    else only its last component (records must not carry a machine's directories)."""
    path = os.path.abspath(path)
    inside = os.path.commonpath([path, ROOT]) == ROOT
    return os.path.relpath(path, ROOT) if inside else os.path.basename(path)


def parse_size(s: str) -> tuple[int, int]:
    n, m = s.lower().split("x")
    return int(n), int(m)


def set_platform(name: str) -> None:
    """Select the JAX platform of this benchmark process (`"cpu"` or `"gpu"`) before JAX
    starts, with jdrkf's large CPU pool (`jdrkf.use_large_cpu_pool`: jaxlib 0.10's batched
    LAPACK can deadlock otherwise); `"gpu"` fails early with a clear message when no GPU
    backend is available."""
    # "cuda,cpu": the GPU computes, and the host platform stays available to the host
    # callbacks of jdrkf's run-time checks (with "cuda" alone, the check's raise becomes
    # "pure_callback failed to find a local CPU device"; measured on an H200, 2026-11-28).
    os.environ["JAX_PLATFORMS"] = "cuda,cpu" if name == "gpu" else "cpu"
    import jdrkf

    jdrkf.use_large_cpu_pool()
    if "jax" in sys.modules:  # imported already (cvxpy imports it): JAX read the variable then
        sys.modules["jax"].config.update("jax_platforms", os.environ["JAX_PLATFORMS"])
    if name == "gpu":
        import jax

        try:
            jax.devices("gpu")
        except (RuntimeError, AssertionError) as e:  # AssertionError: jax 0.10 with jax_platforms set in the config
            raise SystemExit(f"--platform gpu: no GPU backend available to JAX ({str(e) or 'no visible NVIDIA GPU'}); install jax[cuda12] on a GPU machine") from e


def check_platform(name: str) -> None:
    """For a parent process that runs the timed work in children: fail early (exit status 1,
    set_platform's message) when `name` is "gpu" and JAX has no GPU backend. Checked in a
    short-lived subprocess, so that the parent never starts a JAX backend itself (on a GPU
    it would hold device memory the children need)."""
    if name == "cpu":
        return
    here = os.path.dirname(os.path.abspath(__file__))
    code = f"import sys; sys.path.insert(0, {here!r}); from _provenance import set_platform; set_platform({name!r})"
    if subprocess.run([sys.executable, "-c", code]).returncode != 0:
        raise SystemExit(1)


def device_summary(jax) -> str:
    """The devices JAX computes on and the platforms it was limited to, e.g. 'cpu (1 device;
    JAX_PLATFORMS=cpu)' or 'gpu: NVIDIA H100 80GB HBM3 (1 device; JAX_PLATFORMS=cuda)'."""
    devs = jax.devices()
    kind = devs[0].device_kind if devs[0].platform != "cpu" else ""
    platforms = os.environ.get("JAX_PLATFORMS")
    return (f"{devs[0].platform}{': ' + kind if kind else ''} ({len(devs)} device{'s' if len(devs) > 1 else ''}"
            f"{'; JAX_PLATFORMS=' + platforms if platforms else ''})")


def write_results(res: dict, stem: str, render, started: tuple[float, float], packages=("jax", "jaxlib", "numpy", "scipy", "jdrkf")) -> str:
    """Finish a results dict and write `stem.json` and `stem.md` (`render(res)`): wall and CPU
    seconds since `started = (time.time(), time.process_time())`, versions, git state, the
    library's source hash and the load average. Returns the portable stem for the log."""
    import json
    import time

    res["wall_s"] = time.time() - started[0]
    res["cpu_s"] = time.process_time() - started[1]
    res["provenance"] = {"versions": versions(packages), "git": git_info(), "jdrkf_source_sha256": package_source_hash(),
                         "loadavg": loadavg()}
    os.makedirs(os.path.dirname(stem) or ".", exist_ok=True)
    with open(stem + ".json", "w") as f:
        json.dump(res, f, indent=1, default=_json_default)
    with open(stem + ".md", "w") as f:
        f.write(render(res))
    return portable_path(stem)


def _json_default(x):
    """NumPy scalars and arrays in a results dict, as JSON."""
    import numpy as np

    if isinstance(x, np.ndarray):
        return x.tolist()
    if isinstance(x, (np.floating, np.integer, np.bool_)):
        return x.item()
    raise TypeError(f"not JSON serializable: {type(x).__name__}")
