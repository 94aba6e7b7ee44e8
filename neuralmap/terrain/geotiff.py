"""A fitted map as GeoTIFF on its source DEM's grid: heights, residual against the DEM, slope.

Every layer is a single-band float32 GeoTIFF with the source DEM's CRS, pixel grid and
no-data cells, so it opens in QGIS (or rasterio, GDAL) on top of the DEM it was fitted to:

* ``height``: the map at every DEM node (m);
* ``residual``: map − DEM (m);
* ``slope``: the map's gradient magnitude ``|∇h|`` (m/m), by autograd (any terrain model).

The grid is rebuilt from the tile's georeference: a projected tile
(`ProjectedReference`) gets its absolute coordinates back
(``easting = x + x_offset``); a geographic tile (`GeoReference`)
its lon/lat grid (the inverse of the reader's equirectangular map); a tile without a
georeference (a plain ``.npy``) is written in its tile-local metres without a CRS. The CRS
is the one the reader kept: a GeoTIFF's own, a ``.prj`` sidecar's WKT, ``EPSG:4326`` for
SRTM ``.hgt`` (and any lon/lat grid that names no other); a CRS recorded only by name (maps
written before the readers kept the WKT) is looked up by pyproj (`rasterio_crs`). Pixels are
areas (GDAL convention): node centres lie half a pixel inside the bounds, as the readers
assume. DEM voids are written as the no-data value. Every layer is built in memory and
written all or nothing (`neuralmap.io.atomic_files`). Needs rasterio (``geotiff`` extra;
pyproj for CRS names: ``nav`` extra).
"""

from __future__ import annotations

import math
import os
from contextlib import ExitStack
from pathlib import Path
from typing import Any

import numpy as np
import torch

from neuralmap.dem.geo import SRTM_CRS, pyproj_crs
from neuralmap.dem.tile import DemTile
from neuralmap.exceptions import NeuralMapError
from neuralmap.io import AtomicFiles, atomic_files

__all__ = ["LAYERS", "NODATA", "geotiff_bytes", "map_layers", "rasterio_crs", "source_grid",
           "write_geotiff", "write_map_geotiffs"]

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


def rasterio_crs(crs: str | None) -> Any:
    """The CRS text a tile records as a rasterio CRS (None stays None).

    WKT and ``EPSG:<code>`` are read directly; a CRS recorded only by name (maps and
    tilesets written before the readers kept the ``.prj`` WKT, a ``.prj`` with incomplete
    WKT) goes through pyproj (`neuralmap.dem.geo.pyproj_crs`).

    Raises:
        NeuralMapError: rasterio missing (``geotiff`` extra), pyproj needed but missing
            (``nav`` extra), or a name pyproj does not know, with the fix.
    """
    if crs is None:
        return None
    _rasterio()
    from rasterio.crs import CRS
    from rasterio.errors import CRSError

    try:
        return CRS.from_user_input(crs)
    except CRSError:
        return CRS.from_wkt(pyproj_crs(crs, "GeoTIFF export").to_wkt())


