"""Nine-point fit: least-squares plane through the 3 x 3 DEM nodes around the estimate."""

from __future__ import annotations

import torch

from neuralmap.dem.tile import DemTile
from neuralmap.exceptions import NeuralMapError
from neuralmap.linearize.base import Linearization, Linearizer
from neuralmap.linearize.checks import check_points
from neuralmap.terrain.grid import GridTerrain


class NinePointLinearizer(Linearizer):
    """Least-squares plane through the 3 x 3 nodes centred on the node nearest the estimate.

    SEEDS 000, LCK = 1. With node offsets ``a, b in {-1, 0, 1}`` the normal equations are
    diagonal, so the plane ``f = c0 + c1 a + c2 b`` is

    ``c0 = mean(f_ab)``, ``c1 = sum(a f_ab) / 6``, ``c2 = sum(b f_ab) / 6``,

    slope ``(c1 / dx, c2 / dy)``, and the variance is the plane-fit residual variance
    ``sum(r_ab^2) / (9 - 3)``. The height is the bilinear DEM height at the estimate (the
    map look-up ``h_d(x^, y^)`` of SEEDS 000 eq. 4); the plane supplies the slope and the
    variance. Near the border the 3 x 3 block is shifted inside the grid; points outside the
    tile use the border block (flag them with ``linearizer.grid.contains(xy)``).

    Args:
        tile: The DEM tile (at least 3 x 3 nodes).
        dtype: Dtype of the height buffer (outputs use ``xy``'s dtype).

    Raises:
        NeuralMapError: The tile has fewer than 3 nodes along an axis.
    """

    solver: torch.Tensor
    design: torch.Tensor
    offsets: torch.Tensor

    def __init__(self, tile: DemTile, *, dtype: torch.dtype = torch.float64) -> None:
        super().__init__()
        if min(tile.shape) < 3:
            raise NeuralMapError(
                f"NinePointLinearizer: tile '{tile.name}' has shape {tile.shape}; the nine-point "
                "fit needs at least 3 x 3 nodes. Use TaylorLinearizer for such a small tile."
            )
        self.grid = GridTerrain(tile, method="bilinear", dtype=dtype)
        nx = tile.shape[1]
        b, a = torch.meshgrid(torch.arange(-1, 2), torch.arange(-1, 2), indexing="ij")
        a, b = a.reshape(9), b.reshape(9)
        design = torch.stack([torch.ones(9), a.double(), b.double()], dim=1).double()  # (9, 3)
        self.register_buffer("design", design.to(dtype), persistent=False)
        solver = torch.linalg.pinv(design)  # (3, 9): diag(1/9, 1/6, 1/6) @ design.T
        self.register_buffer("solver", solver.to(dtype), persistent=False)
        self.register_buffer("offsets", (b * nx + a).unsqueeze(-1), persistent=False)

    def forward(self, xy: torch.Tensor, pos_cov: torch.Tensor | None = None) -> Linearization:
        """Fits the nine-point plane at ``xy``.

        Args:
            xy: ``(N, 2)`` metric points.
            pos_cov: Ignored.

        Returns:
            `Linearization` with shapes ``(N,)``, ``(N, 2)``, ``(N,)``.
        """
        xy = check_points(xy, "NinePointLinearizer")
        grid = self.grid
        ny, nx = grid.shape
        (x0, y0), (dx, dy) = grid.origin, grid.spacing
        dt = xy.dtype
        with torch.no_grad():
            height = grid(xy)
            j = torch.round((xy[:, 0] - x0) / dx)
            i = torch.round((xy[:, 1] - y0) / dy)
            j = torch.nan_to_num(j, nan=1.0).clamp_(1.0, nx - 2.0).long()
            i = torch.nan_to_num(i, nan=1.0).clamp_(1.0, ny - 2.0).long()
            centre = i * nx + j
            nodes = grid.heights.view(-1)[self.offsets + centre].to(dt)  # (9, N)
            coef = self.solver.to(dt) @ nodes  # (3, N)
            resid = nodes - self.design.to(dt) @ coef
            variance = resid.square().sum(0) / 6.0
            slope = torch.stack([coef[1] / dx, coef[2] / dy], dim=-1)
            nan = torch.isnan(xy).any(-1, keepdim=True)
            slope = slope.masked_fill(nan, float("nan"))
        return Linearization(height, slope, variance.masked_fill(nan[:, 0], float("nan")))
