"""Region training: memory-mapped batches, shard independence, seamless lazy sharded maps."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from neuralmap.dem.region import synthetic_region
from neuralmap.exceptions import NeuralMapError
from neuralmap.terrain import load_map
from neuralmap.terrain.sharded import ShardedTerrainMap
from neuralmap.training.region import (
    RegionBatches,
    RegionData,
    fit_region,
    plan_layout,
    splitmix64,
    train_shard,
)

SHAPE = (49, 73)  # 2 x 3 blocks of 24 node intervals


@pytest.fixture(scope="module")
def region_path(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("region") / "r.npy"
    synthetic_region(path, shape=SHAPE, spacing=100.0, seed=1)
    heights = np.load(path, mmap_mode="r+")
    heights[3, 4] = np.nan  # a void
    heights.flush()
    return path


def _grid_xy(data: RegionData) -> torch.Tensor:
    ny, nx = data.shape
    ii, jj = np.meshgrid(np.arange(ny), np.arange(nx), indexing="ij")
    return torch.tensor(np.stack([jj * 100.0, ii * 100.0], -1).reshape(-1, 2), dtype=torch.float32)


def test_splitmix64_reference_values() -> None:
    # reference outputs of splitmix64 seeded with 0 (Vigna's splitmix64.c: next() from x=0)
    out = splitmix64(np.array([0, 0x9E3779B97F4A7C15], dtype=np.uint64))
    assert out.tolist() == [0xE220A8397B1DCDAF, 0x6E789E6AA1B965F4]


def test_memmap_and_in_memory_batches_identical(region_path: Path) -> None:
    mapped = RegionData.open(region_path)
    loaded = RegionData.open(region_path, in_memory=True)
    assert isinstance(mapped.heights, np.memmap) and not isinstance(loaded.heights, np.memmap)
    layout = plan_layout(mapped, block_nodes=24)
    ids = np.arange(layout.count)
    windows = mapped.node_window(layout.block_bounds())
    a = RegionBatches(
        mapped.heights, (0, 0), mapped, windows, ids, points_per_block=50, steps=3, seed=4
    )
    b = RegionBatches(
        loaded.heights, (0, 0), loaded, windows, ids, points_per_block=50, steps=3, seed=4
    )
    for step in range(3):
        for x, y in zip(a[step], b[step], strict=True):
            assert torch.equal(x, y)
    xy, h, block = a[1]
    # every sample is a node of its block's extended domain, with the stored height
    bounds = torch.as_tensor(layout.block_bounds(), dtype=torch.float32)[block]
    assert bool(((xy[:, 0] >= bounds[:, 0] - 1e-3) & (xy[:, 0] <= bounds[:, 1] + 1e-3)).all())
    rows, cols = (xy[:, 1] / 100).round().long(), (xy[:, 0] / 100).round().long()
    assert torch.equal(h, torch.as_tensor(np.asarray(loaded.heights)[rows, cols]))
    assert bool(torch.isfinite(h).all())  # void nodes are dropped
    net_a, _ = train_shard(mapped, layout, (0, 3, 0, 2), steps=5, seed=2, points_per_block=32)
    net_b, _ = train_shard(loaded, layout, (0, 3, 0, 2), steps=5, seed=2, points_per_block=32)
    for key, value in net_a.state_dict().items():
        assert torch.equal(value, net_b.state_dict()[key]), key


def test_shard_layout_does_not_change_the_fit(region_path: Path, tmp_path: Path) -> None:
    data = RegionData.open(region_path)
    one = fit_region(
        data, tmp_path / "one", shard_blocks=(3, 2), steps=40, lr=1e-2, points_per_block=64
    )
    six = fit_region(
        data, tmp_path / "six", shard_blocks=(1, 1), steps=40, lr=1e-2, points_per_block=64
    )
    assert one["shards"] == 1 and six["shards"] == 6
    xy = _grid_xy(data)
    with torch.no_grad():
        h_one, h_six = load_map(one["index"])(xy), load_map(six["index"])(xy)
    np.testing.assert_allclose(h_six.numpy(), h_one.numpy(), atol=1e-3, rtol=0)


def test_sharded_map_is_seamless_and_lazy(region_path: Path, tmp_path: Path) -> None:
    data = RegionData.open(region_path)
    summary = fit_region(
        data, tmp_path / "m", shard_blocks=(1, 1), steps=100, lr=2e-2, points_per_block=64
    )
    model = load_map(tmp_path / "m")
    assert isinstance(model, ShardedTerrainMap) and model.loaded_shards == []
    with torch.no_grad():
        model(torch.tensor([[150.0, 150.0]]))
    assert model.loaded_shards == [0]  # only the south-west shard was read
    # a shard border at x = 2400 m: height and slope continuous (C2 blending, global weights)
    y = torch.linspace(200.0, 4600.0, 23)
    eps = 1e-2
    left = torch.stack([torch.full_like(y, 2400.0 - eps), y], -1).requires_grad_(True)
    right = torch.stack([torch.full_like(y, 2400.0 + eps), y], -1).requires_grad_(True)
    h_l, h_r = model(left), model(right)
    (g_l,) = torch.autograd.grad(h_l.sum(), left)
    (g_r,) = torch.autograd.grad(h_r.sum(), right)
    assert float((h_l - h_r).abs().max()) < 1e-2
    assert float((g_l - g_r).abs().max()) < 2e-3
    # the fit is a terrain map: RMSE well below the relief (std about 160 m)
    xy = _grid_xy(data)
    ref = torch.tensor(np.asarray(data.heights, dtype=np.float32)).reshape(-1)
    with torch.no_grad():
        pred = model(xy)
    ok = torch.isfinite(ref)
    rmse = float(((pred - ref)[ok] ** 2).mean().sqrt())
    assert rmse < 0.2 * float(ref[ok].std()), rmse
    assert summary["points"] > 0


def test_bad_region_input(tmp_path: Path) -> None:
    with pytest.raises(NeuralMapError, match="not found"):
        RegionData.open(tmp_path / "none.npy")
    np.save(tmp_path / "flat.npy", np.zeros((10, 10)))
    with pytest.raises(NeuralMapError, match="spacing"):
        RegionData.open(tmp_path / "flat.npy")
    data = RegionData.open(tmp_path / "flat.npy", spacing=30.0)
    with pytest.raises(NeuralMapError, match="devices"):
        fit_region(data, tmp_path / "o", devices=0)
    with pytest.raises(NeuralMapError, match="sharded"):
        (tmp_path / "bad.json").write_text("{}")
        load_map(tmp_path / "bad.json")


@pytest.mark.slow
def test_two_processes_equal_one(region_path: Path, tmp_path: Path) -> None:
    data = RegionData.open(region_path)
    one = fit_region(
        data, tmp_path / "p1", shard_blocks=(1, 1), steps=40, lr=1e-2, points_per_block=64
    )
    two = fit_region(
        data,
        tmp_path / "p2",
        shard_blocks=(1, 1),
        steps=40,
        lr=1e-2,
        devices=2,
        points_per_block=64,
    )
    assert two["world_size"] == 2 and [r["shards"] for r in two["per_rank"]] == [3, 3]
    xy = _grid_xy(data)
    with torch.no_grad():
        h1, h2 = load_map(one["index"])(xy), load_map(two["index"])(xy)
    np.testing.assert_allclose(h2.numpy(), h1.numpy(), atol=1e-4, rtol=0)


def test_cli_trains_a_two_tile_mosaic(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    from neuralmap.training.region_cli import main

    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:25, 0:50]
    whole = 400 + 3.0 * xx + 2.0 * yy + rng.normal(0, 0.1, (25, 50))
    for name, part, x0 in (("a", whole[:, :25], 0.0), ("b", whole[:, 25:], 25 * 30.0)):
        rows = "\n".join(" ".join(f"{v:.2f}" for v in r) for r in np.flipud(part))
        (tmp_path / f"{name}.asc").write_text(
            f"ncols 25\nnrows 25\nxllcenter {500000 + x0}\nyllcenter 4000000\ncellsize 30\n"
            + rows
            + "\n"
        )
        (tmp_path / f"{name}.prj").write_text('PROJCS["WGS 84 / UTM zone 16N"]')
    code = main(
        [
            str(tmp_path / "*.asc"),
            "--out",
            str(tmp_path / "out"),
            "--steps",
            "80",
            "--block_nodes",
            "12",
            "--overlap_nodes",
            "2",
            "--lr",
            "1e-2",
        ]
    )
    assert code == 0, capsys.readouterr().err
    model = load_map(tmp_path / "out")
    stored = np.load(tmp_path / "out" / "region.npy")
    np.testing.assert_allclose(stored, np.round(whole, 2), atol=1e-4)
    xy = torch.tensor([[30.0 * 30, 10 * 30.0], [10 * 30.0, 20 * 30.0]])
    with torch.no_grad():
        h = model(xy)
    expected = torch.tensor([whole[10, 30], whole[20, 10]], dtype=torch.float32)
    assert float((h - expected).abs().max()) < 5.0  # a 3 m/node plane, fitted in 80 steps
