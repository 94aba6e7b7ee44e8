"""Off-node training points: the continuous surface between the DEM nodes.

A map trained on the nodes alone is free between them, and that is where the filter
samples it: a network can pass every node and still ripple or flatten inside the cells.
The natural continuous surface a DEM stands for is its bicubic interpolant (Keys cubic
convolution, `GridTerrain`): it reproduces quadratics and
is what a grid map answers between the nodes. `OffNodeSampler` draws seeded
uniform points inside the cells whose four corner nodes are valid and returns the bicubic
heights and slopes there, so a trainer can fit the whole surface and the fit report can
measure how far a map departs from it between the nodes.
"""

from __future__ import annotations

import numpy as np
import torch

from neuralmap.dem.tile import DemTile
from neuralmap.exceptions import NeuralMapError
from neuralmap.terrain.grid import GridTerrain

__all__ = ["OffNodeSampler"]


class OffNodeSampler:
    """Uniform random points between the nodes with the bicubic DEM as target.

    Points are drawn uniformly over the *valid cells* (cells whose four corner nodes are
    valid): a cell is picked uniformly, then a uniform position inside it. Targets are the
    bicubic interpolant of the DEM (float64, voids filled nearest by `GridTerrain`;
    cells touching a void are never sampled).

    Args:
        tile: The DEM tile.

    Raises:
        NeuralMapError: The tile has no valid cell (fewer than 2 x 2 valid nodes).
    """

    def __init__(self, tile: DemTile) -> None:
        valid = tile.valid_mask
        cells = valid[:-1, :-1] & valid[1:, :-1] & valid[:-1, 1:] & valid[1:, 1:]
        rows, cols = np.nonzero(cells)
        if rows.size == 0:
            raise NeuralMapError(
                f"tile '{tile.name}' has no cell with four valid corner nodes, so there is "
                "no surface between the nodes to train on; set data.offnode_ratio: 0."
            )
        self.cell_rows = torch.as_tensor(rows, dtype=torch.float64)
        self.cell_cols = torch.as_tensor(cols, dtype=torch.float64)
        self.origin = tuple(float(o) for o in tile.origin)
        self.spacing = tuple(float(s) for s in tile.spacing)
        self.grid = GridTerrain(tile, method="bicubic", dtype=torch.float64)

    @property
    def n_cells(self) -> int:
        """Number of valid cells."""
        return int(self.cell_rows.shape[0])

    def points(self, n: int, generator: torch.Generator) -> torch.Tensor:
        """``(n, 2)`` float64 uniform points inside the valid cells, metres."""
        pick = torch.randint(self.n_cells, (int(n),), generator=generator)
        u = torch.rand(int(n), 2, generator=generator, dtype=torch.float64)
        x = self.origin[0] + (self.cell_cols[pick] + u[:, 0]) * self.spacing[0]
        y = self.origin[1] + (self.cell_rows[pick] + u[:, 1]) * self.spacing[1]
        return torch.stack([x, y], dim=-1)

    def sample(
        self, n: int, generator: torch.Generator, *, dtype: torch.dtype = torch.float32
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Draws ``n`` points with their bicubic targets.

        Args:
            n: Number of points.
            generator: Seeded generator (the draw is a function of its state).
            dtype: Output dtype.

        Returns:
            ``(xy (n, 2), height (n,), slope (n, 2))``: points in metres, the bicubic DEM
            height (m) and slope (m/m) there.
        """
        xy = self.points(n, generator)
        height, slope = self.grid.height_and_slope(xy)
        return xy.to(dtype), height.to(dtype), slope.to(dtype)
