"""GridTerrain: exactness, node reproduction, analytic vs autograd slopes, clamping, voids."""

from __future__ import annotations

import sys

import numpy as np
import pytest
import torch
from scipy.interpolate import RegularGridInterpolator

from neuralmap.dem.tile import DemTile
from neuralmap.exceptions import NeuralMapError
from neuralmap.terrain.base import TerrainModel
from neuralmap.terrain.grid import GridTerrain, fill_voids_nearest

SPACING = (30.0, 20.0)
ORIGIN = (100.0, -50.0)
SHAPE = (9, 11)  # ny, nx


def make_tile(fn=None, shape=SHAPE, seed=0) -> DemTile:
    """A small tile: heights from fn(x, y) at the nodes, or seeded random terrain."""
    ny, nx = shape
    x = ORIGIN[0] + np.arange(nx) * SPACING[0]
    y = ORIGIN[1] + np.arange(ny) * SPACING[1]
    xx, yy = np.meshgrid(x, y)
    if fn is None:
        heights = 300.0 + 40.0 * np.random.default_rng(seed).standard_normal(shape)
    else:
        heights = fn(xx, yy)
    return DemTile(heights, spacing=SPACING, origin=ORIGIN, name="test")


def random_points(n: int, tile: DemTile, *, margin: float = 0.0, seed: int = 1) -> torch.Tensor:
    """Uniform points over the tile extent grown by ``margin`` metres (float64)."""
    xmin, xmax, ymin, ymax = tile.extent
    g = torch.Generator().manual_seed(seed)
    u = torch.rand(n, 2, generator=g, dtype=torch.float64)
    lo = torch.tensor([xmin - margin, ymin - margin], dtype=torch.float64)
    hi = torch.tensor([xmax + margin, ymax + margin], dtype=torch.float64)
    return lo + u * (hi - lo)


def border_points(tile: DemTile) -> torch.Tensor:
    """Points inside the outermost cells (and exactly on the border and corners)."""
    xmin, xmax, ymin, ymax = tile.extent
    dx, dy = tile.spacing
    xs = [xmin, xmin + 0.3 * dx, xmin + 0.9 * dx, 0.5 * (xmin + xmax), xmax - 0.4 * dx, xmax]
    ys = [ymin, ymin + 0.2 * dy, ymin + 0.7 * dy, 0.5 * (ymin + ymax), ymax - 0.6 * dy, ymax]
    return torch.tensor([[x, y] for x in xs for y in ys], dtype=torch.float64)


def plane(x, y):
    return 250.0 + 0.3 * x - 0.15 * y


def quadratic(x, y):
    return 80.0 + 0.2 * x - 0.1 * y + 1e-3 * x * x - 2e-3 * x * y + 5e-4 * y * y


def quadratic_grad(x, y):
    return torch.stack([0.2 + 2e-3 * x - 2e-3 * y, -0.1 - 2e-3 * x + 1e-3 * y], dim=-1)


def keys_kernel(s: np.ndarray) -> np.ndarray:
    """Keys (1981) cubic convolution kernel, a = -1/2 (independent reference form)."""
    s = np.abs(s)
    return np.where(
        s <= 1,
        1.5 * s**3 - 2.5 * s**2 + 1,
        np.where(s < 2, -0.5 * s**3 + 2.5 * s**2 - 4 * s + 2, 0.0),
    )


def keys_reference(tile: DemTile, xy: np.ndarray) -> np.ndarray:
    """Per-point Keys interpolation with the f[-1] = 3f0 - 3f1 + f2 border rule (numpy)."""
    f = tile.heights
    ny, nx = f.shape

    def node(i: int, j: int) -> float:
        def ext(idx: int, n: int) -> list[tuple[int, float]]:
            if idx < 0:
                return [(0, 3.0), (1, -3.0), (2, 1.0)]
            if idx > n - 1:
                return [(n - 1, 3.0), (n - 2, -3.0), (n - 3, 1.0)]
            return [(idx, 1.0)]

        return sum(wi * wj * f[ii, jj] for ii, wi in ext(i, ny) for jj, wj in ext(j, nx))

    out = np.empty(len(xy))
    for k, (x, y) in enumerate(xy):
        u = (x - tile.origin[0]) / tile.spacing[0]
        v = (y - tile.origin[1]) / tile.spacing[1]
        j0 = min(int(np.floor(u)), nx - 2)
        i0 = min(int(np.floor(v)), ny - 2)
        total = 0.0
        for i in range(i0 - 1, i0 + 3):
            for j in range(j0 - 1, j0 + 3):
                total += keys_kernel(u - j) * keys_kernel(v - i) * node(i, j)
        out[k] = total
    return out


