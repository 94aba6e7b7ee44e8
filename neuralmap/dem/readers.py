"""DEM readers: sample tiles and files, chosen by extension, returned as a :class:`DemTile`.

Every reader returns heights in DemTile order (row 0 = south, column 0 = west), voids as NaN,
and a metric grid spacing. Geographic (lon/lat) sources are projected to metres with the
equirectangular map of :mod:`neuralmap.dem.geo` (WGS-84 radii of curvature at the tile's
centre latitude), kept on the tile as ``tile.geo``. Node ``[0, 0]`` sits at ``origin``
(default ``(0, 0)``; metric ``.asc``/GeoTIFF files keep their own coordinates).

Supported sources:

========================  =================================================================
``"jacksboro"``           matplotlib's sample ``jacksboro_fault_dem.npz`` (344 × 403, 3″).
``"synthetic"``           :func:`neuralmap.dem.synthetic_tile` defaults (128 × 128, 30 m);
                          ``"synthetic:256"`` or ``"synthetic:200x300"`` pick the shape.
``.npz`` (matplotlib)     keys ``elevation, dx, dy, xmin, xmax, ymin, ymax`` in degrees;
                          first row north (image order).
``.npz`` / ``.npy``       one 2-D array (or key ``heights``/``elevation``) in DemTile order
                          (row 0 south); ``spacing`` (metres) must be given; optional key
                          ``nodata``.
``.hgt`` (SRTM)           1″ (3601²) or 3″ (1201²) big-endian int16, −32768 = void, SW corner
                          from the name (``N36W085.hgt``); first row north.
``.asc`` (ESRI ASCII)     header + rows, first row north, ``NODATA_value`` → void.
``.tif`` / ``.tiff``      single-band GeoTIFF via rasterio (``pip install 'neuralmap[geotiff]'``).
========================  =================================================================
"""

from __future__ import annotations

import math
import re
from pathlib import Path
from typing import Any

import numpy as np

from neuralmap.dem.geo import geographic_grid, geographic_reference, looks_geographic
from neuralmap.dem.tile import DemTile, broadcast_pair
from neuralmap.exceptions import NeuralMapError

#: Built-in tile names accepted by :func:`load_tile` (see :mod:`neuralmap.dem.samples`).
SAMPLE_NAMES = ("jacksboro", "synthetic")
#: File extensions accepted by :func:`load_tile` (case-insensitive).
SUPPORTED_EXTENSIONS = (".npz", ".npy", ".hgt", ".asc", ".tif", ".tiff")
#: Keys of a matplotlib-style geographic .npz (``jacksboro_fault_dem.npz``).
MATPLOTLIB_NPZ_KEYS = ("elevation", "dx", "dy", "xmin", "xmax", "ymin", "ymax")
#: SRTM void marker.
HGT_VOID = -32768
#: SRTM side lengths: nodes per side -> arc-seconds per node.
HGT_SIZES = {3601: 1, 1201: 3}

_HGT_NAME_RE = re.compile(r"^([NS])(\d{1,2})([EW])(\d{1,3})", re.IGNORECASE)
_SPACING_HINT = "Pass the grid spacing in metres: load_tile(path, spacing=30) or --data.spacing 30."


