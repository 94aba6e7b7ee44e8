"""The package's modules import each other without circles (at any depth of their code).

The graph has an edge ``a → b`` for every ``import neuralmap.b`` / ``from neuralmap.b
import …`` inside module ``a``, module level or inside a function; its strongly connected
components of more than one module are the circles.
"""

from __future__ import annotations

import ast
import sys
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[1] / "neuralmap"


def _modules() -> dict[str, Path]:
    found = {}
    for path in PACKAGE.rglob("*.py"):
        name = ".".join(path.relative_to(PACKAGE.parent).with_suffix("").parts)
        found[name.removesuffix(".__init__")] = path
    return found


def import_graph(modules: dict[str, Path]) -> dict[str, set[str]]:
    """``module -> {package modules it imports}`` (absolute imports of ``neuralmap``)."""
    graph: dict[str, set[str]] = {name: set() for name in modules}
    for name, path in modules.items():
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.ImportFrom) and node.module and not node.level:
                targets = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
            elif isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            else:
                continue
            graph[name].update(t for t in targets if t in modules and t != name)
    return graph


def circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan, 1972)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    found: list[list[str]] = []
    counter = [0]

    def visit(v: str) -> None:
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
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

    limit = sys.getrecursionlimit()
    sys.setrecursionlimit(max(limit, 10 * len(graph)))
    try:
        for v in sorted(graph):
            if v not in index:
                visit(v)
    finally:
        sys.setrecursionlimit(limit)
    return sorted(found)


def test_the_package_has_no_import_circle() -> None:
    assert circles(import_graph(_modules())) == []


def test_the_checker_finds_a_circle_through_a_function_level_import(tmp_path: Path) -> None:
    (tmp_path / "a.py").write_text("from neuralmap.b import f\n")
    (tmp_path / "b.py").write_text("def f():\n    import neuralmap.c\n")
    (tmp_path / "c.py").write_text("from neuralmap.a import x\n")
    (tmp_path / "d.py").write_text("from neuralmap.a import x\n")
    modules = {f"neuralmap.{p.stem}": p for p in tmp_path.glob("*.py")}
    assert circles(import_graph(modules)) == [["neuralmap.a", "neuralmap.b", "neuralmap.c"]]


#: Packages each package must not import (lower layers never import upper ones; the lab
#: and the recorded flights use the product's engine, the engine the methods, never the
#: other way).
FORBIDDEN: dict[str, tuple[str, ...]] = {
    "neuralmap.dem": ("neuralmap.terrain", "neuralmap.linearize", "neuralmap.filters",
                      "neuralmap.tan", "neuralmap.nav", "neuralmap.flights", "neuralmap.lab",
                      "neuralmap.studies", "neuralmap.training"),
    "neuralmap.filters": ("neuralmap.terrain", "neuralmap.linearize", "neuralmap.tan",
                          "neuralmap.nav", "neuralmap.flights", "neuralmap.lab",
                          "neuralmap.studies", "neuralmap.training", "lightning"),
    "neuralmap.terrain": ("neuralmap.tan", "neuralmap.nav", "neuralmap.flights",
                          "neuralmap.lab", "neuralmap.studies"),
    "neuralmap.tan": ("neuralmap.nav", "neuralmap.flights", "neuralmap.lab",
                      "neuralmap.studies", "neuralmap.training", "neuralmap.learning"),
    "neuralmap.nav": ("neuralmap.flights", "neuralmap.lab", "neuralmap.studies",
                      "neuralmap.training", "neuralmap.learning"),
    "neuralmap.flights": ("neuralmap.lab", "neuralmap.studies", "neuralmap.training",
                          "neuralmap.learning"),
    "neuralmap.lab": ("neuralmap.flights", "neuralmap.studies", "neuralmap.training"),
}


def _imports(path: Path) -> list[tuple[str, list[str]]]:
    """``(module, names)`` of every absolute import in ``path`` (any depth)."""
    out = []
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module and not node.level:
            out.append((node.module, [a.name for a in node.names]))
        elif isinstance(node, ast.Import):
            out.extend((a.name, []) for a in node.names)
    return out


def upward_imports(modules: dict[str, Path]) -> list[str]:
    """``"a -> b"`` for every import of a package `FORBIDDEN` for ``a``'s package."""
    found = []
    for name, path in sorted(modules.items()):
        for layer, banned in FORBIDDEN.items():
            if name != layer and not name.startswith(layer + "."):
                continue
            found.extend(f"{name} -> {target}" for target, _ in _imports(path)
                         if any(target == b or target.startswith(b + ".") for b in banned))
    return found


def test_no_package_imports_an_upper_layer() -> None:
    assert upward_imports(_modules()) == []


def test_the_navigation_packages_import_no_private_name_of_another_module() -> None:
    found = []
    for name, path in _modules().items():
        if not name.startswith(("neuralmap.tan", "neuralmap.nav", "neuralmap.flights",
                                "neuralmap.lab")):
            continue
        for target, names in _imports(path):
            if target != name and target.startswith("neuralmap."):
                found.extend(f"{name}: {target}.{n}" for n in names if n.startswith("_"))
    assert found == []


def test_the_layer_check_finds_an_upward_import(tmp_path: Path) -> None:
    (tmp_path / "m.py").write_text("def f():\n    from neuralmap.nav.navigator import Navigator\n")
    assert upward_imports({"neuralmap.tan.m": tmp_path / "m.py"}) == [
        "neuralmap.tan.m -> neuralmap.nav.navigator"]


#: Lines a navigation package may hold (about 3 k: a package a reader can take in whole).
PACKAGE_LINES = 3_500


@pytest.mark.parametrize("package", ["tan", "nav", "flights", "lab"])
def test_each_navigation_package_stays_small(package: str) -> None:
    root = Path(__file__).resolve().parents[1] / "neuralmap" / package
    lines = sum(len(p.read_text(encoding="utf-8").splitlines()) for p in root.rglob("*.py"))
    assert lines <= PACKAGE_LINES, (
        f"neuralmap/{package} holds {lines} lines (limit {PACKAGE_LINES}): split it by job")
