"""Sample tiles: matplotlib's topobathy DEM in a tile-local metric frame."""

from __future__ import annotations

import math

import numpy as np
import pytest

from neuralmap.dem import load_tile
from neuralmap.exceptions import NeuralMapError


def _raw() -> dict[str, np.ndarray]:
    from matplotlib import cbook

    data = cbook.get_sample_data("topobathy.npz")
    return {k: np.asarray(data[k], dtype=np.float64) for k in data.files}


def test_topobathy_is_land_heights_on_an_even_metric_grid() -> None:
    tile = load_tile("topobathy")
    raw = _raw()
    assert tile.shape == (91, 120) and tile.name == "topobathy"
    # the sea surface at 0 m, land heights as in the file
    assert tile.heights.min() == 0.0
    assert tile.meta["n_sea"] == int((tile.heights == 0.0).sum())
    # even latitudes keep the file's first and last rows (row 0 south, as the file)
    np.testing.assert_allclose(tile.heights[0], np.maximum(raw["topo"][0], 0.0))
    np.testing.assert_allclose(tile.heights[-1], np.maximum(raw["topo"][-1], 0.0))
    # interior rows: linear in latitude between the file's rows (closed form at row 45)
    lat = raw["latitude"]
    even = lat[0] + 45 * (lat[-1] - lat[0]) / 90
    k = int(np.searchsorted(lat, even)) - 1
    w = (even - lat[k]) / (lat[k + 1] - lat[k])
    expected = np.maximum((1 - w) * raw["topo"][k] + w * raw["topo"][k + 1], 0.0)
    np.testing.assert_allclose(tile.heights[45], expected, atol=1e-9)
    # spacing: 4 deg of longitude / 119 and 1.97 deg of latitude / 90 at 49 deg N, in metres
    dx, dy = tile.spacing
    lon_step = (raw["longitude"][-1] - raw["longitude"][0]) / 119
    lat_step = (lat[-1] - lat[0]) / 90
    assert dx == pytest.approx(lon_step * 111_320 * math.cos(math.radians(49.0)), rel=0.01)
    assert dy == pytest.approx(lat_step * 111_132, rel=0.01)
    assert tile.origin == (0.0, 0.0)


def test_topobathy_takes_no_options() -> None:
    with pytest.raises(NeuralMapError, match="topobathy"):
        load_tile("topobathy", spacing=30.0)