def load_tile(
    name_or_path: str | Path,
    *,
    spacing: float | tuple[float, float] | None = None,
    origin: tuple[float, float] | None = None,
    name: str | None = None,
    geographic: bool | None = None,
    **options: Any,
) -> DemTile:
    """Loads a sample tile by name or a DEM file by path (reader chosen by extension).

    Args:
        name_or_path: A sample name (:data:`SAMPLE_NAMES`, case-insensitive; ``"synthetic"``
            also as ``"synthetic:N"`` / ``"synthetic:NYxNX"``) or a path with one of
            :data:`SUPPORTED_EXTENSIONS` (case-insensitive).
        spacing: ``(dx, dy)`` or one value, metres. Required for generic ``.npy``/``.npz``
            grids, optional for ``"synthetic"``; refused for sources that carry their own
            georeferencing (the two could disagree).
        origin: Metric ``(x0, y0)`` of node ``[0, 0]`` (the south-west node). Default
            ``(0, 0)``, except metric ``.asc``/GeoTIFF files, which keep their own
            coordinates of that node.
        name: Tile name; defaults to the sample name or the file stem.
        geographic: For ``.asc`` and GeoTIFF without a CRS: True = coordinates are lon/lat
            degrees, False = metres, None = decide (``.prj`` sidecar, else
            :func:`neuralmap.dem.geo.looks_geographic`).
        **options: For ``"synthetic"`` only: ``shape``, ``seed``, ``relief``, ``hurst`` of
            :func:`neuralmap.dem.synthetic_tile`.

    Returns:
        The tile: heights ``(ny, nx)`` float64 metres (row 0 south, NaN = void), metric
        spacing, ``geo`` set for geographic sources, ``meta`` with reader details.

    Raises:
        NeuralMapError: Missing file, unknown extension, missing or malformed content,
            wrong array rank, bad spacing, an all-void tile, options that do not apply.
    """
    if origin is not None:
        origin = as_pair(origin, "origin", str(name_or_path), positive=False)
    text = str(name_or_path).strip()
    if not Path(text).exists():
        from neuralmap.dem.samples import is_sample_name, load_sample

        if is_sample_name(text):
            return load_sample(text, spacing=spacing, origin=origin, name=name, **options)
    if options:
        raise NeuralMapError(
            f"load_tile('{text}'): options {sorted(options)} apply only to the 'synthetic' "
            "sample (shape, seed, relief, hurst); remove them for files and 'jacksboro'."
        )
    path = Path(text).expanduser()
    suffix = path.suffix.lower()
    if suffix not in SUPPORTED_EXTENSIONS:
        raise NeuralMapError(
            f"DEM source '{path}': unknown DEM file type '{path.suffix or '(no extension)'}'. "
            f"Supported extensions: {', '.join(SUPPORTED_EXTENSIONS)}; sample names: "
            f"{', '.join(SAMPLE_NAMES)}."
        )
    if not path.exists():
        raise NeuralMapError(
            f"DEM file not found: '{path}' (working directory {Path.cwd()}). Give an existing "
            f"{', '.join(SUPPORTED_EXTENSIONS)} file or a sample name: "
            f"{', '.join(SAMPLE_NAMES)}."
        )
    if not path.is_file():
        raise NeuralMapError(f"DEM path '{path}' is a directory, not a file; name the file.")
    tile_name = name if name is not None else path.stem
    try:
        if suffix == ".npz":
            return _read_npz(path, spacing=spacing, origin=origin, name=tile_name)
        if suffix == ".npy":
            return _read_npy(path, spacing=spacing, origin=origin, name=tile_name)
        if suffix == ".hgt":
            reject_spacing(spacing, f"SRTM file '{path}'")
            return read_hgt(path, origin=origin, name=tile_name)
        if suffix == ".asc":
            reject_spacing(spacing, f"ESRI ASCII file '{path}'")
            return read_asc(path, origin=origin, name=tile_name, geographic=geographic)
        reject_spacing(spacing, f"GeoTIFF '{path}'")
        return read_geotiff(path, origin=origin, name=tile_name, geographic=geographic)
    except NeuralMapError:
        raise
    except (OSError, ValueError, KeyError, EOFError, MemoryError) as exc:
        raise NeuralMapError(
            f"DEM file '{path}' could not be read as a {suffix} DEM ({type(exc).__name__}: "
            f"{exc}). Check that the file is complete and of the type its extension says."
        ) from exc


# --------------------------------------------------------------------------- helpers


