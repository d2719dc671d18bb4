"""The intra-package import graph of `jdrkf` has no cycle.

The graph is read with `ast` from the source files: an edge `a -> b` for each import in
module `a` of a `jdrkf` module `b` (`from . import linalg` names the submodule, `from .x
import y` the module `x`). Module-level imports (including those under a module-level `if`
or `try`, excluding `if TYPE_CHECKING:` blocks) form the import-time graph, which must be
acyclic. Imports inside functions are deferred; they may not close a cycle either, except
the ones listed in `DEFERRED_ALLOWED`, each with its reason.
"""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent
PACKAGE = "jdrkf"

# Deferred imports that are allowed to point back down the layers, with the reason.
DEFERRED_ALLOWED = {
    # LinearModel.to_dynamax reuses the Kalman prediction for dynamax's initial law.
    ("jdrkf._models", "jdrkf.filters._kalman"),
}


def _modules() -> dict[str, tuple[Path, bool]]:
    out = {}
    for path in sorted((ROOT / PACKAGE).rglob("*.py")):
        parts = list(path.relative_to(ROOT).with_suffix("").parts)
        if "__pycache__" in parts:
            continue
        is_pkg = parts[-1] == "__init__"
        out[".".join(parts[:-1] if is_pkg else parts)] = (path, is_pkg)
    return out


def _is_type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or (
        isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"
    )


def _module_level_imports(body):
    for node in body:
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            yield node
        elif isinstance(node, ast.If):
            if not _is_type_checking(node.test):
                yield from _module_level_imports(node.body)
            yield from _module_level_imports(node.orelse)
        elif isinstance(node, ast.Try):
            for block in (node.body, node.orelse, node.finalbody, *(h.body for h in node.handlers)):
                yield from _module_level_imports(block)


def _targets(node, name: str, is_pkg: bool, modules) -> set[str]:
    if isinstance(node, ast.Import):
        names = [a.name for a in node.names]
    else:
        if node.level:
            base = name.split(".") if is_pkg else name.split(".")[:-1]
            base = base[: len(base) - (node.level - 1)]
            base = ".".join(base + ([node.module] if node.module else []))
        else:
            base = node.module
        names = [f"{base}.{a.name}" if f"{base}.{a.name}" in modules else base for a in node.names]
    out = set()
    for target in names:
        while target not in modules and "." in target:
            target = target.rsplit(".", 1)[0]
        if target in modules and target != name:
            out.add(target)
    return out


