"""The map-size query benchmark (quick mode): its printed table against its own rows."""

from __future__ import annotations

import argparse
import importlib.util
import math
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]


def test_bench_map_size_table_matches_its_measurements(
    capsys: pytest.CaptureFixture[str],
) -> None:
    spec = importlib.util.spec_from_file_location(
        "bench_map_size", REPO_ROOT / "benchmarks" / "bench_map_size.py"
    )
    assert spec is not None and spec.loader is not None
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    from neuralmap.terrain.blockwise import BlockwiseTerrainNet

    args = argparse.Namespace(n=2000, repeats=1, threads=1, map=[], quick=True)
    rows = bench.run(args)
    out = capsys.readouterr().out
    raw = 344 * 403 * 4  # jacksboro, float32
    assert [r.name for r in rows[:2]] == ["torch bicubic grid, analytic",
                                          "torch bilinear grid, analytic"]
    assert {r.name for r in rows[2:]} == {"neural, autograd slope", "neural, forward-mode slope",
                                           "neural baked to bicubic grid"}
    label, kwargs = bench.ARCHITECTURES[-1]
    net = BlockwiseTerrainNet.from_tile(bench.load_tile("jacksboro"), **kwargs)
    n_params = net.num_parameters
    lines = [line for line in out.splitlines() if line and not line.startswith(("#", "map "))]
    assert len(lines) == len(rows)
    for row, line in zip(rows, lines, strict=True):
        assert math.isfinite(row.rate) and row.rate > 0 and row.best >= row.rate
        nbytes = int(row.detail)
        if row.group == "grid":
            assert nbytes == raw
        else:  # int8 weights: at least one byte per parameter, far below float32
            assert n_params <= nbytes < 2 * n_params
        fields = line.split()
        assert int(fields[-5]) == nbytes
        assert float(fields[-4]) == pytest.approx(100 * nbytes / raw, abs=0.06)
        assert float(fields[-1]) == pytest.approx(row.rate / rows[0].rate, abs=6e-4)
