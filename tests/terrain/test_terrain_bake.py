"""Baking a terrain model onto a grid: node values are the model's, between nodes bicubic."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from neuralmap.dem.synthetic import synthetic_tile
from neuralmap.dem.tile import DemTile
from neuralmap.exceptions import NeuralMapError
from neuralmap.terrain.bake import bake_to_grid
from neuralmap.terrain.blockwise import BlockwiseTerrainNet


@pytest.mark.parametrize("oversample", [1, 2])
def test_baked_grid_holds_the_model_at_its_nodes(oversample: int) -> None:
    tile = synthetic_tile((21, 27), (30.0, 20.0), seed=4)
    net = BlockwiseTerrainNet.from_tile(tile, block_nodes=10, hidden=8, n_frequencies=4).eval()
    grid = bake_to_grid(net, tile, oversample=oversample)
    assert grid.extent == tile.extent
    assert grid.shape == ((21 - 1) * oversample + 1, (27 - 1) * oversample + 1)
    # nodes of the original tile are nodes of the baked grid: exact model values there
    xy = torch.from_numpy(tile.node_xy().reshape(-1, 2))
    with torch.no_grad():
        expected = net(xy.float()).double()
    torch.testing.assert_close(grid(xy), expected, rtol=0, atol=1e-9)
    # between nodes: the Keys cubic convolution (a = -1/2) of the baked node values, by a
    # NumPy reference, at interior points (their 4 x 4 stencil needs no padding)
    heights = grid.heights.numpy()
    nodes = DemTile(heights, grid.spacing, origin=tile.origin).node_xy()
    gen = np.random.default_rng(0)
    frac_idx = gen.uniform(1.0, np.array(heights.shape) - 3.0, size=(40, 2))  # (row, col)
    row0, col0 = np.floor(frac_idx).astype(int).T
    step_x, step_y = nodes[0, 1, 0] - nodes[0, 0, 0], nodes[1, 0, 1] - nodes[0, 0, 1]
    mid = np.stack([nodes[0, 0, 0] + frac_idx[:, 1] * step_x,
                    nodes[0, 0, 1] + frac_idx[:, 0] * step_y], -1)
    ref = np.zeros(len(mid))
    for n in range(len(mid)):  # test reference: one point at a time
        wy = _keys(frac_idx[n, 0] - row0[n])
        wx = _keys(frac_idx[n, 1] - col0[n])
        block = heights[row0[n] - 1:row0[n] + 3, col0[n] - 1:col0[n] + 3]
        ref[n] = wy @ block @ wx
    torch.testing.assert_close(grid(torch.from_numpy(mid)), torch.from_numpy(ref),
                               rtol=0, atol=1e-9)


def _keys(t: float) -> np.ndarray:
    """Keys (1981) cubic-convolution weights, a = -1/2, of the nodes at -1, 0, 1, 2 for a
    point at ``t`` in [0, 1)."""
    a = -0.5
    s = np.abs(np.array([t + 1.0, t, 1.0 - t, 2.0 - t]))
    near = (a + 2) * s**3 - (a + 3) * s**2 + 1
    far = a * s**3 - 5 * a * s**2 + 8 * a * s - 4 * a
    return np.where(s <= 1.0, near, far)


def test_bad_oversample() -> None:
    tile = synthetic_tile((17, 17), 30.0)
    net = BlockwiseTerrainNet.from_tile(tile, block_nodes=8, hidden=4)
    with pytest.raises(NeuralMapError, match="oversample"):
        bake_to_grid(net, tile, oversample=0)