def source_grid(tile: DemTile) -> tuple[Any, Any]:
    """The tile's grid in its source coordinates: ``(affine transform, rasterio CRS or None)``.

    The transform maps (column, row) of a north-up raster (row 0 north) to the source
    coordinates of the pixel corner, as GDAL does; the CRS is the one the tile records
    (`rasterio_crs`).
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
        crs = rasterio_crs(tile.meta.get("crs") or SRTM_CRS)
        return from_origin(float(lon0) - 0.5 * dlon, float(lat1) + 0.5 * dlat, float(dlon),
                           float(dlat)), crs
    if tile.projected is not None:
        e0, _ = tile.projected.to_projected(tile.origin[0], tile.origin[1])
        _, n1 = tile.projected.to_projected(x_last, y_last)
        return from_origin(float(e0) - 0.5 * dx, float(n1) + 0.5 * dy, dx, dy), \
            rasterio_crs(tile.projected.crs)
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


def geotiff_bytes(values: np.ndarray, tile: DemTile, *, nodata: float | None = None,
                  description: str = "", cog: bool = False) -> bytes:
    """One ``(ny, nx)`` layer (DemTile order, NaN = void) as the bytes of a GeoTIFF on the
    tile's source grid, built in memory (GDAL's ``/vsimem/``).

    Building in memory lets the file reach the disk through Python's own writes
    (`neuralmap.io.atomic_files`), which report a full disk; GDAL writing to disk itself
    can report success and leave a truncated file. With ``cog`` it is a Cloud Optimized
    GeoTIFF (GDAL's COG driver: 512-pixel tiles, deflate, internal overviews, the header
    first), which web map servers and ``/vsicurl/`` readers fetch by range.

    Args:
        values: The layer, row 0 south.
        tile: The tile whose grid and CRS the file takes.
        nodata: No-data value; None = the source's (when finite) else `NODATA`.
        description: Band description (shown by GIS tools).
        cog: A Cloud Optimized GeoTIFF.

    Raises:
        NeuralMapError: rasterio missing, wrong shape, a CRS that cannot be written.
    """
    _rasterio()
    from rasterio.io import MemoryFile

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
    with MemoryFile() as plain:
        with plain.open(
            driver="GTiff", height=raster.shape[0], width=raster.shape[1], count=1,
            dtype="float32", crs=crs, transform=transform, nodata=nodata, compress="deflate",
            tiled=raster.shape[0] >= 256 and raster.shape[1] >= 256,
        ) as dst:
            dst.write(raster, 1)
            if description:
                dst.set_band_description(1, description)
        if not cog:
            return plain.read()
        from rasterio.shutil import copy as raster_copy

        with MemoryFile() as out:  # the COG driver only copies: the plain file is its source
            raster_copy(plain.name, out.name, driver="COG", compress="DEFLATE", blocksize=512,
                        overviews="AUTO")
            return out.read()


def write_geotiff(path: str | os.PathLike[str], values: np.ndarray, tile: DemTile, *,
                  nodata: float | None = None, description: str = "",
                  cog: bool = False, files: AtomicFiles | None = None) -> Path:
    """Writes one ``(ny, nx)`` layer (DemTile order, NaN = void) on the tile's source grid.

    The file (`geotiff_bytes`) is written under a hidden name in the destination folder
    and renamed when complete; with ``files`` it joins that all-or-nothing batch and is
    renamed with the others when the batch commits.

    Args:
        path: Destination ``.tif``.
        values: The layer, row 0 south.
        tile: The tile whose grid and CRS the file takes.
        nodata: No-data value; None = the source's (when finite) else `NODATA`.
        description: Band description (shown by GIS tools).
        cog: Write a Cloud Optimized GeoTIFF.
        files: The batch to join (`neuralmap.io.atomic_files`); None = a batch of its own.

    Returns:
        The path written.

    Raises:
        NeuralMapError: rasterio missing, wrong shape, or a destination that cannot be
            written (read-only folder, a file in the way, a full disk), with the path.
    """
    data = geotiff_bytes(values, tile, nodata=nodata, description=description, cog=cog)
    if files is not None:
        return files.write_bytes(path, data)
    with atomic_files(option="GeoTIFF export") as own:
        return own.write_bytes(path, data)


_DESCRIPTIONS = {
    "height": "neural map height (m)",
    "residual": "neural map minus DEM (m)",
    "slope": "neural map slope |grad h| (m/m)",
}


def write_map_geotiffs(terrain: torch.nn.Module, tile: DemTile, out_dir: str | os.PathLike[str],
                       *, layers: tuple[str, ...] = LAYERS, stem: str = "neural_map",
                       nodata: float | None = None, cog: bool = False,
                       files: AtomicFiles | None = None) -> dict[str, Path]:
    """Writes the map's layers as ``<out_dir>/<stem>_<layer>.tif`` on the DEM's grid.

    All layers or none: each goes to a hidden temporary file as it is built, and all are
    renamed into place at the end (`neuralmap.io.atomic_files`); a failure part-way (a
    full disk) leaves the earlier files of the folder as they were and no new one.

    Args:
        terrain: The fitted map.
        tile: The DEM tile it was fitted to.
        out_dir: Output folder (created when missing).
        layers: Any of `LAYERS`.
        stem: File name prefix.
        nodata: No-data value (see `write_geotiff`).
        cog: Cloud Optimized GeoTIFFs (see `write_geotiff`).
        files: A batch to join (the files are renamed when it commits); None = its own.

    Returns:
        Layer name -> path.

    Raises:
        NeuralMapError: Unknown layer, a map of another tile, an unwritable folder, a full
            disk.
    """
    unknown = [name for name in layers if name not in LAYERS]
    if unknown or not layers:
        raise NeuralMapError(f"GeoTIFF export: unknown layer(s) {unknown or list(layers)}; "
                             f"choose from {list(LAYERS)}.")
    out_dir = Path(out_dir)
    _check_folder(out_dir)
    values = map_layers(terrain, tile)
    with ExitStack() as stack:
        if files is None:
            files = stack.enter_context(atomic_files(option="GeoTIFF export"))
        return {name: write_geotiff(out_dir / f"{stem}_{name}.tif", values[name], tile,
                                    nodata=nodata, description=_DESCRIPTIONS[name], cog=cog,
                                    files=files)
                for name in layers}


def _check_folder(out_dir: Path) -> None:
    """Refuses, before any work, an output folder that cannot be created or written."""
    from neuralmap.io import check_writable_dir

    check_writable_dir(out_dir, option="GeoTIFF output folder")
