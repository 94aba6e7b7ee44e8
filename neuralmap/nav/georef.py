"""The map frame on the Earth: tile-frame metres <-> WGS-84 latitude/longitude.

Every `DemTile` works in a tile-local east-north metric frame;
its georeference says where that frame lies:

- `GeoReference` (a lon/lat source): the frame *is* the
  equirectangular projection about the tile centre on the WGS-84 ellipsoid
  (`neuralmap.dem.geo`), ``x = x0 + (lon − lon0)·m_lon``, ``y = y0 + (lat − lat0)·m_lat``.
  Both directions are closed forms, exact inverses of each other; longitudes are taken
  modulo 360° about ``lon0`` (a map across the antimeridian) and returned in [−180, 180).
- `ProjectedReference` (a metric source with a CRS): the frame is
  the file's projected CRS shifted to a local origin; lat/lon go through pyproj
  (``EPSG:4326`` <-> the file's CRS, ``always_xy``) and the offset. pyproj is optional:
  ``pip install 'neuralmap[nav]'``.

Heights are not converted here: the vertical datum is handled by
`neuralmap.flights.vertical_datum`.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from neuralmap.dem.tile import DemTile, GeoReference, ProjectedReference
from neuralmap.exceptions import NeuralMapError

__all__ = ["MapFrame"]

#: Geographic CRS of latitude/longitude inputs and outputs.
WGS84_CRS = "EPSG:4326"


def _as_float64(value: Any) -> tuple[np.ndarray, Any]:
    """``value`` as a float64 array, and a function that turns results back into its type."""
    if isinstance(value, torch.Tensor):
        dtype = value.dtype if value.is_floating_point() else torch.float64
        device = value.device
        array = value.detach().cpu().to(torch.float64).numpy()
        return array, lambda a: torch.as_tensor(a, dtype=dtype, device=device)
    array = np.asarray(value, dtype=np.float64)
    if array.ndim == 0:
        return array, lambda a: float(a)
    return array, lambda a: a


class MapFrame:
    """Converts between a tile's map frame and WGS-84 latitude/longitude (vectorised).

    Args:
        reference: The tile's georeference (``tile.georeference``).
        name: Tile name, for messages.

    Raises:
        NeuralMapError: No georeference, a projected reference without a CRS, or pyproj
            missing for a projected reference (names the extra to install).

    Example::

        frame = MapFrame.from_tile(load_tile("jacksboro"))
        x, y = frame.to_map(lat, lon)          # degrees -> tile-frame metres
        lat2, lon2 = frame.to_geo(x, y)        # and back
    """

    def __init__(self, reference: GeoReference | ProjectedReference | None, *,
                 name: str = "map") -> None:
        self.name = name
        if reference is None:
            raise NeuralMapError(
                f"map '{name}' has no georeference (neither a lon/lat grid nor a projected "
                "CRS), so latitude/longitude cannot be placed on it. Give a map-frame log "
                "(columns time, ins_x, ins_y, ins_h, radar) or a georeferenced DEM "
                "(GeoTIFF with a CRS, .asc with a .prj, .hgt).")
        self.reference = reference
        self._to_crs: Any = None
        self._from_crs: Any = None
        if isinstance(reference, ProjectedReference):
            if not reference.crs:
                raise NeuralMapError(
                    f"map '{name}' is a metric grid without a named CRS (no .prj / GeoTIFF "
                    "CRS), so latitude/longitude cannot be converted to it. Add the CRS to "
                    "the file (gdal_edit.py -a_srs EPSG:<code>) or give a map-frame log.")
            from neuralmap.dem.geo import pyproj_crs

            crs = pyproj_crs(reference.crs, f"map '{name}'")  # WKT, EPSG code or a CRS name
            from pyproj import Transformer

            self._to_crs = Transformer.from_crs(WGS84_CRS, crs, always_xy=True)
            self._from_crs = Transformer.from_crs(crs, WGS84_CRS, always_xy=True)
        elif not isinstance(reference, GeoReference):
            raise NeuralMapError(
                f"MapFrame: reference must be a GeoReference or ProjectedReference, got "
                f"{type(reference).__name__}.")

    @classmethod
    def from_tile(cls, tile: DemTile) -> MapFrame:
        """The map frame of a DEM tile (its ``geo`` or ``projected`` reference)."""
        return cls(tile.georeference, name=tile.name)

    @property
    def kind(self) -> str:
        """``"equirectangular"`` (lon/lat source) or ``"projected"``."""
        return "equirectangular" if isinstance(self.reference, GeoReference) else "projected"

    def to_map(self, lat: Any, lon: Any) -> tuple[Any, Any]:
        """Latitude/longitude (degrees, WGS-84) to map-frame ``(x, y)`` metres.

        Args:
            lat: ``(...)`` latitudes; NumPy array, torch tensor or float.
            lon: ``(...)`` longitudes, same shape.

        Returns:
            ``(x, y)`` east/north metres in the tile frame, of the input's type (torch:
            same dtype and device; computed in float64).
        """
        lat_a, back = _as_float64(lat)
        lon_a, _ = _as_float64(lon)
        if isinstance(self.reference, GeoReference):
            # longitudes wrapped to [−180, 180) unwrap about the map's centre, so a map that
            # crosses the antimeridian takes both −179.9° and 180.1° for the same place
            lon0 = self.reference.lon0
            lon_a = lon0 + np.mod(lon_a - lon0 + 180.0, 360.0) - 180.0
            x, y = self.reference.to_metric(lon_a, lat_a)
        else:
            east, north = self._to_crs.transform(lon_a, lat_a)
            x, y = self.reference.to_tile(np.asarray(east), np.asarray(north))
        return back(np.asarray(x, dtype=np.float64)), back(np.asarray(y, dtype=np.float64))

    def to_geo(self, x: Any, y: Any) -> tuple[Any, Any]:
        """Map-frame ``(x, y)`` metres to ``(lat, lon)`` degrees (WGS-84); inverse of
        `to_map`, same types and shapes."""
        x_a, back = _as_float64(x)
        y_a, _ = _as_float64(y)
        if isinstance(self.reference, GeoReference):
            lon, lat = self.reference.to_geographic(x_a, y_a)
            lon = np.mod(np.asarray(lon) + 180.0, 360.0) - 180.0  # WGS-84 longitudes in [−180, 180)
        else:
            east, north = self.reference.to_projected(x_a, y_a)
            lon, lat = self._from_crs.transform(east, north)
        return back(np.asarray(lat, dtype=np.float64)), back(np.asarray(lon, dtype=np.float64))

    def describe(self) -> dict[str, Any]:
        """JSON-serialisable summary: kind, the reference's fields, the geographic CRS."""
        return {"kind": self.kind, "geographic_crs": WGS84_CRS,
                **self.reference.describe()}

    def __repr__(self) -> str:
        return f"MapFrame({self.name!r}, {self.kind})"