def as_pair(value: Any, what: str, where: str, *, positive: bool) -> tuple[float, float]:
    """Broadcasts a scalar or length-2 value to a finite float pair, or raises."""
    pair = broadcast_pair(value, what, where)
    if not all(math.isfinite(v) for v in pair) or (positive and min(pair) <= 0.0):
        need = "finite and > 0 metres" if positive else "finite"
        hint = f" {_SPACING_HINT}" if positive else ""
        raise NeuralMapError(f"{where}: {what} must be {need}, got {value!r}.{hint}")
    return pair


def reject_spacing(spacing: Any, where: str) -> None:
    """Refuses a caller spacing for sources that carry their own grid geometry."""
    if spacing is not None:
        raise NeuralMapError(
            f"{where} carries its own grid spacing, so spacing={spacing!r} would conflict; "
            "leave spacing unset (remove --data.spacing) for this source."
        )


def _heights_2d(array: Any, where: str) -> np.ndarray:
    """Validates a numeric 2-D height array and returns it as float64."""
    arr = np.asarray(array)
    if arr.ndim == 3 and 1 in (arr.shape[0], arr.shape[-1]):
        hint = " It looks like a single band with an extra axis: squeeze it (arr[..., 0])."
    else:
        hint = " Save one 2-D grid (rows x columns)."
    if arr.ndim != 2:
        raise NeuralMapError(
            f"{where}: heights must be a 2-D array, got rank {arr.ndim} with shape {arr.shape}."
            + hint
        )
    if not (np.issubdtype(arr.dtype, np.number) or arr.dtype == bool):
        raise NeuralMapError(f"{where}: heights must be numeric, got dtype {arr.dtype}.")
    return arr.astype(np.float64)


def _make_tile(
    heights: np.ndarray,
    *,
    spacing: tuple[float, float],
    origin: tuple[float, float] | None,
    name: str,
    source: str,
    geo: Any = None,
    meta: dict[str, Any] | None = None,
) -> DemTile:
    """Builds the tile (DemTile validates shape, spacing and voids)."""
    return DemTile(
        heights=heights,
        spacing=spacing,
        origin=(0.0, 0.0) if origin is None else origin,
        name=name,
        geo=geo,
        source=source,
        meta=meta or {},
    )


# --------------------------------------------------------------------------- .npz / .npy


def _read_npz(
    path: Path, *, spacing: Any, origin: tuple[float, float] | None, name: str
) -> DemTile:
    """Dispatches a .npz to the matplotlib-style or the generic reader by its keys."""
    try:
        with np.load(path, allow_pickle=False) as data:
            arrays = {key: np.asarray(data[key]) for key in data.files}
    except (OSError, ValueError, EOFError) as exc:
        raise NeuralMapError(
            f"DEM file '{path}' could not be read as a NumPy .npz archive ({exc}). "
            "Write it with numpy.savez(path, heights=array)."
        ) from exc
    where = f"DEM file '{path}'"
    geo_keys = set(MATPLOTLIB_NPZ_KEYS) - {"elevation"}
    present_geo = geo_keys & arrays.keys()
    if present_geo:
        missing = [k for k in MATPLOTLIB_NPZ_KEYS if k not in arrays]
        if missing:
            raise NeuralMapError(
                f"{where}: a geographic (matplotlib-style) .npz needs keys "
                f"{', '.join(MATPLOTLIB_NPZ_KEYS)}; missing keys {', '.join(missing)} "
                f"(found {', '.join(sorted(arrays))})."
            )
        reject_spacing(spacing, where)
        return read_matplotlib_arrays(arrays, where=where, origin=origin, name=name, source=str(path))
    for key in ("heights", "elevation"):
        if key in arrays:
            chosen = key
            break
    else:
        if len(arrays) != 1:
            raise NeuralMapError(
                f"{where}: cannot tell which array holds the heights; found keys "
                f"{', '.join(sorted(arrays)) or '(none)'}. Store the grid under key 'heights' "
                f"(or 'elevation'), or give all matplotlib-style keys "
                f"{', '.join(MATPLOTLIB_NPZ_KEYS)}."
            )
        chosen = next(iter(arrays))
    nodata = arrays.get("nodata")
    return _generic_grid(
        arrays[chosen],
        where=f"{where} key '{chosen}'",
        spacing=spacing,
        origin=origin,
        name=name,
        source=str(path),
        nodata=None if nodata is None else float(np.asarray(nodata).reshape(-1)[0]),
        fmt="npz",
    )


