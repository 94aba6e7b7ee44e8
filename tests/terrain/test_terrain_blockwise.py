"""BlockwiseTerrainNet: batched blocks equal a per-block loop, seamless blending, eq. (8)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from neuralmap.dem.tile import DemTile
from neuralmap.exceptions import NeuralMapError
from neuralmap.terrain.block_layout import smoothstep
from neuralmap.terrain.blockwise import BlockwiseTerrainNet, block_height_statistics
from neuralmap.terrain.export import load_map, save_map


@pytest.fixture(scope="module")
def tile() -> DemTile:
    x = np.linspace(0.0, 1.0, 61)
    xx, yy = np.meshgrid(x, np.linspace(0.0, 1.0, 49))
    heights = 400.0 + 80.0 * np.sin(5.0 * xx) * np.cos(3.0 * yy) + 30.0 * yy
    return DemTile(heights, (30.0, 25.0), origin=(1000.0, -500.0), name="wave")


def _points(tile: DemTile, n: int, seed: int = 0) -> torch.Tensor:
    xmin, xmax, ymin, ymax = tile.extent
    u = torch.rand(n, 2, generator=torch.Generator().manual_seed(seed), dtype=torch.float64)
    return torch.stack([xmin + u[:, 0] * (xmax - xmin), ymin + u[:, 1] * (ymax - ymin)], -1)


def _smoothstep_np(t: np.ndarray) -> np.ndarray:
    """Quintic smoothstep 6t^5 - 15t^4 + 10t^3 on t clamped to [0, 1]."""
    t = np.clip(t, 0.0, 1.0)
    return 6.0 * t**5 - 15.0 * t**4 + 10.0 * t**3


def _axis_weights_np(u: float, lo: float, core: float, half: float, n: int) -> np.ndarray:
    """Blend weight of each of the ``n`` blocks along one axis, from the layout's formula.

    Block ``i`` owns the core ``[b_i, b_{i+1}]`` with ``b_i = lo + i core``; across each
    interior border ``b`` its weight ramps over ``[b - half, b + half]`` as the smoothstep of
    ``t = (u - (b - half)) / (2 half)``: up at its lower border, down at its upper one.
    """
    weights = np.ones(n)
    for i in range(n):
        if i > 0:
            weights[i] *= _smoothstep_np((u - (lo + i * core - half)) / (2.0 * half))
        if i < n - 1:
            weights[i] *= 1.0 - _smoothstep_np((u - (lo + (i + 1) * core - half)) / (2.0 * half))
    return weights


def _reference_height(net: BlockwiseTerrainNet, xy: torch.Tensor) -> np.ndarray:
    """Independent NumPy evaluation: loops over points and blocks, blend weights, block
    frames and Fourier features rebuilt from the documented formulas (only the learnt
    parameters and the per-block height statistics are read from the net)."""
    assert net.activation_name == "sine" and net.encoding == "fourier"
    xmin, xmax, ymin, ymax = net.layout.extent
    nbx, nby = net.layout.num_blocks
    cx, cy = (xmax - xmin) / nbx, (ymax - ymin) / nby
    wx, wy = net.layout.blend_width
    freq = net.frequencies.detach().double().numpy()  # (2, F)
    weights = [w.detach().double().numpy() for w in net.weights]
    biases = [b.detach().double().numpy() for b in net.biases]
    out_w = net.out_weight.detach().double().numpy()
    out_b = net.out_bias.detach().double().numpy()
    mean = net.height_mean.double().numpy()
    std = net.height_std.double().numpy()
    points = xy.detach().double().numpy()
    out = np.zeros(len(points))
    for p, (x, y) in enumerate(points):
        blend = np.outer(
            _axis_weights_np(y, ymin, cy, wy, nby), _axis_weights_np(x, xmin, cx, wx, nbx)
        )  # (nby, nbx)
        for iy in range(nby):
            for ix in range(nbx):
                if blend[iy, ix] == 0.0:
                    continue
                b = iy * nbx + ix
                centre = np.array([xmin + (ix + 0.5) * cx, ymin + (iy + 0.5) * cy])
                half = np.array([0.5 * cx + wx, 0.5 * cy + wy])  # core + blend zone
                local = (np.array([x, y]) - centre) / half
                angle = 2.0 * np.pi * (local @ freq)
                hidden = np.concatenate([local, np.sin(angle), np.cos(angle)])
                for weight, bias in zip(weights, biases, strict=True):
                    hidden = np.sin(hidden @ weight[b] + bias[b])
                normalised = hidden @ out_w[b] + out_b[b]
                out[p] += blend[iy, ix] * (mean[b] + std[b] * normalised)
    return out


def test_blend_weights_match_the_formula_and_sum_to_one(tile: DemTile) -> None:
    net = BlockwiseTerrainNet.from_tile(tile, block_nodes=12, overlap_nodes=4).double()
    xy = _points(tile, 300, seed=4)
    point, block, weight = net.layout.assign(xy)
    got = np.zeros((300, net.layout.count))
    got[point.numpy(), block.numpy()] = weight.numpy()
    (xmin, xmax, ymin, ymax), (nbx, nby) = net.layout.extent, net.layout.num_blocks
    wx, wy = net.layout.blend_width
    assert wx > 0 and wy > 0
    expected = np.stack([
        np.outer(
            _axis_weights_np(float(y), ymin, (ymax - ymin) / nby, wy, nby),
            _axis_weights_np(float(x), xmin, (xmax - xmin) / nbx, wx, nbx),
        ).ravel()
        for x, y in xy.numpy()
    ])
    np.testing.assert_allclose(got, expected, rtol=0, atol=1e-12)
    np.testing.assert_allclose(expected.sum(1), 1.0, rtol=0, atol=1e-12)
    assert ((expected > 0) & (expected < 1)).any()  # some points do sit in a blend zone


def test_grouped_blocks_equal_per_block_loop(tile: DemTile) -> None:
    net = BlockwiseTerrainNet.from_tile(tile, block_nodes=12, overlap_nodes=4, hidden=8).double()
    xy = _points(tile, 64)
    np.testing.assert_allclose(net(xy).detach(), _reference_height(net, xy), rtol=0, atol=1e-9)
    # The sample crosses blend zones (several blocks per point), so the blending is checked.
    point, _, _ = net.layout.assign(xy)
    assert point.shape[0] > xy.shape[0]


def test_all_points_in_one_block_same_result(tile: DemTile) -> None:
    """Concentrated points (a filter's batch) pack into few tiles and still agree."""
    net = BlockwiseTerrainNet.from_tile(tile, block_nodes=12, overlap_nodes=4).double()
    xy = torch.tensor([[1200.0, -300.0]], dtype=torch.float64) + 0.1 * torch.randn(
        5000, 2, generator=torch.Generator().manual_seed(1), dtype=torch.float64
    )
    one = torch.stack([net(p) for p in xy[:5]]).detach()
    np.testing.assert_allclose(net(xy)[:5].detach(), one, atol=1e-10)


def test_no_points_give_empty_heights_and_slopes(tile: DemTile) -> None:
    """Zero points (a filter batch with every run off the map) are an empty answer, not a
    reshape error: height, analytic slope and the autograd linearisation."""
    from neuralmap.linearize.autograd import AutogradLinearizer

    net = BlockwiseTerrainNet.from_tile(tile, block_nodes=12, overlap_nodes=4, hidden=8).double()
    xy = torch.zeros(0, 2, dtype=torch.float64)
    assert net(xy).shape == (0,)
    height, slope = net.height_and_slope(xy)
    assert height.shape == (0,) and slope.shape == (0, 2)
    lin = AutogradLinearizer(net)(xy, torch.zeros(0, 2, 2, dtype=torch.float64))
    assert lin.height.shape == (0,) and lin.slope.shape == (0, 2)
    # the same net still answers a real batch afterwards, as before
    np.testing.assert_allclose(net(_points(tile, 8)).detach(), _reference_height(
        net, _points(tile, 8)), rtol=0, atol=1e-9)


def test_partition_of_unity(tile: DemTile) -> None:
    net = BlockwiseTerrainNet.from_tile(tile, block_nodes=10, overlap_nodes=4)
    xy = _points(tile, 2000).float()
    point, block, weight = net.layout.assign(xy)
    total = torch.zeros(2000).index_add(0, point, weight)
    np.testing.assert_allclose(total.numpy(), 1.0, atol=1e-6)
    assert point.shape[0] <= 4 * 2000 and (weight > 0).all()
    assert net.layout.num_blocks == (6, 5)


def _border_slopes(net: BlockwiseTerrainNet, x_border: float, y: float, eps: float) -> torch.Tensor:
    xy = torch.tensor([[x_border - eps, y], [x_border + eps, y]], dtype=torch.float64)
    xy.requires_grad_(True)
    (grad,) = torch.autograd.grad(net(xy).sum(), xy)
    return grad


@pytest.mark.parametrize("blend", [True, False])
def test_height_and_slope_continuity_across_block_border(tile: DemTile, blend: bool) -> None:
    """Blended maps are C1 across borders; the paper's hard gate is not (control case)."""
    net = BlockwiseTerrainNet.from_tile(
        tile, block_nodes=12, overlap_nodes=4, blend=blend, seed=3
    ).double()
    x_border = net.layout.extent[0] + net.layout.core_size[0]  # between block 0 and 1
    y = -200.0
    eps = 1e-6
    xy = torch.tensor([[x_border - eps, y], [x_border + eps, y]], dtype=torch.float64)
    height_jump = (net(xy)[1] - net(xy)[0]).abs().item()
    slope_jump = (_border_slopes(net, x_border, y, eps)[1] - _border_slopes(net, x_border, y, eps)[0]).abs().max().item()
    if blend:
        assert height_jump < 1e-4  # O(eps * slope)
        assert slope_jump < 1e-4  # C1: O(eps * curvature)
    else:
        # Untrained independent blocks disagree: the hard gate leaves a seam.
        assert height_jump > 1e-2 or slope_jump > 1e-3


def test_blend_zone_edges_are_smooth() -> None:
    t = torch.linspace(-0.5, 1.5, 2001, dtype=torch.float64, requires_grad=True)
    s = smoothstep(t)
    (ds,) = torch.autograd.grad(s.sum(), t)
    assert s[0] == 0 and s[-1] == 1
    # Quintic smoothstep: zero first derivative at both ends, peak 15/8 at t = 1/2.
    assert ds[t.detach() <= 0].abs().max() == 0 and ds[t.detach() >= 1].abs().max() == 0
    np.testing.assert_allclose(ds.max().item(), 15.0 / 8.0, rtol=1e-6)


@pytest.mark.parametrize("blend", [True, False])
def test_analytic_eq8_gradient_equals_autograd(tile: DemTile, blend: bool) -> None:
    net = BlockwiseTerrainNet.from_tile(
        tile,
        num_blocks=(3, 1),
        overlap_nodes=6,
        encoding="none",
        activation="bipolar_sigmoid",
        hidden=30,
        depth=1,
        blend=blend,
    ).double()
    xy = _points(tile, 500).requires_grad_(True)
    (auto,) = torch.autograd.grad(net(xy).sum(), xy)
    analytic = net.analytic_slope(xy.detach())
    np.testing.assert_allclose(analytic.detach(), auto, rtol=1e-9, atol=1e-12)


def test_analytic_slope_needs_bp_preset(tile: DemTile) -> None:
    net = BlockwiseTerrainNet.from_tile(tile, block_nodes=20)
    with pytest.raises(NeuralMapError, match="BP preset"):
        net.analytic_slope(_points(tile, 3).float())


def test_bipolar_sigmoid_is_the_paper_function() -> None:
    from neuralmap.terrain.activations import bipolar_sigmoid

    a = torch.linspace(-6, 6, 101, dtype=torch.float64)
    np.testing.assert_allclose(bipolar_sigmoid(a), (1 - torch.exp(-a)) / (1 + torch.exp(-a)), atol=1e-15)


def test_block_statistics_match_direct_computation(tile: DemTile) -> None:
    net = BlockwiseTerrainNet.from_tile(tile, block_nodes=12, overlap_nodes=4)
    mean, std = block_height_statistics(tile, net.layout)
    bounds = net.layout.block_bounds()
    xy = tile.node_xy()
    for b in (0, 7, len(bounds) - 1):
        x0, x1, y0, y1 = bounds[b]
        inside = (xy[..., 0] >= x0 - 1e-6) & (xy[..., 0] <= x1 + 1e-6)
        inside &= (xy[..., 1] >= y0 - 1e-6) & (xy[..., 1] <= y1 + 1e-6)
        h = tile.heights[inside]
        np.testing.assert_allclose(mean[b], h.mean(), rtol=1e-10)
        np.testing.assert_allclose(std[b], max(h.std(), 1.0), rtol=1e-8)


def test_outputs_are_metres_and_dtype_follows_input(tile: DemTile) -> None:
    net = BlockwiseTerrainNet.from_tile(tile, block_nodes=12)
    xy = _points(tile, 10)
    out = net(xy)
    assert out.dtype == torch.float64 and out.shape == (10,)
    assert net(xy.float().reshape(2, 5, 2)).shape == (2, 5)
    # Untrained output stays near the block means (metres, not normalised units).
    assert 250.0 < float(out.detach().mean()) < 600.0


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"num_blocks": (40, 1)}, "cannot feed"),
        ({"block_nodes": 1}, "block_nodes"),
        ({"block_nodes": 12, "overlap_nodes": 20}, "overlap_nodes"),
        ({"encoding": "wavelet"}, "encoding"),
        ({"activation": "relu6"}, "activation"),
    ],
)
def test_bad_block_configs_raise_clear_errors(tile: DemTile, kwargs: dict, match: str) -> None:
    with pytest.raises(NeuralMapError, match=match):
        BlockwiseTerrainNet.from_tile(tile, **kwargs)


