"""The between-node benchmark: its splits, its bicubic against an independent upsampler,
and the tiny run's table and files against its own results."""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path
from types import ModuleType

import numpy as np
import pytest
import torch

from neuralmap.dem import synthetic_tile
from neuralmap.terrain.superres import ResidualSuperRes, bicubic_upsample

REPO_ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def bench() -> ModuleType:
    spec = importlib.util.spec_from_file_location(
        "bench_between_nodes", REPO_ROOT / "benchmarks" / "bench_between_nodes.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module  # its dataclass looks its module up there
    spec.loader.exec_module(module)
    return module


def test_x2_split_keeps_every_other_node_and_its_bicubic_is_the_upsampler(
        bench: ModuleType) -> None:
    tile = synthetic_tile((20, 17), spacing=(30.0, 25.0), seed=4)
    split = bench.split_x2(tile)
    assert split.tile.shape == (19, 17) and split.kept.shape == (10, 9)
    assert split.kept.spacing == (60.0, 50.0)
    np.testing.assert_array_equal(split.kept.heights, tile.heights[:19:2, ::2])
    assert split.withheld.sum() == 19 * 17 - 10 * 9
    # Keys bicubic of the kept grid at the withheld nodes = the matrix upsampler there
    # (an independent implementation: Keys weights with the boundary rule folded in).
    fine = bicubic_upsample(torch.as_tensor(split.kept.heights), 2).numpy()
    np.testing.assert_allclose(bench.predict_bicubic(split), fine[split.withheld],
                               atol=1e-9, rtol=0)
    # a prior whose last layer is zero is exactly that bicubic
    prior = ResidualSuperRes(factor=2, channels=4, depth=2)
    with torch.no_grad():
        prior.last_layer.weight.zero_()
        prior.last_layer.bias.zero_()
    np.testing.assert_allclose(bench.predict_superres(split, prior),
                               fine[split.withheld], atol=1e-3, rtol=0)  # float32 prior


def test_random_and_square_splits_withhold_interior_nodes_only(bench: ModuleType) -> None:
    tile = synthetic_tile((60, 50), spacing=30.0, seed=1)
    for split in (bench.split_random(tile, 0.25, 0), bench.split_squares(tile, 3, 0.25, 0)):
        held = split.withheld
        assert not held[0].any() and not held[-1].any()
        assert not held[:, 0].any() and not held[:, -1].any()
        assert 0.15 < held.mean() < 0.35
        np.testing.assert_array_equal(np.isnan(split.kept.heights), held)
    squares = bench.split_squares(tile, 3, 0.25, 0).withheld
    # every withheld node belongs to a complete 3 x 3 block of withheld nodes
    from scipy import ndimage

    labels, n = ndimage.label(squares)
    sizes = ndimage.sum(squares, labels, range(1, n + 1))
    assert n > 0 and set(sizes.tolist()) == {9.0}


def test_clough_tocher_reproduces_a_linear_surface(bench: ModuleType) -> None:
    tile = synthetic_tile((30, 30), spacing=10.0, seed=0)
    xy = tile.node_xy()
    plane = 3.0 + 0.2 * xy[..., 0] - 0.1 * xy[..., 1]
    from dataclasses import replace

    split = bench.split_random(replace(tile, heights=plane), 0.25, 0)
    np.testing.assert_allclose(bench.predict_clough_tocher(split), split.truth, atol=1e-6)


def test_tiny_run_writes_the_table_it_prints(bench: ModuleType, tmp_path: Path,
                                             capsys: pytest.CaptureFixture[str]) -> None:
    out = bench.main(["--tiny", "--out", str(tmp_path)])
    printed = capsys.readouterr().out
    saved = json.loads((tmp_path / "results.json").read_text())
    assert (tmp_path / "results.md").read_text().strip() in printed
    assert [(r["tile"], r["pattern"]) for r in saved["results"]] == [
        ("synthetic:61x87", "x2"), ("synthetic:61x87", "random25")]
    assert saved["target_met"] == out["target_met"]
    for row in saved["results"]:
        base = row["bicubic"]["rmse_m"]
        assert row["bicubic"]["ratio"] == 1.0
        for method in ("blockwise", "latent"):
            assert row[method]["ratio"] == pytest.approx(row[method]["rmse_m"] / base)
            assert row[method]["max_m"] >= row[method]["rmse_m"] > 0
            assert f"{row[method]['rmse_m']:.3f} ({row[method]['max_m']:.2f})" in printed
        assert ("superres" in row) == (row["pattern"] == "x2")


def test_bad_override_is_refused(bench: ModuleType) -> None:
    with pytest.raises(SystemExit) as info:
        bench.main(["--tiny", "--set", "epochs=3"])
    assert info.value.code == 2
