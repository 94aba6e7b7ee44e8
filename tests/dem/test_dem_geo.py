"""Geographic -> metric conversion against an independent ECEF computation, and jacksboro."""

from __future__ import annotations

import math

import numpy as np
import pytest

from neuralmap.dem import load_tile
from neuralmap.dem.geo import (
    decide_units,
    geographic_grid,
    geographic_reference,
    metres_per_degree,
)
from neuralmap.dem.samples import jacksboro_arrays
from neuralmap.exceptions import NeuralMapError

A = 6378137.0  # WGS-84, written out independently of neuralmap.dem.geo
F = 1.0 / 298.257223563


def _meridian_point(lat_deg: float) -> tuple[float, float]:
    """(p, z) of the WGS-84 meridian ellipse at a geodetic latitude, via the reduced latitude.

    tan(beta) = (b/a) tan(phi);  p = a cos(beta),  z = b sin(beta).
    """
    b = A * (1.0 - F)
    beta = math.atan((b / A) * math.tan(math.radians(lat_deg)))
    return A * math.cos(beta), b * math.sin(beta)


def _hand_metres_per_degree(lat_deg: float) -> tuple[float, float]:
    """East: radius of the parallel times pi/180. North: chord of a 1e-4 deg meridian step."""
    p, _ = _meridian_point(lat_deg)
    h = 1e-4
    p1, z1 = _meridian_point(lat_deg - h / 2)
    p2, z2 = _meridian_point(lat_deg + h / 2)
    return p * math.pi / 180.0, math.hypot(p2 - p1, z2 - z1) / h


@pytest.mark.parametrize("lat", [0.0, 36.5, 45.0, -60.25, 80.0])
def test_metres_per_degree_matches_ellipse_geometry(lat: float) -> None:
    # Chord vs arc over 1e-4 deg differs by ~1e-14 relative; finite differencing ~1e-10.
    np.testing.assert_allclose(metres_per_degree(lat), _hand_metres_per_degree(lat), rtol=1e-8)


def _meridian_arc(lat1: float, lat2: float, n: int = 2000) -> float:
    """Meridian arc length between two latitudes as a sum of short chords."""
    pts = np.array([_meridian_point(lat) for lat in np.linspace(lat1, lat2, n + 1)])
    return float(np.hypot(*np.diff(pts, axis=0).T).sum())


def test_textbook_values() -> None:
    m_lon, m_lat = metres_per_degree(45.0)
    # The 1-degree meridian arc 44.5..45.5 deg equals M(45) pi/180 to 1 mm.
    assert m_lat == pytest.approx(_meridian_arc(44.5, 45.5), abs=1e-3)
    # The common series 111132.92 - 559.82 cos 2phi + 1.175 cos 4phi (truncated, cm-level).
    phi = math.radians(45.0)
    series = 111132.92 - 559.82 * math.cos(2 * phi) + 1.175 * math.cos(4 * phi)
    assert m_lat == pytest.approx(series, abs=0.05)
    assert m_lon == pytest.approx(78846.835, abs=1e-3)  # N cos(phi) pi/180 at 45 deg
    # Within 0.5 % of a sphere of mean radius 6371008.8 m (ellipsoid vs sphere at 45 deg).
    sphere = 6371008.8 * math.pi / 180.0
    assert abs(m_lat / sphere - 1.0) < 5e-3 and abs(m_lon / (sphere * math.cos(math.pi / 4)) - 1) < 5e-3


def test_geographic_grid_frame_round_trip() -> None:
    spacing, origin, geo = geographic_grid(-85.0, 36.0, 1 / 1200, 1 / 1200, (1201, 1201),
                                           origin=(1000.0, -500.0))
    assert origin == (1000.0, -500.0)
    m_lon, m_lat = _hand_metres_per_degree(36.5)
    np.testing.assert_allclose(spacing, (m_lon / 1200, m_lat / 1200), rtol=1e-8)
    # The SW node maps to the origin, the NE node to origin + 1200 spacings.
    np.testing.assert_allclose(geo.to_metric(-85.0, 36.0), origin, atol=1e-8)
    np.testing.assert_allclose(
        geo.to_metric(-84.0, 37.0),
        (1000.0 + 1200 * spacing[0], -500.0 + 1200 * spacing[1]), atol=1e-8,
    )
    lon = np.array([[-84.9, -84.2]])
    lat = np.array([[36.1, 36.7]])
    back = geo.to_geographic(*geo.to_metric(lon, lat))
    np.testing.assert_allclose(back, (lon, lat), atol=1e-12)


