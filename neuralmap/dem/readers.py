"""DEM readers chosen by file extension, and the sample tiles.

Every reader returns a :class:`DemTile` in a local east-north metric frame with row 0
south. Geographic grids (degrees) are converted with an equirectangular projection about
the tile centre (:func:`geographic_reference`), kept on the tile as ``tile.geo``.
"""

from __future__ import annotations

import math
import re
from pathlib import Path

import numpy as np

from neuralmap.dem.synthetic import synthetic_tile
from neuralmap.dem.tile import DemTile, GeoReference
from neuralmap.exceptions import NeuralMapError

SAMPLE_NAMES = ("jacksboro", "synthetic")
SUPPORTED_EXTENSIONS = (".npz", ".npy", ".hgt", ".asc", ".tif", ".tiff")

#: WGS-84 semi-major axis (m) and first eccentricity squared.
WGS84_A = 6378137.0
WGS84_E2 = 6.69437999014e-3
MATPLOTLIB_KEYS = ("elevation", "dx", "dy", "xmin", "xmax", "ymin", "ymax")
HGT_VOID = -32768


def geographic_reference(lon0: float, lat0: float) -> GeoReference:
    """Equirectangular projection about ``(lon0, lat0)`` on the WGS-84 ellipsoid.

    Metres per degree use the meridian radius ``M = a(1-e²)/(1-e² sin²φ)^1.5`` (north) and the
    normal radius ``N = a/(1-e² sin²φ)^0.5`` times ``cos φ`` (east) at the centre latitude.

    Args:
        lon0: Centre longitude, degrees.
        lat0: Centre latitude, degrees.
    """
    phi = math.radians(lat0)
    w = 1.0 - WGS84_E2 * math.sin(phi) ** 2
    meridian = WGS84_A * (1.0 - WGS84_E2) / w**1.5
    normal = WGS84_A / math.sqrt(w)
    return GeoReference(
        lon0=float(lon0),
        lat0=float(lat0),
        m_per_deg_lon=math.radians(1.0) * normal * math.cos(phi),
        m_per_deg_lat=math.radians(1.0) * meridian,
    )


def _geographic_tile(
    heights_north_up: np.ndarray,
    *,
    lon_west: float,
    lat_south: float,
    dlon: float,
    dlat: float,
    name: str,
    source: str,
    origin: tuple[float, float] | None,
) -> DemTile:
    """Builds a metric tile from a north-up geographic grid (first row = north)."""
    heights = np.asarray(heights_north_up, dtype=np.float64)[::-1]
    ny, nx = heights.shape
    lon0 = lon_west + 0.5 * (nx - 1) * dlon
    lat0 = lat_south + 0.5 * (ny - 1) * dlat
    geo = geographic_reference(lon0, lat0)
    spacing = (dlon * geo.m_per_deg_lon, dlat * geo.m_per_deg_lat)
    # Default metric origin: the south-west node at (0, 0); geo maps lon/lat about the centre,
    # so record the offset to convert back.
    sw_x, sw_y = geo.to_metric(np.array(lon_west), np.array(lat_south))
    tile_origin = origin if origin is not None else (0.0, 0.0)
    meta = {
        "geographic": {
            "lon_west": float(lon_west),
            "lat_south": float(lat_south),
            "dlon_deg": float(dlon),
            "dlat_deg": float(dlat),
            "projection": "equirectangular about the tile centre, WGS-84 radii",
            "sw_node_projected_m": [float(sw_x), float(sw_y)],
        }
    }
    return DemTile(
        heights, spacing, origin=tile_origin, name=name, geo=geo, source=source, meta=meta
    )


def _spacing_pair(spacing: float | tuple[float, float] | list[float] | None, where: str) -> tuple[float, float]:
    if spacing is None:
        raise NeuralMapError(
            f"{where}: this file carries no grid spacing. Pass it in metres: "
            "load_tile(path, spacing=30.0) or `--data.spacing 30` (or `[dx, dy]`)."
        )
    try:
        pair = np.broadcast_to(np.asarray(spacing, dtype=np.float64), (2,))
    except (TypeError, ValueError):
        raise NeuralMapError(
            f"{where}: spacing must be a number or a pair [dx, dy] in metres, got {spacing!r}."
        ) from None
    return float(pair[0]), float(pair[1])


