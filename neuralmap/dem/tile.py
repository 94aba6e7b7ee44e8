"""The DEM tile: heights on a regular metric east-north grid."""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from neuralmap.exceptions import NeuralMapError


def broadcast_pair(value: Any, what: str, where: str) -> tuple[float, float]:
    """Broadcasts a scalar or length-2 value to a float pair, or raises NeuralMapError.

    Args:
        value: A number or a pair.
        what: Name of the value, for the message (e.g. ``"spacing"``).
        where: Where it came from (file, function), for the message.
    """
    try:
        arr = np.broadcast_to(np.asarray(value, dtype=np.float64), (2,))
    except (TypeError, ValueError) as exc:
        raise NeuralMapError(
            f"{where}: {what} must be one number or a pair, got {value!r}."
        ) from exc
    return float(arr[0]), float(arr[1])


@dataclass(frozen=True)
class GeoReference:
    """How a geographic (lon/lat degrees) grid was converted to local metres.

    Equirectangular projection about the tile centre:
    ``x = x0 + (lon - lon0) * m_per_deg_lon``, ``y = y0 + (lat - lat0) * m_per_deg_lat``,
    where ``(x0, y0)`` are the tile-frame metric coordinates of the centre ``(lon0, lat0)``
    (so ``to_metric`` lands in the same frame as ``DemTile.node_xy()``). The Earth model
    (``neuralmap.dem.geo``: WGS-84 radii of curvature at ``lat0``) is named in ``model``.

    Attributes:
        lon0: Longitude of the projection centre, degrees.
        lat0: Latitude of the projection centre, degrees.
        m_per_deg_lon: Metres per degree of longitude at ``lat0``.
        m_per_deg_lat: Metres per degree of latitude at ``lat0``.
        x0: Metric x of ``(lon0, lat0)`` in the tile frame (0 for a centred frame).
        y0: Metric y of ``(lon0, lat0)`` in the tile frame.
        model: Human-readable Earth model used for the metres-per-degree factors.
    """

    lon0: float
    lat0: float
    m_per_deg_lon: float
    m_per_deg_lat: float
    x0: float = 0.0
    y0: float = 0.0
    model: str = ""

    def to_metric(self, lon: np.ndarray, lat: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Converts degrees to tile-frame metres (x east, y north); any matching shapes."""
        return self.x0 + (np.asarray(lon) - self.lon0) * self.m_per_deg_lon, self.y0 + (
            np.asarray(lat) - self.lat0
        ) * self.m_per_deg_lat

    def to_geographic(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Converts tile-frame metres back to degrees (lon, lat); inverse of ``to_metric``."""
        return self.lon0 + (np.asarray(x) - self.x0) / self.m_per_deg_lon, self.lat0 + (
            np.asarray(y) - self.y0
        ) / self.m_per_deg_lat

    def describe(self) -> dict[str, Any]:
        """JSON-serialisable summary (all fields)."""
        return {
            "lon0": self.lon0,
            "lat0": self.lat0,
            "m_per_deg_lon": self.m_per_deg_lon,
            "m_per_deg_lat": self.m_per_deg_lat,
            "x0": self.x0,
            "y0": self.y0,
            "model": self.model,
        }


@dataclass(frozen=True)
class ProjectedReference:
    """Where a metric (projected) tile sits in its source coordinate system.

    Tiles work in a tile-local frame (node ``[0, 0]`` near ``(0, 0)``): float32 coordinates
    near a UTM northing of 4e6 m round to 0.25–0.5 m, which is larger than the slope
    signal a terrain-aided filter lives on. The file's absolute coordinates are kept here
    as metadata only: ``easting = x_offset + x`` and ``northing = y_offset + y`` for
    tile-frame ``(x, y)``, in float64.

    Attributes:
        x_offset: Source-system x (easting) of the tile-frame point ``(0, 0)``, metres.
        y_offset: Source-system y (northing) of the tile-frame point ``(0, 0)``, metres.
        crs: The source coordinate reference system as text that rasterio and pyproj
            read back (the ``.prj`` sidecar's WKT, the GeoTIFF's CRS as ``EPSG:<code>`` or
            WKT), or ``None`` when the file names none; `neuralmap.dem.geo.crs_name` gives
            its name for messages.
    """

    x_offset: float
    y_offset: float
    crs: str | None = None

    def to_projected(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Tile-frame metres to the file's absolute coordinates (float64, any shapes)."""
        return (np.asarray(x, dtype=np.float64) + self.x_offset,
                np.asarray(y, dtype=np.float64) + self.y_offset)

    def to_tile(self, easting: np.ndarray, northing: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The file's absolute coordinates to tile-frame metres; inverse of ``to_projected``."""
        return (np.asarray(easting, dtype=np.float64) - self.x_offset,
                np.asarray(northing, dtype=np.float64) - self.y_offset)

    def describe(self) -> dict[str, Any]:
        """JSON-serialisable summary (all fields)."""
        return {"x_offset": self.x_offset, "y_offset": self.y_offset, "crs": self.crs}


@dataclass
class DemTile:
    """Heights on a regular grid in a local east-north metric frame.

    Node ``heights[i, j]`` lies at ``x = origin[0] + j * spacing[0]`` (east) and
    ``y = origin[1] + i * spacing[1]`` (north): row 0 is the southernmost row.

    Attributes:
        heights: ``(ny, nx)`` float64 heights in metres; voids are NaN.
        spacing: ``(dx, dy)`` grid spacing in metres, both finite and > 0.
        origin: ``(x0, y0)`` metric coordinates of node ``[0, 0]``.
        name: Short name used in run folders and map exports.
        geo: The geographic-to-metric conversion, when the source was geographic.
        source: Where the tile came from (path or sample name).
        meta: Reader details (format, no-data value, units decision and its reason, ...).
        projected: The absolute (projected) position of the tile frame, when the source was
            a metric grid with its own coordinates (kept as metadata; the tile frame stays
            local).
    """

    heights: np.ndarray
    spacing: tuple[float, float]
    origin: tuple[float, float] = (0.0, 0.0)
    name: str = "tile"
    geo: GeoReference | None = None
    source: str = ""
    meta: dict[str, Any] = field(default_factory=dict)
    projected: ProjectedReference | None = None

    def __post_init__(self) -> None:
        heights = np.asarray(self.heights, dtype=np.float64)
        where = f"tile '{self.name}'" + (f" ({self.source})" if self.source else "")
        if heights.ndim != 2:
            raise NeuralMapError(
                f"{where}: heights must be a 2-D array (rows = north, columns = east), "
                f"got shape {heights.shape}. Pass a single-band grid."
            )
        if heights.shape[0] < 2 or heights.shape[1] < 2:
            raise NeuralMapError(
                f"{where}: heights need at least 2 x 2 nodes, got {heights.shape}."
            )
        spacing = tuple(float(s) for s in np.broadcast_to(np.asarray(self.spacing, float), (2,)))
        if not all(np.isfinite(s) and s > 0 for s in spacing):
            raise NeuralMapError(
                f"{where}: grid spacing must be finite and > 0 metres, got {spacing}. "
                "Set it in the reader options: load_tile(path, spacing=30), --data.spacing 30 "
                "for train.py, or tile_options: {spacing: 30} in a scenario YAML."
            )
        origin = tuple(float(o) for o in np.broadcast_to(np.asarray(self.origin, float), (2,)))
        if not all(np.isfinite(o) for o in origin):
            raise NeuralMapError(f"{where}: origin must be finite, got {origin}.")
        heights = np.where(np.isfinite(heights), heights, np.nan)
        if not np.isfinite(heights).any():
            raise NeuralMapError(
                f"{where}: every node is void (NaN / no-data); there is nothing to fit. "
                "Check the file's no-data value or pick another tile."
            )
        self.heights = heights
        self.spacing = spacing  # type: ignore[assignment]
        self.origin = origin  # type: ignore[assignment]

    @property
    def shape(self) -> tuple[int, int]:
        """``(ny, nx)`` node counts."""
        return self.heights.shape  # type: ignore[return-value]

    @property
    def valid_mask(self) -> np.ndarray:
        """``(ny, nx)`` bool, True where the height is not void."""
        return np.isfinite(self.heights)

    @property
    def n_void(self) -> int:
        """Number of void (NaN) nodes."""
        return int((~self.valid_mask).sum())

    @property
    def extent(self) -> tuple[float, float, float, float]:
        """``(xmin, xmax, ymin, ymax)`` metric bounds of the node grid."""
        ny, nx = self.shape
        x0, y0 = self.origin
        dx, dy = self.spacing
        return (x0, x0 + (nx - 1) * dx, y0, y0 + (ny - 1) * dy)

    @property
    def georeference(self) -> GeoReference | ProjectedReference | None:
        """Where the tile frame lies on Earth: ``geo`` (lon/lat sources) or ``projected``."""
        return self.geo if self.geo is not None else self.projected

    def void_under(self, xy: np.ndarray, *, halo: int = 0) -> np.ndarray:
        """Whether interpolating the tile at points touches a void node.

        A point inside cell ``(i, j)`` (nodes ``i..i+1``, ``j..j+1``) is over a void when
        any of the cell's 4 corner nodes is void (what bilinear interpolation reads), or,
        with ``halo = 1``, any node of the 4 x 4 neighbourhood (what bicubic reads). Points
        outside the node extent (or not finite) are reported False: off-tile is a
        separate condition (see ``extent``). Vectorised over any leading shape.

        Args:
            xy: ``(..., 2)`` tile-frame metres.
            halo: Extra nodes around the cell (0 = bilinear support, 1 = bicubic).

        Returns:
            ``(...)`` bool, True where the interpolated height depends on a void node.
        """
        xy = np.asarray(xy, dtype=np.float64)
        if xy.shape[-1:] != (2,):
            raise NeuralMapError(f"void_under: xy must have shape (..., 2), got {xy.shape}.")
        if halo < 0:
            raise NeuralMapError(f"void_under: halo must be >= 0, got {halo}.")
        ny, nx = self.shape
        void = ~self.valid_mask
        # cell (i, j) touches a void when any node in rows i-halo..i+1+halo, cols likewise
        pad = np.pad(void, halo + 1, constant_values=False)
        size = 2 + 2 * halo
        windows = np.lib.stride_tricks.sliding_window_view(pad, (size, size))
        cell_void = windows.any(axis=(-2, -1))[1 : ny, 1 : nx]  # (ny - 1, nx - 1)
        u = (xy[..., 0] - self.origin[0]) / self.spacing[0]
        v = (xy[..., 1] - self.origin[1]) / self.spacing[1]
        inside = np.isfinite(u) & np.isfinite(v) & (u >= 0) & (v >= 0) & (u <= nx - 1) & (
            v <= ny - 1
        )
        j = np.clip(np.floor(np.where(inside, u, 0.0)), 0, nx - 2).astype(np.int64)
        i = np.clip(np.floor(np.where(inside, v, 0.0)), 0, ny - 2).astype(np.int64)
        return inside & cell_void[i, j]

    def node_xy(self) -> np.ndarray:
        """Metric coordinates of every node.

        Returns:
            ``(ny, nx, 2)`` float64 array of ``(x, y)`` in metres.
        """
        ny, nx = self.shape
        x = self.origin[0] + np.arange(nx) * self.spacing[0]
        y = self.origin[1] + np.arange(ny) * self.spacing[1]
        xx, yy = np.meshgrid(x, y)
        return np.stack([xx, yy], axis=-1)

    def fingerprint(self) -> str:
        """Short content hash of heights, spacing and origin; identifies the tile in exports."""
        digest = hashlib.sha256()
        digest.update(np.ascontiguousarray(np.nan_to_num(self.heights, nan=-1e30)).tobytes())
        digest.update(np.asarray(self.spacing + self.origin, dtype=np.float64).tobytes())
        digest.update(str(self.shape).encode())
        if self.projected is not None:  # same heights elsewhere on Earth: another tile
            digest.update(
                np.asarray([self.projected.x_offset, self.projected.y_offset]).tobytes()
            )
        return digest.hexdigest()[:16]

    def describe(self) -> dict[str, Any]:
        """Summary recorded in exports and reports (JSON-serialisable)."""
        return {
            "name": self.name,
            "source": self.source,
            "shape": list(self.shape),
            "spacing": list(self.spacing),
            "origin": list(self.origin),
            "extent": list(self.extent),
            "fingerprint": self.fingerprint(),
            "n_void": self.n_void,
            "height_range": [float(np.nanmin(self.heights)), float(np.nanmax(self.heights))],
            "geo": None if self.geo is None else self.geo.describe(),
            "projected": None if self.projected is None else self.projected.describe(),
            "crs": self.meta.get("crs"),
            "units": self.meta.get("units"),
            "units_reason": self.meta.get("units_reason"),
        }
