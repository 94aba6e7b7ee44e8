"""Classical DEM linearisations (SEEDS 000): exact on planes, correct on quadratics."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from neuralmap.dem.tile import DemTile
from neuralmap.exceptions import NeuralMapError
from neuralmap.linearize import (
    MeanPointLinearizer,
    NinePointLinearizer,
    PlaneFitLinearizer,
    TaylorLinearizer,
)
from neuralmap.linearize.window import sample_pattern

SPACING = (100.0, 80.0)  # dx, dy
ORIGIN = (-1000.0, 500.0)
SHAPE = (101, 91)  # ny, nx: 9 km x 8 km, so Omega_max (2.4 km) fits around the centre
CENTRE = (ORIGIN[0] + 45 * SPACING[0], ORIGIN[1] + 50 * SPACING[1])

# quadratic h = c0 + gx x' + gy y' + a x'^2 + b x'y' + c y'^2 about the tile centre
A, B, C = 2e-5, -3e-5, 1.5e-5


def node_tile(fn) -> DemTile:
    ny, nx = SHAPE
    x = ORIGIN[0] + np.arange(nx) * SPACING[0]
    y = ORIGIN[1] + np.arange(ny) * SPACING[1]
    xx, yy = np.meshgrid(x, y)
    return DemTile(fn(xx, yy), spacing=SPACING, origin=ORIGIN, name="quad")


def plane(x, y):
    return 400.0 + 0.12 * x - 0.07 * y


def quadratic(x, y):
    u, v = x - CENTRE[0], y - CENTRE[1]
    return 500.0 + 0.1 * u - 0.05 * v + A * u * u + B * u * v + C * v * v


def quadratic_grad(x, y) -> torch.Tensor:
    u, v = x - CENTRE[0], y - CENTRE[1]
    return torch.stack([0.1 + 2 * A * u + B * v, -0.05 + B * u + 2 * C * v], dim=-1)


def estimates(n: int = 40, spread: float = 1500.0, seed: int = 0) -> torch.Tensor:
    """Points within ``spread`` m of the tile centre (windows stay inside the tile)."""
    g = torch.Generator().manual_seed(seed)
    off = (torch.rand(n, 2, generator=g, dtype=torch.float64) * 2 - 1) * spread
    return torch.tensor(CENTRE, dtype=torch.float64) + off


def pos_cov(n: int, sx: float, sy: float, rho: float = 0.3) -> torch.Tensor:
    cov = torch.tensor([[sx * sx, rho * sx * sy], [rho * sx * sy, sy * sy]], dtype=torch.float64)
    return cov.expand(n, 2, 2).clone()


METHODS = {
    "taylor": lambda tile: TaylorLinearizer(tile),
    "nine_point": lambda tile: NinePointLinearizer(tile),
    "mean_point": lambda tile: MeanPointLinearizer(tile),
    "lsq_max": lambda tile: PlaneFitLinearizer(tile, sigma=400.0),
    "lsq_mean": lambda tile: PlaneFitLinearizer(tile, sigma=240.0),
    "lsq_min": lambda tile: PlaneFitLinearizer(tile, sigma=80.0),
    "lsq_adaptive": lambda tile: PlaneFitLinearizer(tile, sigma="adaptive"),
}


@pytest.mark.parametrize("name", list(METHODS))
def test_exact_on_a_plane(name: str) -> None:
    tile = node_tile(plane)
    lin = METHODS[name](tile)
    xy = estimates(spread=1000.0)
    out = lin(xy, pos_cov(len(xy), 150.0, 90.0))
    assert out.height.shape == (40,) and out.slope.shape == (40, 2)
    assert out.variance.shape == (40,)
    expected = torch.tensor([0.12, -0.07], dtype=torch.float64).expand(40, 2)
    torch.testing.assert_close(out.slope, expected, rtol=0, atol=1e-9)
    torch.testing.assert_close(out.height, plane(xy[:, 0], xy[:, 1]), rtol=0, atol=1e-9)
    assert out.variance.abs().max() < 1e-12


def test_taylor_on_quadratic_gives_cell_midpoint_gradient_and_twist_variance() -> None:
    tile = node_tile(quadratic)
    xy = estimates(seed=1)
    out = TaylorLinearizer(tile)(xy)
    dx, dy = SPACING
    j = torch.floor((xy[:, 0] - ORIGIN[0]) / dx)
    i = torch.floor((xy[:, 1] - ORIGIN[1]) / dy)
    x_mid = ORIGIN[0] + (j + 0.5) * dx
    y_mid = ORIGIN[1] + (i + 0.5) * dy
    # bilinear slope along x is the secant of the cell edge, linearly blended in y:
    expected_x = quadratic_grad(x_mid, xy[:, 1])[:, 0]
    expected_y = quadratic_grad(xy[:, 0], y_mid)[:, 1]
    torch.testing.assert_close(out.slope[:, 0], expected_x, rtol=0, atol=1e-9)
    torch.testing.assert_close(out.slope[:, 1], expected_y, rtol=0, atol=1e-9)
    # variance: mean squared deviation of the 4 cell nodes from the tangent plane
    corners_x = torch.stack([ORIGIN[0] + (j + a) * dx for a in (0, 1, 0, 1)], dim=-1)
    corners_y = torch.stack([ORIGIN[1] + (i + b) * dy for b in (0, 0, 1, 1)], dim=-1)
    tangent = (
        out.height[:, None]
        + out.slope[:, :1] * (corners_x - xy[:, :1])
        + out.slope[:, 1:] * (corners_y - xy[:, 1:])
    )
    expected_var = (quadratic(corners_x, corners_y) - tangent).square().mean(-1)
    torch.testing.assert_close(out.variance, expected_var, rtol=1e-9, atol=1e-12)
    assert (out.variance > 0).all()
    zero = TaylorLinearizer(tile, variance="zero")(xy)
    assert (zero.variance == 0).all()
    torch.testing.assert_close(zero.slope, out.slope, rtol=0, atol=0)


def test_nine_point_on_quadratic_gives_gradient_at_nearest_node() -> None:
    tile = node_tile(quadratic)
    xy = estimates(seed=2)
    out = NinePointLinearizer(tile)(xy)
    dx, dy = SPACING
    jc = torch.round((xy[:, 0] - ORIGIN[0]) / dx)
    ic = torch.round((xy[:, 1] - ORIGIN[1]) / dy)
    xc, yc = ORIGIN[0] + jc * dx, ORIGIN[1] + ic * dy
    torch.testing.assert_close(out.slope, quadratic_grad(xc, yc), rtol=0, atol=1e-9)
    # variance vs an independent least-squares fit (numpy) of the 3 x 3 nodes
    for k in range(0, 40, 7):
        ox, oy = np.meshgrid([-dx, 0, dx], [-dy, 0, dy])
        px, py = float(xc[k]) + ox.ravel(), float(yc[k]) + oy.ravel()
        design = np.stack([np.ones(9), px - float(xc[k]), py - float(yc[k])], axis=1)
        h = quadratic(px, py)
        coef, *_ = np.linalg.lstsq(design, h, rcond=None)
        resid = h - design @ coef
        np.testing.assert_allclose(float(out.variance[k]), resid @ resid / 6, rtol=1e-8)
        np.testing.assert_allclose(float(out.slope[k, 0]), coef[1], rtol=0, atol=1e-10)


@pytest.mark.parametrize("cls", [PlaneFitLinearizer, MeanPointLinearizer])
def test_window_fit_recovers_centre_gradient_of_quadratic(cls) -> None:
    """Symmetric sampling: the plane of a quadratic has the gradient at the centre."""
    tile = node_tile(quadratic)
    xy = estimates(seed=3)
    exact = quadratic_grad(xy[:, 0], xy[:, 1])
    lin_bicubic = cls(tile, sigma=240.0, interpolation="bicubic")
    torch.testing.assert_close(lin_bicubic(xy).slope, exact, rtol=0, atol=1e-9)
    # on the bilinear DEM the samples carry interpolation error <= (|A| dx^2 + ...) / 8,
    # about 0.06 m here, so the slope agrees to ~1e-4
    lin = cls(tile, sigma=240.0)
    torch.testing.assert_close(lin(xy).slope, exact, rtol=0, atol=1e-4)


def test_least_squares_matches_numpy_lstsq() -> None:
    tile = node_tile(quadratic)
    xy = estimates(n=5, seed=4)
    sx, sy = 170.0, 95.0
    n = 9
    lin = PlaneFitLinearizer(tile, sigma=(sx, sy), n_samples=n, interpolation="bicubic")
    out = lin(xy)
    pattern = sample_pattern(n).numpy()
    for k in range(5):
        px = float(xy[k, 0]) + sx * pattern[:, 0]
        py = float(xy[k, 1]) + sy * pattern[:, 1]
        design = np.stack([np.ones(n * n), px - float(xy[k, 0]), py - float(xy[k, 1])], axis=1)
        h = quadratic(px, py)
        coef, *_ = np.linalg.lstsq(design, h, rcond=None)
        resid = h - design @ coef
        np.testing.assert_allclose(out.slope[k].numpy(), coef[1:], rtol=0, atol=1e-10)
        np.testing.assert_allclose(float(out.variance[k]), resid @ resid / (n * n - 3), rtol=1e-8)
        assert float(out.variance[k]) > 1.0


def test_adaptive_window_follows_position_covariance() -> None:
    tile = node_tile(quadratic)
    lin = PlaneFitLinearizer(tile, sigma="adaptive", interpolation="bicubic", max_sigma=600.0)
    xy = estimates(n=4, seed=5)
    cov = torch.cat([pos_cov(1, 150.0, 90.0), pos_cov(1, 20.0, 30.0), pos_cov(1, 5e3, 200.0),
                     torch.full((1, 2, 2), float("nan"), dtype=torch.float64)])
    sigma = lin.window_sigma(xy, cov)
    expected = torch.tensor(
        [[150.0, 90.0], [100.0, 80.0], [600.0, 200.0], [600.0, 600.0]], dtype=torch.float64
    )  # clamped below at the grid spacing (100, 80) and above at max_sigma
    torch.testing.assert_close(sigma, expected, rtol=0, atol=1e-9)
    # same fit as the fixed window of those sigmas
    out = lin(xy, cov)
    for k in range(4):
        fixed = PlaneFitLinearizer(
            tile, sigma=tuple(expected[k].tolist()), n_samples=lin.n_samples,
            interpolation="bicubic",
        )(xy[k : k + 1])
        torch.testing.assert_close(out.slope[k], fixed.slope[0], rtol=0, atol=1e-10)
        torch.testing.assert_close(out.variance[k], fixed.variance[0], rtol=1e-10, atol=1e-10)
    # on a quadratic the residual variance scales as sigma^4: doubling sigma -> x16
    big = lin(xy[:1], pos_cov(1, 300.0, 180.0)).variance
    torch.testing.assert_close(big, 16.0 * out.variance[:1], rtol=1e-9, atol=0)


def test_adaptive_without_pos_cov_is_a_clear_error() -> None:
    tile = node_tile(plane)
    for lin in (PlaneFitLinearizer(tile, sigma="adaptive"), MeanPointLinearizer(tile)):
        with pytest.raises(NeuralMapError, match="pos_cov"):
            lin(estimates(n=3))
        with pytest.raises(NeuralMapError, match=r"\(3, 2, 2\)"):
            lin(estimates(n=3), torch.eye(2, dtype=torch.float64).expand(4, 2, 2))


def test_fixed_window_sizes_and_auto_sample_count() -> None:
    tile = node_tile(plane)
    # sample spacing no coarser than the grid: ceil(6 sigma / min(dx, dy)) + 1
    assert PlaneFitLinearizer(tile, sigma=80.0).n_samples == 7
    assert PlaneFitLinearizer(tile, sigma=400.0).n_samples == 31
    assert PlaneFitLinearizer(tile, sigma=400.0, n_samples=7).n_samples == 7


def test_bad_options() -> None:
    tile = node_tile(plane)
    with pytest.raises(NeuralMapError, match="sigma"):
        PlaneFitLinearizer(tile, sigma=-5.0)
    with pytest.raises(NeuralMapError, match="sigma"):
        PlaneFitLinearizer(tile, sigma="auto")
    with pytest.raises(NeuralMapError, match="n_samples"):
        PlaneFitLinearizer(tile, n_samples=1)
    with pytest.raises(NeuralMapError, match="max_sigma"):
        PlaneFitLinearizer(tile, sigma="adaptive", max_sigma=10.0)
    with pytest.raises(NeuralMapError, match="interpolation"):
        MeanPointLinearizer(tile, interpolation="nearest")
    with pytest.raises(NeuralMapError, match="variance"):
        TaylorLinearizer(tile, variance="big")
    small = DemTile(np.zeros((2, 5)), spacing=(10.0, 10.0))
    with pytest.raises(NeuralMapError, match="3 x 3"):
        NinePointLinearizer(small)
    with pytest.raises(NeuralMapError, match=r"\(N, 2\)"):
        TaylorLinearizer(tile)(torch.zeros(4, dtype=torch.float64))


@pytest.mark.parametrize("name", list(METHODS))
def test_float32_batched_and_single(name: str) -> None:
    tile = node_tile(quadratic)
    lin32 = METHODS[name](tile).to(torch.float32)  # buffers converted in place
    xy = estimates(n=257, seed=6)
    cov = pos_cov(257, 130.0, 110.0)
    out = lin32(xy.float(), cov.float())
    assert out.height.dtype == out.slope.dtype == out.variance.dtype == torch.float32
    assert out.slope.shape == (257, 2)
    ref = METHODS[name](tile)(xy, cov)
    torch.testing.assert_close(out.slope.double(), ref.slope, rtol=0, atol=2e-4)
    torch.testing.assert_close(out.height.double(), ref.height, rtol=0, atol=1e-2)
    torch.testing.assert_close(out.variance.double(), ref.variance, rtol=1e-2, atol=1e-2)
    one = METHODS[name](tile)(xy[:1], cov[:1])
    assert one.height.shape == (1,) and one.slope.shape == (1, 2)
    torch.testing.assert_close(one.slope, ref.slope[:1], rtol=0, atol=1e-12)
