"""Latent-grid map: kernel exactness, analytic slope, C¹ continuity, between-node error."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from neuralmap.dem.tile import DemTile
from neuralmap.terrain.grid import GridTerrain
from neuralmap.terrain.latent import LatentTerrainMap
from neuralmap.terrain.latent.encode import fit_latent_map
from neuralmap.terrain.latent.synthesis import Synthesis
from neuralmap.terrain.latent.wavelet import inverse_2d


def _truth(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Smooth test relief with detail a few nodes long (30 m spacing)."""
    return (400.0 + 60.0 * np.sin(x / 310.0) * np.cos(y / 270.0)
            + 12.0 * np.sin(x / 55.0 + 0.3) * np.sin(y / 70.0)
            + 4.0 * np.cos((x - 2 * y) / 41.0))


def _tile(ny: int = 36, nx: int = 44) -> DemTile:
    x = np.arange(nx) * 30.0
    y = np.arange(ny) * 30.0
    xx, yy = np.meshgrid(x, y)
    return DemTile(_truth(xx, yy), spacing=(30.0, 30.0), name="latent_test")


@pytest.fixture(scope="module", params=["wavelet", "pyramid"])
def fitted(request) -> tuple[DemTile, LatentTerrainMap]:
    tile = _tile()
    latent_map, _ = fit_latent_map(tile, rate_weight=0.002, steps=150, levels=4, hidden=4,
                                   lr=0.02, init_step=0.05, between_points=1024,
                                   basis=request.param)
    return tile, latent_map


def _double(m: LatentTerrainMap) -> LatentTerrainMap:
    return LatentTerrainMap(m.symbols, m.steps, m.scales, m.synthesis_vector, m.feature_scale,
                            hidden=m.hidden, tile_info=m.tile_info, dtype=torch.float64,
                            basis=m.basis)


def _bspline(x: np.ndarray) -> np.ndarray:
    """Centred cubic B-spline, closed form."""
    a = np.abs(x)
    return np.where(a < 1, 2 / 3 - a**2 + a**3 / 2, np.where(a < 2, (2 - a) ** 3 / 6, 0.0))


def test_query_equals_direct_multilevel_sum(fitted):
    """Refined, folded coefficient grid == direct sum of every level's spline + MLP (the
    wavelet basis: the spline of the inverse-transformed subbands, one channel)."""
    tile, m = fitted
    m64 = _double(m)
    rng = np.random.default_rng(0)
    ny, nx = tile.shape
    uv = rng.uniform([0, 0], [nx - 1, ny - 1], size=(200, 2))
    grids = m.decoded_latents
    if m.basis.name == "wavelet":
        grids = [inverse_2d(grids, m.basis.wavelet)]
    feats = np.zeros((200, len(grids)))
    for level, z in enumerate(grids):
        s = 2.0**level
        c = z.numpy()
        wy = _bspline(uv[:, 1, None] / s - (np.arange(c.shape[0]) - 1)[None])
        wx = _bspline(uv[:, 0, None] / s - (np.arange(c.shape[1]) - 1)[None])
        feats[:, level] = np.einsum("mi,ij,mj->m", wy, c, wx)
    synth = Synthesis(len(grids), m.hidden, torch.from_numpy(m.feature_scale))
    synth.load_parameter_vector(torch.from_numpy(m.synthesis_vector))
    expected = synth.double()(torch.from_numpy(feats)).detach().numpy()
    got = m64(torch.from_numpy(uv * 30.0)).numpy()
    np.testing.assert_allclose(got, expected, atol=1e-8, rtol=0)
    # the float32 query agrees to float32 rounding
    got32 = m(torch.from_numpy(uv * 30.0).float()).double().numpy()
    np.testing.assert_allclose(got32, expected, atol=2e-3, rtol=0)


def test_analytic_slope_matches_autograd_and_finite_differences(fitted):
    tile, m = fitted
    m64 = _double(m)
    rng = np.random.default_rng(1)
    xy = torch.from_numpy(rng.uniform([1, 1], [1289, 1049], size=(300, 2)))
    h, slope = m64.height_and_slope(xy)
    xr = xy.clone().requires_grad_(True)
    ha = m64(xr)
    (grad,) = torch.autograd.grad(ha.sum(), xr)
    np.testing.assert_allclose(h.numpy(), ha.detach().numpy(), atol=1e-10)
    np.testing.assert_allclose(slope.numpy(), grad.numpy(), atol=1e-10)
    eps = 1e-4
    for axis in range(2):
        d = torch.zeros(2, dtype=torch.float64)
        d[axis] = eps
        fd = (m64(xy + d) - m64(xy - d)) / (2 * eps)
        np.testing.assert_allclose(slope[:, axis].numpy(), fd.numpy(), atol=1e-6)


