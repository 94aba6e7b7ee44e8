"""Geographic (lon/lat degrees) to local metric grids: Earth model and the equirectangular map.

Earth model: the WGS-84 ellipsoid (semi-major axis ``a = 6378137 m``, flattening
``f = 1/298.257223563``). A degree of latitude is ``M(φ0)·π/180`` metres and a degree of
longitude ``N(φ0)·cos φ0·π/180`` metres, with the meridian and prime-vertical radii of curvature
``M = a(1-e²)/(1-e² sin²φ)^{3/2}`` and ``N = a/(1-e² sin²φ)^{1/2}`` taken at the tile's
centre latitude ``φ0`` (equirectangular projection with standard parallel ``φ0``). The
east-west scale of this flat local frame is exact on the centre parallel and off by about
``tan φ0 · Δφ`` at a parallel ``Δφ`` (radians) away: 0.64 % at the edge of a 1° tile at
36.5° N, 0.05 % at the edge of the 0.29° jacksboro tile. North-south scale errors stay
below 1e-4. Heights are unchanged.
"""

from __future__ import annotations

import math
import re
from typing import Any

from neuralmap.dem.tile import GeoReference
from neuralmap.exceptions import NeuralMapError

#: WGS-84 semi-major axis, metres.
WGS84_A = 6378137.0
#: WGS-84 flattening.
WGS84_F = 1.0 / 298.257223563
#: WGS-84 first eccentricity squared, ``e² = f(2 - f)``.
WGS84_E2 = WGS84_F * (2.0 - WGS84_F)
#: Description stored in ``GeoReference.model``.
EARTH_MODEL = "WGS-84 ellipsoid, radii of curvature M, N at the centre latitude"


#: The CRS of SRTM ``.hgt`` tiles (WGS-84 lon/lat), as rasterio and pyproj read it.
SRTM_CRS = "EPSG:4326"
#: The CRS name SRTM mosaics recorded before they kept `SRTM_CRS`.
LEGACY_SRTM_CRS = "WGS 84 (SRTM)"

_WKT_NAME = re.compile(r'^\s*[A-Z_]+\s*\[\s*"([^"]*)"')


def crs_name(crs: str | None) -> str | None:
    """A short name of a CRS text for messages: the name of a WKT (``PROJCS["WGS 84 / UTM
    zone 16N", ...]`` gives ``WGS 84 / UTM zone 16N``), else the text itself (``EPSG:32616``).
    """
    if crs is None:
        return None
    match = _WKT_NAME.match(crs)
    return match.group(1) if match else crs


def pyproj_crs(crs: str, where: str) -> Any:
    """A CRS text as a `pyproj.CRS`: WKT, ``EPSG:<code>``, or only a CRS *name*.

    Tiles read before the readers kept the ``.prj`` WKT (and ``.prj`` files whose WKT is
    incomplete) record a name such as ``"WGS 84 / UTM zone 16N"``; pyproj looks it up in
    its database. ``"WGS 84 (SRTM)"``, the name SRTM mosaics recorded, is `SRTM_CRS`.

    Args:
        crs: The CRS text a tile records.
        where: What records it, for the messages (``"GeoTIFF export"``, ``"map 'x'"``).

    Raises:
        NeuralMapError: pyproj missing (the ``nav`` extra), or a text that is neither a CRS
            nor a name pyproj knows, with the fix.
    """
    try:
        import pyproj
    except ImportError:
        raise NeuralMapError(
            f"{where}: the CRS {crs_name(crs)!r} has to be turned into a CRS by pyproj, which "
            "is not installed. Install it with pip install 'neuralmap[nav]' (pyproj and "
            "rasterio), or give the DEM with its full CRS (a GeoTIFF with a CRS, an .asc "
            "whose .prj holds the WKT)."
        ) from None
    for text in dict.fromkeys((crs, crs_name(crs))):
        text = SRTM_CRS if text == LEGACY_SRTM_CRS else text
        try:
            return pyproj.CRS.from_user_input(text)
        except pyproj.exceptions.CRSError:
            continue
    raise NeuralMapError(
        f"{where}: the CRS {crs_name(crs)!r} is neither WKT, an EPSG code nor a CRS name "
        "pyproj knows. Give the DEM with its full CRS: a GeoTIFF with a CRS, or an .asc whose "
        ".prj holds the WKT (gdalsrsinfo -o wkt1 EPSG:<code> > file.prj)."
    )


