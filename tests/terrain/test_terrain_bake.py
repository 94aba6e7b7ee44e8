"""Baking a terrain model onto a grid: node values are the model's, between nodes bicubic."""

from __future__ import annotations

import pytest
import torch

from neuralmap.dem.synthetic import synthetic_tile
from neuralmap.dem.tile import DemTile
from neuralmap.exceptions import NeuralMapError
from neuralmap.terrain.bake import bake_to_grid
from neuralmap.terrain.blockwise import BlockwiseTerrainNet
from neuralmap.terrain.grid import GridTerrain


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
    # between nodes: the Keys bicubic of the baked node values (independent GridTerrain)
    baked = DemTile(grid.heights.numpy(), grid.spacing, origin=tile.origin)
    mid = xy[:50] + torch.tensor([7.0, 3.0], dtype=torch.float64)
    torch.testing.assert_close(grid(mid), GridTerrain(baked, method="bicubic")(mid))


def test_bad_oversample() -> None:
    tile = synthetic_tile((17, 17), 30.0)
    net = BlockwiseTerrainNet.from_tile(tile, block_nodes=8, hidden=4)
    with pytest.raises(NeuralMapError, match="oversample"):
        bake_to_grid(net, tile, oversample=0)