def import_graph(deferred: bool = False) -> dict[str, set[str]]:
    """Module-level import edges; with `deferred=True`, imports inside functions too."""
    modules = _modules()
    graph = {}
    for name, (path, is_pkg) in modules.items():
        tree = ast.parse(path.read_text(encoding="utf-8"))
        if deferred:
            nodes = [n for n in ast.walk(tree) if isinstance(n, (ast.Import, ast.ImportFrom))]
        else:
            nodes = list(_module_level_imports(tree.body))
        graph[name] = set().union(*(_targets(n, name, is_pkg, modules) for n in nodes))
    return graph


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One cycle `[a, b, ..., a]` of the directed graph, or `None` (iterative DFS)."""
    colour = dict.fromkeys(graph, 0)  # 0 unvisited, 1 on the stack, 2 done
    for root in sorted(graph):
        if colour[root]:
            continue
        stack, path = [(root, iter(sorted(graph[root])))], [root]
        colour[root] = 1
        while stack:
            node, children = stack[-1]
            child = next(children, None)
            if child is None:
                colour[node] = 2
                stack.pop()
                path.pop()
            elif colour.get(child, 2) == 1:
                return path[path.index(child):] + [child]
            elif colour.get(child, 2) == 0:
                colour[child] = 1
                stack.append((child, iter(sorted(graph[child]))))
                path.append(child)
    return None


def test_cycle_finder_finds_cycles():
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b", "c"}, "b": {"c"}, "c": set()}) is None


def test_graph_sees_known_edges():
    graph = import_graph()
    assert {"jdrkf._simulate", "jdrkf.linalg", "jdrkf._gaussian"} <= graph["jdrkf._nonlinear"]
    assert "jdrkf._models" in graph["jdrkf.filters._kalman"]  # from .._models import LinearModel
    assert "jdrkf._simulate" not in graph["jdrkf"]  # the lazy top level imports under TYPE_CHECKING only
    assert len(graph) > 40


def test_module_level_imports_have_no_cycle():
    assert find_cycle(import_graph()) is None


def test_deferred_imports_close_no_cycle():
    graph = import_graph(deferred=True)
    for a, b in DEFERRED_ALLOWED:
        assert b in graph[a], f"{a} no longer imports {b}: drop it from DEFERRED_ALLOWED"
        graph[a].discard(b)
    assert find_cycle(graph) is None


def _is_private(name: str) -> bool:
    return name.startswith("_") and not name.startswith("__")


def _base_module(node: ast.ImportFrom, name: str, is_pkg: bool) -> str:
    """The absolute module that `from ... import` reads from, inside module `name`."""
    if not node.level:
        return node.module or ""
    base = name.split(".") if is_pkg else name.split(".")[:-1]
    base = base[: len(base) - (node.level - 1)]
    return ".".join(base + ([node.module] if node.module else []))


def private_uses(name: str, is_pkg: bool, tree: ast.Module, modules) -> list[str]:
    """Single-underscore names that module `name` takes from another `jdrkf` module:
    `from .x import _y` (unless `_y` is a submodule) and `m._y` on a name `m` bound to an
    imported `jdrkf` module (unless `m._y` is a submodule)."""
    found, module_aliases = [], {}
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            base = _base_module(node, name, is_pkg)
            if base != PACKAGE and not base.startswith(PACKAGE + "."):
                continue
            for alias in node.names:
                target = f"{base}.{alias.name}"
                if target in modules:
                    module_aliases[alias.asname or alias.name] = target
                elif _is_private(alias.name) and base != name:
                    found.append(f"{name}:{node.lineno} from {base} import {alias.name}")
        elif isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name in modules:
                    module_aliases[alias.asname or alias.name] = alias.name if alias.asname else alias.name.split(".")[0]
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id in module_aliases:
            target = module_aliases[node.value.id]
            if _is_private(node.attr) and f"{target}.{node.attr}" not in modules and target != name:
                found.append(f"{name}:{node.lineno} {node.value.id}.{node.attr} ({target})")
    return found


def test_private_use_finder_finds_private_uses():
    modules = {"jdrkf", "jdrkf.a", "jdrkf.a._b", "jdrkf.c", "jdrkf._d"}
    src = (
        "from ._b import _hidden, visible\n"  # private name from a sibling module: found
        "from . import _b\n"  # a private submodule: fine
        "from .. import _d\n"
        "from .._d import _e as e\n"  # found (aliasing does not hide it)
        "import numpy as np\n"
        "x = _b._inner + _b.public + _d._f + np._private + self._g\n"  # `_b._inner`, `_d._f` found
    )
    found = private_uses("jdrkf.a", True, ast.parse(src), modules)
    assert sorted(f.split(" ", 1)[1] for f in found) == sorted([
        "from jdrkf.a._b import _hidden",
        "from jdrkf._d import _e",
        "_b._inner (jdrkf.a._b)",
        "_d._f (jdrkf._d)",
    ])
    assert private_uses("jdrkf.c", False, ast.parse("from . import _d\nfrom .a import visible\ny = _d.g"), modules) == []


def test_no_private_names_across_modules():
    """Modules share internal pieces under names without a leading underscore (in private
    modules such as `jdrkf.filters._steps`); a single-underscore name stays in its module."""
    modules = _modules()
    found = []
    for name, (path, is_pkg) in modules.items():
        found += private_uses(name, is_pkg, ast.parse(path.read_text(encoding="utf-8")), modules)
    assert not found, "private names used across modules:\n" + "\n".join(found)


def test_worst_case_solvers_live_in_sets_and_old_filter_names_warn():
    """Issue 19: worst-case problems are in `jdrkf.sets`; the names that moved out of
    `jdrkf.filters` still resolve there, with a DeprecationWarning, to the same objects."""
    import warnings

    import pytest

    import jdrkf

    moved = ("BCOTWorstCase", "bcot_worst_case", "CIWeights", "ci_weights", "covariance_intersection",
             "SteadyStateDR", "ThetaMax", "theta_max")
    for name in moved:
        new = getattr(jdrkf.sets, name)
        assert new.__module__.startswith("jdrkf.sets."), (name, new.__module__)
        with pytest.warns(DeprecationWarning, match=f"jdrkf.sets.{name}"):
            old = getattr(jdrkf.filters, name)
        assert old is new
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert jdrkf.theta_max is jdrkf.sets.theta_max and jdrkf.SteadyStateDR is jdrkf.sets.SteadyStateDR
    with pytest.raises(AttributeError, match="no_such_name"):
        jdrkf.filters.no_such_name  # noqa: B018
