"""The terrain-model interface every map representation implements."""

from __future__ import annotations

from typing import Any

import torch
from torch import nn


def model_device(terrain: Any) -> torch.device | None:
    """The device of a map's tensors (its first parameter, else its first buffer); None
    for a map that holds no tensors (an analytic surface, a plain callable)."""
    for name in ("parameters", "buffers"):
        tensors = getattr(terrain, name, None)
        if callable(tensors):
            for tensor in tensors():
                return tensor.device
    return None


def inside_extent(
    xy: torch.Tensor, extent: tuple[float, float, float, float], margin: float = 0.0
) -> torch.Tensor:
    """Whether points lie inside ``extent = (xmin, xmax, ymin, ymax)`` shrunk by ``margin``.

    Args:
        xy: ``(..., 2)`` metric points.
        extent: Metric bounds.
        margin: Distance kept from the border, metres.

    Returns:
        ``(...)`` bool.
    """
    xmin, xmax, ymin, ymax = extent
    x, y = xy[..., 0], xy[..., 1]
    return (x >= xmin + margin) & (x <= xmax - margin) & (y >= ymin + margin) & (
        y <= ymax - margin
    )


class TerrainModel(nn.Module):
    """A terrain height field ``h(x, y)`` in metres over a metric east-north frame.

    Subclasses implement `forward`; grid and neural models are interchangeable in
    the linearisation layer and the filter.

    Attributes:
        extent: ``(xmin, xmax, ymin, ymax)`` metric bounds where the model is valid.
        tile_name: Name of the DEM tile the model represents.
        tile_fingerprint: `DemTile.fingerprint` of that tile ("" when unknown).
    """

    extent: tuple[float, float, float, float]
    tile_name: str = ""
    tile_fingerprint: str = ""

    def forward(self, xy: torch.Tensor) -> torch.Tensor:  # pragma: no cover - interface
        """Heights at metric points.

        Args:
            xy: ``(..., 2)`` east/north coordinates in metres.

        Returns:
            ``(...)`` heights in metres.
        """
        raise NotImplementedError

    def contains(self, xy: torch.Tensor, margin: float = 0.0) -> torch.Tensor:
        """Whether points lie inside `extent` shrunk by ``margin`` metres.

        Args:
            xy: ``(..., 2)`` metric points.
            margin: Distance kept from the border, metres.

        Returns:
            ``(...)`` bool.
        """
        return inside_extent(xy, self.extent, margin)

    def to_geotiff(self, out_dir: Any, tile: Any, *, layers: tuple[str, ...] | None = None,
                   stem: str = "neural_map") -> dict[str, Any]:
        """Writes the map's height, residual and slope as GeoTIFF on ``tile``'s source grid.

        See `neuralmap.terrain.geotiff.write_map_geotiffs` (needs rasterio).

        Args:
            out_dir: Output folder.
            tile: The DEM tile the map was fitted to.
            layers: Any of ``("height", "residual", "slope")`` (default all).
            stem: File name prefix.

        Returns:
            Layer name -> path.
        """
        from neuralmap.terrain.geotiff import LAYERS, write_map_geotiffs

        return write_map_geotiffs(self, tile, out_dir, layers=layers or LAYERS, stem=stem)
