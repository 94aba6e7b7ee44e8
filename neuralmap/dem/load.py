"""The one way a DEM enters the toolkit: `load_tile`, a sample tile by name
(`neuralmap.dem.samples`) or a file by extension (`neuralmap.dem.readers`),
screened for no-data values and implausible heights.

It sits above both (samples build the jacksboro tile with a reader), so neither imports the
other back.
"""

from __future__ import annotations

import errno
import math
import os
from pathlib import Path
from typing import Any

import numpy as np

from neuralmap.dem.geo import canonical_units
from neuralmap.dem.readers import (
    HEIGHT_CHECKS,
    SAMPLE_NAMES,
    SUPPORTED_EXTENSIONS,
    as_pair,
    read_asc,
    read_geotiff,
    read_hgt,
    read_npy,
    read_npz,
    reject_spacing,
    screen_heights,
)
from neuralmap.dem.samples import is_sample_name, load_sample
from neuralmap.dem.tile import DemTile
from neuralmap.exceptions import NeuralMapError

__all__ = ["load_tile"]


def load_tile(
    name_or_path: str | Path,
    *,
    spacing: float | tuple[float, float] | None = None,
    origin: tuple[float, float] | None = None,
    name: str | None = None,
    geographic: bool | None = None,
    units: str | None = None,
    nodata: float | list[float] | None = None,
    height_check: str = "refuse",
    **options: Any,
) -> DemTile:
    """Loads a sample tile by name or a DEM file by path (reader chosen by extension).

    Every tile is in a tile-local metric frame: node ``[0, 0]`` at ``origin`` (default
    ``(0, 0)``). Geographic sources keep their lon/lat conversion in ``tile.geo``; metric
    files with their own coordinates (UTM eastings/northings) keep them in
    ``tile.projected`` as metadata, never in the float32 training coordinates.

    Heights are screened after reading: values equal to ``nodata`` (compared at float32
    precision, as grids are stored) become voids, and heights outside
    `PLAUSIBLE_HEIGHT_M` (−12 000 … +9 000 m, and ±inf) are refused
    (``height_check="refuse"``, the default: the message counts them and names the fix),
    voided and counted (``"void"``: ``meta["n_implausible"]``), or kept (``"off"``).

    Args:
        name_or_path: A sample name (`SAMPLE_NAMES`, case-insensitive; ``"synthetic"``
            also as ``"synthetic:N"`` / ``"synthetic:NYxNX"``) or a path with one of
            `SUPPORTED_EXTENSIONS` (case-insensitive).
        spacing: ``(dx, dy)`` or one value, metres. Required for generic ``.npy``/``.npz``
            grids, optional for ``"synthetic"``; refused for sources that carry their own
            georeferencing (the two could disagree).
        origin: Tile-frame ``(x0, y0)`` metres of node ``[0, 0]`` (the south-west node),
            default ``(0, 0)`` for every source. A metric file's own coordinates of that
            node are kept in ``tile.projected`` (``to_projected``/``to_tile`` convert).
        name: Tile name; defaults to the sample name or the file stem.
        geographic: Older spelling of ``units``: True = ``"degrees"``, False = ``"metres"``.
        units: For ``.asc`` and GeoTIFF without a CRS: ``"metres"`` or ``"degrees"``;
            None = decide from the ``.prj`` sidecar, else from the corner and cell-size
            ranges (`neuralmap.dem.geo.decide_units`, which refuses ambiguous grids).
            The decision and its reason are in ``meta["units"]``/``meta["units_reason"]``.
        nodata: Extra no-data value(s) for any format (e.g. ``-32768`` for an int16
            ``.npy`` with SRTM voids), on top of the file's own.
        height_check: ``"refuse"``, ``"void"`` or ``"off"`` for implausible heights.
        **options: For ``"synthetic"`` only: ``shape``, ``seed``, ``relief``, ``hurst`` of
            `neuralmap.dem.synthetic_tile`.

    Returns:
        The tile: heights ``(ny, nx)`` float64 metres (row 0 south, NaN = void), metric
        spacing, ``geo`` set for geographic sources, ``meta`` with reader details.

    Raises:
        NeuralMapError: Missing file, unknown extension, missing or malformed content,
            wrong array rank, bad spacing, an all-void tile, options that do not apply.
    """
    if not isinstance(name_or_path, (str, os.PathLike)):
        raise NeuralMapError(
            f"load_tile: name_or_path must be a sample name or a file path, got "
            f"{type(name_or_path).__name__} {name_or_path!r}."
        )
    if origin is not None:
        origin = as_pair(origin, "origin", str(name_or_path), positive=False)
    where_call = f"load_tile('{name_or_path}')"
    units = canonical_units(units, where_call)
    if geographic is not None:
        implied = "degrees" if geographic else "metres"
        if units is not None and units != implied:
            raise NeuralMapError(
                f"{where_call}: geographic={geographic} and units={units!r} disagree; "
                "give only units."
            )
        units = implied
    if height_check not in HEIGHT_CHECKS:
        raise NeuralMapError(
            f"{where_call}: height_check must be one of {HEIGHT_CHECKS}, got {height_check!r}."
        )
    nodata_values = _nodata_values(nodata, where_call)
    text = str(name_or_path).strip()
    if not Path(text).exists() and not Path(text).is_symlink():
        if is_sample_name(text):
            if units is not None:
                raise NeuralMapError(
                    f"sample '{text}': units apply to .asc and GeoTIFF files only; remove "
                    "units (--data.units) for samples."
                )
            tile = load_sample(text, spacing=spacing, origin=origin, name=name, **options)
            return screen_heights(tile, nodata=nodata_values, height_check=height_check)
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
    _check_symlink(path)
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
            tile = read_npz(path, spacing=spacing, origin=origin, name=tile_name)
        elif suffix == ".npy":
            tile = read_npy(path, spacing=spacing, origin=origin, name=tile_name)
        elif suffix == ".hgt":
            reject_spacing(spacing, f"SRTM file '{path}'")
            tile = read_hgt(path, origin=origin, name=tile_name)
        elif suffix == ".asc":
            reject_spacing(spacing, f"ESRI ASCII file '{path}'")
            tile = read_asc(path, origin=origin, name=tile_name, units=units)
        else:
            reject_spacing(spacing, f"GeoTIFF '{path}'")
            tile = read_geotiff(path, origin=origin, name=tile_name, units=units)
        if units is not None and tile.meta.get("units", units) != units:
            raise NeuralMapError(
                f"DEM file '{path}': a {suffix} file is in {tile.meta['units']} by its format, "
                f"so units={units!r} does not apply; remove units (--data.units)."
            )
        return screen_heights(tile, nodata=nodata_values, height_check=height_check)
    except NeuralMapError:
        raise
    except (OSError, ValueError, KeyError, EOFError, MemoryError) as exc:
        raise NeuralMapError(
            f"DEM file '{path}' could not be read as a {suffix} DEM ({type(exc).__name__}: "
            f"{exc}). Check that the file is complete and of the type its extension says."
        ) from exc