@pytest.mark.parametrize("method", ["bilinear", "bicubic"])
def test_exact_on_plane_everywhere(method: str) -> None:
    tile = make_tile(plane)
    grid = GridTerrain(tile, method=method)
    xy = torch.cat([random_points(500, tile), border_points(tile)])
    h, slope = grid.height_and_slope(xy)
    torch.testing.assert_close(grid(xy), plane(xy[:, 0], xy[:, 1]), rtol=0, atol=1e-9)
    torch.testing.assert_close(h, plane(xy[:, 0], xy[:, 1]), rtol=0, atol=1e-9)
    expected = torch.tensor([0.3, -0.15], dtype=torch.float64).expand_as(slope)
    torch.testing.assert_close(slope, expected, rtol=0, atol=1e-11)


def test_bicubic_exact_on_quadratic_interior_and_edges() -> None:
    tile = make_tile(quadratic)
    grid = GridTerrain(tile, method="bicubic")
    xy = torch.cat([random_points(500, tile), border_points(tile)])
    h, slope = grid.height_and_slope(xy)
    torch.testing.assert_close(h, quadratic(xy[:, 0], xy[:, 1]), rtol=0, atol=1e-9)
    torch.testing.assert_close(slope, quadratic_grad(xy[:, 0], xy[:, 1]), rtol=0, atol=1e-11)


def test_bilinear_is_not_exact_on_quadratic() -> None:
    """Sanity check that the exactness tests can fail: bilinear misses curvature."""
    tile = make_tile(quadratic)
    xy = random_points(200, tile)
    err = (GridTerrain(tile)(xy) - quadratic(xy[:, 0], xy[:, 1])).abs().max()
    assert err > 1e-2


@pytest.mark.parametrize("method", ["bilinear", "bicubic"])
def test_reproduces_node_values(method: str) -> None:
    tile = make_tile()
    grid = GridTerrain(tile, method=method)
    nodes = torch.from_numpy(tile.node_xy())
    torch.testing.assert_close(grid(nodes), torch.from_numpy(tile.heights), rtol=0, atol=1e-10)


def test_bilinear_matches_scipy() -> None:
    tile = make_tile(seed=3)
    xy = random_points(1000, tile, seed=4)
    ny, nx = tile.shape
    axes = (
        tile.origin[1] + np.arange(ny) * tile.spacing[1],
        tile.origin[0] + np.arange(nx) * tile.spacing[0],
    )
    ref = RegularGridInterpolator(axes, tile.heights, method="linear")(xy.numpy()[:, ::-1])
    np.testing.assert_allclose(GridTerrain(tile)(xy).numpy(), ref, rtol=0, atol=1e-10)


def test_bicubic_matches_keys_kernel_reference() -> None:
    tile = make_tile(seed=5)
    xy = torch.cat([random_points(300, tile, seed=6), border_points(tile)])
    ref = keys_reference(tile, xy.numpy())
    got = GridTerrain(tile, method="bicubic")(xy).numpy()
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-9)


@pytest.mark.parametrize("method", ["bilinear", "bicubic"])
def test_analytic_slope_equals_autograd(method: str) -> None:
    tile = make_tile(seed=7)
    grid = GridTerrain(tile, method=method)
    # includes points outside the extent (clamped) and a leading batch shape
    xy = random_points(600, tile, margin=40.0, seed=8).reshape(3, 200, 2)
    xy_req = xy.clone().requires_grad_(True)
    h_auto = grid(xy_req)
    (g_auto,) = torch.autograd.grad(h_auto.sum(), xy_req)
    h, slope = grid.height_and_slope(xy)
    assert h.shape == (3, 200) and slope.shape == (3, 200, 2)
    torch.testing.assert_close(h, h_auto.detach(), rtol=0, atol=1e-10)
    torch.testing.assert_close(slope, g_auto, rtol=0, atol=1e-10)
    assert not h.requires_grad and not slope.requires_grad


@pytest.mark.parametrize("method", ["bilinear", "bicubic"])
def test_slope_matches_central_differences(method: str) -> None:
    tile = make_tile(seed=9)
    grid = GridTerrain(tile, method=method)
    xy = random_points(200, tile, seed=10)
    step = 1e-4
    ex = torch.tensor([step, 0.0], dtype=torch.float64)
    ey = torch.tensor([0.0, step], dtype=torch.float64)
    fd = torch.stack(
        [(grid(xy + ex) - grid(xy - ex)) / (2 * step), (grid(xy + ey) - grid(xy - ey)) / (2 * step)],
        dim=-1,
    )
    # random points are never within 1e-4 m of a cell edge (probability ~1e-5 per point)
    torch.testing.assert_close(grid.height_and_slope(xy)[1], fd, rtol=0, atol=1e-6)