def _read_npy(
    path: Path, *, spacing: Any, origin: tuple[float, float] | None, name: str
) -> DemTile:
    """A bare 2-D .npy array in DemTile order; spacing from the caller."""
    try:
        array = np.load(path, allow_pickle=False)
    except (OSError, ValueError, EOFError) as exc:
        raise NeuralMapError(
            f"DEM file '{path}' could not be read as a NumPy .npy array ({exc}). "
            "Write it with numpy.save(path, array)."
        ) from exc
    return _generic_grid(
        array,
        where=f"DEM file '{path}'",
        spacing=spacing,
        origin=origin,
        name=name,
        source=str(path),
        nodata=None,
        fmt="npy",
    )


def _generic_grid(
    array: Any,
    *,
    where: str,
    spacing: Any,
    origin: tuple[float, float] | None,
    name: str,
    source: str,
    nodata: float | None,
    fmt: str,
) -> DemTile:
    """A bare metric grid: taken as stored (row 0 = south), spacing required."""
    heights = _heights_2d(array, where)
    if spacing is None:
        raise NeuralMapError(
            f"{where}: a plain .{fmt} grid has no georeferencing, so its spacing is unknown. "
            + _SPACING_HINT
        )
    spacing_pair = as_pair(spacing, "spacing", where, positive=True)
    if nodata is not None:
        heights = np.where(heights == nodata, np.nan, heights)
    return _make_tile(
        heights,
        spacing=spacing_pair,
        origin=origin,
        name=name,
        source=source,
        meta={"format": fmt, "row0": "south (stored order)", "nodata": nodata},
    )


def read_matplotlib_arrays(
    arrays: dict[str, np.ndarray],
    *,
    where: str,
    origin: tuple[float, float] | None,
    name: str,
    source: str,
) -> DemTile:
    """matplotlib-style geographic grid (``jacksboro_fault_dem.npz`` layout).

    Layout rule (checked on the jacksboro sample, whose ``ymin`` key holds the *northern*
    latitude): the array is in image order, first row north, first column west, whatever
    the order of the ``ymin``/``ymax`` values; latitude and longitude bounds are the min/max
    of the two values. ``dx``/``dy`` are the node spacing in degrees. The bounds are cell
    edges when they span ``n·d`` (jacksboro: 403·dx, 344·dy; node centres half a cell
    inside) and node positions when they span ``(n−1)·d``; anything else is an error.
    """
    heights = _heights_2d(arrays["elevation"], f"{where} key 'elevation'")
    try:
        values = {k: float(np.asarray(arrays[k]).reshape(-1)[0]) for k in MATPLOTLIB_NPZ_KEYS[1:]}
    except (IndexError, TypeError, ValueError) as exc:
        raise NeuralMapError(
            f"{where}: keys dx, dy, xmin, xmax, ymin, ymax must be numbers ({exc})."
        ) from exc
    dlon, dlat = values["dx"], values["dy"]
    if not all(math.isfinite(v) for v in values.values()) or min(dlon, dlat) <= 0.0:
        raise NeuralMapError(
            f"{where}: dx, dy must be finite and > 0 degrees and the bounds finite, got "
            f"{values}."
        )
    ny, nx = heights.shape
    lon_w, lon_e = sorted((values["xmin"], values["xmax"]))
    lat_s, lat_n = sorted((values["ymin"], values["ymax"]))
    offsets = []
    for span, step, count, axis in ((lon_e - lon_w, dlon, nx, "x"), (lat_n - lat_s, dlat, ny, "y")):
        if abs(span - count * step) < 0.5 * step:
            offsets.append(0.5 * step)  # cell-edge bounds
        elif abs(span - (count - 1) * step) < 0.5 * step:
            offsets.append(0.0)  # node bounds
        else:
            raise NeuralMapError(
                f"{where}: the {axis} bounds span {span:.8g} degrees, which matches neither "
                f"{count} cells nor {count - 1} node steps of {step:.8g}; check d{axis} and the "
                f"{axis}min/{axis}max keys."
            )
    lon_first = lon_w + offsets[0]
    lat_first = lat_s + offsets[1]
    spacing, origin_m, geo = geographic_grid(
        lon_first, lat_first, dlon, dlat, (ny, nx), origin=origin, where=where
    )
    return _make_tile(
        np.flipud(heights),
        spacing=spacing,
        origin=origin_m,
        name=name,
        source=source,
        geo=geo,
        meta={
            "format": "matplotlib-npz",
            "row0": "south (file rows flipped: first file row is north)",
            "lon_range": [lon_w, lon_e],
            "lat_range": [lat_s, lat_n],
            "bounds": "cell edges" if offsets[0] > 0 else "nodes",
            "dlon_deg": dlon,
            "dlat_deg": dlat,
        },
    )