def _check_symlink(path: Path) -> None:
    """Refuses a dangling symbolic link or a link loop with that diagnosis (not "not found")."""
    if not path.is_symlink() and path.exists():
        return
    try:
        os.stat(path)
    except OSError as exc:
        if exc.errno == errno.ELOOP:
            raise NeuralMapError(
                f"DEM path '{path}' is a symbolic link loop (the link points, directly or "
                "through other links, back to itself); point it at the real file."
            ) from None
        if path.is_symlink():
            raise NeuralMapError(
                f"DEM path '{path}' is a dangling symbolic link to '{os.readlink(path)}', "
                "which does not exist; fix the link or give the file itself."
            ) from None


def _nodata_values(nodata: Any, where: str) -> tuple[float, ...]:
    """The caller's no-data value(s) as a tuple of floats (empty when None)."""
    if nodata is None:
        return ()
    try:
        values = tuple(float(v) for v in np.atleast_1d(np.asarray(nodata, dtype=np.float64)))
    except (TypeError, ValueError) as exc:
        raise NeuralMapError(
            f"{where}: nodata must be a number or a list of numbers, got {nodata!r}."
        ) from exc
    if any(math.isnan(v) for v in values):
        raise NeuralMapError(f"{where}: nodata NaN is meaningless (NaN is always void).")
    return values
