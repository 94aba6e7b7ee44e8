"""The DEM package's layers: readers (files) < samples (built-in tiles, built with a reader)
< load (the front door). No module imports one above it, not even inside a function."""

from __future__ import annotations

import ast
from pathlib import Path

import pytest

DEM = Path(__file__).resolve().parents[2] / "neuralmap" / "dem"
#: module -> the package modules above it, which it must never import
ABOVE = {
    "readers": {"samples", "load", "mosaic"},
    "samples": {"load", "mosaic"},
}


def _dem_imports(path: Path) -> set[str]:
    """Every ``neuralmap.dem.X`` a module imports, at any depth of its code."""
    found: set[str] = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom) and node.module:
            names = [node.module] + [f"{node.module}.{a.name}" for a in node.names]
        elif isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        else:
            continue
        for name in names:
            parts = name.split(".")
            if parts[:2] == ["neuralmap", "dem"] and len(parts) > 2:
                found.add(parts[2])
    return found


@pytest.mark.parametrize("module", sorted(ABOVE))
def test_no_import_of_a_layer_above(module: str) -> None:
    assert not (_dem_imports(DEM / f"{module}.py") & ABOVE[module])


def test_the_check_sees_a_function_level_import(tmp_path: Path) -> None:
    """The checker itself: an import inside a function is found."""
    probe = tmp_path / "probe.py"
    probe.write_text("def f():\n    from neuralmap.dem.samples import load_sample\n")
    assert _dem_imports(probe) == {"samples"}
