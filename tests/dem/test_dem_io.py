"""DEM readers on tiny files, the jacksboro sample, metric conversion and bad input."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from neuralmap.dem import DemTile, load_tile, synthetic_tile
from neuralmap.dem.readers import geographic_reference
from neuralmap.exceptions import NeuralMapError


def _write_hgt(path: Path, side: int = 1201) -> np.ndarray:
    grid = (np.arange(side * side, dtype=np.int64).reshape(side, side) % 3000).astype(">i2")
    grid[0, 0] = -32768  # void at the north-west corner
    grid.tofile(path)
    return grid


def test_hgt_reader_flips_north_up_and_takes_origin_from_name(tmp_path: Path) -> None:
    path = tmp_path / "N36W085.hgt"
    raw = _write_hgt(path)
    tile = load_tile(path)
    assert tile.shape == (1201, 1201)
    assert tile.n_void == 1
    assert np.isnan(tile.heights[-1, 0])  # file's first row is north = tile's last row
    assert tile.heights[0, 5] == raw[-1, 5]
    geo = tile.geo
    assert geo is not None
    np.testing.assert_allclose([geo.lon0, geo.lat0], [-84.5, 36.5], atol=1e-12)
    # 3 arc-seconds: spacing = (1/1200) degree in metres at the centre latitude.
    np.testing.assert_allclose(tile.spacing[1], geo.m_per_deg_lat / 1200.0, rtol=1e-12)
    assert 91.0 < tile.spacing[1] < 93.0 and 73.0 < tile.spacing[0] < 76.0


def test_metric_conversion_matches_hand_computation() -> None:
    # WGS-84 at 45 deg: M = a(1-e2)/(1-e2 sin^2)^1.5, N = a/(1-e2 sin^2)^0.5.
    a, e2 = 6378137.0, 6.69437999014e-3
    s2 = math.sin(math.radians(45.0)) ** 2
    m_lat = math.pi / 180 * a * (1 - e2) / (1 - e2 * s2) ** 1.5
    m_lon = math.pi / 180 * a / math.sqrt(1 - e2 * s2) * math.cos(math.radians(45.0))
    geo = geographic_reference(10.0, 45.0)
    np.testing.assert_allclose(geo.m_per_deg_lat, 111131.745, rtol=1e-6)  # textbook value
    np.testing.assert_allclose([geo.m_per_deg_lat, geo.m_per_deg_lon], [m_lat, m_lon], rtol=1e-12)
    x, y = geo.to_metric(np.array(10.01), np.array(45.02))
    np.testing.assert_allclose([x, y], [0.01 * m_lon, 0.02 * m_lat], rtol=1e-12)
    lon, lat = geo.to_geographic(x, y)
    np.testing.assert_allclose([lon, lat], [10.01, 45.02], atol=1e-12)


def test_asc_reader_with_nodata_and_metric_corner(tmp_path: Path) -> None:
    path = tmp_path / "small.asc"
    path.write_text(
        "ncols 3\nnrows 2\nxllcorner 1000\nyllcorner 2000\ncellsize 30\nNODATA_value -9999\n"
        "1 2 3\n4 -9999 6\n"
    )
    tile = load_tile(path)
    assert tile.shape == (2, 3) and tile.spacing == (30.0, 30.0)
    np.testing.assert_array_equal(tile.heights[1], [1, 2, 3])  # north row last
    assert np.isnan(tile.heights[0, 1]) and tile.n_void == 1
    assert tile.origin == (1015.0, 2015.0)  # cell centres
    assert tile.geo is None


def test_asc_geographic_detection(tmp_path: Path) -> None:
    path = tmp_path / "geo.asc"
    path.write_text("ncols 2\nnrows 2\nxllcenter -84\nyllcenter 36\ncellsize 0.001\n1 2\n3 4\n")
    tile = load_tile(path)
    assert tile.geo is not None and 80.0 < tile.spacing[0] < 92.0


def test_generic_npy_and_npz_need_spacing(tmp_path: Path) -> None:
    grid = np.arange(12.0).reshape(3, 4)
    np.save(tmp_path / "g.npy", grid)
    np.savez(tmp_path / "g.npz", heights=grid)
    for path in (tmp_path / "g.npy", tmp_path / "g.npz"):
        tile = load_tile(path, spacing=[10, 20])
        np.testing.assert_array_equal(tile.heights, grid)
        assert tile.spacing == (10.0, 20.0) and tile.name == "g"
        with pytest.raises(NeuralMapError, match="spacing"):
            load_tile(path)


def test_matplotlib_style_npz(tmp_path: Path) -> None:
    elevation = np.array([[3, 4, 5], [0, 1, 2]], dtype=np.int16)  # first row north
    np.savez(tmp_path / "m.npz", elevation=elevation, dx=0.01, dy=0.01, xmin=10.0, xmax=10.02,
             ymin=45.01, ymax=45.0)
    tile = load_tile(tmp_path / "m.npz")
    np.testing.assert_array_equal(tile.heights, [[0, 1, 2], [3, 4, 5]])
    np.testing.assert_allclose(tile.geo.lat0, 45.005)
    np.savez(tmp_path / "bad.npz", elevation=elevation, dx=0.01)
    with pytest.raises(NeuralMapError, match="missing keys"):
        load_tile(tmp_path / "bad.npz")


def test_jacksboro_sample() -> None:
    from matplotlib import cbook

    tile = load_tile("jacksboro")
    raw = np.load(cbook.get_sample_data("jacksboro_fault_dem.npz", asfileobj=False))
    assert tile.shape == (344, 403) and tile.n_void == 0
    assert tile.describe()["height_range"] == [236.0, 1076.0]
    np.testing.assert_allclose(tile.spacing, (74.6, 92.5), atol=1.0)
    np.testing.assert_array_equal(tile.heights[0], raw["elevation"][-1])  # row 0 south
    assert tile.node_xy().shape == (344, 403, 2)
    assert tile.fingerprint() == load_tile("jacksboro").fingerprint()


def test_node_xy_and_extent() -> None:
    tile = DemTile(np.zeros((3, 4)), (10.0, 20.0), origin=(5.0, -5.0))
    xy = tile.node_xy()
    np.testing.assert_array_equal(xy[2, 3], [35.0, 35.0])
    assert tile.extent == (5.0, 35.0, -5.0, 35.0)


def test_synthetic_is_seeded_and_sized() -> None:
    a = synthetic_tile((40, 50), seed=3)
    b = synthetic_tile((40, 50), seed=3)
    c = synthetic_tile((40, 50), seed=4)
    assert a.shape == (40, 50)
    np.testing.assert_array_equal(a.heights, b.heights)
    assert not np.array_equal(a.heights, c.heights)
    assert a.fingerprint() != c.fingerprint()


@pytest.mark.parametrize(
    ("make", "match"),
    [
        (lambda p: p / "nope.hgt", "not found"),
        (lambda p: p / "tile.xyz", "unknown DEM file type"),
    ],
)
def test_missing_and_unknown_files(tmp_path: Path, make, match: str) -> None:
    target = make(tmp_path)
    if target.suffix == ".xyz":
        target.write_text("1 2 3")
    with pytest.raises(NeuralMapError, match=match):
        load_tile(target)


def test_bad_contents(tmp_path: Path) -> None:
    np.save(tmp_path / "cube.npy", np.zeros((2, 2, 2)))
    with pytest.raises(NeuralMapError, match="rank 3"):
        load_tile(tmp_path / "cube.npy", spacing=10)
    np.save(tmp_path / "void.npy", np.full((3, 3), np.nan))
    with pytest.raises(NeuralMapError, match="void"):
        load_tile(tmp_path / "void.npy", spacing=10)
    np.save(tmp_path / "ok.npy", np.zeros((3, 3)))
    for spacing in (0.0, -1.0, float("nan")):
        with pytest.raises(NeuralMapError, match="spacing"):
            load_tile(tmp_path / "ok.npy", spacing=spacing)
    (tmp_path / "N36W085.hgt").write_bytes(b"\x00" * 1000)
    with pytest.raises(NeuralMapError, match="neither"):
        load_tile(tmp_path / "N36W085.hgt")
    (tmp_path / "tile.hgt").write_bytes(b"\x00" * 8)
    with pytest.raises(NeuralMapError, match="south-west corner"):
        load_tile(tmp_path / "tile.hgt")
    (tmp_path / "bad.asc").write_text("ncols 3\nhello\n1 2 3\n")
    with pytest.raises(NeuralMapError, match="header"):
        load_tile(tmp_path / "bad.asc")


def test_geotiff_without_rasterio_says_how_to_install(tmp_path: Path) -> None:
    pytest.importorskip("numpy")
    try:
        import rasterio  # noqa: F401

        pytest.skip("rasterio installed")
    except ImportError:
        pass
    (tmp_path / "t.tif").write_bytes(b"II*\x00")
    with pytest.raises(NeuralMapError, match="rasterio"):
        load_tile(tmp_path / "t.tif")
