"""Map frame <-> WGS-84 lat/lon (MapFrame) and the vertical datum rules.

References: pyproj's geodesic (Geod.inv) for distances, the UTM closed point on the central
meridian, rasterio's own node coordinates of GeoTIFFs written here.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from neuralmap.dem.geo import geographic_reference
from neuralmap.dem.tile import DemTile, ProjectedReference
from neuralmap.exceptions import NeuralMapError
from neuralmap.flights.vertical_datum import apply_datum, check_datum
from neuralmap.nav.georef import MapFrame
from neuralmap.nav.map_source import resolve_map

pyproj = pytest.importorskip("pyproj")
rasterio = pytest.importorskip("rasterio")


def write_geotiff(path: Path, heights: np.ndarray, *, crs: str, west: float, north: float,
                  dx: float, dy: float) -> Path:
    """A north-up single-band GeoTIFF; ``heights`` row 0 south (flipped into the file)."""
    from rasterio.transform import from_origin

    ny, nx = heights.shape
    with rasterio.open(path, "w", driver="GTiff", height=ny, width=nx, count=1,
                       dtype="float64", crs=crs, transform=from_origin(west, north, dx, dy)
                       ) as dst:
        dst.write(np.flipud(heights), 1)
    return path


def _heights(n: int = 40) -> np.ndarray:
    y, x = np.mgrid[0:n, 0:n].astype(float)
    return 300.0 + 20.0 * np.sin(x / 5.0) + 15.0 * np.cos(y / 7.0)


def test_equirectangular_round_trip_and_geodesic_distance() -> None:
    ref = geographic_reference(-84.2, 36.6)
    frame = MapFrame(ref, name="geo")
    rng = np.random.default_rng(0)
    x, y = rng.uniform(-15e3, 15e3, (2, 3, 5))
    lat, lon = frame.to_geo(x, y)
    x2, y2 = frame.to_map(lat, lon)
    np.testing.assert_allclose(x2, x, rtol=0, atol=1e-8)
    np.testing.assert_allclose(y2, y, rtol=0, atol=1e-8)
    # the frame's distances are the ellipsoid's within the equirectangular scale error
    # (tan φ0 · Δφ, geo.py: 0.05 % at 15 km from the centre at 36.6° N)
    geod = pyproj.Geod(ellps="WGS84")
    _, _, dist = geod.inv(lon[0], lat[0], lon[1], lat[1])
    planar = np.hypot(x[0] - x[1], y[0] - y[1])
    np.testing.assert_allclose(planar, dist, rtol=1.5e-3)


def test_types_and_shapes_follow_the_input() -> None:
    frame = MapFrame(geographic_reference(10.0, 45.0))
    lat = torch.tensor([[45.0, 45.01]], dtype=torch.float32)
    x, y = frame.to_map(lat, lat * 0 + 10.0)
    assert isinstance(x, torch.Tensor) and x.dtype == torch.float32 and x.shape == (1, 2)
    assert abs(float(x[0, 0])) < 1e-3 and abs(float(y[0, 0])) < 1e-3
    xs, ys = frame.to_map(45.0, 10.0)
    assert isinstance(xs, float) and abs(xs) < 1e-9 and abs(ys) < 1e-9


def test_projected_utm_central_meridian_closed_point() -> None:
    """UTM zone 17N: (lat 0, lon -81) is (500000, 0) exactly; the offsets move the frame."""
    frame = MapFrame(ProjectedReference(x_offset=499000.0, y_offset=-100.0, crs="EPSG:32617"))
    x, y = frame.to_map(np.array([0.0]), np.array([-81.0]))
    np.testing.assert_allclose([x[0], y[0]], [1000.0, 100.0], atol=1e-6)
    lat, lon = frame.to_geo(np.array([1000.0, 5000.0]), np.array([100.0, 3e6]))
    x2, y2 = frame.to_map(lat, lon)
    np.testing.assert_allclose(x2, [1000.0, 5000.0], atol=1e-6)
    np.testing.assert_allclose(y2, [100.0, 3e6], atol=1e-6)


def test_projected_geotiff_nodes(tmp_path: Path) -> None:
    """Node centres of a UTM GeoTIFF (rasterio's own coordinates -> lat/lon by pyproj)
    land on the tile's node coordinates."""
    h = _heights()
    path = write_geotiff(tmp_path / "utm.tif", h, crs="EPSG:32617", west=600000.0,
                         north=4050000.0, dx=30.0, dy=30.0)
    source = resolve_map(str(path))
    tile = source.tile
    with rasterio.open(path) as src:
        rows, cols = np.array([0, 10, 39]), np.array([0, 25, 39])
        east, north = rasterio.transform.xy(src.transform, rows, cols)
    to_geo = pyproj.Transformer.from_crs("EPSG:32617", "EPSG:4326", always_xy=True)
    lon, lat = to_geo.transform(np.asarray(east), np.asarray(north))
    x, y = source.frame.to_map(lat, lon)
    nodes = tile.node_xy()[tile.shape[0] - 1 - rows, cols]  # file row 0 is north
    np.testing.assert_allclose(np.stack([x, y], -1), nodes, atol=1e-6)


def test_geographic_geotiff_nodes(tmp_path: Path) -> None:
    h = _heights()
    d = 1.0 / 1200.0  # 3 arc-seconds
    path = write_geotiff(tmp_path / "geo.tif", h, crs="EPSG:4326", west=-84.0,
                         north=36.5, dx=d, dy=d)
    source = resolve_map(str(path))
    tile = source.tile
    assert source.frame.kind == "equirectangular"
    with rasterio.open(path) as src:
        rows, cols = np.array([0, 7, 39]), np.array([3, 20, 39])
        lon, lat = rasterio.transform.xy(src.transform, rows, cols)
    x, y = source.frame.to_map(np.asarray(lat), np.asarray(lon))
    nodes = tile.node_xy()[tile.shape[0] - 1 - rows, cols]
    np.testing.assert_allclose(np.stack([x, y], -1), nodes, atol=1e-6)


def test_no_georeference_is_refused() -> None:
    tile = DemTile(heights=_heights(4), spacing=(10.0, 10.0), name="bare")
    with pytest.raises(NeuralMapError, match="no georeference"):
        MapFrame.from_tile(tile)
    with pytest.raises(NeuralMapError, match="without a named CRS"):
        MapFrame(ProjectedReference(0.0, 0.0, crs=None), name="nocrs")


def test_vertical_datum_rules() -> None:
    alt = np.array([1000.0, 1010.0])
    np.testing.assert_array_equal(apply_datum(alt, "dem", None, where="w"), alt)
    np.testing.assert_array_equal(apply_datum(alt, "ellipsoidal", -30.0, where="w"), alt + 30.0)
    with pytest.raises(NeuralMapError, match="--geoid_undulation"):
        apply_datum(alt, "ellipsoidal", None, where="w")
    with pytest.raises(NeuralMapError, match="applies only with --alt_datum ellipsoidal"):
        apply_datum(alt, "dem", 5.0, where="w")
    ground = np.full(50, 400.0)
    clearance = np.full(50, 600.0)
    ok = check_datum(np.full(50, 1000.0), ground, clearance, sigma_m=10.0, alt_datum="dem",
                     where="w")
    assert ok["median_offset_m"] == 0.0
    with pytest.raises(NeuralMapError, match="--alt_datum dem.*vertical datum mismatch"):
        check_datum(np.full(50, 1040.0), ground, clearance, sigma_m=10.0, n_sigma=3.0,
                    alt_datum="dem", where="w")
    with pytest.raises(NeuralMapError, match="below the map surface"):
        check_datum(np.full(50, 390.0), ground, np.full(50, 5.0), sigma_m=10.0,
                    alt_datum="ellipsoidal", where="w")


def test_trained_map_carries_its_frame_and_fit_error(tmp_path: Path) -> None:
    """A neural_map.pt records the tile's georeference and fit error: --map on it gives the
    same frame as the DEM and the map error variance σ_DEM² + σ_fit²."""
    from neuralmap.terrain.blockwise import BlockwiseTerrainNet
    from neuralmap.terrain.export import save_map

    h = _heights()
    tif = write_geotiff(tmp_path / "utm.tif", h, crs="EPSG:32617", west=600000.0,
                        north=4050000.0, dx=30.0, dy=30.0)
    dem = resolve_map(str(tif), dem_accuracy_m=2.0)
    net = BlockwiseTerrainNet.from_tile(dem.tile, block_nodes=24, hidden=8)
    path = save_map(net, tmp_path / "neural_map.pt", metrics={"rmse_m": 1.5})
    trained = resolve_map(str(path), dem_accuracy_m=2.0)
    assert trained.kind == "trained_map" and dem.kind == "dem"
    assert trained.extent == pytest.approx(dem.extent)
    assert trained.map_error_variance == pytest.approx(2.0**2 + 1.5**2)
    assert dem.map_error_variance == pytest.approx(2.0**2)
    lat, lon = dem.frame.to_geo(np.array([100.0, 900.0]), np.array([50.0, 1000.0]))
    np.testing.assert_array_equal(np.stack(trained.frame.to_map(lat, lon)),
                                  np.stack(dem.frame.to_map(lat, lon)))
    preview = trained.preview_tile()
    assert preview.extent == pytest.approx(dem.extent) and np.isfinite(preview.heights).all()
    with pytest.raises(NeuralMapError, match="not an embedded tile"):
        resolve_map(str(tmp_path / "missing.tif"))


def test_projected_map_without_pyproj_names_the_extra(monkeypatch) -> None:  # noqa: ANN001
    import sys

    monkeypatch.setitem(sys.modules, "pyproj", None)  # import pyproj -> ImportError
    with pytest.raises(NeuralMapError, match=r"pip install 'neuralmap\[nav\]'"):
        MapFrame(ProjectedReference(0.0, 0.0, crs="EPSG:32617"))
