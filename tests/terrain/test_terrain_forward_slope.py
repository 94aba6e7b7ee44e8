"""Forward-mode height and slope of the blockwise net equal autograd of its forward pass."""

from __future__ import annotations

import pytest
import torch

from neuralmap.dem.synthetic import synthetic_tile
from neuralmap.exceptions import NeuralMapError
from neuralmap.terrain.blockwise import BlockwiseTerrainNet
from neuralmap.terrain.forward_slope import blockwise_height_and_slope


@pytest.mark.parametrize(
    "kw",
    [
        {"encoding": "fourier", "depth": 2, "activation": "sine"},
        {"encoding": "fourier", "depth": 3, "activation": "tanh"},
        {"encoding": "none", "depth": 1, "activation": "bipolar_sigmoid", "blend": False},
    ],
)
def test_equals_autograd_in_float64(kw: dict) -> None:
    tile = synthetic_tile((41, 57), (30.0, 25.0), seed=2)
    net = BlockwiseTerrainNet.from_tile(tile, block_nodes=12, n_frequencies=5, hidden=7, **kw)
    net = net.double()
    g = torch.Generator().manual_seed(0)
    xmin, xmax, ymin, ymax = tile.extent
    u = torch.rand(2998, 2, generator=g, dtype=torch.float64)
    xy = torch.stack([xmin + u[:, 0] * (xmax - xmin), ymin + u[:, 1] * (ymax - ymin)], -1)
    # points exactly on block borders and in blending zones are part of the draw above;
    # add the extent corners too
    xy = torch.cat([xy, torch.tensor([[xmin, ymin], [xmax, ymax]], dtype=torch.float64)])
    points = xy.clone().requires_grad_(True)
    height = net(points)
    (slope,) = torch.autograd.grad(height.sum(), points)
    h, s = blockwise_height_and_slope(net, xy.reshape(2, -1, 2))
    torch.testing.assert_close(h.reshape(-1), height.detach(), rtol=0, atol=1e-9)
    torch.testing.assert_close(s.reshape(-1, 2), slope, rtol=0, atol=1e-11)


def test_bad_shape() -> None:
    tile = synthetic_tile((20, 20), 30.0)
    net = BlockwiseTerrainNet.from_tile(tile, block_nodes=8, hidden=4)
    with pytest.raises(NeuralMapError, match=r"\(\.\.\., 2\)"):
        blockwise_height_and_slope(net, torch.zeros(4, 3))


def test_nan_points_give_nan_like_forward() -> None:
    tile = synthetic_tile((20, 20), 30.0)
    net = BlockwiseTerrainNet.from_tile(tile, block_nodes=8, hidden=4)
    xy = torch.tensor([[100.0, 200.0], [float("nan"), 10.0], [300.0, 300.0]])
    h, s = blockwise_height_and_slope(net, xy)
    assert torch.isnan(h[1]) and torch.isnan(s[1]).all()
    torch.testing.assert_close(h[[0, 2]], net(xy[[0, 2]]))
