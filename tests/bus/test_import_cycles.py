"""No import cycles between the project's modules (issue 11): the graph of module-level
imports over the top-level packages (``bus``, ``sitl``, ``perception``, ``policy``,
``mavlink_bridge``, ``skyloop``) has no cycle. Imports deferred into a function body, and
those under ``if TYPE_CHECKING:``, do not run at import time and are not counted: a
cycle hidden that way (bus.node/bus.session, policy.algorithms.abr/rewards,
vehicle_link/gcs_services, learner/learner_node were) works only as long as nobody
moves the import, which is what this test guards. Built with :mod:`ast`, nothing is
imported."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
PACKAGES = ("bus", "sitl", "perception", "policy", "mavlink_bridge", "skyloop")


def project_modules(root: Path | None = None) -> dict[str, Path]:
    """Dotted module name -> its file, for every module of :data:`PACKAGES` under
    ``root`` (default: the repository)."""
    root = ROOT if root is None else root
    out: dict[str, Path] = {}
    for pkg in PACKAGES:
        for path in sorted((root / pkg).rglob("*.py")):
            parts = list(path.relative_to(root).with_suffix("").parts)
            if parts[-1] == "__init__":
                parts.pop()
            out[".".join(parts)] = path
    return out


def _is_type_checking(test: ast.expr) -> bool:
    return (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING") or \
        (isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING")


def _module_level_imports(body: list[ast.stmt]):
    """The import statements that run when the module is imported: at the top level and
    inside module-level ``if``/``try``/``with`` blocks, not in functions or classes'
    methods, not under ``if TYPE_CHECKING:``."""
    for node in body:
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            yield node
        elif isinstance(node, ast.If):
            if not _is_type_checking(node.test):
                yield from _module_level_imports(node.body)
            yield from _module_level_imports(node.orelse)
        elif isinstance(node, ast.Try):
            for block in (node.body, *(h.body for h in node.handlers), node.orelse,
                          node.finalbody):
                yield from _module_level_imports(block)
        elif isinstance(node, (ast.With, ast.ClassDef)):  # a class body runs at import
            yield from _module_level_imports(node.body)


def import_graph(modules: dict[str, Path]) -> dict[str, set[str]]:
    """Module -> the project modules its module-level imports name (``from a.b import
    c``: ``a.b.c`` when that is a module, else ``a.b``)."""
    graph: dict[str, set[str]] = {}
    for name, path in modules.items():
        is_pkg = path.name == "__init__.py"
        edges: set[str] = set()
        for node in _module_level_imports(ast.parse(path.read_text(), str(path)).body):
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            else:
                base = node.module or ""
                if node.level:  # relative: from the module's package
                    pkg = name.split(".") if is_pkg else name.split(".")[:-1]
                    pkg = pkg[:len(pkg) - (node.level - 1)]
                    base = ".".join([*pkg, *([base] if base else [])])
                targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in modules else base
                           for a in node.names]
            for t in targets:
                while t and t not in modules:  # import a.b.c of a non-module: its package
                    t = t.rpartition(".")[0]
                if t and t != name:
                    edges.add(t)
        graph[name] = edges
    return graph


def find_cycle(graph: dict[str, set[str]]) -> list[str] | None:
    """One cycle of ``graph`` as [a, b, ..., a], or None (iterative depth-first search)."""
    state: dict[str, int] = {}  # 1: on the current path, 2: done
    for start in sorted(graph):
        if state.get(start):
            continue
        path, stack = [start], [iter(sorted(graph[start]))]
        state[start] = 1
        while stack:
            nxt = next(stack[-1], None)
            if nxt is None:
                state[path.pop()] = 2
                stack.pop()
            elif state.get(nxt) == 1:
                return path[path.index(nxt):] + [nxt]
            elif not state.get(nxt):
                state[nxt] = 1
                path.append(nxt)
                stack.append(iter(sorted(graph.get(nxt, ()))))
    return None


def test_no_import_cycle_between_project_modules():
    modules = project_modules()
    assert {"bus.node", "bus.session", "policy.algorithms.abr", "policy.algorithms.rewards",
            "mavlink_bridge.vehicle_link", "mavlink_bridge.gcs.services",
            "policy.nodes.learner", "policy.nodes.learner_node"} <= set(modules)
    graph = import_graph(modules)
    assert sum(map(len, graph.values())) > 100  # the graph was really built
    cycle = find_cycle(graph)
    assert cycle is None, "import cycle: " + " -> ".join(cycle)


def test_the_cycle_finder_finds_a_cycle(tmp_path):
    """The test above can fail: a cycle through a module-level import (here via a
    relative import and a module-level ``if``) is found and printed; the same cycle
    deferred into a function, or under TYPE_CHECKING, is not one."""
    pkg = tmp_path / "bus"
    pkg.mkdir()
    (pkg / "__init__.py").write_text("")
    (pkg / "a.py").write_text("import os\nfrom bus import b\n")
    (pkg / "b.py").write_text("if True:\n    from .c import thing\n")
    (pkg / "c.py").write_text("from bus.a import x\nthing = 1\n")
    cycle = find_cycle(import_graph(project_modules(tmp_path)))
    assert cycle == ["bus.a", "bus.b", "bus.c", "bus.a"], cycle
    (pkg / "c.py").write_text("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n"
                              "    from bus.a import x\n"
                              "def f():\n    from bus.a import x\n    return x\nthing = 1\n")
    assert find_cycle(import_graph(project_modules(tmp_path))) is None