def test_outside_points_are_clamped_to_border() -> None:
    tile = make_tile(seed=11)
    grid = GridTerrain(tile, method="bicubic")
    xmin, xmax, ymin, ymax = tile.extent
    outside = torch.tensor(
        [[xmin - 500.0, ymin + 33.0], [xmax + 1e4, ymax + 7.0], [xmin + 45.0, ymax + 100.0]],
        dtype=torch.float64,
    )
    clamped = torch.stack(
        [outside[:, 0].clamp(xmin, xmax), outside[:, 1].clamp(ymin, ymax)], dim=-1
    )
    torch.testing.assert_close(grid(outside), grid(clamped), rtol=0, atol=1e-12)
    _, slope = grid.height_and_slope(outside)
    assert slope[0, 0] == 0 and slope[0, 1] != 0  # clamped in x only
    assert (slope[1] == 0).all()
    assert slope[2, 0] != 0 and slope[2, 1] == 0
    assert not grid.contains(outside).any()
    assert grid.contains(random_points(10, tile)).all()


def test_nan_points_give_nan_not_errors() -> None:
    tile = make_tile()
    for method in ("bilinear", "bicubic"):
        grid = GridTerrain(tile, method=method)
        xy = torch.tensor([[float("nan"), 0.0], [200.0, 10.0]], dtype=torch.float64)
        h, slope = grid.height_and_slope(xy)
        assert torch.isnan(h[0])
        assert torch.isnan(grid(xy)[0])
        assert torch.isfinite(h[1]) and torch.isfinite(slope[1]).all()


def test_voids_filled_by_nearest_valid_node() -> None:
    tile = make_tile(seed=12)
    heights = tile.heights.copy()
    voids = [(0, 0), (4, 5), (4, 6), (8, 10), (2, 9)]
    for i, j in voids:
        heights[i, j] = np.nan
    void_tile = DemTile(heights, spacing=SPACING, origin=ORIGIN)
    grid = GridTerrain(void_tile, method="bicubic")
    assert grid.n_filled == len(voids)
    filled = grid.heights.numpy()
    assert np.isfinite(filled).all()
    valid = np.argwhere(np.isfinite(heights))
    metric = valid * np.array([SPACING[1], SPACING[0]])
    for i, j in voids:
        dist = np.linalg.norm(metric - np.array([i * SPACING[1], j * SPACING[0]]), axis=1)
        candidates = {heights[tuple(valid[k])] for k in np.flatnonzero(dist == dist.min())}
        assert filled[i, j] in candidates
    assert torch.isfinite(grid(random_points(200, void_tile))).all()


def test_void_fill_without_scipy_matches(monkeypatch: pytest.MonkeyPatch) -> None:
    heights = make_tile(seed=15).heights.copy()
    heights[np.random.default_rng(16).random(heights.shape) < 0.3] = np.nan
    with_scipy = fill_voids_nearest(heights, SPACING)
    monkeypatch.setitem(sys.modules, "scipy.ndimage", None)  # import now fails
    fallback = fill_voids_nearest(heights, SPACING)
    valid = np.argwhere(np.isfinite(heights))
    metric = valid * np.array([SPACING[1], SPACING[0]])
    for i, j in np.argwhere(~np.isfinite(heights)):
        dist = np.linalg.norm(metric - np.array([i * SPACING[1], j * SPACING[0]]), axis=1)
        candidates = {heights[tuple(valid[k])] for k in np.flatnonzero(dist <= dist.min() + 1e-9)}
        assert fallback[i, j] in candidates and with_scipy[i, j] in candidates


def test_attributes_buffers_and_dtypes() -> None:
    tile = make_tile(seed=13)
    grid = GridTerrain(tile, method="bicubic")
    assert isinstance(grid, TerrainModel)
    assert grid.extent == tile.extent
    assert grid.tile_name == tile.name and grid.tile_fingerprint == tile.fingerprint()
    assert "heights" in grid.state_dict()
    other = GridTerrain(make_tile(seed=99), method="bicubic")
    other.load_state_dict(grid.state_dict())  # padding is rebuilt from the loaded heights
    torch.testing.assert_close(other(random_points(50, tile)), grid(random_points(50, tile)))
    xy64 = random_points(100, tile)
    h64 = grid(xy64)
    # float32 grid via .to(); float32 points -> float32 heights close to float64
    grid32 = GridTerrain(tile, method="bicubic").to(torch.float32)
    assert grid32.heights.dtype == torch.float32 and grid32.padded.dtype == torch.float32
    h32, s32 = grid32.height_and_slope(xy64.float())
    assert h32.dtype == torch.float32 and s32.dtype == torch.float32
    torch.testing.assert_close(h32.double(), h64, rtol=0, atol=1e-3)
    # float64 grid with float32 points: output follows the points
    assert grid(xy64.float()).dtype == torch.float32
    bil32 = GridTerrain(tile, dtype=torch.float32)
    h, s = bil32.height_and_slope(xy64.float())
    assert h.dtype == s.dtype == torch.float32
    torch.testing.assert_close(h.double(), GridTerrain(tile)(xy64), rtol=0, atol=1e-3)


