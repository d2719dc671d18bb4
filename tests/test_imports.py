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
