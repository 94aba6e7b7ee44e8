"""Compressed grids: every codec decodes within its stated maximum error; bad input errors."""

from __future__ import annotations

import builtins
import sys

import numpy as np
import pytest
import torch

from neuralmap.dem.synthetic import synthetic_tile
from neuralmap.dem.tile import DemTile
from neuralmap.exceptions import NeuralMapError
from neuralmap.terrain.codecs import GRID_CODECS, HEADER_BYTES, compress_grid
from neuralmap.terrain.grid import GridTerrain

pytest.importorskip("imagecodecs")


@pytest.fixture(scope="module")
def tile() -> DemTile:
    return synthetic_tile((65, 81), 30.0, seed=3, relief=400.0, hurst=0.7, name="synth")


@pytest.mark.parametrize("codec", GRID_CODECS)
@pytest.mark.parametrize("max_error", [0.3, 2.0])
def test_round_trip_within_stated_max_error(tile: DemTile, codec: str, max_error: float) -> None:
    grid = compress_grid(tile, codec=codec, max_error=max_error)
    error = np.abs(grid.tile.heights - tile.heights)
    # LERC adds the float32 rounding of heights (~3e-5 m at 900 m) to maxZError.
    assert error.max() <= grid.error_bound + 1e-9
    assert grid.error_bound <= max_error + 1e-4
    # lossy, not a copy: the error budget is used (except LERC, which may be lossless)
    if codec != "lerc":
        assert error.max() > 0.05 * max_error
    assert grid.nbytes == len(grid.payload) + HEADER_BYTES
    assert grid.nbytes < tile.heights.size * 4  # smaller than raw float32
    assert grid.bits_per_node == pytest.approx(8 * grid.nbytes / tile.heights.size)
    assert grid.tile.shape == tile.shape and grid.tile.extent == tile.extent


def test_quantised_codecs_decode_exactly_the_quantised_levels(tile: DemTile) -> None:
    """zstd is lossless after quantisation: decoded = step * round((h - min) / step) + min."""
    grid = compress_grid(tile, codec="zstd", max_error=0.5)
    h = tile.heights
    expected = np.rint((h - h.min()) / 1.0) * 1.0 + h.min()
    np.testing.assert_allclose(grid.tile.heights, expected, rtol=0, atol=1e-9)


def test_larger_max_error_stores_fewer_bytes(tile: DemTile) -> None:
    for codec in GRID_CODECS:
        fine = compress_grid(tile, codec=codec, max_error=0.2)
        coarse = compress_grid(tile, codec=codec, max_error=5.0)
        assert coarse.nbytes < fine.nbytes, codec


def test_decimated_grid_matches_bicubic_of_coarse_nodes(tile: DemTile) -> None:
    """x2: the coarse nodes decode within the bound, and the tile is bicubic between them."""
    grid = compress_grid(tile, codec="zstd", max_error=0.25, decimation=2)
    ny, nx = tile.shape
    assert grid.stored_shape == ((ny - 1) // 2 + 1, (nx - 1) // 2 + 1)  # 64, 80 intervals
    # even nodes of the original are coarse nodes: error there = coarse codec error only
    coarse_err = np.abs(grid.tile.heights[::2, ::2] - tile.heights[::2, ::2])
    assert coarse_err.max() <= 0.25 + 1e-9
    # between coarse nodes the decoded value is the Keys bicubic of the decoded coarse grid
    coarse = DemTile(grid.tile.heights[::2, ::2], (60.0, 60.0), name="c")
    mid = torch.tensor([[30.0 * 3, 30.0 * 5]], dtype=torch.float64)  # node (5, 3): odd/odd
    ref = GridTerrain(coarse, method="bicubic")(mid)
    assert grid.tile.heights[5, 3] == pytest.approx(float(ref), abs=1e-9)
    assert grid.nbytes < compress_grid(tile, codec="zstd", max_error=0.25).nbytes / 2


def test_terrain_is_a_grid_over_the_decoded_tile(tile: DemTile) -> None:
    grid = compress_grid(tile, codec="jpegls", max_error=1.0)
    terrain = grid.terrain(method="bilinear")
    assert isinstance(terrain, GridTerrain)
    xy = torch.from_numpy(tile.node_xy()[10, 20][None])
    assert float(terrain(xy)) == pytest.approx(grid.tile.heights[10, 20], abs=1e-9)


@pytest.mark.parametrize("bad", [0.0, -1.0, float("nan"), float("inf"), "x"])
def test_bad_max_error(tile: DemTile, bad: object) -> None:
    with pytest.raises(NeuralMapError, match="max_error"):
        compress_grid(tile, codec="lerc", max_error=bad)  # type: ignore[arg-type]


def test_bad_codec_decimation_near(tile: DemTile) -> None:
    with pytest.raises(NeuralMapError, match="unknown codec"):
        compress_grid(tile, codec="png", max_error=1.0)
    with pytest.raises(NeuralMapError, match="decimation"):
        compress_grid(tile, codec="zstd", max_error=1.0, decimation=0)
    with pytest.raises(NeuralMapError, match="near"):
        compress_grid(tile, codec="jpegls", max_error=1.0, near=-1)


def test_span_too_wide_for_16_bits() -> None:
    wide = DemTile(np.array([[0.0, 9000.0], [10.0, 20.0]]), (30.0, 30.0))
    with pytest.raises(NeuralMapError, match="16 bits"):
        compress_grid(wide, codec="jpegls", max_error=0.01)


def test_missing_imagecodecs_names_the_extra(
    tile: DemTile, monkeypatch: pytest.MonkeyPatch
) -> None:
    real_import = builtins.__import__

    def fake_import(name: str, *args: object, **kwargs: object) -> object:
        if name == "imagecodecs":
            raise ImportError("no imagecodecs")
        return real_import(name, *args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.delitem(sys.modules, "imagecodecs", raising=False)
    monkeypatch.setattr(builtins, "__import__", fake_import)
    with pytest.raises(NeuralMapError, match=r"neuralmap\[codecs\]"):
        compress_grid(tile, codec="zstd", max_error=1.0)


def test_missing_pysz_names_the_extra(tile: DemTile, monkeypatch: pytest.MonkeyPatch) -> None:
    real_import = builtins.__import__

    def fake_import(name: str, *args: object, **kwargs: object) -> object:
        if name == "pysz":
            raise ImportError("no pysz")
        return real_import(name, *args, **kwargs)  # type: ignore[arg-type]

    monkeypatch.delitem(sys.modules, "pysz", raising=False)
    monkeypatch.setattr(builtins, "__import__", fake_import)
    with pytest.raises(NeuralMapError, match=r"neuralmap\[codecs\].*pysz"):
        compress_grid(tile, codec="sz3", max_error=1.0)


@pytest.mark.parametrize("codec", GRID_CODECS)
def test_decimated_coarse_nodes_within_stated_bound(tile: DemTile, codec: str) -> None:
    """Every codec's x2 form: the coarse nodes (every other node) decode within the bound
    of the coarse grid, which is the bicubic resample of the tile (exact at even nodes)."""
    grid = compress_grid(tile, codec=codec, max_error=1.0, decimation=2)
    err = np.abs(grid.tile.heights[::2, ::2] - tile.heights[::2, ::2])
    assert err.max() <= grid.error_bound + 1e-6
