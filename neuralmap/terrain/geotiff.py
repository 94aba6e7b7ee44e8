"""A fitted map as GeoTIFF on its source DEM's grid: heights, residual against the DEM, slope.

Every layer is a single-band float32 GeoTIFF with the source DEM's CRS, pixel grid and
no-data cells, so it opens in QGIS (or rasterio, GDAL) on top of the DEM it was fitted to:

* ``height``: the map at every DEM node (m);
* ``residual``: map − DEM (m);
* ``slope``: the map's gradient magnitude ``|∇h|`` (m/m), by autograd (any terrain model).

The grid is rebuilt from the tile's georeference: a projected tile
(`ProjectedReference`) gets its absolute coordinates back
(``easting = x + x_offset``); a geographic tile (`GeoReference`)
its lon/lat grid (the inverse of the reader's equirectangular map, ``EPSG:4326`` unless
the source GeoTIFF named another geographic CRS); a tile without a georeference (a plain
``.npy``) is written in its tile-local metres without a CRS. Pixels are areas (GDAL
convention): node centres lie half a pixel inside the bounds, as the readers assume. DEM
voids are written as the no-data value. Needs rasterio (``geotiff`` extra).
"""

from __future__ import annotations

import math
import os
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
import torch

from neuralmap.dem.tile import DemTile
from neuralmap.exceptions import NeuralMapError
from neuralmap.io import default_mode

__all__ = ["LAYERS", "NODATA", "map_layers", "source_grid", "write_geotiff", "write_map_geotiffs"]

#: Layers `write_map_geotiffs` can write.
LAYERS = ("height", "residual", "slope")
#: No-data value written when the source names none.
NODATA = -9999.0


def _rasterio() -> Any:
    try:
        import rasterio
    except ImportError as exc:
        raise NeuralMapError(
            "GeoTIFF export needs rasterio, which is not installed. Install it with "
            "pip install 'neuralmap[geotiff]' (or pip install rasterio)."
        ) from exc
    return rasterio


def source_grid(tile: DemTile) -> tuple[Any, str | None]:
    """The tile's grid in its source coordinates: ``(affine transform, CRS text or None)``.

    The transform maps (column, row) of a north-up raster (row 0 north) to the source
    coordinates of the pixel corner, as GDAL does.
    """
    _rasterio()
    from rasterio.transform import from_origin

    ny, nx = tile.shape
    dx, dy = tile.spacing
    x_last = tile.origin[0] + (nx - 1) * dx  # tile-frame metres of the NE node
    y_last = tile.origin[1] + (ny - 1) * dy
    if tile.geo is not None:
        lon0, lat0 = tile.geo.to_geographic(tile.origin[0], tile.origin[1])
        lon1, lat1 = tile.geo.to_geographic(x_last, y_last)
        dlon, dlat = (lon1 - lon0) / (nx - 1), (lat1 - lat0) / (ny - 1)
        crs = tile.meta.get("crs") or "EPSG:4326"
        return from_origin(float(lon0) - 0.5 * dlon, float(lat1) + 0.5 * dlat, float(dlon),
                           float(dlat)), crs
    if tile.projected is not None:
        e0, _ = tile.projected.to_projected(tile.origin[0], tile.origin[1])
        _, n1 = tile.projected.to_projected(x_last, y_last)
        return from_origin(float(e0) - 0.5 * dx, float(n1) + 0.5 * dy, dx, dy), \
            tile.projected.crs
    return from_origin(tile.origin[0] - 0.5 * dx, y_last + 0.5 * dy, dx, dy), None


def map_layers(terrain: torch.nn.Module, tile: DemTile, *,
               batch: int = 65536) -> dict[str, np.ndarray]:
    """The map's height, residual and slope at every node of ``tile`` (DemTile order).

    Args:
        terrain: Any terrain model (``forward(xy) -> height``) over the tile's frame.
        tile: The DEM tile the map was fitted to.
        batch: Nodes per evaluation.

    Returns:
        ``{"height", "residual", "slope"}``, ``(ny, nx)`` float64 each, NaN at DEM voids.

    Raises:
        NeuralMapError: The map was fitted to another tile (fingerprints differ).
    """
    expected = getattr(terrain, "tile_fingerprint", "")
    if expected and expected != tile.fingerprint():
        raise NeuralMapError(
            f"the map was fitted to tile {getattr(terrain, 'tile_name', '?')!r} (fingerprint "
            f"{expected}), not to {tile.name!r} ({tile.fingerprint()}); give the DEM the map "
            "was trained on (same file, spacing and no-data options)."
        )
    param = next(iter(terrain.parameters()), None)
    dtype = param.dtype if param is not None else torch.float64
    device = param.device if param is not None else torch.device("cpu")
    xy = torch.as_tensor(tile.node_xy().reshape(-1, 2), dtype=dtype, device=device)
    height = torch.empty(xy.shape[0], dtype=torch.float64)
    slope = torch.empty(xy.shape[0], dtype=torch.float64)
    was_training = terrain.training
    terrain.eval()
    try:
        for lo in range(0, xy.shape[0], batch):
            points = xy[lo:lo + batch].clone().requires_grad_(True)
            h = terrain(points)
            (grad,) = torch.autograd.grad(h.sum(), points)
            height[lo:lo + batch] = h.detach().double().cpu()
            slope[lo:lo + batch] = grad.detach().double().norm(dim=-1).cpu()
    finally:
        terrain.train(was_training)
    void = ~tile.valid_mask
    out = {"height": height.numpy().reshape(tile.shape), "slope": slope.numpy().reshape(tile.shape)}
    out["residual"] = out["height"] - tile.heights
    for values in out.values():
        values[void] = np.nan
    return out