def _check_grid(array: np.ndarray, where: str) -> np.ndarray:
    if array.ndim != 2:
        raise NeuralMapError(
            f"{where}: expected a 2-D height grid (rows = north-south), got an array of rank "
            f"{array.ndim} with shape {array.shape}. Save a single band."
        )
    if not np.issubdtype(array.dtype, np.number):
        raise NeuralMapError(f"{where}: heights must be numeric, got dtype {array.dtype}.")
    return array


def read_npz(
    path: Path,
    *,
    spacing: float | tuple[float, float] | None = None,
    origin: tuple[float, float] | None = None,
    name: str | None = None,
) -> DemTile:
    """Reads a ``.npz``: matplotlib-style geographic, or a generic array with given spacing.

    Matplotlib style (as ``jacksboro_fault_dem.npz``): keys ``elevation`` (first row north),
    ``dx``, ``dy`` (degrees), ``xmin``, ``xmax`` (longitudes), ``ymin``, ``ymax`` (latitudes of
    the first and last rows). Generic: one array, or key ``heights`` / ``elevation``, first
    row SOUTH (numpy/``DemTile`` convention), spacing in metres from the caller.
    """
    name = name or path.stem
    with np.load(path, allow_pickle=False) as data:
        keys = list(data.files)
        if "elevation" in keys and any(k in keys for k in MATPLOTLIB_KEYS[1:]):
            missing = [k for k in MATPLOTLIB_KEYS if k not in keys]
            if missing:
                raise NeuralMapError(
                    f"{path}: matplotlib-style DEM .npz is missing keys {missing} (has {keys}); "
                    f"it needs {list(MATPLOTLIB_KEYS)} in degrees."
                )
            elevation = _check_grid(np.asarray(data["elevation"]), str(path))
            dx, dy = float(data["dx"]), float(data["dy"])
            lons = (float(data["xmin"]), float(data["xmax"]))
            lats = (float(data["ymin"]), float(data["ymax"]))
            if not (np.isfinite([dx, dy]).all() and dx > 0 and dy > 0):
                raise NeuralMapError(
                    f"{path}: dx, dy must be finite and > 0 degrees, got {dx}, {dy}."
                )
            return _geographic_tile(
                elevation,
                lon_west=min(lons),
                lat_south=min(lats),
                dlon=dx,
                dlat=dy,
                name=name,
                source=str(path),
                origin=origin,
            )
        for key in ("heights", "elevation"):
            if key in keys:
                array = data[key]
                break
        else:
            if len(keys) != 1:
                raise NeuralMapError(
                    f"{path}: cannot tell which array holds the heights (keys {keys}). Store "
                    f"it as 'heights', or use matplotlib style with keys {list(MATPLOTLIB_KEYS)}."
                )
            array = data[keys[0]]
        array = _check_grid(np.asarray(array), str(path))
    return DemTile(
        array.astype(np.float64),
        _spacing_pair(spacing, str(path)),
        origin=origin or (0.0, 0.0),
        name=name,
        source=str(path),
    )


def read_npy(
    path: Path,
    *,
    spacing: float | tuple[float, float] | None = None,
    origin: tuple[float, float] | None = None,
    name: str | None = None,
) -> DemTile:
    """Reads a ``.npy`` 2-D height grid (row 0 south), spacing in metres from the caller."""
    array = _check_grid(np.load(path, allow_pickle=False), str(path))
    return DemTile(
        array.astype(np.float64),
        _spacing_pair(spacing, str(path)),
        origin=origin or (0.0, 0.0),
        name=name or path.stem,
        source=str(path),
    )


_HGT_NAME = re.compile(r"^([NS])(\d{1,2})([EW])(\d{1,3})", re.IGNORECASE)


def read_hgt(
    path: Path,
    *,
    origin: tuple[float, float] | None = None,
    name: str | None = None,
    **_: object,
) -> DemTile:
    """Reads an SRTM ``.hgt`` tile (1″ 3601², or 3″ 1201²; big-endian int16; -32768 = void).

    The south-west corner comes from the name (``N36W085.hgt`` → lat 36, lon -85); the
    first row of the file is the northern edge.
    """
    match = _HGT_NAME.match(path.name)
    if not match:
        raise NeuralMapError(
            f"{path}: SRTM .hgt names give the south-west corner, like N36W085.hgt; cannot "
            f"parse '{path.name}'. Rename the file."
        )
    lat = int(match.group(2)) * (1 if match.group(1).upper() == "N" else -1)
    lon = int(match.group(4)) * (1 if match.group(3).upper() == "E" else -1)
    raw = np.fromfile(path, dtype=">i2")
    side = int(round(math.sqrt(raw.size)))
    if side * side != raw.size or side not in (1201, 3601):
        raise NeuralMapError(
            f"{path}: {raw.size} samples is neither a 1″ (3601 x 3601) nor a 3″ (1201 x 1201) "
            "SRTM tile; the file is truncated or not SRTM .hgt."
        )
    heights = raw.reshape(side, side).astype(np.float64)
    heights[raw.reshape(side, side) == HGT_VOID] = np.nan
    step = 1.0 / (side - 1)
    return _geographic_tile(
        heights,
        lon_west=lon,
        lat_south=lat,
        dlon=step,
        dlat=step,
        name=name or path.stem,
        source=str(path),
        origin=origin,
    )


