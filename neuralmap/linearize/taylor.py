"""First-order Taylor linearisation on the bilinear grid (the classical baseline, SEEDS 000)."""

from __future__ import annotations

import torch

from neuralmap.dem.tile import DemTile
from neuralmap.exceptions import NeuralMapError
from neuralmap.linearize.base import Linearization, Linearizer
from neuralmap.linearize.checks import check_points
from neuralmap.terrain.grid import GridTerrain

TAYLOR_VARIANCES = ("cell", "zero")


class TaylorLinearizer(Linearizer):
    """Bilinear DEM height and its analytic slopes at the estimate (first-order Taylor).

    Variance (``variance="cell"``, default): the mean squared deviation of the four nodes
    of the grid cell holding the point from the tangent plane there. The bilinear surface
    deviates from its tangent plane at ``(fu, fv)`` by ``twist * (u - fu) * (v - fv)``
    (``twist = h00 - h01 - h10 + h11``), so the mean over the corners is

    ``twist^2 / 4 * (fu^2 + (1 - fu)^2) * (fv^2 + (1 - fv)^2)``:

    zero on a plane, largest in a twisted cell. It measures how well one tangent plane
    represents the cell, not the terrain over the position uncertainty (that is what the
    region methods add). ``variance="zero"`` returns zeros (the bare SEEDS 000 baseline).

    Points outside the tile are clamped to its border (zero slope across the border); flag
    them with ``linearizer.grid.contains(xy)``.

    Args:
        tile: The DEM tile.
        dtype: Dtype of the height buffer (outputs use ``xy``'s dtype).
        variance: ``"cell"`` or ``"zero"``.

    Raises:
        NeuralMapError: Unknown ``variance``.
    """

    def __init__(
        self, tile: DemTile, *, dtype: torch.dtype = torch.float64, variance: str = "cell"
    ) -> None:
        super().__init__()
        if variance not in TAYLOR_VARIANCES:
            raise NeuralMapError(
                f"TaylorLinearizer: unknown variance {variance!r}; choose one of "
                f"{', '.join(TAYLOR_VARIANCES)}."
            )
        self.grid = GridTerrain(tile, method="bilinear", dtype=dtype)
        self.variance_mode = variance

    def extra_repr(self) -> str:
        """Short description for ``print(linearizer)``."""
        return f"variance={self.variance_mode!r}"

    def forward(self, xy: torch.Tensor, pos_cov: torch.Tensor | None = None) -> Linearization:
        """Linearises the bilinear DEM at ``xy``.

        Args:
            xy: ``(N, 2)`` metric points.
            pos_cov: Ignored.

        Returns:
            `Linearization` with shapes ``(N,)``, ``(N, 2)``, ``(N,)``.
        """
        xy = check_points(xy, "TaylorLinearizer")
        parts = self.grid.bilinear_parts(xy)
        if self.variance_mode == "zero":
            return Linearization(parts.height, parts.slope, torch.zeros_like(parts.height))
        fu, fv = parts.fu, parts.fv
        gu = (1.0 - fu).square_().addcmul_(fu, fu)
        gv = (1.0 - fv).square_().addcmul_(fv, fv)
        variance = parts.twist.square().mul_(gu).mul_(gv).mul_(0.25)
        return Linearization(parts.height, parts.slope, variance)
