"""Off-node training points and errors: the surface between the nodes, not only the nodes."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from torch import nn

from neuralmap.dem.tile import DemTile
from neuralmap.exceptions import NeuralMapError
from neuralmap.terrain.grid import GridTerrain
from neuralmap.training.datamodule import DemDataModule
from neuralmap.training.evaluation import offnode_error
from neuralmap.training.module import TerrainFitModule
from neuralmap.training.offnode import OffNodeSampler

SPACING = (30.0, 40.0)
ORIGIN = (1000.0, -500.0)


def _quadratic(x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    u, v = (x - ORIGIN[0]) / 300.0, (y - ORIGIN[1]) / 300.0
    return 200.0 + 15.0 * u - 7.0 * v + 4.0 * u * u - 3.0 * u * v + 2.0 * v * v


def _tile(ny: int = 17, nx: int = 23, voids: bool = False) -> DemTile:
    ys = ORIGIN[1] + SPACING[1] * np.arange(ny)
    xs = ORIGIN[0] + SPACING[0] * np.arange(nx)
    xx, yy = np.meshgrid(xs, ys)
    heights = _quadratic(torch.from_numpy(xx), torch.from_numpy(yy)).numpy()
    if voids:
        heights[5, 7] = np.nan
    return DemTile(heights=heights, spacing=SPACING, origin=ORIGIN, name="quad")


class Rippled(nn.Module):
    """The exact quadratic plus ``A sin(pi i) sin(pi j)``: zero at every node, ripples between."""

    def __init__(self, amplitude: float) -> None:
        super().__init__()
        self.amplitude = amplitude

    def forward(self, xy: torch.Tensor) -> torch.Tensor:
        x, y = xy[..., 0], xy[..., 1]
        i = (x - ORIGIN[0]) / SPACING[0]
        j = (y - ORIGIN[1]) / SPACING[1]
        return _quadratic(x, y) + self.amplitude * torch.sin(math.pi * i) * torch.sin(math.pi * j)


def test_sampler_points_lie_in_valid_cells_and_targets_are_bicubic() -> None:
    tile = _tile(voids=True)
    sampler = OffNodeSampler(tile)
    assert sampler.n_cells == 16 * 22 - 4  # the void touches four cells
    xy, h, slope = sampler.sample(5000, torch.Generator().manual_seed(1), dtype=torch.float64)
    col = torch.floor((xy[:, 0] - ORIGIN[0]) / SPACING[0])
    row = torch.floor((xy[:, 1] - ORIGIN[1]) / SPACING[1])
    assert not bool(((col == 7) | (col == 6)).logical_and((row == 5) | (row == 4)).any())
    ref_h, ref_s = GridTerrain(tile, method="bicubic").height_and_slope(xy)
    torch.testing.assert_close(h, ref_h, rtol=0, atol=1e-9)
    torch.testing.assert_close(slope, ref_s, rtol=0, atol=1e-9)
    # seeded: the same generator state gives the same points
    again = sampler.points(5000, torch.Generator().manual_seed(1))
    torch.testing.assert_close(again, xy)


def test_sampler_refuses_a_tile_without_a_valid_cell() -> None:
    heights = np.full((3, 3), np.nan)
    heights[1, 1] = 5.0
    with pytest.raises(NeuralMapError, match="offnode_ratio"):
        OffNodeSampler(DemTile(heights=heights, spacing=SPACING))


def test_offnode_error_sees_ripples_that_the_nodes_cannot() -> None:
    """Closed form: bicubic reproduces the quadratic, so the off-node error of the rippled
    model is ``A sin(pi u) sin(pi v)`` with ``u, v ~ U(0, 1)``: RMS ``A / 2``; at the nodes
    it is 0."""
    tile = _tile()
    exact = offnode_error(Rippled(0.0), tile, n_points=20000, seed=3)
    assert exact["offnode_rmse_m"] < 1e-9
    rippled = offnode_error(Rippled(2.0), tile, n_points=20000, seed=3)
    assert rippled["offnode_rmse_m"] == pytest.approx(1.0, rel=0.02)
    assert rippled["offnode_max_abs_m"] <= 2.0 + 1e-9
    nodes = torch.from_numpy(tile.node_xy().reshape(-1, 2))
    node_err = Rippled(2.0)(nodes).numpy() - tile.heights.reshape(-1)
    assert np.abs(node_err).max() < 1e-9


def test_batches_carry_seeded_offnode_points() -> None:
    tile = _tile()
    dm = DemDataModule.from_tile(tile, batch_size=50, val_fraction=0.1, offnode_ratio=0.4)
    loader = dm.train_dataloader()
    batch = loader.dataset[0]
    assert len(batch) == 5
    xy, h, xy_off, h_off, slope_off = batch
    assert xy_off.shape == (20, 2) and h_off.shape == (20,) and slope_off.shape == (20, 2)
    ref = GridTerrain(tile, method="bicubic")(xy_off.double())
    torch.testing.assert_close(h_off.double(), ref, rtol=0, atol=1e-3)
    torch.testing.assert_close(loader.dataset[0][2], xy_off)  # same epoch, same draw
    assert not torch.equal(loader.dataset[1][2], xy_off)
    nodes_only = DemDataModule.from_tile(tile, batch_size=50, offnode_ratio=0.0)
    assert len(nodes_only.train_dataloader().dataset[0]) == 2
    with pytest.raises(NeuralMapError, match="offnode_ratio"):
        DemDataModule.from_tile(tile, offnode_ratio=-1.0)


def test_training_loss_adds_the_weighted_offnode_terms() -> None:
    tile = _tile()
    module = TerrainFitModule(block_nodes=None, num_blocks=[1, 1], hidden=8, depth=1,
                              n_frequencies=2, offnode_weight=0.5, offnode_slope_weight=2.0)
    net = module.build(tile)
    dm = DemDataModule.from_tile(tile, batch_size=40, offnode_ratio=0.5)
    batch = dm.train_dataloader().dataset[0]
    xy, h, xy_off, h_off, s_off = batch
    s2 = net.height_scale**2
    points = xy_off.clone().requires_grad_(True)
    pred_off = net(points)
    (slope,) = torch.autograd.grad(pred_off.sum(), points)
    expected = (((net(xy) - h) ** 2).mean()
                + 0.5 * ((pred_off - h_off) ** 2).mean()
                + 2.0 * SPACING[0] * SPACING[1] * ((slope - s_off) ** 2).sum(-1).mean()) / s2
    module.log = lambda *a, **k: None  # type: ignore[method-assign]
    loss = module.training_step(batch, 0)
    assert float(loss) == pytest.approx(float(expected), rel=1e-5)
    with pytest.raises(NeuralMapError, match="offnode_weight"):
        TerrainFitModule(offnode_weight=float("nan"))
