"""Rate-distortion objective of a latent-grid map: ``D_nodes + mu D_between + lambda R``.

``D_nodes`` is the mean squared error (m²) at the tile's valid nodes; ``D_between`` the
mean squared error at random points between the nodes against bicubic interpolation of the
DEM (the continuous surface the grid stands for, so the map is trained between the nodes
and not only on them); ``R`` the rate in bits per node of the relaxed latents under the
entropy model (`LatentGrid.relaxed`). ``lambda`` trades metres² for bits per node,
as in learned image compression (Ballé et al. 2018; Cool-chic).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from neuralmap.dem.tile import DemTile
from neuralmap.exceptions import NeuralMapError
from neuralmap.terrain.grid import GridTerrain, fill_voids_nearest
from neuralmap.terrain.latent.latent_grid import LatentGrid


def check_rate_weight(lam: float) -> float:
    """``lambda`` must be finite and > 0 (it weighs bits against m²).

    Raises:
        NeuralMapError: Otherwise, naming the key and a typical range.
    """
    if not (isinstance(lam, (int, float)) and math.isfinite(lam) and lam > 0):
        raise NeuralMapError(
            f"latent map: the rate weight lambda (model.rate_weight) must be finite and > 0 "
            f"(m² per bit per node; about 0.3 for ~0.7 m node RMSE on jacksboro, 10 for ~3 m), "
            f"got {lam!r}. A larger lambda gives a smaller, coarser map."
        )
    return float(lam)


@dataclass
class ObjectiveTerms:
    """One evaluation of the objective (tensors, differentiable).

    Attributes:
        loss: ``D_nodes + mu D_between + lambda R``.
        node_mse: ``D_nodes`` (m²).
        between_mse: ``D_between`` (m²; 0 without between-node points).
        bits: Total rate of the latents (bits).
        bits_per_node: ``R``.
    """

    loss: torch.Tensor
    node_mse: torch.Tensor
    between_mse: torch.Tensor
    bits: torch.Tensor
    bits_per_node: torch.Tensor


class RateDistortion:
    """Targets of one tile and the objective of its `LatentGrid`.

    Args:
        tile: The DEM tile.
        rate_weight: ``lambda`` (m² per bit per node), > 0.
        between_weight: ``mu``; 0 trains on the nodes only.
        between_points: Random between-node points per evaluation.

    Raises:
        NeuralMapError: ``rate_weight`` <= 0 or not finite, negative ``between_weight``.
    """

    def __init__(self, tile: DemTile, *, rate_weight: float, between_weight: float = 0.5,
                 between_points: int = 8192) -> None:
        self.rate_weight = check_rate_weight(rate_weight)
        if not (math.isfinite(between_weight) and between_weight >= 0):
            raise NeuralMapError(
                f"latent map: between_weight must be >= 0, got {between_weight}.")
        self.between_weight = float(between_weight)
        self.between_points = int(between_points)
        filled = fill_voids_nearest(tile.heights, tile.spacing)
        self.heights = torch.as_tensor(filled, dtype=torch.float32)
        self.valid = torch.as_tensor(tile.valid_mask)
        self.n_nodes = int(self.valid.sum())
        self.all_valid = self.n_nodes == self.valid.numel()
        self.bicubic = GridTerrain(tile, method="bicubic", dtype=torch.float64)
        self.spacing = tile.spacing
        self.origin = tile.origin
        self.shape = tile.shape

    def between_targets(self, count: int, generator: torch.Generator | None = None
                        ) -> tuple[torch.Tensor, torch.Tensor]:
        """``count`` uniform random points ``uv (count, 2)`` (node units) and their bicubic
        DEM heights ``(count,)``."""
        ny, nx = self.shape
        uv = torch.rand(count, 2, generator=generator, dtype=torch.float64)
        uv = uv * torch.tensor([nx - 1.0, ny - 1.0], dtype=torch.float64)
        xy = uv * torch.tensor(self.spacing, dtype=torch.float64) + torch.tensor(
            self.origin, dtype=torch.float64)
        with torch.no_grad():
            target = self.bicubic(xy)
        return uv.float(), target.float()

    def __call__(self, grid: LatentGrid, quantizer: str,
                 generator: torch.Generator | None = None, alpha: float = 8.0) -> ObjectiveTerms:
        """The objective under a rounding relaxation (see `LatentGrid.relaxed`; ``alpha``
        is the soft-rounding sharpness of ``"soft"``)."""
        decoded, bits = grid.relaxed(quantizer, alpha)
        nodes = grid.node_heights(decoded)
        err2 = (nodes - self.heights) ** 2
        node_mse = err2.mean() if self.all_valid else err2[self.valid].mean()
        between = node_mse.new_zeros(())
        if self.between_weight > 0 and self.between_points > 0:
            uv, target = self.between_targets(self.between_points, generator)
            between = ((grid.point_heights(decoded, uv) - target) ** 2).mean()
        bpn = bits / self.n_nodes
        loss = node_mse + self.between_weight * between + self.rate_weight * bpn
        return ObjectiveTerms(loss, node_mse, between, bits, bpn)
