"""DEM mosaics: several adjacent tiles stitched into one grid in one metric frame.

`load_mosaic` reads every file with `neuralmap.dem.load_tile`, recovers each
tile's native grid (lon/lat degrees for SRTM ``.hgt`` and geographic ``.asc``/GeoTIFF, the
projected metres of a metric file), checks that the tiles share units, spacing and datum
(CRS) and lie on one common grid, and places them into one array. Shared nodes (the edge
row/column that neighbouring SRTM tiles both hold) must agree within ``tolerance_m``
where both are valid; a void in one tile is filled from the other. The tiles must form
one connected group (each touches or overlaps another).

Projection. A geographic mosaic is one regular lon/lat grid; it is mapped to metres by the
equirectangular projection of `neuralmap.dem.geo` about the **mosaic's** centre (one
frame for the whole area, WGS-84 radii of curvature at the centre latitude ``φ0``). Its
east-west scale is exact on the centre parallel and off by ``cos φ / cos φ0 − 1`` at
latitude ``φ`` (north-south scale by ``M(φ)/M(φ0) − 1``); the positions of the corners are
off by ``Δλ·(m_λ(φ0) − m_λ(φ))`` metres east-west. `projection_distortion` computes
these figures; they are stored in ``tile.meta["projection"]`` (e.g. a 2° × 1° mosaic at
36° N: 0.64 % east-west scale error at the northern and southern edges, 570 m at the
corners). Metric mosaics keep the files' own projected frame (no distortion added).
"""

from __future__ import annotations

import glob as _glob
import math
import shutil
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from neuralmap.dem.geo import SRTM_CRS, crs_name, geographic_grid, metres_per_degree
from neuralmap.dem.load import load_tile
from neuralmap.dem.tile import DemTile, ProjectedReference
from neuralmap.exceptions import NeuralMapError

__all__ = [
    "MosaicPlan",
    "load_mosaic",
    "mosaic_sources",
    "plan_mosaic",
    "projection_distortion",
    "write_mosaic",
]

#: Relative tolerance on spacings and on the grid alignment of tile corners.
GRID_RTOL = 1e-6
#: Bytes kept free on the disk after writing a mosaic file.
DISK_MARGIN_BYTES = 256 * 2**20


def mosaic_sources(sources: str | Path | Sequence[str | Path]) -> list[Path]:
    """The files of a mosaic: a glob pattern, one path, or a list of paths/patterns.

    Returns:
        The files, sorted and without duplicates.

    Raises:
        NeuralMapError: A pattern that matches nothing or an empty list.
    """
    items = [sources] if isinstance(sources, (str, Path)) else list(sources)
    if not items:
        raise NeuralMapError("load_mosaic: no DEM files given; pass a list of paths or a glob.")
    paths: list[Path] = []
    for item in items:
        text = str(Path(item).expanduser())
        if any(c in text for c in "*?["):
            found = sorted(_glob.glob(text))
            if not found:
                raise NeuralMapError(
                    f"load_mosaic: the pattern '{text}' matches no file (working directory "
                    f"{Path.cwd()}); check the folder and the extension (e.g. tiles/*.hgt)."
                )
            paths.extend(Path(f) for f in found)
        else:
            paths.append(Path(text))
    unique = sorted(set(paths), key=str)
    return unique


@dataclass
class _Native:
    """A tile in its native grid: first node, steps, units, CRS."""

    tile: DemTile
    first: tuple[float, float]
    step: tuple[float, float]
    units: str
    crs: str | None


