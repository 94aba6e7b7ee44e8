"""Baking a terrain model onto a grid: decode once at load time, query at grid speed.

A compressed grid is decoded into a full grid in memory before the filter runs; a compact
neural map can be treated the same way: evaluate it once at the DEM nodes (optionally
``oversample`` times finer) and interpolate that grid (bicubic). Storage is the compact
map's; query speed is the grid's; the surface between nodes is the grid interpolant of
the network, not the network itself.
"""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import nn

from neuralmap.dem.tile import DemTile
from neuralmap.exceptions import NeuralMapError
from neuralmap.terrain.grid import GridTerrain


def bake_to_grid(
    model: nn.Module,
    tile: DemTile,
    *,
    oversample: int = 1,
    method: str = "bicubic",
    chunk: int = 65536,
) -> GridTerrain:
    """Evaluates ``model`` on ``tile``'s node grid (refined ``oversample`` times).

    Args:
        model: Terrain model mapping ``(..., 2)`` metres to heights.
        tile: Geometry to bake on (its heights are not used).
        oversample: Integer refinement ``>= 1`` of the node spacing.
        method: Interpolation of the baked grid (``"bicubic"`` or ``"bilinear"``).
        chunk: Points per evaluation batch.

    Returns:
        The `GridTerrain` of the baked heights (float64 buffer).

    Raises:
        NeuralMapError: ``oversample`` not an integer ``>= 1``.
    """
    if not (isinstance(oversample, int) and oversample >= 1):
        raise NeuralMapError(f"bake_to_grid: oversample must be an integer >= 1, got {oversample!r}.")
    ny, nx = tile.shape
    fy, fx = (ny - 1) * oversample + 1, (nx - 1) * oversample + 1
    spacing = (tile.spacing[0] / oversample, tile.spacing[1] / oversample)
    xs = tile.origin[0] + np.arange(fx) * spacing[0]
    ys = tile.origin[1] + np.arange(fy) * spacing[1]
    xx, yy = np.meshgrid(xs, ys)
    xy = torch.from_numpy(np.stack([xx, yy], -1).reshape(-1, 2))
    dtype = next((p.dtype for p in model.parameters()), torch.float32)
    with torch.no_grad():
        parts = [
            model(xy[i : i + chunk].to(dtype)).double()
            for i in range(0, xy.shape[0], max(1, chunk))
        ]
    heights = torch.cat(parts).reshape(fy, fx).numpy()
    if not math.isfinite(float(heights.sum())):
        raise NeuralMapError("bake_to_grid: the model returned non-finite heights on the grid.")
    baked = DemTile(
        heights=heights,
        spacing=spacing,
        origin=tile.origin,
        name=tile.name,
        geo=tile.geo,
        source=f"baked from {type(model).__name__} (x{oversample})",
    )
    return GridTerrain(baked, method=method)