def metres_per_degree(lat_deg: float) -> tuple[float, float]:
    """Metres per degree of longitude and of latitude at a latitude (WGS-84).

    Args:
        lat_deg: Geodetic latitude in degrees, within ``[-90, 90]``.

    Returns:
        ``(m_per_deg_lon, m_per_deg_lat) = (N cos φ · π/180, M · π/180)``.

    Raises:
        NeuralMapError: If the latitude is not finite or outside ``[-90, 90]``.
    """
    if not (math.isfinite(lat_deg) and -90.0 <= lat_deg <= 90.0):
        raise NeuralMapError(
            f"latitude must be a finite number in [-90, 90] degrees, got {lat_deg!r}; "
            "check the file's georeferencing (is it really geographic?)."
        )
    phi = math.radians(lat_deg)
    w = 1.0 - WGS84_E2 * math.sin(phi) ** 2
    m_radius = WGS84_A * (1.0 - WGS84_E2) / w**1.5
    n_radius = WGS84_A / math.sqrt(w)
    rad = math.pi / 180.0
    return n_radius * math.cos(phi) * rad, m_radius * rad


def geographic_reference(lon0: float, lat0: float) -> GeoReference:
    """Equirectangular projection about ``(lon0, lat0)``, the centre at metric ``(0, 0)``.

    Args:
        lon0: Centre longitude, degrees.
        lat0: Centre latitude, degrees (sets the metres-per-degree factors, WGS-84).

    Returns:
        The `GeoReference` with ``x0 = y0 = 0``.
    """
    m_lon, m_lat = metres_per_degree(lat0)
    return GeoReference(
        lon0=float(lon0), lat0=float(lat0), m_per_deg_lon=m_lon, m_per_deg_lat=m_lat,
        model=EARTH_MODEL,
    )


def geographic_grid(
    lon_first: float,
    lat_first: float,
    dlon: float,
    dlat: float,
    shape: tuple[int, int],
    *,
    origin: tuple[float, float] | None = None,
    where: str = "grid",
) -> tuple[tuple[float, float], tuple[float, float], GeoReference]:
    """Metric spacing, origin and georeference of a regular lon/lat node grid.

    The grid's node ``[i, j]`` (row 0 south) lies at ``lon = lon_first + j·dlon``,
    ``lat = lat_first + i·dlat``. The equirectangular projection is centred on the middle of
    the grid; the metric frame puts node ``[0, 0]`` at ``origin`` (default ``(0, 0)``).

    Args:
        lon_first: Longitude of node ``[0, 0]`` (south-west node), degrees.
        lat_first: Latitude of node ``[0, 0]``, degrees.
        dlon: Node spacing in longitude, degrees (> 0).
        dlat: Node spacing in latitude, degrees (> 0).
        shape: ``(ny, nx)`` node counts.
        origin: Metric coordinates of node ``[0, 0]``; None gives ``(0, 0)``.
        where: Name of the source, for error messages.

    Returns:
        ``(spacing_m, origin_m, geo)``: ``(dx, dy)`` in metres, ``(x0, y0)``, and the
        `GeoReference` whose ``to_metric`` maps degrees into this tile frame.

    Raises:
        NeuralMapError: On non-finite or non-positive degree spacing or a grid that leaves
            the valid latitude range.
    """
    if not all(math.isfinite(v) for v in (lon_first, lat_first, dlon, dlat)) or min(
        dlon, dlat
    ) <= 0.0:
        raise NeuralMapError(
            f"{where}: geographic grid needs finite corner coordinates and spacing > 0 degrees, "
            f"got lon={lon_first}, lat={lat_first}, dlon={dlon}, dlat={dlat}."
        )
    ny, nx = shape
    lat_last = lat_first + (ny - 1) * dlat
    if lat_first < -90.0 or lat_last > 90.0:
        raise NeuralMapError(
            f"{where}: latitudes {lat_first:.6f}..{lat_last:.6f} leave [-90, 90]; the file's "
            "coordinates are probably not geographic degrees (pass geographic=False)."
        )
    lon0 = lon_first + 0.5 * (nx - 1) * dlon
    lat0 = lat_first + 0.5 * (ny - 1) * dlat
    m_lon, m_lat = metres_per_degree(lat0)
    spacing = (dlon * m_lon, dlat * m_lat)
    origin_m = (0.0, 0.0) if origin is None else (float(origin[0]), float(origin[1]))
    geo = GeoReference(
        lon0=lon0,
        lat0=lat0,
        m_per_deg_lon=m_lon,
        m_per_deg_lat=m_lat,
        x0=origin_m[0] + 0.5 * (nx - 1) * spacing[0],
        y0=origin_m[1] + 0.5 * (ny - 1) * spacing[1],
        model=EARTH_MODEL,
    )
    return spacing, origin_m, geo


#: Accepted spellings of the two coordinate units of a grid file.
UNIT_NAMES = {"metres": "metres", "meters": "metres", "metre": "metres", "meter": "metres",
              "m": "metres", "degrees": "degrees", "degree": "degrees", "deg": "degrees"}
#: Largest cell size read as degrees (1°); smallest plausible metric cell (1 cm).
MAX_DEGREE_CELL = 1.0
MIN_METRE_CELL = 0.01
#: How to settle the units, for messages.
UNITS_HINT = (
    "Say which: load_tile(path, units='metres') or units='degrees' from Python, "
    "--data.units metres|degrees for train.py, tile_options: {units: metres} in a scenario "
    "YAML, or put a .prj sidecar (the file's CRS) next to the file."
)