_ASC_KEYS = ("ncols", "nrows", "cellsize")


def read_asc(
    path: Path,
    *,
    origin: tuple[float, float] | None = None,
    name: str | None = None,
    geographic: bool | None = None,
    **_: object,
) -> DemTile:
    """Reads an ESRI ASCII grid (``.asc``): header then rows, first row north.

    Header keys: ``ncols``, ``nrows``, ``xllcorner``/``xllcenter``, ``yllcorner``/``yllcenter``,
    ``cellsize``, optional ``NODATA_value``. Coordinates are metric unless ``geographic=True``,
    or, when ``geographic`` is None, when the cell size is below 0.1 and the corner lies within
    ±180/±90 (degrees are then the only plausible unit).
    """
    header: dict[str, float] = {}
    with open(path, encoding="ascii", errors="replace") as handle:
        lines = handle.readlines()
    row = 0
    for row, line in enumerate(lines):  # noqa: B007 - row is used after the loop
        parts = line.split()
        if len(parts) == 2 and parts[0][0].isalpha():
            try:
                header[parts[0].lower()] = float(parts[1])
            except ValueError:
                raise NeuralMapError(
                    f"{path}: header line {row + 1} '{line.strip()}' has a non-numeric value."
                ) from None
        else:
            break
    missing = [k for k in _ASC_KEYS if k not in header]
    if missing or not any(k in header for k in ("xllcorner", "xllcenter")) or not any(
        k in header for k in ("yllcorner", "yllcenter")
    ):
        raise NeuralMapError(
            f"{path}: malformed ESRI ASCII header, missing {missing or 'xll*/yll*'}; expected "
            "ncols, nrows, xllcorner|xllcenter, yllcorner|yllcenter, cellsize [, NODATA_value]."
        )
    ncols, nrows = int(header["ncols"]), int(header["nrows"])
    try:
        values = np.array(" ".join(lines[row:]).split(), dtype=np.float64)
    except ValueError:
        raise NeuralMapError(f"{path}: the grid holds non-numeric values.") from None
    if values.size != ncols * nrows:
        raise NeuralMapError(
            f"{path}: header says {nrows} rows x {ncols} columns = {nrows * ncols} values, "
            f"the file holds {values.size}."
        )
    grid = values.reshape(nrows, ncols)
    if "nodata_value" in header:
        grid[grid == header["nodata_value"]] = np.nan
    cell = header["cellsize"]
    centre = "xllcenter" in header
    x_ll = header.get("xllcenter", header.get("xllcorner", 0.0)) + (0 if centre else 0.5 * cell)
    y_ll = header.get("yllcenter", header.get("yllcorner", 0.0)) + (0 if centre else 0.5 * cell)
    if geographic is None:
        geographic = cell < 0.1 and abs(x_ll) <= 180 and abs(y_ll) <= 90
    if geographic:
        return _geographic_tile(
            grid,
            lon_west=x_ll,
            lat_south=y_ll,
            dlon=cell,
            dlat=cell,
            name=name or path.stem,
            source=str(path),
            origin=origin,
        )
    return DemTile(
        grid[::-1].copy(),
        (cell, cell),
        origin=origin if origin is not None else (x_ll, y_ll),
        name=name or path.stem,
        source=str(path),
    )