def test_bad_input_raises_clear_errors() -> None:
    tile = make_tile()
    with pytest.raises(NeuralMapError, match="bicubic"):
        GridTerrain(tile, method="nearest")
    with pytest.raises(NeuralMapError, match="DemTile"):
        GridTerrain(np.zeros((3, 3)))  # type: ignore[arg-type]
    with pytest.raises(NeuralMapError, match="floating"):
        GridTerrain(tile, dtype=torch.int64)
    grid = GridTerrain(tile)
    with pytest.raises(NeuralMapError, match=r"\(\.\.\., 2\)"):
        grid(torch.zeros(5, 3))


def test_two_node_axis_uses_linear_extrapolation() -> None:
    tile = make_tile(plane, shape=(2, 5))
    grid = GridTerrain(tile, method="bicubic")
    xy = random_points(100, tile)
    torch.testing.assert_close(grid(xy), plane(xy[:, 0], xy[:, 1]), rtol=0, atol=1e-9)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_matches_cpu() -> None:
    tile = make_tile(seed=14)
    for method in ("bilinear", "bicubic"):
        grid = GridTerrain(tile, method=method)
        xy = random_points(1000, tile, margin=10.0)
        h, s = grid.height_and_slope(xy)
        hc, sc = grid.to("cuda").height_and_slope(xy.cuda())
        torch.testing.assert_close(hc.cpu(), h, rtol=0, atol=1e-9)
        torch.testing.assert_close(sc.cpu(), s, rtol=0, atol=1e-9)


@pytest.mark.parametrize("method", ["bilinear", "bicubic"])
def test_float32_slopes_at_every_node_match_float64(method: str) -> None:
    """jacksboro (344 x 403 nodes, 75 x 92 m): at every node, border nodes included, the
    float32 grid gives the float64 grid's slope. A node's float32 coordinate lands a hair
    off the node (u = 14.999999), which used to pick the neighbouring cell's one-sided
    bilinear slope, and at a border node the clamp zeroed the slope across the border
    (worst 0.49 m/m); both tested here against the float64 reference, analytic and
    autograd."""
    from neuralmap.dem import load_tile

    tile = load_tile("jacksboro")
    ny, nx = tile.shape
    (x0, y0), (dx, dy) = tile.origin, tile.spacing
    jj, ii = np.meshgrid(np.arange(nx), np.arange(ny))
    xy = np.stack([x0 + jj.ravel() * dx, y0 + ii.ravel() * dy], -1)
    border = ((ii == 0) | (ii == ny - 1) | (jj == 0) | (jj == nx - 1)).ravel()
    g64 = GridTerrain(tile, method=method, dtype=torch.float64)
    g32 = GridTerrain(tile, method=method, dtype=torch.float32)
    h64, s64 = g64.height_and_slope(torch.tensor(xy, dtype=torch.float64))
    p32 = torch.tensor(xy, dtype=torch.float32)
    h32, s32 = g32.height_and_slope(p32)
    err = (s32.double() - s64).abs().amax(-1)
    assert float(err[torch.from_numpy(border)].max()) < 1e-5
    assert float(err.max()) < 1e-5
    np.testing.assert_allclose(h32.double(), h64, rtol=0, atol=2e-4)
    # autograd keeps the same slope (the snap to the node is a constant offset)
    sample = p32[torch.from_numpy(border)][::7].clone().requires_grad_(True)
    (grad,) = torch.autograd.grad(g32(sample).sum(), sample)
    np.testing.assert_allclose(grad.double(), s64[torch.from_numpy(border)][::7], rtol=0,
                               atol=1e-5)
    # points truly off the tile still get a zero slope across the border
    outside = torch.tensor([[x0 - 0.5 * dx, y0 + 3.3 * dy]], dtype=torch.float32)
    assert float(g32.height_and_slope(outside)[1][0, 0]) == 0.0
