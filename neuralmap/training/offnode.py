"""Off-node training points: the continuous surface between the DEM nodes.

A map trained on the nodes alone is free between them, and that is where the filter
samples it: a network can pass every node and still ripple or flatten inside the cells.
The natural continuous surface a DEM stands for is its bicubic interpolant (Keys cubic
convolution, `GridTerrain`): it reproduces quadratics and
is what a grid map answers between the nodes. `OffNodeSampler` draws seeded
uniform points inside the cells whose four corner nodes are valid and returns the bicubic
heights and slopes there, so a trainer can fit the whole surface and the fit report can
measure how far a map departs from it between the nodes.

``surface="spline"`` takes the interpolating cubic B-spline of the nodes instead
(`SplineSurface`, FITPACK's ``RectBivariateSpline`` with ``s = 0``): at real DEM nodes
withheld by the x2 decimation it is closer to the truth than Keys on rough terrain
(``benchmarks/bench_between_nodes.py``: RMSE 0.94x Keys on jacksboro, 0.90x on rmnp,
0.97x on minnesota; 1.01x on volcano, 1.02x on topobathy), because Keys' kernel is only a
C1 approximation of the cubic spline's cardinal function.

``voids="fill"`` also trains the cells next to a void: the target surface is built on the
grid with its voids filled by the Clough-Tocher cubic of the valid nodes (`fill_voids_cubic`)
and every cell with at least one valid corner is sampled. Without it (``"skip"``) the map is
free around a missing node (only the nodes pull on it there), and at the nodes withheld from
the fit it rippled: 1.28x the Clough-Tocher cubic's RMSE on volcano with 25 % of the nodes
withheld (``benchmarks/bench_between_nodes.py``).
"""

from __future__ import annotations

import numpy as np
import torch

from neuralmap.dem.tile import DemTile
from neuralmap.exceptions import NeuralMapError
from neuralmap.terrain.grid import GridTerrain

__all__ = ["SURFACES", "VOID_RULES", "OffNodeSampler", "SplineSurface", "fill_voids_cubic"]

#: Target surfaces between the nodes: Keys bicubic (the grid's answer) or the cubic spline.
SURFACES = ("bicubic", "spline")
#: What the sampler does at voids: skip the cells touching one, or fill them (cubic).
VOID_RULES = ("skip", "fill")


def fill_voids_cubic(tile: DemTile) -> DemTile:
    """The tile with its voids filled by the Clough-Tocher cubic of the valid nodes.

    Clough-Tocher (``scipy.interpolate.CloughTocher2DInterpolator``) is the C1 piecewise
    cubic on the Delaunay triangles of the valid nodes; voids outside their convex hull
    take the nearest valid height (`neuralmap.terrain.grid.fill_voids_nearest`).

    Returns:
        A void-free copy of ``tile`` (the tile itself when it has no void).
    """
    import dataclasses

    from scipy.interpolate import CloughTocher2DInterpolator

    from neuralmap.terrain.grid import fill_voids_nearest

    valid = tile.valid_mask
    if valid.all():
        return tile
    nodes = tile.node_xy()
    heights = tile.heights.copy()
    if int(valid.sum()) >= 3:
        cubic = CloughTocher2DInterpolator(nodes[valid], tile.heights[valid])
        heights[~valid] = cubic(nodes[~valid])
    heights = fill_voids_nearest(heights, tile.spacing)  # outside the hull
    return dataclasses.replace(tile, heights=heights, meta=dict(tile.meta))


class SplineSurface:
    """The interpolating bicubic B-spline of a tile's nodes (voids filled nearest first).

    Args:
        tile: The DEM tile (at least 4 x 4 nodes).

    Raises:
        NeuralMapError: Fewer than 4 nodes along an axis.
    """

    def __init__(self, tile: DemTile) -> None:
        from scipy.interpolate import RectBivariateSpline

        from neuralmap.terrain.grid import fill_voids_nearest

        ny, nx = tile.shape
        if min(ny, nx) < 4:
            raise NeuralMapError(
                f"tile '{tile.name}': the cubic spline surface needs at least 4 x 4 nodes, got "
                f"{ny} x {nx}; set data.offnode_surface: bicubic.")
        filled = fill_voids_nearest(tile.heights, tile.spacing)
        x = tile.origin[0] + np.arange(nx) * tile.spacing[0]
        y = tile.origin[1] + np.arange(ny) * tile.spacing[1]
        self.spline = RectBivariateSpline(y, x, filled, kx=3, ky=3, s=0)

    def height_and_slope(self, xy: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(height (n,), slope (n, 2))`` float64 at ``xy`` ``(n, 2)`` metres."""
        x, y = xy[:, 0].double().numpy(), xy[:, 1].double().numpy()
        height = self.spline.ev(y, x)
        slope = np.stack([self.spline.ev(y, x, dy=1), self.spline.ev(y, x, dx=1)], -1)
        return torch.from_numpy(height), torch.from_numpy(slope)


class OffNodeSampler:
    """Uniform random points between the nodes with the bicubic DEM as target.

    Points are drawn uniformly over the *valid cells* (cells whose four corner nodes are
    valid): a cell is picked uniformly, then a uniform position inside it. Targets are the
    bicubic interpolant of the DEM (float64, voids filled nearest by `GridTerrain`;
    cells touching a void are never sampled).

    Args:
        tile: The DEM tile.
        surface: ``"bicubic"`` (Keys, `GridTerrain`) or ``"spline"`` (`SplineSurface`).
        voids: ``"skip"`` (cells touching a void are never sampled; the surface fills voids
            nearest) or ``"fill"`` (the surface is built on `fill_voids_cubic` of the tile
            and every cell with a valid corner is sampled).

    Raises:
        NeuralMapError: The tile has no valid cell (fewer than 2 x 2 valid nodes), or an
            unknown surface or void rule.
    """

    def __init__(self, tile: DemTile, surface: str = "bicubic", voids: str = "skip") -> None:
        if surface not in SURFACES:
            raise NeuralMapError(
                f"--data.offnode_surface {surface!r}: choose one of {list(SURFACES)}.")
        if voids not in VOID_RULES:
            raise NeuralMapError(
                f"--data.offnode_voids {voids!r}: choose one of {list(VOID_RULES)}.")
        self.surface = surface
        self.voids = voids
        valid = tile.valid_mask
        if voids == "fill":
            cells = valid[:-1, :-1] | valid[1:, :-1] | valid[:-1, 1:] | valid[1:, 1:]
            if valid.sum() >= 4 and cells.any():
                tile = fill_voids_cubic(tile)
        else:
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
        self.spline = SplineSurface(tile) if surface == "spline" else None

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
            ``(xy (n, 2), height (n,), slope (n, 2))``: points in metres, the target
            surface's height (m) and slope (m/m) there.
        """
        xy = self.points(n, generator)
        surface = self.spline if self.spline is not None else self.grid
        height, slope = surface.height_and_slope(xy)
        return xy.to(dtype), height.to(dtype), slope.to(dtype)