def test_export_round_trip_identical(tile: DemTile, tmp_path) -> None:
    net = BlockwiseTerrainNet.from_tile(tile, block_nodes=12, seed=5)
    with torch.no_grad():
        for p in net.parameters():
            p.add_(0.01 * torch.randn_like(p))
    path = save_map(net, tmp_path / "run" / "neural_map.pt", metrics={"rmse_m": 1.5})
    loaded = load_map(path)
    xy = _points(tile, 300).float()
    assert torch.equal(net(xy), loaded(xy))
    assert loaded.tile_name == "wave" and loaded.tile_fingerprint == tile.fingerprint()
    assert loaded.metrics == {"rmse_m": 1.5}
    assert loaded.extent == net.extent
    assert not list(tmp_path.joinpath("run").glob("*.tmp"))


def test_load_map_rejects_other_files(tmp_path) -> None:
    with pytest.raises(NeuralMapError, match="not found"):
        load_map(tmp_path / "missing.pt")
    other = tmp_path / "weights.pt"
    torch.save({"state_dict": {}}, other)
    with pytest.raises(NeuralMapError, match="not a neuralmap map export"):
        load_map(other)
    garbage = tmp_path / "garbage.pt"
    garbage.write_bytes(b"not a torch file")
    with pytest.raises(NeuralMapError, match="not a neuralmap map export"):
        load_map(garbage)