def _native(tile: DemTile, path: Path) -> _Native:
    """The tile's native grid (degrees for geographic sources, projected metres else)."""
    meta = tile.meta
    if tile.geo is not None:
        geo = tile.geo
        step = (tile.spacing[0] / geo.m_per_deg_lon, tile.spacing[1] / geo.m_per_deg_lat)
        if meta.get("format") == "srtm-hgt":
            lat, lon = meta["sw_corner_deg"]
            arc = float(meta["arcsec"]) / 3600.0
            first, step = (float(lon), float(lat)), (arc, arc)
            crs: str | None = meta.get("crs") or SRTM_CRS
        else:
            lon, lat = geo.to_geographic(*tile.origin)
            first = (float(meta.get("first_node", (lon, lat))[0]),
                     float(meta.get("first_node", (lon, lat))[1]))
            crs = meta.get("crs")
        return _Native(tile, first, step, "degrees", crs)
    if tile.projected is not None:
        e, n = tile.projected.to_projected(*tile.origin)
        return _Native(tile, (float(e), float(n)), tile.spacing, "metres", tile.projected.crs)
    raise NeuralMapError(
        f"load_mosaic: '{path}' carries no georeference (a plain .npy/.npz grid); a mosaic "
        "needs files that say where they lie (.hgt, .asc, GeoTIFF)."
    )


def _same_datum(a: str | None, b: str | None) -> bool:
    """CRS names agree (unknown on either side counts as agreement; SRTM is WGS 84); a WKT
    is compared by its name (`crs_name`)."""
    if a is None or b is None:
        return True

    def norm(s: str) -> str:
        s = str(crs_name(s)).upper().replace("_", " ").replace("-", " ")
        return "WGS 84" if ("WGS 84" in s or "WGS84" in s.replace(" ", "") or "4326" in s) else s

    return norm(a) == norm(b)


@dataclass
class MosaicPlan:
    """Where each tile goes in the mosaic grid.

    Attributes:
        tiles: The loaded tiles, in file order.
        paths: Their files.
        offsets: ``(row, col)`` of each tile's node ``[0, 0]`` in the mosaic (row 0 south).
        shape: ``(ny, nx)`` mosaic nodes.
        first: Native coordinates of mosaic node ``[0, 0]`` (lon/lat or easting/northing).
        step: Native node steps.
        units: ``"degrees"`` or ``"metres"``.
        crs: The common CRS as text rasterio and pyproj read (WKT or ``EPSG:<code>``), or
            None.
    """

    tiles: list[DemTile]
    paths: list[Path]
    offsets: list[tuple[int, int]]
    shape: tuple[int, int]
    first: tuple[float, float]
    step: tuple[float, float]
    units: str
    crs: str | None


def plan_mosaic(
    sources: str | Path | Sequence[str | Path], **load_options: Any
) -> MosaicPlan:
    """Loads the tiles and checks that they form one mosaic (see the module docstring).

    Args:
        sources: Glob pattern, path, or list of paths/patterns.
        **load_options: Passed to `load_tile` (``units``, ``nodata``,
            ``height_check``).

    Raises:
        NeuralMapError: Mixed units, different spacings or datums, tiles off the common
            grid, tiles that do not touch.
    """
    paths = mosaic_sources(sources)
    natives = [_native(load_tile(p, **load_options), p) for p in paths]
    ref = natives[0]
    for p, nat in zip(paths, natives, strict=True):
        if nat.units != ref.units:
            raise NeuralMapError(
                f"load_mosaic: '{p}' is in {nat.units} but '{paths[0]}' in {ref.units}; a "
                "mosaic needs one coordinate system. Reproject the files to one (gdalwarp)."
            )
        if not _same_datum(nat.crs, ref.crs):
            raise NeuralMapError(
                f"load_mosaic: '{p}' uses datum/CRS {crs_name(nat.crs)!r} but '{paths[0]}' "
                f"uses {crs_name(ref.crs)!r}; heights and positions would not match. "
                "Reproject the files to one CRS (gdalwarp -t_srs) first."
            )
        for axis in (0, 1):
            if not math.isclose(nat.step[axis], ref.step[axis], rel_tol=GRID_RTOL):
                unit = "°" if ref.units == "degrees" else " m"
                raise NeuralMapError(
                    f"load_mosaic: '{p}' has a node spacing of {nat.step[0]:.9g}{unit} x "
                    f"{nat.step[1]:.9g}{unit}, '{paths[0]}' {ref.step[0]:.9g}{unit} x "
                    f"{ref.step[1]:.9g}{unit}; tiles of a mosaic must share the spacing "
                    "(e.g. all SRTM 1″ or all 3″). Resample them to one spacing first."
                )
    step = ref.step
    first = (min(n.first[0] for n in natives), min(n.first[1] for n in natives))
    offsets: list[tuple[int, int]] = []
    for p, nat in zip(paths, natives, strict=True):
        pos = [(nat.first[a] - first[a]) / step[a] for a in (0, 1)]
        idx = [round(v) for v in pos]
        if any(abs(v - i) > 1e-3 for v, i in zip(pos, idx, strict=True)):
            raise NeuralMapError(
                f"load_mosaic: '{p}' is not on the common grid: its first node lies "
                f"{pos[0]:.4f} x {pos[1]:.4f} nodes from the mosaic corner (must be whole "
                "nodes). Resample the tiles onto one grid first."
            )
        offsets.append((idx[1], idx[0]))
    boxes = [(r, r + t.shape[0] - 1, c, c + t.shape[1] - 1)
             for (r, c), t in zip(offsets, (n.tile for n in natives), strict=True)]
    _check_connected(boxes, paths)
    shape = (max(b[1] for b in boxes) + 1, max(b[3] for b in boxes) + 1)
    return MosaicPlan([n.tile for n in natives], paths, offsets, shape, first, step,
                      ref.units, ref.crs)


