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
    """

    heights: np.ndarray
    spacing: tuple[float, float]
    origin: tuple[float, float] = (0.0, 0.0)
    name: str = "tile"
    geo: GeoReference | None = None
    source: str = ""
    meta: dict[str, Any] = field(default_factory=dict)

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
                "Set it in the reader options (e.g. --data.spacing 30)."
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
        }
