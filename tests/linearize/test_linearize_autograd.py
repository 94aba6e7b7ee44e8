"""AutogradLinearizer vs analytic gradients, central differences and the bicubic grid."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from neuralmap.dem.tile import DemTile
from neuralmap.exceptions import NeuralMapError
from neuralmap.linearize import AutogradLinearizer, Linearization
from neuralmap.terrain.base import TerrainModel
from neuralmap.terrain.grid import GridTerrain


class SinusoidTerrain(TerrainModel):
    """h = A sin(kx x) cos(ky y) + c x: smooth, with a learnable amplitude A."""

    def __init__(self, amplitude: float = 120.0, dtype: torch.dtype = torch.float64) -> None:
        super().__init__()
        self.amplitude = torch.nn.Parameter(torch.tensor(amplitude, dtype=dtype))
        self.kx = 2 * math.pi / 900.0
        self.ky = 2 * math.pi / 1300.0
        self.c = 0.05
        self.extent = (0.0, 5000.0, 0.0, 5000.0)

    def forward(self, xy: torch.Tensor) -> torch.Tensor:
        xy = xy.to(self.amplitude.dtype)
        x, y = xy[..., 0], xy[..., 1]
        return self.amplitude * torch.sin(self.kx * x) * torch.cos(self.ky * y) + self.c * x

    def gradient(self, xy: torch.Tensor) -> torch.Tensor:
        a = self.amplitude.detach()
        x, y = xy[..., 0], xy[..., 1]
        gx = a * self.kx * torch.cos(self.kx * x) * torch.cos(self.ky * y) + self.c
        gy = -a * self.ky * torch.sin(self.kx * x) * torch.sin(self.ky * y)
        return torch.stack([gx, gy], dim=-1)


def points(n: int, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return torch.rand(n, 2, generator=g, dtype=torch.float64) * 5000.0


def test_matches_analytic_gradient_and_height() -> None:
    terrain = SinusoidTerrain()
    xy = points(500)
    lin = AutogradLinearizer(terrain, fit_variance=6.0)(xy)
    assert isinstance(lin, Linearization)
    assert lin.height.shape == (500,) and lin.slope.shape == (500, 2)
    assert lin.variance.shape == (500,)
    torch.testing.assert_close(lin.slope, terrain.gradient(xy), rtol=0, atol=1e-12)
    torch.testing.assert_close(lin.height, terrain(xy).detach(), rtol=0, atol=0)
    assert (lin.variance == 6.0).all()


def test_matches_central_differences() -> None:
    """Central differences, step 1e-3 m: truncation ~A k^3 h^2 / 6 ~ 1e-11, roundoff ~1e-11."""
    terrain = SinusoidTerrain()
    xy = points(300, seed=1)
    step = 1e-3
    with torch.no_grad():
        fd = torch.stack(
            [
                (terrain(xy + torch.tensor([step, 0.0], dtype=torch.float64))
                 - terrain(xy - torch.tensor([step, 0.0], dtype=torch.float64))) / (2 * step),
                (terrain(xy + torch.tensor([0.0, step], dtype=torch.float64))
                 - terrain(xy - torch.tensor([0.0, step], dtype=torch.float64))) / (2 * step),
            ],
            dim=-1,
        )
    slope = AutogradLinearizer(terrain)(xy).slope
    torch.testing.assert_close(slope, fd, rtol=0, atol=1e-8)


def test_matches_bicubic_grid_analytic_slopes() -> None:
    rng = np.random.default_rng(2)
    tile = DemTile(300 + 30 * rng.standard_normal((20, 25)), spacing=(50.0, 40.0))
    grid = GridTerrain(tile, method="bicubic")
    xy = points(400, seed=3) * torch.tensor([24 * 50.0, 19 * 40.0], dtype=torch.float64) / 5000
    lin = AutogradLinearizer(grid)(xy)
    h, slope = grid.height_and_slope(xy)
    torch.testing.assert_close(lin.slope, slope, rtol=0, atol=1e-10)
    torch.testing.assert_close(lin.height, h, rtol=0, atol=1e-10)


def test_works_under_no_grad_and_detaches_by_default() -> None:
    terrain = SinusoidTerrain()
    xy = points(50, seed=4)
    with torch.no_grad():
        lin = AutogradLinearizer(terrain)(xy)
    torch.testing.assert_close(lin.slope, terrain.gradient(xy), rtol=0, atol=1e-12)
    assert not lin.height.requires_grad and not lin.slope.requires_grad
    assert terrain.amplitude.grad is None


def test_create_graph_lets_gradients_reach_terrain_parameters() -> None:
    terrain = SinusoidTerrain()
    xy = points(64, seed=5)
    lin = AutogradLinearizer(terrain, create_graph=True)(xy)
    assert lin.slope.requires_grad and lin.height.requires_grad
    (lin.slope[:, 1].sum() + lin.height.sum()).backward()
    # d/dA of (gy + h) = sum(-ky sin sin + sin cos)
    x, y = xy[:, 0], xy[:, 1]
    expected = (
        -terrain.ky * torch.sin(terrain.kx * x) * torch.sin(terrain.ky * y)
        + torch.sin(terrain.kx * x) * torch.cos(terrain.ky * y)
    ).sum()
    torch.testing.assert_close(terrain.amplitude.grad, expected, rtol=1e-12, atol=1e-12)


def test_create_graph_lets_gradients_reach_the_points() -> None:
    """Second derivatives through the slope: d(sum gx)/dx = h_xx, compared with analytic."""
    terrain = SinusoidTerrain()
    xy = points(32, seed=6).requires_grad_(True)
    lin = AutogradLinearizer(terrain, create_graph=True)(xy)
    (grad_xy,) = torch.autograd.grad(lin.slope[:, 0].sum(), xy)
    a, kx, ky = terrain.amplitude.detach(), terrain.kx, terrain.ky
    x, y = xy.detach()[:, 0], xy.detach()[:, 1]
    hxx = -a * kx**2 * torch.sin(kx * x) * torch.cos(ky * y)
    hxy = -a * kx * ky * torch.cos(kx * x) * torch.sin(ky * y)
    torch.testing.assert_close(grad_xy, torch.stack([hxx, hxy], dim=-1), rtol=0, atol=1e-12)


def test_float32_model_and_points() -> None:
    terrain = SinusoidTerrain(dtype=torch.float32)
    xy64 = points(200, seed=7)
    lin32 = AutogradLinearizer(terrain)(xy64.float())
    assert lin32.slope.dtype == torch.float32 and lin32.height.dtype == torch.float32
    torch.testing.assert_close(lin32.slope.double(), terrain.gradient(xy64).double(),
                               rtol=0, atol=2e-3)
    # float32 model, float64 filter: outputs follow the points' dtype
    lin = AutogradLinearizer(terrain)(xy64)
    assert lin.slope.dtype == torch.float64 and lin.variance.dtype == torch.float64


def test_bad_inputs() -> None:
    with pytest.raises(NeuralMapError, match="nn.Module"):
        AutogradLinearizer(lambda xy: xy[:, 0])  # type: ignore[arg-type]
    with pytest.raises(NeuralMapError, match="fit_variance"):
        AutogradLinearizer(SinusoidTerrain(), fit_variance=-1.0)
    lin = AutogradLinearizer(SinusoidTerrain())
    with pytest.raises(NeuralMapError, match=r"\(N, 2\)"):
        lin(torch.zeros(3, 4, 2, dtype=torch.float64))

    class Wrong(torch.nn.Module):
        def forward(self, xy: torch.Tensor) -> torch.Tensor:
            return xy

    with pytest.raises(NeuralMapError, match=r"\(N,\) heights"):
        AutogradLinearizer(Wrong())(points(3))

    class Detached(torch.nn.Module):
        def forward(self, xy: torch.Tensor) -> torch.Tensor:
            return xy[:, 0].detach()

    with pytest.raises(NeuralMapError, match="differentiabl"):
        AutogradLinearizer(Detached())(points(3))


def test_region_variance_is_exact_on_a_quadratic() -> None:
    """E[(½ dᵀ H d)²] = ¼ (2 tr((HΣ)²) + tr(HΣ)²) for d ~ N(0, Σ) (Gaussian moments)."""

    class Quadratic(torch.nn.Module):
        def forward(self, xy: torch.Tensor) -> torch.Tensor:
            x, y = xy[..., 0], xy[..., 1]
            return 0.01 * x**2 + 0.02 * x * y - 0.005 * y**2 + 3.0 * x - 2.0 * y

    hessian = torch.tensor([[0.02, 0.02], [0.02, -0.01]], dtype=torch.float64)
    cov = torch.tensor([[400.0, 100.0], [100.0, 900.0]], dtype=torch.float64)
    hs = hessian @ cov
    exact = 0.25 * (2.0 * torch.trace(hs @ hs) + torch.trace(hs) ** 2)
    lin = AutogradLinearizer(Quadratic(), region_variance=True, fit_variance=6.0)
    xy = torch.randn(7, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(0)) * 300
    out = lin(xy, cov.expand(7, 2, 2))
    torch.testing.assert_close(out.variance, torch.full((7,), float(exact) + 6.0, dtype=torch.float64))
    with pytest.raises(NeuralMapError, match="pos_cov"):
        lin(xy)


def test_region_variance_matches_monte_carlo_on_a_sinusoid() -> None:
    class Wave(torch.nn.Module):
        def forward(self, xy: torch.Tensor) -> torch.Tensor:
            return 40.0 * torch.sin(xy[..., 0] / 300.0) * torch.cos(xy[..., 1] / 500.0)

    terrain = Wave()
    cov = torch.tensor([[30.0**2, 0.0], [0.0, 50.0**2]], dtype=torch.float64)
    xy = torch.tensor([[200.0, -100.0]], dtype=torch.float64)
    out = AutogradLinearizer(terrain, region_variance=True)(xy, cov.unsqueeze(0))
    d = torch.randn(400_000, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    d = d @ torch.linalg.cholesky(cov).T
    miss = terrain(xy + d) - terrain(xy) - d @ out.slope[0]
    torch.testing.assert_close(out.variance[0], miss.square().mean(), rtol=0.03, atol=0.0)