def _touch(a: tuple[int, int, int, int], b: tuple[int, int, int, int]) -> bool:
    """Two node boxes share an edge (overlap, a shared row/column, or abut side by side)."""
    rows = min(a[1], b[1]) - max(a[0], b[0])  # >= 0: rows overlap
    cols = min(a[3], b[3]) - max(a[2], b[2])
    return (rows >= 0 and cols >= -1 and (rows > 0 or cols >= 0)) or (
        cols >= 0 and rows >= -1 and (cols > 0 or rows >= 0))


def _check_connected(boxes: list[tuple[int, int, int, int]], paths: list[Path]) -> None:
    """Refuses tiles that do not form one group of neighbours (a gap between them)."""
    seen, todo = {0}, [0]
    while todo:
        i = todo.pop()
        for j in range(len(boxes)):
            if j not in seen and _touch(boxes[i], boxes[j]):
                seen.add(j)
                todo.append(j)
    if len(seen) != len(boxes):
        apart = [str(paths[j]) for j in range(len(boxes)) if j not in seen]
        raise NeuralMapError(
            f"load_mosaic: tiles {apart} do not touch the group of '{paths[0]}' (not adjacent: "
            "there would be a gap of missing nodes between them). Add the tiles in between or "
            "load the groups separately."
        )


def stitch_into(plan: MosaicPlan, out: np.ndarray, tolerance_m: float) -> int:
    """Writes the tiles into ``out`` (NaN-filled), checking shared nodes; returns overlaps."""
    n_shared = 0
    filled = np.zeros(out.shape, dtype=bool)
    for tile, path, (r, c) in zip(plan.tiles, plan.paths, plan.offsets, strict=True):
        ny, nx = tile.shape
        window = out[r:r + ny, c:c + nx]
        had = filled[r:r + ny, c:c + nx]
        current = np.asarray(window, dtype=np.float64)
        new = tile.heights
        both = had & np.isfinite(current) & np.isfinite(new)
        if both.any():
            diff = np.abs(current[both] - new[both])
            worst = float(diff.max())
            if worst > tolerance_m:
                rows, cols = np.nonzero(both)
                k = int(np.argmax(diff))
                raise NeuralMapError(
                    f"load_mosaic: '{path}' overlaps an earlier tile and disagrees with it by "
                    f"up to {worst:.2f} m (mosaic node row {r + rows[k]}, column {c + cols[k]}; "
                    f"tolerance {tolerance_m} m). The tiles are from different surveys or "
                    "misplaced; drop one or raise tolerance_m."
                )
            n_shared += int(both.sum())
        take = ~had | ~np.isfinite(current)
        window[take] = new[take]
        filled[r:r + ny, c:c + nx] = True
    return n_shared