# --------------------------------------------------------------------------- SRTM .hgt


def parse_hgt_name(path: str | Path) -> tuple[int, int]:
    """South-west corner ``(lat, lon)`` in whole degrees from an SRTM file name.

    Args:
        path: File name such as ``N36W085.hgt`` (case-insensitive; suffixes after the
            7-character tag, e.g. ``N36W085.SRTMGL1.hgt``, are allowed).

    Returns:
        ``(lat, lon)`` of the tile's south-west node, e.g. ``(36, -85)``.

    Raises:
        NeuralMapError: If the name does not start with ``[NS]dd[EW]ddd`` or is out of range.
    """
    stem = Path(path).name
    match = _HGT_NAME_RE.match(stem)
    if not match:
        raise NeuralMapError(
            f"SRTM file '{path}': cannot read the tile corner from the name '{stem}'. SRTM "
            "tiles are named by their south-west corner, e.g. N36W085.hgt; rename the file."
        )
    lat = int(match.group(2)) * (1 if match.group(1).upper() == "N" else -1)
    lon = int(match.group(4)) * (1 if match.group(3).upper() == "E" else -1)
    if not (-90 <= lat < 90 and -180 <= lon < 180):
        raise NeuralMapError(
            f"SRTM file '{path}': corner lat={lat}, lon={lon} from the name is out of range "
            "(lat in [-90, 89], lon in [-180, 179])."
        )
    return lat, lon


