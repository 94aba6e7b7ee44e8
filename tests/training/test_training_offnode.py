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


def _cubic(x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A bicubic polynomial (degree <= 3 in each axis), its d/dx and d/dy."""
    u, v = (x - ORIGIN[0]) / 300.0, (y - ORIGIN[1]) / 300.0
    h = 100.0 + 5.0 * u**3 - 2.0 * u**2 * v + 3.0 * u * v**3 - v**2 + 4.0 * u
    dx = (15.0 * u**2 - 4.0 * u * v + 3.0 * v**3 + 4.0) / 300.0
    dy = (-2.0 * u**2 + 9.0 * u * v**2 - 2.0 * v) / 300.0
    return h, dx, dy


def test_spline_surface_reproduces_a_bicubic_polynomial_and_its_slope() -> None:
    # The interpolating cubic spline (not-a-knot ends) is exact on cubics; Keys is not.
    ys = ORIGIN[1] + SPACING[1] * np.arange(13)
    xs = ORIGIN[0] + SPACING[0] * np.arange(11)
    xx, yy = np.meshgrid(xs, ys)
    tile = DemTile(heights=_cubic(xx, yy)[0], spacing=SPACING, origin=ORIGIN, name="cubic")
    sampler = OffNodeSampler(tile, surface="spline")
    xy, height, slope = sampler.sample(500, torch.Generator().manual_seed(0),
                                       dtype=torch.float64)
    h, dx, dy = _cubic(xy[:, 0].numpy(), xy[:, 1].numpy())
    np.testing.assert_allclose(height.numpy(), h, atol=1e-8)
    np.testing.assert_allclose(slope.numpy(), np.stack([dx, dy], -1), atol=1e-10)
    keys = OffNodeSampler(tile).sample(500, torch.Generator().manual_seed(0),
                                       dtype=torch.float64)
    torch.testing.assert_close(keys[0], xy)  # same points, another surface
    assert float((keys[1] - torch.as_tensor(h)).abs().max()) > 1e-3


def test_spline_surface_keeps_the_bicubic_validation_points_and_refuses_bad_names() -> None:
    tile = _tile()
    spline = DemDataModule.from_tile(tile, offnode_surface="spline", offnode_val_points=64)
    keys = DemDataModule.from_tile(tile, offnode_val_points=64)
    for a, b in zip(spline.offnode_val, keys.offnode_val, strict=True):  # type: ignore[arg-type]
        torch.testing.assert_close(a, b)
    with pytest.raises(NeuralMapError, match="offnode_surface"):
        DemDataModule.from_tile(tile, offnode_surface="nearest")


def test_min_batches_gives_small_tiles_steps_per_epoch() -> None:
    tile = _tile()  # 17 x 23 = 391 nodes
    dm = DemDataModule.from_tile(tile, batch_size=8192, val_fraction=0.05, min_batches=16,
                                 offnode_ratio=0.0)
    assert dm.train_batch_size == math.ceil(dm.n_train / 16)
    batches = list(dm.train_dataloader())
    assert len(batches) == 16
    assert sum(b[0].shape[0] for b in batches) == dm.n_train
    one = DemDataModule.from_tile(tile, batch_size=8192, val_fraction=0.05, offnode_ratio=0.0)
    assert len(one.train_dataloader()) == 1
    with pytest.raises(NeuralMapError, match="min_batches"):
        DemDataModule.from_tile(tile, min_batches=0)


def test_void_fill_samples_next_to_voids_with_a_cubic_fill() -> None:
    from neuralmap.training.offnode import fill_voids_cubic

    ys = ORIGIN[1] + SPACING[1] * np.arange(15)
    xs = ORIGIN[0] + SPACING[0] * np.arange(12)
    xx, yy = np.meshgrid(xs, ys)
    plane = 50.0 + 0.3 * (xx - ORIGIN[0]) - 0.2 * (yy - ORIGIN[1])
    holed = plane.copy()
    holed[5:7, 4:7] = np.nan  # a 2 x 3 hole: nearest fill would put steps in the plane
    tile = DemTile(heights=holed, spacing=SPACING, origin=ORIGIN, name="plane")
    # Clough-Tocher is exact on planes up to its iterative gradient estimate (tol 1e-6)
    np.testing.assert_allclose(fill_voids_cubic(tile).heights, plane, atol=1e-4, rtol=0)
    skip = OffNodeSampler(tile)
    fill = OffNodeSampler(tile, voids="fill")
    # cells with a valid corner (two lie wholly inside the hole) vs cells touching no void
    assert fill.n_cells == 11 * 14 - 2 and skip.n_cells == 11 * 14 - 3 * 4
    xy, height, slope = fill.sample(4000, torch.Generator().manual_seed(1), dtype=torch.float64)
    col = (xy[:, 0] - ORIGIN[0]) / SPACING[0]
    row = (xy[:, 1] - ORIGIN[1]) / SPACING[1]
    near_hole = (row > 4) & (row < 7) & (col > 3) & (col < 7)
    assert int(near_hole.sum()) > 0
    expected = 50.0 + 0.3 * (xy[:, 0] - ORIGIN[0]) - 0.2 * (xy[:, 1] - ORIGIN[1])
    torch.testing.assert_close(height, expected, atol=1e-4, rtol=0)
    torch.testing.assert_close(slope, torch.tensor([0.3, -0.2], dtype=torch.float64).expand_as(
        slope), atol=1e-5, rtol=0)
    # nearest fill (the skip rule's surface) would be off by metres next to the hole
    nearest = GridTerrain(tile, method="bicubic", dtype=torch.float64)(xy[near_hole])
    assert float((nearest - expected[near_hole]).abs().max()) > 1.0
    with pytest.raises(NeuralMapError, match="offnode_voids"):
        OffNodeSampler(tile, voids="nearest")
