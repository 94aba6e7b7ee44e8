"""DemDataModule: split rule, voids, batching, DDP sharding and reference slopes."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from torch.utils.data import DistributedSampler

from neuralmap.dem.tile import DemTile
from neuralmap.exceptions import NeuralMapError
from neuralmap.terrain.grid import GridTerrain
from neuralmap.training.datamodule import DemDataModule


def _tile(ny: int = 21, nx: int = 31, voids: bool = True) -> DemTile:
    rng = np.random.default_rng(5)
    y, x = np.mgrid[0:ny, 0:nx]
    heights = 300.0 + 20.0 * np.sin(x / 4.0) + 10.0 * np.cos(y / 3.0) + rng.normal(0, 1, (ny, nx))
    if voids:
        heights[3:6, 7:12] = np.nan  # 15 voids
        heights[0, 0] = np.nan
    return DemTile(heights=heights, spacing=(30.0, 40.0), origin=(1000.0, -500.0), name="t")


def _rows(xy: torch.Tensor) -> set[tuple[float, float]]:
    return {tuple(p) for p in xy.tolist()}


def test_split_is_disjoint_covers_valid_nodes_and_counts_voids() -> None:
    tile = _tile()
    dm = DemDataModule.from_tile(tile, val_fraction=0.1, batch_size=64, seed=3)
    n_valid = int(np.isfinite(tile.heights).sum())
    assert dm.n_void == 16 == tile.heights.size - n_valid
    assert dm.n_valid == n_valid
    assert dm.n_val == round(0.1 * n_valid)
    assert dm.n_train + dm.n_val == n_valid
    train, val = set(dm.train_index.tolist()), set(dm.val_index.tolist())
    assert not train & val
    assert train | val == set(range(n_valid))
    # Coordinates and heights are those of the tile's valid nodes (row 0 south).
    xy_ref = tile.node_xy().reshape(-1, 2)[np.isfinite(tile.heights).reshape(-1)]
    np.testing.assert_allclose(dm.xy.numpy(), xy_ref, rtol=0, atol=1e-3)
    flat = dm.node_index.numpy()
    np.testing.assert_allclose(dm.heights.numpy(), tile.heights.reshape(-1)[flat], rtol=1e-6)
    assert np.isfinite(dm.heights.numpy()).all()


def test_split_is_seeded() -> None:
    tile = _tile()
    a = DemDataModule.from_tile(tile, val_fraction=0.1, seed=1)
    b = DemDataModule.from_tile(tile, val_fraction=0.1, seed=1)
    c = DemDataModule.from_tile(tile, val_fraction=0.1, seed=2)
    assert torch.equal(a.val_index, b.val_index)
    assert not torch.equal(a.val_index, c.val_index)


def test_train_batches_cover_training_nodes_once_per_epoch_and_reshuffle() -> None:
    tile = _tile()
    dm = DemDataModule.from_tile(tile, val_fraction=0.1, batch_size=100, seed=0)
    dataset = dm.train_dataloader().dataset
    epoch = {"e": 0}
    dataset.epoch_fn = lambda: epoch["e"]
    first = [dataset[i] for i in range(len(dataset))]
    sizes = [b[0].shape[0] for b in first]
    assert sizes[:-1] == [100] * (len(sizes) - 1) and 0 < sizes[-1] <= 100
    xy0 = torch.cat([b[0] for b in first])
    assert xy0.shape[0] == dm.n_train
    assert _rows(xy0) == _rows(dm.xy[dm.train_index])
    assert len(_rows(xy0)) == dm.n_train  # each training node exactly once
    # heights travel with their coordinates
    lookup = {tuple(p): h for p, h in zip(dm.xy.tolist(), dm.heights.tolist(), strict=True)}
    h0 = torch.cat([b[1] for b in first])
    assert all(lookup[tuple(p)] == h for p, h in zip(xy0.tolist(), h0.tolist(), strict=True))
    epoch["e"] = 1
    xy1 = torch.cat([dataset[i][0] for i in range(len(dataset))])
    assert _rows(xy1) == _rows(xy0) and not torch.equal(xy1, xy0)


def test_refit_epochs_train_on_every_valid_node_with_same_batch_count() -> None:
    tile = _tile()
    dm = DemDataModule.from_tile(tile, val_fraction=0.1, batch_size=100, seed=0, refit_epochs=2)

    class _Trainer:
        max_epochs = 5

    dm.trainer = _Trainer()  # type: ignore[assignment]
    assert dm.refit_start_epoch == 3
    assert [dm.in_refit(e) for e in range(5)] == [False, False, False, True, True]
    dataset = dm.train_dataloader().dataset
    epoch = {"e": 2}
    dataset.epoch_fn = lambda: epoch["e"]
    n_batches = len(dataset)
    before = torch.cat([dataset[i][0] for i in range(n_batches)])
    assert _rows(before) == _rows(dm.xy[dm.train_index])  # held-out nodes unseen
    epoch["e"] = 3
    during = [dataset[i] for i in range(n_batches)]
    xy = torch.cat([b[0] for b in during])
    assert xy.shape[0] == dm.n_valid and _rows(xy) == _rows(dm.xy)  # all nodes, each once
    lookup = {tuple(p): h for p, h in zip(dm.xy.tolist(), dm.heights.tolist(), strict=True)}
    h = torch.cat([b[1] for b in during])
    assert all(lookup[tuple(p)] == v for p, v in zip(xy.tolist(), h.tolist(), strict=True))
    with pytest.raises(NeuralMapError, match="refit_epochs"):
        DemDataModule.from_tile(tile, refit_epochs=-1)


def test_distributed_sampler_gives_ranks_disjoint_batches() -> None:
    tile = _tile(voids=False)
    dm = DemDataModule.from_tile(tile, val_fraction=0.05, batch_size=62, seed=0)
    dataset = dm.train_dataloader().dataset
    assert len(dataset) % 2 == 0, "choose sizes so that no padding duplicates occur"
    seen = []
    for rank in range(2):
        sampler = DistributedSampler(dataset, num_replicas=2, rank=rank, shuffle=False)
        seen.append(torch.cat([dataset[i][0] for i in sampler]))
    assert not _rows(seen[0]) & _rows(seen[1])
    assert _rows(torch.cat(seen)) == _rows(dm.xy[dm.train_index])


def test_validation_and_test_sets() -> None:
    tile = _tile()
    dm = DemDataModule.from_tile(tile, val_fraction=0.2, eval_batch_size=50, seed=0)
    val = [b for b in dm.val_dataloader()]
    xy_val = torch.cat([b[0] for b in val])
    assert _rows(xy_val) == _rows(dm.xy[dm.val_index])
    assert all(b[2].shape == (b[0].shape[0], 2) for b in val)
    xy_all = torch.cat([b[0] for b in dm.test_dataloader()])
    assert xy_all.shape[0] == dm.n_valid and _rows(xy_all) == _rows(dm.xy)


def test_reference_slopes_are_bicubic_autograd_slopes() -> None:
    tile = _tile()
    dm = DemDataModule.from_tile(tile, val_fraction=0.2, seed=0)
    grid = GridTerrain(tile, method="bicubic", dtype=torch.float64)
    xy = dm.xy[dm.val_index].double().requires_grad_(True)
    (slope,) = torch.autograd.grad(grid(xy).sum(), xy)
    np.testing.assert_allclose(dm.val_slopes.numpy(), slope.numpy(), rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"val_fraction": 0.0}, "val_fraction"),
        ({"val_fraction": 0.9}, "val_fraction"),
        ({"batch_size": 0}, "batch_size"),
    ],
)
def test_bad_settings_raise(kwargs: dict, match: str) -> None:
    with pytest.raises(NeuralMapError, match=match):
        DemDataModule.from_tile(_tile(), **kwargs)


def test_single_valid_node_raises() -> None:
    heights = np.full((4, 4), np.nan)
    heights[1, 2] = 100.0
    tile = DemTile(heights=heights, spacing=(10.0, 10.0), name="lonely")
    with pytest.raises(NeuralMapError, match="only 1 valid node"):
        DemDataModule.from_tile(tile)
