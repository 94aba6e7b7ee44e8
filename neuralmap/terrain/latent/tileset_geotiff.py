"""A latent tileset as GeoTIFF, one set of files per tile (`neuralmap.terrain.geotiff`).

Each tile's **core** grid (its own nodes; neighbours share their seam node line as the
source tiles do) is written with the blended tileset's height and slope, and, when the
region's DEM is given, the residual against it: ``<out>/<stem>_r000_c000_<layer>.tif`` in
the region's CRS (projected tiles) or lon/lat grid (geographic tiles). Because every layer
comes from the one blended map, the files of two neighbours hold the same values on their
shared nodes. The files of all tiles are written all or nothing (`neuralmap.io.atomic_files`).
Needs rasterio (``geotiff`` extra).
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np
import torch

from neuralmap.dem.tile import DemTile, GeoReference, ProjectedReference
from neuralmap.exceptions import NeuralMapError
from neuralmap.io import atomic_files
from neuralmap.terrain.base import TerrainModel
from neuralmap.terrain.geotiff import write_map_geotiffs
from neuralmap.terrain.latent.tileset import LatentTileset
from neuralmap.terrain.latent.tileset_layout import window_tile

__all__ = ["export_tileset_geotiffs"]


class _CoreView(TerrainModel):
    """The tileset seen over one tile's core (no fingerprint: the core is not the region)."""

    def __init__(self, tileset: LatentTileset) -> None:
        super().__init__()
        self.tileset = tileset
        self.extent = tileset.extent

    def forward(self, xy: torch.Tensor) -> torch.Tensor:
        return self.tileset(xy)


def _reference(info: dict[str, Any]) -> tuple[GeoReference | None, ProjectedReference | None]:
    geo, projected = info.get("geo"), info.get("projected")
    return (GeoReference(**geo) if isinstance(geo, dict) else None,
            ProjectedReference(**projected) if isinstance(projected, dict) else None)


def _map_region(tileset: LatentTileset) -> DemTile:
    """A frame-only region tile (heights from the map) for exports without the DEM."""
    geo, projected = _reference(tileset.tile_info)
    layout = tileset.layout
    return DemTile(heights=np.zeros(layout.shape), spacing=layout.spacing, origin=layout.origin,
                   name=tileset.tile_name or "tileset", geo=geo, projected=projected,
                   meta={"units": tileset.tile_info.get("units"),
                         "crs": tileset.tile_info.get("crs")})


def export_tileset_geotiffs(tileset: LatentTileset, out_dir: str | os.PathLike[str], *,
                            region: DemTile | None = None, layers: tuple[str, ...] | None = None,
                            stem: str = "latent_tileset", cog: bool = False,
                            ) -> dict[tuple[int, int], dict[str, Path]]:
    """Writes every tile's layers as GeoTIFF (module docstring).

    Args:
        tileset: The tileset.
        out_dir: Output folder.
        region: The DEM region the tileset was fitted to (needed for ``residual``).
        layers: Any of ``("height", "residual", "slope")``; default all with ``region``,
            ``("height", "slope")`` without.
        stem: File name prefix.
        cog: Cloud Optimized GeoTIFFs (`neuralmap.terrain.geotiff.write_geotiff`).

    Returns:
        ``(row, col)`` -> layer -> path.

    Raises:
        NeuralMapError: ``residual`` without the region, a region of another fingerprint,
            rasterio missing, an unwritable folder, a full disk (nothing new is left).
    """
    if layers is None:
        layers = ("height", "residual", "slope") if region is not None else ("height", "slope")
    if region is None and "residual" in layers:
        raise NeuralMapError("tileset GeoTIFF export: the residual layer needs the DEM region "
                             "the tileset was fitted to (region=...).")
    if region is not None and tileset.tile_fingerprint and (
            region.fingerprint() != tileset.tile_fingerprint):
        raise NeuralMapError(
            f"tileset GeoTIFF export: the tileset was fitted to region {tileset.tile_name!r} "
            f"(fingerprint {tileset.tile_fingerprint}), not to {region.name!r} "
            f"({region.fingerprint()}); give the DEM files it was trained on.")
    frame = region if region is not None else _map_region(tileset)
    view = _CoreView(tileset)
    written: dict[tuple[int, int], dict[str, Path]] = {}
    with atomic_files(option="tileset GeoTIFF export") as files:  # every tile or none
        for entry in tileset.tiles:
            core = window_tile(frame, entry.core, f"{frame.name}_r{entry.row}c{entry.col}")
            if region is None:  # heights only give the DemTile its grid: the map's own
                with torch.no_grad():
                    xy = torch.as_tensor(core.node_xy().reshape(-1, 2))
                    core.heights = tileset(xy).numpy().reshape(core.shape)
            written[(entry.row, entry.col)] = write_map_geotiffs(
                view, core, out_dir, layers=tuple(layers),
                stem=f"{stem}_r{entry.row:03d}_c{entry.col:03d}", cog=cog, files=files)
    return written
