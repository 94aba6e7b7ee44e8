"""A study's trajectories as CSV and GeoJSON in the source DEM's frame (for QGIS & co.).

``trajectories.csv`` holds one row per run, track and step: the tile-frame ``x, y`` (m)
and the same point in the source DEM's coordinates (``easting, northing`` of a projected
tile, ``lon, lat`` of a geographic one; none for a tile without a georeference), plus
the height. ``trajectories.geojson`` holds one LineString per run and track in WGS-84
lon/lat (RFC 7946; a projected tile's points are transformed with rasterio from its CRS),
written only for georeferenced tiles. Tracks are ``truth``, ``ins`` and each filter's
estimate; the first `TRACK_RUNS` runs are written.
"""

from __future__ import annotations

import csv
import io as _io
from pathlib import Path
from typing import Any

import numpy as np

from neuralmap.dem.tile import DemTile
from neuralmap.exceptions import NeuralMapError
from neuralmap.io import atomic_write_json, atomic_write_text

__all__ = ["TRACK_RUNS", "source_coordinates", "write_trajectories"]

#: Runs written (the first ones): 20 runs × 5 tracks × 600 steps is about 4 MB of CSV.
TRACK_RUNS = 20


def source_coordinates(tile: DemTile, xy: np.ndarray) -> tuple[tuple[str, str] | None,
                                                                np.ndarray | None]:
    """Tile-frame ``xy (..., 2)`` in the source DEM's coordinates.

    Returns:
        ``((name_x, name_y), coordinates (..., 2))``: ``("lon", "lat")`` for a geographic
        tile, ``("easting", "northing")`` for a projected one; ``(None, None)`` without a
        georeference.
    """
    xy = np.asarray(xy, dtype=np.float64)
    if tile.geo is not None:
        lon, lat = tile.geo.to_geographic(xy[..., 0], xy[..., 1])
        return ("lon", "lat"), np.stack([lon, lat], axis=-1)
    if tile.projected is not None:
        e, n = tile.projected.to_projected(xy[..., 0], xy[..., 1])
        return ("easting", "northing"), np.stack([e, n], axis=-1)
    return None, None


def _wgs84(tile: DemTile, coords: np.ndarray) -> np.ndarray | None:
    """Source coordinates ``(M, 2)`` as lon/lat degrees (None when not possible)."""
    if tile.geo is not None:
        return coords
    crs = tile.projected.crs if tile.projected is not None else None
    if not crs:
        return None
    try:  # rasterio is the optional `geotiff` extra: without it, no lon/lat
        from rasterio.warp import transform
    except ImportError:
        return None
    try:
        lon, lat = transform(crs, "EPSG:4326", coords[:, 0].tolist(), coords[:, 1].tolist())
    except Exception:  # an unknown CRS text: no GeoJSON rather than a wrong one
        return None
    return np.column_stack([lon, lat])


def write_trajectories(out_dir: str | Path, tile: DemTile, t: np.ndarray,
                       tracks: dict[str, np.ndarray], *, runs: int = TRACK_RUNS) -> dict[str, Path]:
    """Writes ``trajectories.csv`` (and ``trajectories.geojson`` when georeferenced).

    Args:
        out_dir: The study's output folder.
        tile: The scenario's tile (its georeference gives the source frame).
        t: ``(K,)`` times (s).
        tracks: Track name -> ``(N, K, 2 or 3)`` tile-frame ``x, y[, h]`` (m).
        runs: Runs to write (the first ones).

    Returns:
        File kind -> path.

    Raises:
        NeuralMapError: Tracks of different shapes or not matching ``t``.
    """
    t = np.asarray(t, dtype=np.float64)
    arrays = {name: np.asarray(v, dtype=np.float64)[:runs] for name, v in tracks.items()}
    shapes = {name: a.shape[:2] for name, a in arrays.items()}
    if len(set(shapes.values())) > 1 or any(s[1] != t.shape[0] for s in shapes.values()):
        raise NeuralMapError(f"write_trajectories: tracks {shapes} must share (runs, {t.shape[0]}).")
    out_dir = Path(out_dir)
    buffer = _io.StringIO()
    first = next(iter(arrays.values()))
    names, _ = source_coordinates(tile, first[0, :1, :2])
    header = ["track", "run", "step", "t_s", "x_m", "y_m", "h_m", *(names or ())]
    writer = csv.writer(buffer, lineterminator="\n")
    writer.writerow(header)
    features: list[dict[str, Any]] = []
    for name, values in arrays.items():
        n_runs, k = values.shape[:2]
        _, src = source_coordinates(tile, values[..., :2])
        h = values[..., 2] if values.shape[-1] > 2 else np.full((n_runs, k), np.nan)
        for run in range(n_runs):
            cols = [np.full(k, run), np.arange(k), t, values[run, :, 0], values[run, :, 1],
                    h[run]]
            if src is not None:
                cols += [src[run, :, 0], src[run, :, 1]]
            for row in zip(*cols, strict=True):
                writer.writerow([name, int(row[0]), int(row[1]),
                                 *(repr(float(v)) if v == v else "" for v in row[2:])])
            lonlat = _wgs84(tile, src[run]) if src is not None else None
            if lonlat is not None:
                features.append({
                    "type": "Feature",
                    "properties": {"track": name, "run": run},
                    "geometry": {"type": "LineString",
                                 "coordinates": [[float(a), float(b)] for a, b in lonlat]},
                })
    paths = {"csv": atomic_write_text(out_dir / "trajectories.csv", buffer.getvalue())}
    if features:
        paths["geojson"] = atomic_write_json(out_dir / "trajectories.geojson",
                                             {"type": "FeatureCollection", "features": features})
    return paths
