"""Latent-map bitstream: exact round trip, rate estimate vs file size, bad files."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from neuralmap.dem.tile import DemTile
from neuralmap.exceptions import NeuralMapError
from neuralmap.studies.maps import check_map_tile
from neuralmap.terrain.export import load_map
from neuralmap.terrain.latent import (
    LatentGrid,
    LatentTerrainMap,
    RateDistortion,
    export_map,
    write_latent_map,
)
from neuralmap.terrain.latent.bitstream import MAGIC, encode_latent_map
from neuralmap.terrain.latent.entropy import ideal_bits


def _tile(seed: int = 0) -> DemTile:
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:30, 0:34] * 25.0
    h = 300 + 40 * np.sin(x / 200) * np.cos(y / 150) + rng.normal(0, 0.5, x.shape)
    return DemTile(h, spacing=(25.0, 25.0), name=f"bits{seed}")


@pytest.fixture(scope="module")
def trained() -> tuple[DemTile, LatentGrid, LatentTerrainMap]:
    tile = _tile()
    torch.manual_seed(0)
    grid = LatentGrid(tile, levels=4, hidden=4, init_step=0.2, basis="pyramid")
    objective = RateDistortion(tile, rate_weight=0.05, between_points=256)
    opt = torch.optim.Adam(grid.parameters(), lr=0.02)
    for _ in range(40):
        loss = objective(grid, "noise").loss
        opt.zero_grad()
        loss.backward()
        opt.step()
    return tile, grid, export_map(grid, metrics={"rmse_m": 0.5})


def test_round_trip_is_exact(trained, tmp_path: Path):
    _, grid, m = trained
    path = write_latent_map(m, tmp_path / "map.nlat")
    loaded = load_map(path)
    assert isinstance(loaded, LatentTerrainMap)
    for a, b in zip(grid.symbols(), loaded.symbols, strict=True):
        np.testing.assert_array_equal(a, b)  # decoded latents == quantised latents
    np.testing.assert_array_equal(loaded.steps, grid.steps.detach().numpy())
    torch.testing.assert_close(loaded.coeffs, m.coeffs, rtol=0, atol=0)
    xy = torch.rand(100, 2) * 800
    torch.testing.assert_close(loaded(xy), m(xy), rtol=0, atol=0)
    assert loaded.tile_fingerprint == trained[0].fingerprint()
    assert loaded.metrics == {"rmse_m": 0.5}
    assert not loaded.training


def test_estimated_rate_within_5_percent_of_file(trained):
    _, grid, m = trained
    with torch.no_grad():
        _, bits = grid.relaxed("round")
    assert float(bits) == pytest.approx(ideal_bits(m.symbols, list(m.scales)), rel=1e-4)
    data = encode_latent_map(m)
    # the file = estimated latent bits + fixed-size header and decoder weights
    payload = len(data) - len(encode_latent_map(_with_zero_latents(m)))
    assert abs(payload - float(bits) / 8) <= 0.05 * float(bits) / 8
    assert abs(len(data) - float(bits) / 8) <= 0.05 * len(data) + 1200


def _with_zero_latents(m: LatentTerrainMap) -> LatentTerrainMap:
    zeros = [np.zeros_like(s) for s in m.symbols]
    return LatentTerrainMap(zeros, m.steps, m.scales * 0 + 1e-3, m.synthesis_vector,
                            m.feature_scale, hidden=m.hidden, tile_info=m.tile_info,
                            metrics=m.metrics, basis=m.basis)


def test_truncated_and_corrupted_files_are_refused(trained, tmp_path: Path):
    _, _, m = trained
    data = encode_latent_map(m)
    cut = tmp_path / "cut.nlat"
    cut.write_bytes(data[: len(data) // 2])
    with pytest.raises(NeuralMapError, match="checksum mismatch.*truncated or corrupted"):
        load_map(cut)
    flipped = bytearray(data)
    flipped[len(data) // 2] ^= 0x10
    bad = tmp_path / "bad.nlat"
    bad.write_bytes(bytes(flipped))
    with pytest.raises(NeuralMapError, match="checksum mismatch"):
        load_map(bad)
    tiny = tmp_path / "tiny.nlat"
    tiny.write_bytes(MAGIC + b"\x01")
    with pytest.raises(NeuralMapError, match="truncated"):
        load_map(tiny)


def test_map_of_another_tile_is_refused(trained, tmp_path: Path):
    _, _, m = trained
    path = write_latent_map(m, tmp_path / "map.nlat")
    with pytest.raises(NeuralMapError, match="exported from tile 'bits0'"):
        check_map_tile(load_map(path), _tile(1), map_path=path, scenario_name="other")


def test_missing_entropy_coder_names_the_extra(trained, monkeypatch):
    _, _, m = trained
    monkeypatch.setitem(sys.modules, "constriction", None)
    with pytest.raises(NeuralMapError, match=r"pip install 'neuralmap\[latent\]'"):
        encode_latent_map(m)


@pytest.mark.parametrize("lam", [0.0, -1.0, float("nan"), float("inf")])
def test_rate_weight_must_be_positive(lam):
    with pytest.raises(NeuralMapError, match="rate weight lambda.*must be finite and > 0"):
        RateDistortion(_tile(), rate_weight=lam)


def test_linear_synthesis_map_round_trips_and_matches_direct_decode(tmp_path: Path):
    """hidden = 0 (linear synthesis only): exact round trip, queries equal the node decode."""
    tile = _tile(2)
    m = export_map(LatentGrid(tile, levels=3, hidden=0))
    loaded = load_map(write_latent_map(m, tmp_path / "lin.nlat"))
    for a, b in zip(m.symbols, loaded.symbols, strict=True):
        np.testing.assert_array_equal(a, b)
    xy = torch.from_numpy(tile.node_xy().reshape(-1, 2)).float()
    torch.testing.assert_close(loaded(xy).double().view(tile.shape), loaded.node_heights(),
                               atol=2e-3, rtol=0)


def test_format_1_file_reads_as_the_pyramid(trained, tmp_path: Path):
    """A format-1 file (uncompressed JSON header, no basis key) still loads as the pyramid."""
    import json
    import struct
    import zlib

    _, _, m = trained
    data = encode_latent_map(m)
    (length,) = struct.unpack("<I", data[10:14])
    header = json.loads(zlib.decompress(data[14 : 14 + length]))
    assert header.pop("basis") == "pyramid"
    raw = json.dumps(header).encode()
    body = MAGIC + struct.pack("<HI", 1, len(raw)) + raw + data[14 + length : -4]
    path = tmp_path / "v1.nlat"
    path.write_bytes(body + struct.pack("<I", zlib.crc32(body)))
    loaded = load_map(path)
    assert loaded.basis.name == "pyramid"
    torch.testing.assert_close(loaded.coeffs, m.coeffs, rtol=0, atol=0)