def write_geotiff(path: str | os.PathLike[str], values: np.ndarray, tile: DemTile, *,
                  nodata: float | None = None, description: str = "",
                  cog: bool = False) -> Path:
    """Writes one ``(ny, nx)`` layer (DemTile order, NaN = void) on the tile's source grid.

    The file is built under a hidden name in the destination folder and renamed when
    complete. With ``cog`` it is a Cloud Optimized GeoTIFF (GDAL's COG driver: 512-pixel
    tiles, deflate, internal overviews, the header first), which web map servers and
    ``/vsicurl/`` readers fetch by range.

    Args:
        path: Destination ``.tif``.
        values: The layer, row 0 south.
        tile: The tile whose grid and CRS the file takes.
        nodata: No-data value; None = the source's (when finite) else `NODATA`.
        description: Band description (shown by GIS tools).
        cog: Write a Cloud Optimized GeoTIFF.

    Returns:
        The path written.

    Raises:
        NeuralMapError: rasterio missing, wrong shape, or a destination that cannot be
            written (read-only folder, a file in the way), with the path.
    """
    rasterio = _rasterio()
    values = np.asarray(values, dtype=np.float64)
    if values.shape != tile.shape:
        raise NeuralMapError(f"write_geotiff: layer shape {values.shape} is not the tile's "
                             f"{tile.shape}.")
    if nodata is None:
        source = tile.meta.get("nodata")
        nodata = float(source) if isinstance(source, (int, float)) and math.isfinite(
            float(source)) else NODATA
    transform, crs = source_grid(tile)
    raster = np.flipud(np.where(np.isfinite(values), values, nodata)).astype(np.float32)
    path = Path(path)
    folder = path.parent
    try:
        folder.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp.tif", dir=folder)
        os.close(fd)
    except OSError as exc:
        raise NeuralMapError(
            f"GeoTIFF export: cannot write into '{folder}' ({exc.strerror or exc}); pick a "
            "writable output folder."
        ) from None
    try:
        with rasterio.open(
            tmp, "w", driver="GTiff", height=raster.shape[0], width=raster.shape[1],
            count=1, dtype="float32", crs=crs, transform=transform, nodata=nodata,
            compress="deflate", tiled=raster.shape[0] >= 256 and raster.shape[1] >= 256,
        ) as dst:
            dst.write(raster, 1)
            if description:
                dst.set_band_description(1, description)
        if cog:  # the COG driver only copies: the plain GeoTIFF above is its source
            from rasterio.shutil import copy as raster_copy

            plain, tmp = tmp, tmp.removesuffix(".tmp.tif") + ".cog.tmp.tif"
            try:
                raster_copy(plain, tmp, driver="COG", compress="DEFLATE", blocksize=512,
                            overviews="AUTO")
            finally:
                os.unlink(plain)
        os.chmod(tmp, default_mode())
        os.replace(tmp, path)
    except BaseException as exc:
        if os.path.exists(tmp):
            os.unlink(tmp)
        if isinstance(exc, OSError):
            raise NeuralMapError(f"GeoTIFF export: cannot write '{path}' ({exc}).") from None
        raise
    return path


_DESCRIPTIONS = {
    "height": "neural map height (m)",
    "residual": "neural map minus DEM (m)",
    "slope": "neural map slope |grad h| (m/m)",
}


def write_map_geotiffs(terrain: torch.nn.Module, tile: DemTile, out_dir: str | os.PathLike[str],
                       *, layers: tuple[str, ...] = LAYERS, stem: str = "neural_map",
                       nodata: float | None = None, cog: bool = False) -> dict[str, Path]:
    """Writes the map's layers as ``<out_dir>/<stem>_<layer>.tif`` on the DEM's grid.

    Args:
        terrain: The fitted map.
        tile: The DEM tile it was fitted to.
        out_dir: Output folder (created when missing).
        layers: Any of `LAYERS`.
        stem: File name prefix.
        nodata: No-data value (see `write_geotiff`).
        cog: Cloud Optimized GeoTIFFs (see `write_geotiff`).

    Returns:
        Layer name -> path.

    Raises:
        NeuralMapError: Unknown layer, a map of another tile, an unwritable folder.
    """
    unknown = [name for name in layers if name not in LAYERS]
    if unknown or not layers:
        raise NeuralMapError(f"GeoTIFF export: unknown layer(s) {unknown or list(layers)}; "
                             f"choose from {list(LAYERS)}.")
    out_dir = Path(out_dir)
    _check_folder(out_dir)
    values = map_layers(terrain, tile)
    return {name: write_geotiff(out_dir / f"{stem}_{name}.tif", values[name], tile,
                                nodata=nodata, description=_DESCRIPTIONS[name], cog=cog)
            for name in layers}


def _check_folder(out_dir: Path) -> None:
    """Refuses, before any work, an output folder that cannot be created or written."""
    from neuralmap.io import check_writable_dir

    check_writable_dir(out_dir, option="GeoTIFF output folder")