def read_hgt(
    path: str | Path, *, origin: tuple[float, float] | None = None, name: str | None = None
) -> DemTile:
    """Reads an SRTM ``.hgt`` tile (1″ 3601² or 3″ 1201² big-endian int16).

    The file's first row is the northern edge; nodes sit on whole arc-second positions,
    from the south-west corner given by the file name to one degree north/east of it.
    ``-32768`` marks a void.

    Args:
        path: The ``.hgt`` file.
        origin: Metric coordinates of the south-west node (default ``(0, 0)``).
        name: Tile name (default: file stem).

    Returns:
        The tile with ``geo`` set (equirectangular about the tile centre).

    Raises:
        NeuralMapError: Wrong file size, unparseable name, all-void tile.
    """
    path = Path(path)
    lat_sw, lon_sw = parse_hgt_name(path)
    size = path.stat().st_size
    side = math.isqrt(size // 2)
    if size % 2 or side * side * 2 != size or side not in HGT_SIZES:
        raise NeuralMapError(
            f"SRTM file '{path}' has {size} bytes, neither a 1 nor a 3 arc-second tile: a .hgt "
            f"tile is 3601 x 3601 (1 arc-second, "
            f"{3601 * 3601 * 2} bytes) or 1201 x 1201 (3 arc-second, {1201 * 1201 * 2} bytes) "
            "big-endian int16 values. The file is truncated or not SRTM."
        )
    raw = np.fromfile(path, dtype=">i2").reshape(side, side)
    heights = np.flipud(raw).astype(np.float64)
    heights[np.flipud(raw) == HGT_VOID] = np.nan
    step = 1.0 / (side - 1)
    spacing, origin_m, geo = geographic_grid(
        float(lon_sw), float(lat_sw), step, step, (side, side), origin=origin,
        where=f"SRTM file '{path}'",
    )
    return _make_tile(
        heights,
        spacing=spacing,
        origin=origin_m,
        name=name or path.stem,
        source=str(path),
        geo=geo,
        meta={
            "format": "srtm-hgt",
            "arcsec": HGT_SIZES[side],
            "sw_corner_deg": [lat_sw, lon_sw],
            "row0": "south (file rows flipped: first file row is north)",
        },
    )


# --------------------------------------------------------------------------- ESRI ASCII


_ASC_KEYS = {
    "ncols", "nrows", "xllcorner", "xllcenter", "yllcorner", "yllcenter", "cellsize",
    "dx", "dy", "nodata_value",
}


def _prj_geographic(path: Path) -> bool | None:
    """Reads a ``.prj`` sidecar: True for GEOGCS only, False for PROJCS, None if absent."""
    for candidate in (path.with_suffix(".prj"), path.with_suffix(".PRJ")):
        if candidate.is_file():
            text = candidate.read_text(errors="replace").upper()
            if "PROJCS" in text:
                return False
            if "GEOGCS" in text or "GEOGCRS" in text:
                return True
    return None


def read_asc(
    path: str | Path,
    *,
    origin: tuple[float, float] | None = None,
    name: str | None = None,
    geographic: bool | None = None,
) -> DemTile:
    """Reads an ESRI ASCII grid (``.asc``).

    Header keys (case-insensitive): ``ncols``, ``nrows``, ``xllcorner``|``xllcenter``,
    ``yllcorner``|``yllcenter``, ``cellsize`` (or ``dx`` and ``dy``), optional
    ``NODATA_value``. Data rows follow, the first row north. With ``*llcorner`` the values
    are cell centres, so the south-west node lies half a cell inside the corner.

    Coordinates are metres unless geographic: ``geographic`` decides when given; otherwise a
    ``.prj`` sidecar with ``GEOGCS`` and no ``PROJCS`` means degrees, one with ``PROJCS``
    means metres, and without a sidecar :func:`neuralmap.dem.geo.looks_geographic` applies
    (cell ≤ 0.1 and extent within lon/lat bounds). Heights are taken as metres.

    Args:
        path: The ``.asc`` file.
        origin: Metric coordinates of the south-west node. Default: for a metric grid the
            file's own coordinates of that node (a projected grid keeps its
            eastings/northings; also in ``meta["first_node"]``), for a geographic grid
            ``(0, 0)``.
        name: Tile name (default: file stem).
        geographic: True/False to override the unit rule above.

    Returns:
        The tile (``geo`` set when geographic).

    Raises:
        NeuralMapError: Malformed header, wrong number of values, bad cell size, all-void.
    """
    path = Path(path)
    where = f"ESRI ASCII file '{path}'"
    try:
        lines = path.read_text(errors="strict").splitlines()
    except (OSError, UnicodeDecodeError) as exc:
        raise NeuralMapError(f"{where} could not be read as text ({exc}).") from exc
    header: dict[str, str] = {}
    body_start = 0
    for index, line in enumerate(lines):
        parts = line.split()
        if not parts:
            continue
        if parts[0].lower() in _ASC_KEYS:
            if len(parts) != 2:
                raise NeuralMapError(
                    f"{where}: header line {index + 1} '{line.strip()}' must be 'key value'."
                )
            header[parts[0].lower()] = parts[1]
            body_start = index + 1
        else:
            break
    required = ["ncols", "nrows"]
    missing = [k for k in required if k not in header]
    if "xllcorner" not in header and "xllcenter" not in header:
        missing.append("xllcorner or xllcenter")
    if "yllcorner" not in header and "yllcenter" not in header:
        missing.append("yllcorner or yllcenter")
    if "cellsize" not in header and not ("dx" in header and "dy" in header):
        missing.append("cellsize (or dx and dy)")
    if missing:
        raise NeuralMapError(
            f"{where}: malformed header, missing {', '.join(missing)} (found "
            f"{', '.join(sorted(header)) or 'no header keys'}). An ESRI ASCII grid starts with "
            "ncols, nrows, xllcorner, yllcorner, cellsize and optional NODATA_value lines."
        )
    try:
        ncols, nrows = int(header["ncols"]), int(header["nrows"])
        numbers = {k: float(v) for k, v in header.items() if k not in ("ncols", "nrows")}
    except ValueError as exc:
        raise NeuralMapError(f"{where}: malformed header value ({exc}).") from exc
    if ncols < 2 or nrows < 2:
        raise NeuralMapError(f"{where}: ncols and nrows must be ≥ 2, got {ncols} x {nrows}.")
    if "cellsize" in numbers:
        dx = dy = numbers["cellsize"]
    else:
        dx, dy = numbers["dx"], numbers["dy"]
    not_finite = [k for k, v in numbers.items() if k != "nodata_value" and not math.isfinite(v)]
    if not_finite or not (dx > 0 and dy > 0):
        raise NeuralMapError(
            f"{where}: header values must be finite and the cellsize > 0, got dx={dx}, "
            f"dy={dy}" + (f"; not finite: {', '.join(not_finite)}" if not_finite else "") + "."
        )
    corner = "xllcorner" in numbers
    x_first = numbers["xllcorner"] + 0.5 * dx if corner else numbers["xllcenter"]
    y_first = (
        numbers["yllcorner"] + 0.5 * dy if "yllcorner" in numbers else numbers["yllcenter"]
    )
    try:
        values = np.array(" ".join(lines[body_start:]).split(), dtype=np.float64)
    except ValueError as exc:
        raise NeuralMapError(f"{where}: the grid holds a non-numeric value ({exc}).") from exc
    if values.size != nrows * ncols:
        raise NeuralMapError(
            f"{where}: header says {nrows} rows x {ncols} columns = {nrows * ncols} values, "
            f"but the file holds {values.size}. Fix ncols/nrows or the data."
        )
    grid = values.reshape(nrows, ncols)
    nodata = numbers.get("nodata_value")
    if nodata is not None:
        grid = np.where(grid == nodata, np.nan, grid)
    heights = np.flipud(grid)
    if geographic is None:
        geographic = _prj_geographic(path)
        rule = "prj sidecar" if geographic is not None else "heuristic"
        if geographic is None:
            geographic = looks_geographic(x_first, y_first, dx, dy, (nrows, ncols))
    else:
        rule = "caller"
    meta = {
        "format": "esri-ascii",
        "nodata": nodata,
        "row0": "south (file rows flipped: first file row is north)",
        "units": "degrees" if geographic else "metres",
        "units_rule": rule,
        "first_node": [x_first, y_first],
    }
    if geographic:
        spacing, origin_m, geo = geographic_grid(
            x_first, y_first, dx, dy, (nrows, ncols), origin=origin, where=where
        )
        return _make_tile(heights, spacing=spacing, origin=origin_m, name=name or path.stem,
                          source=str(path), geo=geo, meta=meta)
    return _make_tile(
        heights,
        spacing=(dx, dy),
        origin=(x_first, y_first) if origin is None else origin,
        name=name or path.stem,
        source=str(path),
        meta=meta,
    )


# --------------------------------------------------------------------------- GeoTIFF


def read_geotiff(
    path: str | Path,
    *,
    origin: tuple[float, float] | None = None,
    name: str | None = None,
    geographic: bool | None = None,
) -> DemTile:
    """Reads band 1 of a north-up GeoTIFF through rasterio (optional dependency).

    Pixels are areas (GDAL convention): node centres lie half a pixel inside the bounds.
    The CRS decides degrees vs metres (``crs.is_geographic``); without a CRS, ``geographic``
    or :func:`neuralmap.dem.geo.looks_geographic` decides. The band's no-data value and
    mask become NaN. Origin defaults follow :func:`read_asc` (metric: the file's own
    coordinates of the south-west node centre; geographic: ``(0, 0)``).

    Raises:
        NeuralMapError: rasterio missing (says how to install it), rotated or sheared
            transform, unreadable file, all-void tile.
    """
    path = Path(path)
    where = f"GeoTIFF '{path}'"
    try:
        import rasterio
    except ImportError as exc:
        raise NeuralMapError(
            f"{where}: reading GeoTIFF needs rasterio, which is not installed. Install it with "
            "pip install 'neuralmap[geotiff]' (or pip install rasterio), or convert the file "
            "to .asc/.npz."
        ) from exc
    try:
        with rasterio.open(path) as src:
            band = src.read(1, masked=True)
            transform = src.transform
            crs = src.crs
    except Exception as exc:  # rasterio raises its own RasterioIOError and friends
        raise NeuralMapError(f"{where} could not be read by rasterio ({exc}).") from exc
    if transform.b != 0 or transform.d != 0:
        raise NeuralMapError(
            f"{where}: the grid is rotated or sheared (transform {tuple(transform)[:6]}); "
            "warp it to a north-up grid first (gdalwarp)."
        )
    heights = np.ma.filled(band.astype(np.float64), np.nan)
    dx, dy_signed = float(transform.a), float(transform.e)
    nrows, ncols = heights.shape
    if dy_signed < 0:  # north-up: first row north
        heights = np.flipud(heights)
        y_first = float(transform.f) + (nrows - 0.5) * dy_signed
    else:
        y_first = float(transform.f) + 0.5 * dy_signed
    dy = abs(dy_signed)
    x_first = float(transform.c) + 0.5 * dx
    if geographic is None:
        if crs is not None:
            geographic, rule = bool(crs.is_geographic), "crs"
        else:
            geographic = looks_geographic(x_first, y_first, dx, dy, (nrows, ncols))
            rule = "heuristic"
    else:
        rule = "caller"
    meta = {"format": "geotiff", "crs": None if crs is None else str(crs),
            "units": "degrees" if geographic else "metres", "units_rule": rule}
    if geographic:
        spacing, origin_m, geo = geographic_grid(
            x_first, y_first, dx, dy, (nrows, ncols), origin=origin, where=where
        )
        return _make_tile(heights, spacing=spacing, origin=origin_m, name=name or path.stem,
                          source=str(path), geo=geo, meta=meta)
    meta["first_node"] = [x_first, y_first]
    return _make_tile(heights, spacing=(dx, dy),
                      origin=(x_first, y_first) if origin is None else origin,
                      name=name or path.stem, source=str(path), meta=meta)


__all__ = [
    "HGT_SIZES",
    "HGT_VOID",
    "geographic_reference",
    "MATPLOTLIB_NPZ_KEYS",
    "SAMPLE_NAMES",
    "SUPPORTED_EXTENSIONS",
    "as_pair",
    "load_tile",
    "parse_hgt_name",
    "read_matplotlib_arrays",
    "read_asc",
    "read_geotiff",
    "read_hgt",
    "reject_spacing",
]