def test_height_and_slope_continuous_across_cell_borders(fitted):
    """C¹: height and slope jump by O(eps) across every cell border (both axes)."""
    _, m = fitted
    m64 = _double(m)
    eps = 1e-7
    borders = torch.arange(1, 43, dtype=torch.float64) * 30.0
    other = torch.full_like(borders, 517.3)
    for axis in range(2):
        coords = [borders, other] if axis == 0 else [other, borders[:34]]
        n = coords[0].numel() if axis == 0 else coords[1].numel()
        base = torch.stack([coords[0][:n], coords[1][:n]], dim=-1)
        d = torch.zeros(2, dtype=torch.float64)
        d[axis] = eps
        h_lo, s_lo = m64.height_and_slope(base - d)
        h_hi, s_hi = m64.height_and_slope(base + d)
        assert (h_hi - h_lo).abs().max() < 1e-4
        assert (s_hi - s_lo).abs().max() < 1e-6  # a kink (C0 only) would jump by ~1e-2


def test_node_heights_match_queries_and_fit(fitted):
    tile, m = fitted
    nodes = m.node_heights().numpy()
    xy = torch.from_numpy(tile.node_xy().reshape(-1, 2))
    np.testing.assert_allclose(_double(m)(xy).numpy().reshape(tile.shape), nodes, atol=1e-8)
    assert np.sqrt(np.mean((nodes - tile.heights) ** 2)) < 0.3


def test_between_node_error_not_worse_than_bicubic(fitted):
    """Against the known continuous truth between the nodes, the latent map's error is at
    most bicubic interpolation's of the same DEM (both see only the nodes)."""
    tile, m = fitted
    rng = np.random.default_rng(2)
    xy = rng.uniform([0, 0], [43 * 30.0, 35 * 30.0], size=(4000, 2))
    truth = _truth(xy[:, 0], xy[:, 1])
    latent = m(torch.from_numpy(xy).float()).double().numpy()
    bicubic = GridTerrain(tile, method="bicubic")(torch.from_numpy(xy)).numpy()
    rmse_latent = np.sqrt(np.mean((latent - truth) ** 2))
    rmse_bicubic = np.sqrt(np.mean((bicubic - truth) ** 2))
    assert rmse_bicubic > 0.05  # the truth has detail between the nodes
    assert rmse_latent <= rmse_bicubic, (rmse_latent, rmse_bicubic)


def test_outside_extent_is_clamped_with_zero_cross_slope(fitted):
    _, m = fitted
    xy = torch.tensor([[-50.0, 300.0], [300.0, 5000.0]])
    h, slope = m.height_and_slope(xy)
    h_border, _ = m.height_and_slope(torch.tensor([[0.0, 300.0], [300.0, 1050.0]]))
    torch.testing.assert_close(h, h_border)
    assert slope[0, 0] == 0 and slope[1, 1] == 0


@pytest.mark.parametrize("exact", [True, False])
def test_exact_start_reproduces_every_node(exact: bool):
    """The exact start's unquantised latents give the DEM at every node (float64 spline
    sum against the heights themselves); the sweeps alone leave a residual on rough relief."""
    from neuralmap.terrain.latent import LatentGrid
    from neuralmap.terrain.latent.bspline import node_values
    from neuralmap.terrain.latent.pyramid import node_lattice

    rng = np.random.default_rng(3)
    heights = np.cumsum(rng.normal(0.0, 80.0, (23, 31)), axis=1)  # rough: 80 m per node
    tile = DemTile(heights, spacing=(2000.0, 2000.0), name="rough")
    grid = LatentGrid(tile, levels=4, init_sweeps=2, exact_start=exact, basis="pyramid")
    latents = [z.detach().double() for z in grid.latents]
    nodes = node_values(node_lattice(latents, tile.shape)).sum(0).numpy() + heights.mean()
    err = np.abs(nodes - heights).max()
    if exact:
        assert err < 1e-3  # float32 latents of ~1 km values: ~1e-4 m rounding
    else:
        assert err > 1.0
