"""DEM mosaics: stitched SRTM tiles equal the one-piece grid; bad mosaics are refused."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from neuralmap.dem.geo import geographic_grid, metres_per_degree
from neuralmap.dem.mosaic import load_mosaic, projection_distortion, write_mosaic
from neuralmap.exceptions import NeuralMapError

SIDE = 1201  # 3 arc-second SRTM


def _one_piece(rows: int, cols: int, seed: int = 0) -> np.ndarray:
    """Integer heights (row 0 south) on a grid spanning several 1° tiles."""
    rng = np.random.default_rng(seed)
    r, c = np.meshgrid(np.arange(rows), np.arange(cols), indexing="ij")
    return (200 + (r % 97) + 3 * (c % 89) + rng.integers(0, 5, (rows, cols))).astype(np.int16)


def _write_hgt(path: Path, south_first: np.ndarray) -> None:
    """SRTM file order: first row north, big-endian int16."""
    np.flipud(south_first).astype(">i2").tofile(path)


def _two_tiles(tmp_path: Path) -> np.ndarray:
    whole = _one_piece(SIDE, 2 * SIDE - 1)
    _write_hgt(tmp_path / "N36W085.hgt", whole[:, :SIDE])
    _write_hgt(tmp_path / "N36W084.hgt", whole[:, SIDE - 1:])  # shares column 1200
    return whole


def test_two_hgt_tiles_equal_one_piece(tmp_path: Path) -> None:
    whole = _two_tiles(tmp_path)
    mosaic = load_mosaic(tmp_path / "N36W08*.hgt")
    assert mosaic.shape == (SIDE, 2 * SIDE - 1)
    np.testing.assert_array_equal(mosaic.heights, whole.astype(np.float64))
    # the one-piece grid's metric frame: equirectangular about the centre of the 2°x1° area
    spacing, origin, geo = geographic_grid(-85.0, 36.0, 1 / 1200, 1 / 1200, whole.shape)
    np.testing.assert_allclose(mosaic.spacing, spacing, rtol=1e-12)
    assert mosaic.origin == origin
    assert geo.lon0 == pytest.approx(-84.0) and geo.lat0 == pytest.approx(36.5)
    assert mosaic.meta["n_shared_nodes"] == SIDE
    # distortion at 36..37 N, closed form cos(φ)/cos(φ0) with WGS-84 N(φ)
    proj = mosaic.meta["projection"]
    m0 = metres_per_degree(36.5)[0]
    expect = max(abs(m0 / metres_per_degree(lat)[0] - 1) for lat in (36.0, 37.0))
    assert proj["max_scale_error_ew"] == pytest.approx(expect, rel=1e-12)
    assert 0.005 < proj["max_scale_error_ew"] < 0.008  # ≈ tan(36.5°)·0.5° in radians
    assert proj["max_position_error_m"] == pytest.approx(
        max(abs(m0 - metres_per_degree(lat)[0]) for lat in (36.0, 37.0)), rel=1e-12)


def test_void_on_shared_edge_filled_from_neighbour(tmp_path: Path) -> None:
    whole = _one_piece(SIDE, 2 * SIDE - 1)
    west = whole[:, :SIDE].copy()
    west[100, SIDE - 1] = -32768  # void on the shared column in the west tile only
    west[5, 5] = -32768  # a true void
    _write_hgt(tmp_path / "N36W085.hgt", west)
    _write_hgt(tmp_path / "N36W084.hgt", whole[:, SIDE - 1:])
    mosaic = load_mosaic([tmp_path / "N36W085.hgt", tmp_path / "N36W084.hgt"])
    assert mosaic.heights[100, SIDE - 1] == whole[100, SIDE - 1]
    assert math.isnan(mosaic.heights[5, 5]) and mosaic.n_void == 1


def test_write_mosaic_memmap_equals_in_memory(tmp_path: Path) -> None:
    whole = _two_tiles(tmp_path)
    info = write_mosaic(tmp_path / "*.hgt", tmp_path / "area.npy")
    stored = np.load(tmp_path / "area.npy", mmap_mode="r")
    np.testing.assert_array_equal(stored, whole.astype(np.float32))
    assert info["shape"] == list(whole.shape) and (tmp_path / "area.npy.json").is_file()


def test_disagreeing_overlap_refused(tmp_path: Path) -> None:
    whole = _one_piece(SIDE, 2 * SIDE - 1)
    east = whole[:, SIDE - 1:].copy()
    east[:, 0] += 50  # shared column differs by 50 m
    _write_hgt(tmp_path / "N36W085.hgt", whole[:, :SIDE])
    _write_hgt(tmp_path / "N36W084.hgt", east)
    with pytest.raises(NeuralMapError, match="disagrees"):
        load_mosaic(tmp_path / "*.hgt")


def test_non_adjacent_refused(tmp_path: Path) -> None:
    tile = _one_piece(SIDE, SIDE)
    _write_hgt(tmp_path / "N36W085.hgt", tile)
    _write_hgt(tmp_path / "N36W083.hgt", tile)  # a 1° gap
    with pytest.raises(NeuralMapError, match="not adjacent"):
        load_mosaic(tmp_path / "*.hgt")


def _write_asc(path: Path, heights: np.ndarray, x0: float, y0: float, cell: float) -> None:
    ny, nx = heights.shape
    header = (f"ncols {nx}\nnrows {ny}\nxllcenter {x0}\nyllcenter {y0}\ncellsize {cell}\n")
    rows = "\n".join(" ".join(f"{v:.1f}" for v in row) for row in np.flipud(heights))
    path.write_text(header + rows + "\n")
    path.with_suffix(".prj").write_text('PROJCS["WGS 84 / UTM zone 16N"]')


def test_metric_asc_tiles_abut_and_spacing_checked(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    whole = 300 + rng.random((20, 30)) * 10
    _write_asc(tmp_path / "a.asc", whole[:, :15], 500000.0, 4000000.0, 30.0)
    _write_asc(tmp_path / "b.asc", whole[:, 15:], 500000.0 + 15 * 30, 4000000.0, 30.0)
    mosaic = load_mosaic(tmp_path / "*.asc")
    np.testing.assert_allclose(mosaic.heights, np.round(whole, 1), atol=1e-9)
    assert mosaic.projected is not None and mosaic.projected.x_offset == 500000.0
    _write_asc(tmp_path / "c.asc", whole[:, :15], 500000.0, 4000000.0 + 20 * 30, 10.0)
    with pytest.raises(NeuralMapError, match="share the spacing"):
        load_mosaic(tmp_path / "*.asc")


def test_different_datum_refused(tmp_path: Path) -> None:
    rng = np.random.default_rng(2)
    whole = 300 + rng.random((10, 20))
    _write_asc(tmp_path / "a.asc", whole[:, :10], 500000.0, 4000000.0, 30.0)
    _write_asc(tmp_path / "b.asc", whole[:, 10:], 500300.0, 4000000.0, 30.0)
    (tmp_path / "b.prj").write_text('PROJCS["NAD27 / UTM zone 16N"]')
    with pytest.raises(NeuralMapError, match="datum"):
        load_mosaic(tmp_path / "*.asc")


def test_mosaic_larger_than_disk_refused(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    _two_tiles(tmp_path)
    import neuralmap.dem.mosaic as mosaic_module

    class Usage:
        free = 1000

    monkeypatch.setattr(mosaic_module.shutil, "disk_usage", lambda _path: Usage())
    with pytest.raises(NeuralMapError, match="free on"):
        write_mosaic(tmp_path / "*.hgt", tmp_path / "area.npy")
    assert not (tmp_path / "area.npy").exists()


def test_projection_distortion_zero_on_centre_parallel() -> None:
    d = projection_distortion((10.0, 10.0), (45.0, 45.0))
    assert d["max_scale_error_ew"] == 0.0 and d["max_position_error_m"] == 0.0


def test_mosaic_larger_than_memory_refused(tmp_path: Path,
                                           monkeypatch: pytest.MonkeyPatch) -> None:
    _two_tiles(tmp_path)
    import neuralmap.dem.mosaic as mosaic_module

    monkeypatch.setattr(mosaic_module, "_available_memory", lambda: 1000)
    with pytest.raises(NeuralMapError, match="write_mosaic"):
        load_mosaic(tmp_path / "*.hgt")
