"""DEM readers on tiny files written in tmp_path: .hgt, .asc, generic/matplotlib .npz, .npy, .tif."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import rasterio
from rasterio.transform import from_origin

from neuralmap.dem import load_tile
from neuralmap.dem.geo import crs_name, metres_per_degree
from neuralmap.dem.readers import parse_hgt_name


def _write_hgt(path: Path, raw: np.ndarray) -> None:
    """Writes an SRTM tile exactly as distributed: big-endian int16, first row north."""
    raw.astype(">i2").tofile(path)


def _hgt_raw(side: int) -> np.ndarray:
    """File-order values: raw[r, c] = 100 + r + 2c (row r counted from the north edge)."""
    r, c = np.meshgrid(np.arange(side), np.arange(side), indexing="ij")
    return (100 + r + 2 * c).astype(np.int16)


def test_hgt_3arcsec_flip_void_and_corner(tmp_path: Path) -> None:
    raw = _hgt_raw(1201)
    raw[0, 5] = -32768  # void on the northern edge
    raw[600, 7] = -32768
    path = tmp_path / "N36W085.hgt"
    _write_hgt(path, raw)
    tile = load_tile(path)
    assert tile.shape == (1201, 1201)
    assert tile.name == "N36W085"
    assert tile.n_void == 2
    # Row 0 is south = last file row; value 100 + (1200 - i) + 2j.
    i, j = np.meshgrid(np.arange(1201), np.arange(1201), indexing="ij")
    expected = (100 + (1200 - i) + 2 * j).astype(float)
    expected[1200, 5] = np.nan
    expected[600, 7] = np.nan
    np.testing.assert_array_equal(tile.heights, expected)
    assert tile.origin == (0.0, 0.0)
    # SW node at (lon, lat) = (-85, 36); NE node at (-84, 37), via the kept conversion.
    lon, lat = tile.geo.to_geographic(0.0, 0.0)
    assert lon == pytest.approx(-85.0, abs=1e-12) and lat == pytest.approx(36.0, abs=1e-12)
    xmin, xmax, ymin, ymax = tile.extent
    lon, lat = tile.geo.to_geographic(xmax, ymax)
    assert lon == pytest.approx(-84.0, abs=1e-12) and lat == pytest.approx(37.0, abs=1e-12)
    assert tile.meta["arcsec"] == 3


def test_hgt_1arcsec_spacing(tmp_path: Path) -> None:
    path = tmp_path / "s12e045.hgt"  # lower-case name, southern/eastern hemisphere
    np.full((3601, 3601), 7, dtype=">i2").tofile(path)
    tile = load_tile(path, origin=(100.0, -50.0))
    assert tile.shape == (3601, 3601)
    m_lon, m_lat = metres_per_degree(-11.5)
    np.testing.assert_allclose(tile.spacing, (m_lon / 3600, m_lat / 3600), rtol=1e-12)
    assert tile.origin == (100.0, -50.0)
    lon, lat = tile.geo.to_geographic(100.0, -50.0)
    assert (lon, lat) == pytest.approx((45.0, -12.0), abs=1e-12)
    assert tile.meta["arcsec"] == 1


@pytest.mark.parametrize(
    ("name", "corner"),
    [("N36W085.hgt", (36, -85)), ("S01E000.hgt", (-1, 0)), ("n00e179.SRTMGL3.hgt", (0, 179))],
)
def test_parse_hgt_name(name: str, corner: tuple[int, int]) -> None:
    assert parse_hgt_name(name) == corner


def test_asc_metric_with_nodata(tmp_path: Path) -> None:
    path = tmp_path / "small.asc"
    path.write_text(
        "ncols 4\nNROWS 3\nxllcorner 1000\nyllcorner 2000\ncellsize 25\nNODATA_value -9999\n"
        "1 2 3 4\n5 6 -9999 8\n9 10 11 12\n"
    )
    tile = load_tile(path)
    # First data row is north -> last tile row.
    expected = np.array([[9, 10, 11, 12], [5, 6, np.nan, 8], [1, 2, 3, 4]], dtype=float)
    np.testing.assert_array_equal(tile.heights, expected)
    assert tile.n_void == 1
    assert tile.spacing == (25.0, 25.0)
    # Tile-local frame; the file's own coordinates (cell centres are corner + half a cell)
    # are kept in the projected reference.
    assert tile.origin == (0.0, 0.0)
    assert (tile.projected.x_offset, tile.projected.y_offset) == (1012.5, 2012.5)
    assert tuple(tile.meta["first_node"]) == (1012.5, 2012.5)
    assert tile.geo is None and tile.georeference is tile.projected
    moved = load_tile(path, origin=(5.0, -5.0))
    assert moved.origin == (5.0, -5.0)
    assert moved.projected.to_projected(5.0, -5.0) == (1012.5, 2012.5)
    assert tile.name == "small"


def test_asc_center_registration_and_origin(tmp_path: Path) -> None:
    path = tmp_path / "c.asc"
    path.write_text("ncols 2\nnrows 2\nxllcenter 10\nyllcenter 20\ncellsize 5\n1 2\n3 4\n")
    tile = load_tile(path, origin=(10.0, 20.0), name="mine")
    np.testing.assert_array_equal(tile.heights, [[3, 4], [1, 2]])
    assert tile.meta["first_node"] == [10.0, 20.0]
    assert tile.origin == (10.0, 20.0) and tile.name == "mine"


def test_asc_geographic_rule_and_override(tmp_path: Path) -> None:
    path = tmp_path / "geo.asc"
    path.write_text(
        "ncols 3\nnrows 2\nxllcorner -85.0\nyllcorner 36.0\ncellsize 0.001\n1 2 3\n4 5 6\n"
    )
    tile = load_tile(path)
    assert tile.meta["units"] == "degrees" and "sub-centimetre" in tile.meta["units_reason"]
    m_lon, m_lat = metres_per_degree(36.001)  # centre latitude of the two node rows
    np.testing.assert_allclose(tile.spacing, (0.001 * m_lon, 0.001 * m_lat), rtol=1e-12)
    lon, lat = tile.geo.to_geographic(0.0, 0.0)
    assert (lon, lat) == pytest.approx((-84.9995, 36.0005), abs=1e-12)
    forced = load_tile(path, geographic=False)
    assert forced.geo is None and forced.spacing == (0.001, 0.001)
    assert load_tile(path, units="metres").spacing == (0.001, 0.001)
    # A .prj sidecar naming a projected CRS also makes it metric.
    path.with_suffix(".prj").write_text('PROJCS["WGS 84 / UTM zone 16N",GEOGCS["WGS 84"]]')
    assert ".prj sidecar" in load_tile(path).meta["units_reason"]
    assert crs_name(load_tile(path).projected.crs) == "WGS 84 / UTM zone 16N"
    assert load_tile(path).geo is None


def test_generic_npy_and_npz_with_spacing(tmp_path: Path) -> None:
    grid = np.arange(12, dtype=np.float32).reshape(3, 4)
    np.save(tmp_path / "g.npy", grid)
    tile = load_tile(tmp_path / "g.npy", spacing=30)
    np.testing.assert_array_equal(tile.heights, grid)  # stored order: row 0 south
    assert tile.spacing == (30.0, 30.0) and tile.heights.dtype == np.float64
    np.savez(tmp_path / "h.npz", heights=grid, nodata=np.float32(5.0))
    tile = load_tile(tmp_path / "h.npz", spacing=(10.0, 20.0))
    assert tile.spacing == (10.0, 20.0) and tile.n_void == 1 and np.isnan(tile.heights[1, 1])
    np.savez(tmp_path / "single.npz", grid)  # one unnamed array
    assert load_tile(tmp_path / "single.npz", spacing=1.0).shape == (3, 4)
    np.savez(tmp_path / "e.npz", elevation=grid, other=np.zeros(3))
    assert load_tile(tmp_path / "e.npz", spacing=1.0).shape == (3, 4)


@pytest.mark.parametrize("north_key_first", [True, False])
def test_matplotlib_style_npz(tmp_path: Path, north_key_first: bool) -> None:
    elevation = np.array([[30, 31, 32], [20, 21, 22], [10, 11, 12], [0, 1, 2]], dtype=np.int16)
    d = 0.01
    north, south = 45.04, 45.0  # cell-edge bounds: 4 rows x 0.01
    ymin, ymax = (north, south) if north_key_first else (south, north)
    path = tmp_path / "mpl.NPZ"  # extension match is case-insensitive
    with open(path, "wb") as handle:  # np.savez would append ".npz" to the name
        np.savez(handle, elevation=elevation, dx=d, dy=d, xmin=7.0, xmax=7.03, ymin=ymin,
                 ymax=ymax)
    tile = load_tile(path)
    np.testing.assert_array_equal(tile.heights, np.flipud(elevation))  # first row is north
    lon, lat = tile.geo.to_geographic(0.0, 0.0)
    assert (lon, lat) == pytest.approx((7.005, 45.005), abs=1e-12)
    m_lon, m_lat = metres_per_degree(45.02)
    np.testing.assert_allclose(tile.spacing, (d * m_lon, d * m_lat), rtol=1e-12)
    assert tile.meta["bounds"] == "cell edges"


def test_matplotlib_style_npz_node_bounds(tmp_path: Path) -> None:
    path = tmp_path / "nodes.npz"
    np.savez(path, elevation=np.ones((3, 3)), dx=0.5, dy=0.5, xmin=1.0, xmax=2.0,
             ymin=3.0, ymax=4.0)
    tile = load_tile(path)
    assert tile.meta["bounds"] == "nodes"
    assert tile.geo.to_geographic(0.0, 0.0) == pytest.approx((1.0, 3.0), abs=1e-12)


def test_geotiff_roundtrip(tmp_path: Path) -> None:
    data = np.array([[3, 4, 5], [0, 1, -9999]], dtype=np.float32)  # first row north
    path = tmp_path / "t.tif"
    with rasterio.open(
        path, "w", driver="GTiff", height=2, width=3, count=1, dtype="float32",
        crs="EPSG:32616", transform=from_origin(500000.0, 4000000.0, 30.0, 30.0),
        nodata=-9999,
    ) as dst:
        dst.write(data, 1)
    tile = load_tile(path)
    np.testing.assert_array_equal(tile.heights, [[0, 1, np.nan], [3, 4, 5]])
    assert tile.spacing == (30.0, 30.0) and tile.geo is None
    assert tile.origin == (0.0, 0.0)  # tile-local; the SW pixel centre in the file frame:
    assert (tile.projected.x_offset, tile.projected.y_offset) == (500015.0, 3999955.0)
    geo_path = tmp_path / "g.tif"
    with rasterio.open(
        geo_path, "w", driver="GTiff", height=2, width=3, count=1, dtype="float32",
        crs="EPSG:4326", transform=from_origin(-85.0, 36.002, 0.001, 0.001),
    ) as dst:
        dst.write(data, 1)
    tile = load_tile(geo_path)
    assert tile.geo is not None
    assert tile.geo.to_geographic(0.0, 0.0) == pytest.approx((-84.9995, 36.0005), abs=1e-12)


def test_cloud_optimized_geotiff(tmp_path: Path) -> None:
    """A COG (tiled, with overviews) reads as its full-resolution band; no-data in a mask."""
    rng = np.random.default_rng(3)
    data = (200.0 + rng.normal(0.0, 20.0, size=(300, 260))).astype(np.float32)
    data[10:20, 30:45] = -32768.0
    path = tmp_path / "cog.tif"
    with rasterio.open(
        path, "w", driver="COG", height=300, width=260, count=1, dtype="float32",
        crs="EPSG:32633", transform=from_origin(400000.0, 5200000.0, 10.0, 10.0),
        nodata=-32768.0, blocksize=128, overview_resampling="average",
    ) as dst:
        dst.write(data, 1)
    with rasterio.open(path) as src:
        assert src.overviews(1)  # really a COG with internal overviews
    tile = load_tile(path)
    expected = np.flipud(np.where(data == -32768.0, np.nan, data.astype(np.float64)))
    np.testing.assert_array_equal(tile.heights, expected)
    assert tile.n_void == 150 and tile.spacing == (10.0, 10.0)
    assert (tile.projected.x_offset, tile.projected.y_offset) == (400005.0, 5197005.0)
    assert tile.projected.crs == "EPSG:32633"
