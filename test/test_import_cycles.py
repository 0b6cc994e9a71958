"""No import circles in vmocap_core and vmocap_ros.

The import graph is built from the source (AST), so it sees every import: module level,
inside functions, under TYPE_CHECKING, and `importlib.import_module("...")` with a constant
name. A function-level import that closes a circle still ties the two modules together, so it
counts. Edges go to the module named; a `from pkg import name` goes to `pkg.name` when that is a
module of ours, else to `pkg` (its __init__).
"""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PACKAGES = ("vmocap_core", "vmocap_ros")


def _modules(root: Path) -> dict[str, Path]:
    """Dotted module name -> file, for every .py file of our packages."""
    found: dict[str, Path] = {}
    for package in PACKAGES:
        for path in sorted((root / package).rglob("*.py")):
            parts = list(path.relative_to(root).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts.pop()
            found[".".join(parts)] = path
    return found


def _base(module: str, is_package: bool, level: int, name: str | None) -> str:
    """The absolute module a (possibly relative) import statement names."""
    if level == 0:
        return name or ""
    # A relative import resolves against the package: the module itself for an __init__.
    anchor = module.split(".") if is_package else module.split(".")[:-1]
    anchor = anchor[: len(anchor) - (level - 1)]
    return ".".join(anchor + ([name] if name else []))


def _ours(target: str, modules: dict[str, Path]) -> str | None:
    """The longest prefix of `target` that is one of our modules (a.b.c -> a.b when c is a name)."""
    parts = target.split(".")
    while parts:
        candidate = ".".join(parts)
        if candidate in modules:
            return candidate
        parts.pop()
    return None


def _edges(module: str, path: Path, modules: dict[str, Path]) -> set[str]:
    tree = ast.parse(path.read_text(), filename=str(path))
    is_package = path.name == "__init__.py"
    named: list[str] = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            named += [alias.name for alias in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = _base(module, is_package, node.level, node.module)
            named += [f"{base}.{alias.name}" for alias in node.names]
        elif (
            isinstance(node, ast.Call)
            and isinstance(node.func, ast.Attribute)
            and node.func.attr == "import_module"
            and node.args
            and isinstance(node.args[0], ast.Constant)
            and isinstance(node.args[0].value, str)
        ):
            named.append(node.args[0].value)
    targets = {_ours(name, modules) for name in named}
    return {t for t in targets if t is not None and t != module}


def import_graph(root: Path) -> dict[str, set[str]]:
    modules = _modules(root)
    return {module: _edges(module, path, modules) for module, path in modules.items()}


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components with more than one module (Tarjan), each sorted."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph.get(v, ())):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return sorted(found)


def _describe(component: list[str], graph: dict[str, set[str]]) -> str:
    members = set(component)
    links = [f"{a} -> {b}" for a in component for b in sorted(graph[a] & members)]
    return "circle of " + ", ".join(component) + " (" + "; ".join(links) + ")"


def test_graph_sees_every_kind_of_import(tmp_path: Path) -> None:
    # A tiny tree with one circle per kind of import the check must see.
    pkg = tmp_path / "vmocap_core"
    (pkg / "sub").mkdir(parents=True)
    (tmp_path / "vmocap_ros").mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "sub" / "__init__.py").write_text("")
    (tmp_path / "vmocap_ros" / "__init__.py").write_text("")
    (pkg / "a.py").write_text("from .sub import b\n")
    (pkg / "sub" / "b.py").write_text("def f():\n    from ..a import x\n")
    (pkg / "c.py").write_text("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from . import d\n")
    (pkg / "d.py").write_text("import vmocap_core.c\n")
    (pkg / "e.py").write_text("import importlib\nimportlib.import_module('vmocap_ros.f')\n")
    (tmp_path / "vmocap_ros" / "f.py").write_text("from vmocap_core.e import g\n")
    (pkg / "h.py").write_text("from . import c\n")  # into a circle, not part of one
    found = cycles(import_graph(tmp_path))
    assert found == [
        ["vmocap_core.a", "vmocap_core.sub.b"],
        ["vmocap_core.c", "vmocap_core.d"],
        ["vmocap_core.e", "vmocap_ros.f"],
    ]


def test_no_import_circles() -> None:
    graph = import_graph(ROOT)
    assert "vmocap_core.pcm.blazepose" in graph, "the import graph found none of our modules"
    found = cycles(graph)
    if found:
        pytest.fail("import circles:\n" + "\n".join(_describe(c, graph) for c in found))
