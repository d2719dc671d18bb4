"""`import jdrkf` and `jdrkf --help` load no JAX; the lazy export table is complete and consistent."""

from __future__ import annotations

import ast
import importlib
import subprocess
import sys
from pathlib import Path

import jdrkf

INIT = Path(jdrkf.__file__)


def _child(code: str) -> str:
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    return proc.stdout


def test_import_and_help_load_no_jax():
    out = _child(
        "import sys, contextlib, io\n"
        "import jdrkf\n"
        "print('after import', 'jax' in sys.modules)\n"
        "from jdrkf import cli\n"
        "with contextlib.redirect_stdout(io.StringIO()):\n"
        "    try: cli.main(['--help'])\n"
        "    except SystemExit: pass\n"
        "print('after help', 'jax' in sys.modules, 'numpy' in sys.modules)\n"
        "jdrkf.KalmanFilter\n"
        "print('after use', 'jax' in sys.modules)\n"
    )
    assert "after import False" in out
    assert "after help False False" in out
    assert "after use True" in out  # the check above can fail: first use does import JAX


def test_every_export_resolves_to_its_defining_module():
    for name, module in jdrkf._EXPORTS.items():
        value = getattr(importlib.import_module(module, "jdrkf"), name)
        assert getattr(jdrkf, name) is value, name
    for sub in jdrkf._SUBMODULES:
        assert getattr(jdrkf, sub) is importlib.import_module(f"jdrkf.{sub}")
    assert set(dir(jdrkf)) == set(jdrkf.__all__)


def test_unknown_attribute_raises_attribute_error():
    try:
        jdrkf.NoSuchFilter  # noqa: B018
    except AttributeError as e:
        assert "NoSuchFilter" in str(e)
    else:
        raise AssertionError("expected AttributeError")


def test_type_checking_block_matches_the_table():
    """The `if TYPE_CHECKING:` imports (for IDEs) list exactly the lazy table's names and modules."""
    tree = ast.parse(INIT.read_text())
    block = next(n for n in tree.body if isinstance(n, ast.If) and getattr(n.test, "id", "") == "TYPE_CHECKING")
    static = {}
    subs = set()
    for node in block.body:
        assert isinstance(node, ast.ImportFrom)
        for alias in node.names:
            assert alias.asname in (None, alias.name)
            if node.module is None:
                subs.add(alias.name)
            else:
                static[alias.name] = "." + node.module
    assert static == jdrkf._EXPORTS
    assert subs == set(jdrkf._SUBMODULES)