def projection_distortion(
    lon_range: tuple[float, float], lat_range: tuple[float, float]
) -> dict[str, Any]:
    """Distortion of the equirectangular frame about the centre of a lon/lat area.

    Args:
        lon_range: ``(west, east)`` degrees.
        lat_range: ``(south, north)`` degrees.

    Returns:
        ``name``, ``centre_deg``, ``max_scale_error_ew`` (``|cos φ/cos φ0 − 1|`` at the
        worse edge parallel, as N/N0 included), ``max_scale_error_ns``
        (``|M(φ)/M(φ0) − 1|``) and ``max_position_error_m`` (east-west corner offset).
    """
    lon0 = 0.5 * (lon_range[0] + lon_range[1])
    lat0 = 0.5 * (lat_range[0] + lat_range[1])
    m_lon0, m_lat0 = metres_per_degree(lat0)
    ew, ns, pos = 0.0, 0.0, 0.0
    half_lon = 0.5 * (lon_range[1] - lon_range[0])
    for lat in lat_range:
        m_lon, m_lat = metres_per_degree(lat)
        ew = max(ew, abs(m_lon0 / m_lon - 1.0)) if m_lon > 0 else math.inf
        ns = max(ns, abs(m_lat0 / m_lat - 1.0))
        pos = max(pos, abs(half_lon * (m_lon0 - m_lon)))
    return {
        "name": "equirectangular about the mosaic centre (WGS-84 radii at the centre latitude)",
        "centre_deg": [lon0, lat0],
        "max_scale_error_ew": ew,
        "max_scale_error_ns": ns,
        "max_position_error_m": pos,
    }


def mosaic_tile(plan: MosaicPlan, heights: np.ndarray, name: str, n_shared: int) -> DemTile:
    """The DemTile of a stitched mosaic in one metric frame."""
    ny, nx = plan.shape
    sources = ";".join(str(p) for p in plan.paths)
    meta: dict[str, Any] = {
        "format": "mosaic",
        "files": [str(p) for p in plan.paths],
        "offsets": [list(o) for o in plan.offsets],
        "n_shared_nodes": n_shared,
        "units": plan.units,
        "units_reason": "the files' own georeferencing (mosaic)",
        "crs": plan.crs,
    }
    if plan.units == "degrees":
        spacing, origin, geo = geographic_grid(plan.first[0], plan.first[1], plan.step[0],
                                               plan.step[1], (ny, nx), where="mosaic")
        lon_range = (plan.first[0], plan.first[0] + (nx - 1) * plan.step[0])
        lat_range = (plan.first[1], plan.first[1] + (ny - 1) * plan.step[1])
        meta["projection"] = projection_distortion(lon_range, lat_range)
        return DemTile(heights=heights, spacing=spacing, origin=origin, name=name, geo=geo,
                       source=sources, meta=meta)
    meta["projection"] = {"name": f"the files' own projected CRS ({crs_name(plan.crs)})",
                          "max_scale_error_ew": 0.0, "max_scale_error_ns": 0.0,
                          "max_position_error_m": 0.0}
    projected = ProjectedReference(x_offset=plan.first[0], y_offset=plan.first[1], crs=plan.crs)
    return DemTile(heights=heights, spacing=plan.step, origin=(0.0, 0.0), name=name,
                   source=sources, meta=meta, projected=projected)


def _available_memory() -> int | None:
    """Bytes of memory available to a new allocation (Linux ``MemAvailable``), or None."""
    try:
        with open("/proc/meminfo") as fh:
            for line in fh:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        return None
    return None


