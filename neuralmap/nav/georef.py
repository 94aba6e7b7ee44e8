"""The map frame on the Earth: tile-frame metres <-> WGS-84 latitude/longitude.

Every `DemTile` works in a tile-local east-north metric frame;
its georeference says where that frame lies:

- `GeoReference` (a lon/lat source): the frame *is* the
  equirectangular projection about the tile centre on the WGS-84 ellipsoid
  (`neuralmap.dem.geo`), ``x = x0 + (lon − lon0)·m_lon``, ``y = y0 + (lat − lat0)·m_lat``.
  Both directions are closed forms, exact inverses of each other.
- `ProjectedReference` (a metric source with a CRS): the frame is
  the file's projected CRS shifted to a local origin; lat/lon go through pyproj
  (``EPSG:4326`` <-> the file's CRS, ``always_xy``) and the offset. pyproj is optional:
  ``pip install 'neuralmap[nav]'``.

Heights are not converted here: the vertical datum is handled by
`neuralmap.nav.vertical_datum`.
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
            try:
                from pyproj import CRS, Transformer
            except ImportError as exc:
                raise NeuralMapError(
                    f"map '{name}' is in the projected CRS {reference.crs!r}; converting "
                    "latitude/longitude needs pyproj, which is not installed. Install it "
                    "with pip install 'neuralmap[nav]' (or pip install pyproj).") from exc
            try:
                crs = CRS.from_user_input(reference.crs)
            except Exception as exc:  # noqa: BLE001 - pyproj raises CRSError and friends
                raise NeuralMapError(
                    f"map '{name}': pyproj does not understand the CRS {reference.crs!r} "
                    f"({exc}); give the file an EPSG code (gdal_edit.py -a_srs).") from None
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

    @classmethod
    def from_tile_info(cls, info: dict[str, Any]) -> MapFrame:
        """The map frame from a `DemTile.describe` dict (as a map file records it).

        Raises:
            NeuralMapError: The dict holds neither ``geo`` nor ``projected``.
        """
        name = str(info.get("name") or "map")
        geo, projected = info.get("geo"), info.get("projected")
        if isinstance(geo, dict):
            return cls(GeoReference(**geo), name=name)
        if isinstance(projected, dict):
            return cls(ProjectedReference(**projected), name=name)
        return cls(None, name=name)

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