def test_geographic_reference_centre_at_zero() -> None:
    geo = geographic_reference(10.0, 45.0)
    assert geo.to_metric(10.0, 45.0) == (0.0, 0.0)
    x, y = geo.to_metric(10.01, 45.02)
    m_lon, m_lat = _hand_metres_per_degree(45.0)
    np.testing.assert_allclose([x, y], [0.01 * m_lon, 0.02 * m_lat], rtol=1e-8)


def test_decide_units_rule() -> None:
    assert decide_units(-85.0, 36.0, 0.001, 0.001, (100, 100))[0] == "degrees"
    assert decide_units(500000.0, 4e6, 30.0, 30.0, (100, 100))[0] == "metres"  # UTM
    assert decide_units(0.0, 0.0, 2.0, 2.0, (10, 10))[0] == "metres"  # cells over 1 degree
    with pytest.raises(NeuralMapError, match="cannot tell"):  # 1 m or 1 degree cells
        decide_units(0.0, 0.0, 1.0, 1.0, (10, 10))
    with pytest.raises(NeuralMapError, match="neither"):  # past the pole, or 1 mm cells
        decide_units(-85.0, 89.99, 0.001, 0.001, (100, 100))


def test_jacksboro_sample_against_raw_file() -> None:
    raw = jacksboro_arrays()
    tile = load_tile("jacksboro")
    assert tile.name == "jacksboro" and tile.shape == (344, 403) and tile.n_void == 0
    assert (np.nanmin(tile.heights), np.nanmax(tile.heights)) == (236.0, 1076.0)
    # Row 0 is south: the file's first row is north (its 'ymin' key holds the northern
    # latitude 36.7329; the NE-trending Pine Mountain scarp / NW-trending Jacksboro fault
    # only come out right in that orientation).
    np.testing.assert_array_equal(tile.heights, np.flipud(raw["elevation"]).astype(float))
    # Spacing: 3" at the centre latitude, ~74.6 m east, ~92.5 m north (within 1 m of 74/92
    # rounded in the issue) and equal to the ellipse geometry to 1e-8.
    lat_c = 0.5 * (float(raw["ymin"]) + float(raw["ymax"]))
    m_lon, m_lat = _hand_metres_per_degree(lat_c)
    np.testing.assert_allclose(
        tile.spacing, (float(raw["dx"]) * m_lon, float(raw["dy"]) * m_lat), rtol=1e-8
    )
    assert abs(tile.spacing[0] - 74.5) < 1.0 and abs(tile.spacing[1] - 92.5) < 1.0
    # Bounds are cell edges (403 dx, 344 dy): node [0, 0] is the SW cell centre.
    lon, lat = tile.geo.to_geographic(*tile.node_xy()[0, 0])
    assert lon == pytest.approx(float(raw["xmin"]) + float(raw["dx"]) / 2, abs=1e-9)
    assert lat == pytest.approx(float(raw["ymax"]) + float(raw["dy"]) / 2, abs=1e-9)
    lon, lat = tile.geo.to_geographic(*tile.node_xy()[-1, -1])
    assert lon == pytest.approx(float(raw["xmax"]) - float(raw["dx"]) / 2, abs=1e-9)
    assert lat == pytest.approx(float(raw["ymin"]) - float(raw["dy"]) / 2, abs=1e-9)
    assert tile.origin == (0.0, 0.0)
    assert load_tile("JACKSBORO", origin=(5.0, 6.0)).origin == (5.0, 6.0)