def load_mosaic(
    sources: str | Path | Sequence[str | Path],
    *,
    name: str | None = None,
    tolerance_m: float = 1.0,
    **load_options: Any,
) -> DemTile:
    """Stitches adjacent DEM files into one tile in one metric frame (held in memory).

    Args:
        sources: A glob (``"tiles/N36W08*.hgt"``), a path, or a list of paths/patterns.
        name: Tile name (default ``mosaic_<first file stem>_<n>``).
        tolerance_m: Largest allowed disagreement of shared/overlapping nodes, metres.
        **load_options: For `load_tile` (``units``, ``nodata``, ``height_check``).

    Returns:
        The mosaic (row 0 south, NaN voids); ``meta["projection"]`` describes the metric
        frame and its distortion over the area, ``meta["offsets"]`` where each file went.

    Raises:
        NeuralMapError: See `plan_mosaic`; overlapping tiles that disagree.
    """
    plan = plan_mosaic(sources, **load_options)
    need = 2 * 8 * plan.shape[0] * plan.shape[1]  # float64 heights and the tile's copy
    available = _available_memory()
    if available is not None and need > available:
        raise NeuralMapError(
            f"load_mosaic: the mosaic of {len(plan.paths)} tiles is {plan.shape[0]} x "
            f"{plan.shape[1]} nodes, about {need / 2**30:.1f} GiB in memory, but only "
            f"{available / 2**30:.1f} GiB are available. Write it to disk instead with "
            "write_mosaic(sources, 'area.npy') and train from the memory-mapped file."
        )
    heights = np.full(plan.shape, np.nan)
    n_shared = stitch_into(plan, heights, tolerance_m)
    label = name or f"mosaic_{plan.paths[0].stem}_{len(plan.paths)}"
    return mosaic_tile(plan, heights, label, n_shared)


def write_mosaic(
    sources: str | Path | Sequence[str | Path],
    out: str | Path,
    *,
    tolerance_m: float = 1.0,
    **load_options: Any,
) -> dict[str, Any]:
    """Stitches the files into a float32 ``.npy`` on disk (memory-mapped while writing).

    The heights go straight to the file (row 0 south, NaN voids), one tile in memory at a
    time, so the mosaic may be larger than RAM; it is refused when it would not fit on the
    disk. The returned dict (also written next to it as ``<out>.json``) holds the spacing
    and the georeference for `neuralmap.training.region.RegionData`.

    Raises:
        NeuralMapError: As `load_mosaic`; not enough disk space for the file.
    """
    import json

    out = Path(out)
    plan = plan_mosaic(sources, **load_options)
    ny, nx = plan.shape
    need = ny * nx * 4 + 128
    free = shutil.disk_usage(out.parent if out.parent.exists() else Path.cwd()).free
    if need + DISK_MARGIN_BYTES > free:
        raise NeuralMapError(
            f"write_mosaic: the mosaic of {len(plan.paths)} tiles is {ny} x {nx} nodes = "
            f"{need / 2**30:.2f} GiB as float32, but only {free / 2**30:.2f} GiB are free on "
            f"the disk of '{out}' (keeping {DISK_MARGIN_BYTES // 2**20} MiB spare). Free space, "
            "write elsewhere, or mosaic fewer tiles."
        )
    array = np.lib.format.open_memmap(out, mode="w+", dtype=np.float32, shape=(ny, nx))
    array[:] = np.nan
    n_shared = stitch_into(plan, array, tolerance_m)
    array.flush()
    del array
    small = mosaic_tile(plan, np.zeros((2, 2)), out.stem, n_shared)  # frame only
    reference = small.georeference
    info = {"path": str(out), "shape": [ny, nx], "spacing": list(small.spacing),
            "georeference": None if reference is None else reference.describe(),
            "meta": small.meta}
    Path(str(out) + ".json").write_text(json.dumps(info, indent=1, default=str))
    return info
