"""Smoke test of the map-size query benchmark (quick mode)."""

from __future__ import annotations

import importlib.util
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]


def test_bench_map_size_quick(capsys: pytest.CaptureFixture[str]) -> None:
    spec = importlib.util.spec_from_file_location(
        "bench_map_size", REPO_ROOT / "benchmarks" / "bench_map_size.py"
    )
    assert spec is not None and spec.loader is not None
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    assert bench.main(["--quick", "--n", "2000"]) == 0
    out = capsys.readouterr().out
    assert "torch bicubic grid, analytic" in out and "forward-mode slope" in out
    assert "neural baked to bicubic grid" in out
