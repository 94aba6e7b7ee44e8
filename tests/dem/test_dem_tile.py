"""DemTile: node coordinates, extent, fingerprint stability, describe()."""

from __future__ import annotations

import json

import numpy as np

from neuralmap.dem import DemTile, load_tile


def _tile() -> DemTile:
    heights = np.arange(12.0).reshape(3, 4)
    heights[1, 2] = np.nan
    return DemTile(heights, (10.0, 20.0), origin=(1.0, 2.0), name="t")


def test_node_xy_values_and_extent() -> None:
    tile = _tile()
    xy = tile.node_xy()
    assert xy.shape == (3, 4, 2) and xy.dtype == np.float64
    i, j = np.meshgrid(np.arange(3), np.arange(4), indexing="ij")
    np.testing.assert_array_equal(xy[..., 0], 1.0 + 10.0 * j)  # x grows with the column
    np.testing.assert_array_equal(xy[..., 1], 2.0 + 20.0 * i)  # y grows with the row (north)
    assert tile.extent == (1.0, 31.0, 2.0, 42.0)
    assert tile.n_void == 1 and tile.valid_mask.sum() == 11


def test_fingerprint_is_stable_and_sensitive() -> None:
    tile = _tile()
    # Pinned value: a change here breaks the link between exported maps and their tiles.
    assert tile.fingerprint() == "17fb2e5101d5bfb0"
    assert _tile().fingerprint() == tile.fingerprint()
    changed = _tile()
    changed.heights[0, 0] += 1e-9
    assert changed.fingerprint() != tile.fingerprint()
    assert DemTile(tile.heights, (10.0, 20.0), origin=(1.0, 2.5)).fingerprint() != tile.fingerprint()
    assert DemTile(tile.heights, (10.0, 20.5), origin=(1.0, 2.0)).fingerprint() != tile.fingerprint()


def test_fingerprint_same_file_twice(tmp_path) -> None:
    np.save(tmp_path / "a.npy", np.random.default_rng(0).normal(size=(5, 6)))
    first = load_tile(tmp_path / "a.npy", spacing=3.0)
    second = load_tile(tmp_path / "a.npy", spacing=(3.0, 3.0))
    assert first.fingerprint() == second.fingerprint()


def test_describe_is_json_serialisable_and_has_geo() -> None:
    info = load_tile("jacksboro").describe()
    text = json.dumps(info)
    assert json.loads(text)["geo"]["model"].startswith("WGS-84")
    assert info["shape"] == [344, 403] and info["height_range"] == [236.0, 1076.0]
    assert _tile().describe()["geo"] is None