def read_geotiff(
    path: Path,
    *,
    origin: tuple[float, float] | None = None,
    name: str | None = None,
    **_: object,
) -> DemTile:
    """Reads band 1 of a GeoTIFF with rasterio (optional extra ``neuralmap[geotiff]``)."""
    try:
        import rasterio  # type: ignore[import-not-found]
    except ImportError:
        raise NeuralMapError(
            f"{path}: reading GeoTIFF needs rasterio, which is not installed. Install it with "
            "`pip install 'neuralmap[geotiff]'` (or `pip install rasterio`), or convert the "
            "tile to .asc/.npy."
        ) from None
    with rasterio.open(path) as src:
        band = src.read(1, masked=True).astype(np.float64).filled(np.nan)
        transform = src.transform
        geographic = bool(src.crs is not None and src.crs.is_geographic)
    dx, dy = abs(transform.a), abs(transform.e)
    west = transform.c + 0.5 * dx
    south = transform.f - (band.shape[0] - 0.5) * dy
    if geographic:
        return _geographic_tile(
            band, lon_west=west, lat_south=south, dlon=dx, dlat=dy,
            name=name or path.stem, source=str(path), origin=origin,
        )
    return DemTile(
        band[::-1].copy(), (dx, dy), origin=origin if origin is not None else (west, south),
        name=name or path.stem, source=str(path),
    )


_READERS = {
    ".npz": read_npz,
    ".npy": read_npy,
    ".hgt": read_hgt,
    ".asc": read_asc,
    ".tif": read_geotiff,
    ".tiff": read_geotiff,
}


def jacksboro_tile(*, origin: tuple[float, float] | None = None, name: str | None = None) -> DemTile:
    """Matplotlib's sample DEM ``jacksboro_fault_dem.npz``: 344 x 403 nodes at 3″ (≈ 74 m x 92 m).

    Appalachian ridge-and-valley terrain, heights 236–1076 m. Embedded default tile.
    """
    from matplotlib import cbook

    path = Path(cbook.get_sample_data("jacksboro_fault_dem.npz", asfileobj=False))
    tile = read_npz(path, origin=origin, name=name or "jacksboro")
    tile.source = "matplotlib sample_data/jacksboro_fault_dem.npz"
    return tile


def load_tile(
    name_or_path: str | Path,
    *,
    spacing: float | tuple[float, float] | list[float] | None = None,
    origin: tuple[float, float] | None = None,
    name: str | None = None,
    **options: object,
) -> DemTile:
    """Loads a sample tile by name or a DEM file by path (reader chosen by extension).

    Args:
        name_or_path: ``"jacksboro"``, ``"synthetic"`` or a path to ``.npz``, ``.npy``,
            ``.hgt``, ``.asc``, ``.tif``/``.tiff``.
        spacing: Grid spacing in metres for files that carry none (``.npy``, generic
            ``.npz``); for ``"synthetic"`` the spacing of the generated tile.
        origin: Metric coordinates of node ``[0, 0]`` (default: (0, 0), or the file's own
            metric corner for metric .asc/GeoTIFF).
        name: Tile name (default: sample name or file stem).
        **options: Reader options (``geographic`` for .asc; ``shape``, ``seed``, ``relief``,
            ``hurst`` for ``"synthetic"``).

    Raises:
        NeuralMapError: Missing file, unknown extension, bad contents.
    """
    key = str(name_or_path)
    if key == "jacksboro":
        return jacksboro_tile(origin=origin, name=name)
    if key == "synthetic":
        kwargs = dict(options)
        if spacing is not None:
            kwargs["spacing"] = spacing
        if name is not None:
            kwargs["name"] = name
        tile = synthetic_tile(**kwargs)  # type: ignore[arg-type]
        if origin is not None:
            tile = DemTile(tile.heights, tile.spacing, origin=origin, name=tile.name, source=tile.source)
        return tile
    path = Path(name_or_path).expanduser()
    suffix = path.suffix.lower()
    if suffix not in _READERS:
        raise NeuralMapError(
            f"{path}: unknown DEM file type '{path.suffix or '(none)'}'. Supported: "
            f"{', '.join(SUPPORTED_EXTENSIONS)}, or a sample name: {', '.join(SAMPLE_NAMES)}."
        )
    if not path.is_file():
        raise NeuralMapError(
            f"DEM file not found: {path}. Give an existing {', '.join(SUPPORTED_EXTENSIONS)} "
            f"file or a sample name ({', '.join(SAMPLE_NAMES)})."
        )
    try:
        return _READERS[suffix](path, spacing=spacing, origin=origin, name=name, **options)
    except NeuralMapError:
        raise
    except (OSError, ValueError, KeyError, EOFError) as exc:
        raise NeuralMapError(f"{path}: could not read it as a {suffix} DEM: {exc}") from None
