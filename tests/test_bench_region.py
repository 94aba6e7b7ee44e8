"""Smoke test of the region benchmark (small sizes, child processes)."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_bench_region_quick(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    spec = importlib.util.spec_from_file_location("bench_region_under_test",
                                                  REPO_ROOT / "benchmarks" / "bench_region.py")
    bench = importlib.util.module_from_spec(spec)
    assert spec.loader is not None
    spec.loader.exec_module(bench)
    assert bench.main(["--quick", "--json", str(tmp_path / "n.json")]) == 0
    out = capsys.readouterr().out
    assert "points/s" in out and "Monte Carlo runs" in out and "projected" in out
    numbers = json.loads((tmp_path / "n.json").read_text())
    assert set(numbers["train"]) == {"small/1", "small/2"}
    assert all(v["peak_rss_mb"] > 0 for v in numbers["mc"].values())