def canonical_units(units: str | None, where: str) -> str | None:
    """``"metres"`` / ``"degrees"`` / None from a user spelling, or raises NeuralMapError."""
    if units is None:
        return None
    key = str(units).strip().lower()
    if key not in UNIT_NAMES:
        raise NeuralMapError(
            f"{where}: units must be 'metres' or 'degrees', got {units!r}."
        )
    return UNIT_NAMES[key]


def decide_units(
    x_first: float,
    y_first: float,
    dx: float,
    dy: float,
    shape: tuple[int, int],
    *,
    where: str = "grid",
) -> tuple[str, str]:
    """Decides from the corner and cell-size ranges whether a grid is in degrees or metres.

    Evidence, together: the grid can be lon/lat degrees only when every node lies within
    longitude ``[-180, 360]`` and latitude ``[-90, 90]`` and the cell is at most
    `MAX_DEGREE_CELL` (1°); a metric grid is implausible when its cell is below
    `MIN_METRE_CELL` (1 cm). So:

    * not possible as degrees → metres (e.g. UTM eastings, or 30 m cells), unless the cell
      would then be sub-centimetre too: neither reading fits, refused;
    * possible as degrees and a sub-centimetre cell if metres → degrees (1″ = 0.000278);
    * possible both ways (e.g. 0.1 m lidar at origin (0, 0) vs 0.1° cells) → refused:
      the two readings differ by a factor of ~10⁵ in cell size.

    A ``.prj`` sidecar or GeoTIFF CRS, or the caller's ``units``, settles it before this
    rule is consulted.

    Args:
        x_first: x (or lon) of the first node.
        y_first: y (or lat) of the first node.
        dx: Cell size along x.
        dy: Cell size along y.
        shape: ``(ny, nx)`` node counts.
        where: Name of the source, for messages.

    Returns:
        ``(units, reason)``: ``"metres"`` or ``"degrees"`` and a sentence saying why.

    Raises:
        NeuralMapError: When both readings are plausible (says how to settle it).
    """
    ny, nx = shape
    x_last = x_first + (nx - 1) * dx
    y_last = y_first + (ny - 1) * dy
    cell = max(dx, dy)
    lon_ok = -180.0 <= min(x_first, x_last) and max(x_first, x_last) <= 360.0
    lat_ok = -90.0 <= min(y_first, y_last) and max(y_first, y_last) <= 90.0
    if not (lon_ok and lat_ok and cell <= MAX_DEGREE_CELL):
        why = []
        if not lon_ok:
            why.append(f"x {min(x_first, x_last):.6g}..{max(x_first, x_last):.6g} is no longitude")
        if not lat_ok:
            why.append(f"y {min(y_first, y_last):.6g}..{max(y_first, y_last):.6g} is no latitude")
        if cell > MAX_DEGREE_CELL:
            why.append(f"a cell of {cell:.6g} would be over 1 degree")
        if min(dx, dy) < MIN_METRE_CELL:
            raise NeuralMapError(
                f"{where}: neither metres nor degrees fit: as degrees "
                + "; ".join(why) + f", and as metres the cells ({dx:.6g} x {dy:.6g}) would be "
                "sub-centimetre. Check the header (corner and cellsize). " + UNITS_HINT
            )
        return "metres", "the coordinates cannot be lon/lat degrees (" + "; ".join(why) + ")"
    m_lon, m_lat = metres_per_degree(min(max(0.5 * (y_first + y_last), -90.0), 90.0))
    as_degrees = f"{dx * m_lon:.4g} m x {dy * m_lat:.4g} m cells"
    if min(dx, dy) < MIN_METRE_CELL:
        return "degrees", (
            f"a cell of {min(dx, dy):.6g} would be sub-centimetre in metres, and the nodes fit "
            f"lon/lat ranges (as degrees: {as_degrees})"
        )
    raise NeuralMapError(
        f"{where}: cannot tell whether the coordinates are metres or degrees: corner "
        f"({x_first:.6g}, {y_first:.6g}) and cell {dx:.6g} x {dy:.6g} fit both readings "
        f"(as metres: {dx:.6g} m x {dy:.6g} m cells; as degrees: {as_degrees}) and there is "
        f"no .prj sidecar. {UNITS_HINT}"
    )


__all__ = [
    "EARTH_MODEL",
    "LEGACY_SRTM_CRS",
    "MAX_DEGREE_CELL",
    "MIN_METRE_CELL",
    "SRTM_CRS",
    "UNITS_HINT",
    "UNIT_NAMES",
    "canonical_units",
    "crs_name",
    "decide_units",
    "WGS84_A",
    "WGS84_E2",
    "WGS84_F",
    "geographic_grid",
    "geographic_reference",
    "metres_per_degree",
    "pyproj_crs",
]
