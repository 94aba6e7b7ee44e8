"""Each bad DEM input raises NeuralMapError whose message names the problem and the place."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from neuralmap.dem import DemTile, load_tile
from neuralmap.exceptions import NeuralMapError


def _raises(match: str, *args, **kwargs) -> str:
    with pytest.raises(NeuralMapError, match=match) as info:
        load_tile(*args, **kwargs)
    return str(info.value)


def test_missing_file_names_path_and_samples(tmp_path: Path) -> None:
    msg = _raises("not found", tmp_path / "nope.hgt")
    assert "nope.hgt" in msg and "jacksboro" in msg and "synthetic" in msg


def test_unknown_extension_lists_supported(tmp_path: Path) -> None:
    path = tmp_path / "tile.xyz"
    path.write_text("1 2 3")
    msg = _raises("unknown DEM file type", path)
    for ext in (".npz", ".npy", ".hgt", ".asc", ".tif"):
        assert ext in msg
    assert "jacksboro" in msg
    _raises("unknown DEM file type", "jacksboroo")  # a misspelt sample name


def test_directory_is_not_a_file(tmp_path: Path) -> None:
    (tmp_path / "d.npy").mkdir()
    _raises("directory", tmp_path / "d.npy", spacing=1.0)


def test_missing_npz_keys_are_listed(tmp_path: Path) -> None:
    np.savez(tmp_path / "bad.npz", elevation=np.zeros((3, 3)), dx=0.01, dy=0.01)
    msg = _raises("missing keys", tmp_path / "bad.npz")
    assert "xmin, xmax, ymin, ymax" in msg and "bad.npz" in msg
    np.savez(tmp_path / "two.npz", a=np.zeros((3, 3)), b=np.zeros((3, 3)))
    msg = _raises("which array holds the heights", tmp_path / "two.npz", spacing=1.0)
    assert "a, b" in msg and "'heights'" in msg


def test_inconsistent_matplotlib_bounds(tmp_path: Path) -> None:
    np.savez(tmp_path / "m.npz", elevation=np.zeros((3, 3)), dx=0.01, dy=0.01, xmin=0.0,
             xmax=0.5, ymin=0.0, ymax=0.03)
    _raises("x bounds span", tmp_path / "m.npz")


@pytest.mark.parametrize("shape", [(5,), (2, 3, 4)])
def test_wrong_rank(tmp_path: Path, shape: tuple[int, ...]) -> None:
    np.save(tmp_path / "r.npy", np.zeros(shape))
    msg = _raises(f"rank {len(shape)}", tmp_path / "r.npy", spacing=10.0)
    assert "2-D" in msg


@pytest.mark.parametrize("spacing", [0.0, -1.0, float("nan"), float("inf"), (30.0, 0.0), "x"])
def test_bad_spacing(tmp_path: Path, spacing: object) -> None:
    np.save(tmp_path / "ok.npy", np.zeros((3, 3)))
    msg = _raises("spacing", tmp_path / "ok.npy", spacing=spacing)
    assert "ok.npy" in msg


def test_missing_spacing_says_how_to_pass_it(tmp_path: Path) -> None:
    np.save(tmp_path / "g.npy", np.zeros((3, 3)))
    msg = _raises("spacing", tmp_path / "g.npy")
    assert "--data.spacing 30" in msg


def test_spacing_refused_where_file_has_its_own(tmp_path: Path) -> None:
    _raises("carries its own grid spacing", "jacksboro", spacing=30.0)
    path = tmp_path / "a.asc"
    path.write_text("ncols 2\nnrows 2\nxllcorner 0\nyllcorner 0\ncellsize 5\n1 2\n3 4\n")
    _raises("carries its own grid spacing", path, spacing=5.0)


def test_options_only_for_synthetic(tmp_path: Path) -> None:
    _raises("apply only to the 'synthetic'", tmp_path / "x.npy", seed=3)
    _raises("unknown options", "synthetic", colour="red")
    _raises("shape", "synthetic:32", shape=(8, 8))


def test_bad_origin(tmp_path: Path) -> None:
    _raises("origin", "synthetic", origin=(0.0, float("nan")))


def test_all_void_tiles(tmp_path: Path) -> None:
    np.save(tmp_path / "void.npy", np.full((3, 3), np.nan))
    _raises("void", tmp_path / "void.npy", spacing=10.0)
    np.full((1201, 1201), -32768, dtype=">i2").tofile(tmp_path / "N10E010.hgt")
    msg = _raises("every node is void", tmp_path / "N10E010.hgt")
    assert "N10E010.hgt" in msg
    (tmp_path / "v.asc").write_text(
        "ncols 2\nnrows 2\nxllcorner 0\nyllcorner 0\ncellsize 5\nNODATA_value -1\n-1 -1\n-1 -1\n"
    )
    _raises("void", tmp_path / "v.asc")


def test_void_tile_loads_and_counts() -> None:
    heights = np.ones((4, 4))
    heights[0, :3] = np.nan
    assert DemTile(heights, (1.0, 1.0)).n_void == 3


def test_hgt_wrong_size(tmp_path: Path) -> None:
    (tmp_path / "N36W085.hgt").write_bytes(b"\x00" * 1000)
    msg = _raises("neither a 1 nor a 3 arc-second", tmp_path / "N36W085.hgt")
    assert "3601" in msg and "1201" in msg and "1000 bytes" in msg


def test_hgt_unparseable_name(tmp_path: Path) -> None:
    np.zeros((1201, 1201), dtype=">i2").tofile(tmp_path / "tile.hgt")
    msg = _raises("south-west corner", tmp_path / "tile.hgt")
    assert "N36W085" in msg
    np.zeros((1201, 1201), dtype=">i2").tofile(tmp_path / "N95E010.hgt")
    _raises("out of range", tmp_path / "N95E010.hgt")


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("ncols 3\nhello\n1 2 3\n", "malformed header, missing nrows"),
        ("ncols 2\nnrows 2\nxllcorner 0\nyllcorner 0\n1 2\n3 4\n", "cellsize"),
        ("ncols 2\nnrows 2\nyllcorner 0\ncellsize 1\n1 2\n3 4\n", "xllcorner or xllcenter"),
        ("ncols two\nnrows 2\nxllcorner 0\nyllcorner 0\ncellsize 1\n1 2\n3 4\n", "header value"),
        ("ncols 2\nnrows 2\nxllcorner 0\nyllcorner 0\ncellsize 0\n1 2\n3 4\n", "cellsize"),
        ("ncols 2\nnrows 2\nxllcorner 0\nyllcorner 0\ncellsize 1\n1 2\n3\n", "holds 3"),
        ("ncols 2\nnrows 2\nxllcorner 0\nyllcorner 0\ncellsize 1\n1 2\n3 x\n", "non-numeric"),
        ("ncols 2 3\nnrows 2\n", "must be 'key value'"),
    ],
)
def test_malformed_asc(tmp_path: Path, text: str, match: str) -> None:
    path = tmp_path / "bad.asc"
    path.write_text(text)
    msg = _raises(match, path)
    assert "bad.asc" in msg


def test_corrupt_npz_and_npy(tmp_path: Path) -> None:
    (tmp_path / "c.npz").write_bytes(b"not a zip")
    _raises("could not be read", tmp_path / "c.npz")
    (tmp_path / "c.npy").write_bytes(b"\x93NUMPY garbage")
    _raises("could not be read", tmp_path / "c.npy", spacing=1.0)


def test_geotiff_without_rasterio(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "rasterio", None)  # import rasterio -> ImportError
    (tmp_path / "t.TIF").write_bytes(b"II*\x00")
    msg = _raises("needs rasterio", tmp_path / "t.TIF")
    assert "pip install 'neuralmap[geotiff]'" in msg


def _write_tif(path: Path, data: np.ndarray, transform) -> None:  # noqa: ANN001
    import rasterio

    with rasterio.open(
        path, "w", driver="GTiff", height=data.shape[-2], width=data.shape[-1],
        count=data.shape[0], dtype="float32", crs="EPSG:32616", transform=transform,
    ) as dst:
        dst.write(data.astype(np.float32))


def test_geotiff_with_several_bands_is_refused(tmp_path: Path) -> None:
    from rasterio.transform import from_origin

    path = tmp_path / "rgb.tif"
    _write_tif(path, np.ones((3, 4, 5)), from_origin(500000.0, 4000000.0, 30.0, 30.0))
    msg = _raises("has 3 bands", path)
    assert "rgb.tif" in msg and "gdal_translate -b 1" in msg


def test_rotated_geotiff_is_refused(tmp_path: Path) -> None:
    from rasterio.transform import Affine

    path = tmp_path / "rot.tif"
    rotated = Affine(30.0, 5.0, 500000.0, 5.0, -30.0, 4000000.0)
    _write_tif(path, np.ones((1, 4, 5)), rotated)
    msg = _raises("rotated or sheared", path)
    assert "rot.tif" in msg and "gdalwarp" in msg
