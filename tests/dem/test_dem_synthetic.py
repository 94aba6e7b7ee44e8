"""Synthetic fractal terrain: seeded, any size, scaled, and of the requested roughness."""

from __future__ import annotations

import numpy as np
import pytest

from neuralmap.dem import load_tile, synthetic_tile
from neuralmap.dem.synthetic import SYNTHETIC_BASE_HEIGHT, fractal_surface
from neuralmap.exceptions import NeuralMapError


def test_seeded_and_deterministic() -> None:
    a = synthetic_tile((40, 50), seed=3)
    b = synthetic_tile((40, 50), seed=3)
    c = synthetic_tile((40, 50), seed=4)
    np.testing.assert_array_equal(a.heights, b.heights)
    assert a.fingerprint() == b.fingerprint()
    assert not np.array_equal(a.heights, c.heights)


@pytest.mark.parametrize("shape", [(2, 2), (7, 300), (300, 7), (129, 64)])
def test_any_shape_range_and_spacing(shape: tuple[int, int]) -> None:
    tile = synthetic_tile(shape, spacing=(12.5, 40.0), relief=250.0)
    assert tile.shape == shape and tile.spacing == (12.5, 40.0) and tile.n_void == 0
    assert np.nanmin(tile.heights) == pytest.approx(SYNTHETIC_BASE_HEIGHT, abs=1e-9)
    assert np.nanmax(tile.heights) == pytest.approx(SYNTHETIC_BASE_HEIGHT + 250.0, abs=1e-9)
    assert tile.origin == (0.0, 0.0) and tile.name == "synthetic"


def test_defaults_and_sample_name_forms() -> None:
    tile = synthetic_tile()
    assert tile.shape == (128, 128) and tile.spacing == (30.0, 30.0)
    np.testing.assert_array_equal(load_tile("synthetic").heights, tile.heights)
    assert load_tile("synthetic:64").shape == (64, 64)
    assert load_tile("Synthetic:20x30", spacing=5, name="s").shape == (20, 30)
    tile = load_tile("synthetic", shape=[16, 24], seed=2, relief=10.0, hurst=0.5)
    np.testing.assert_array_equal(
        tile.heights, synthetic_tile((16, 24), seed=2, relief=10.0, hurst=0.5).heights
    )


def _structure_hurst(z: np.ndarray) -> float:
    """Hurst exponent from the structure function E[(z(x+r) - z(x))^2] ~ r^(2H)."""
    lags = np.array([1, 2, 4, 8, 16])
    sf = [np.mean((z[:, k:] - z[:, :-k]) ** 2) + np.mean((z[k:] - z[:-k]) ** 2) for k in lags]
    return float(np.polyfit(np.log(lags), np.log(sf), 1)[0] / 2)


def test_hurst_exponent_is_what_was_asked() -> None:
    # Spectral synthesis with PSD ~ k^-(2H+2) gives a surface whose increments scale as r^H
    # (Voss 1988); the discrete grid biases the estimate upward a little at low H.
    est = {h: _structure_hurst(fractal_surface((256, 256), hurst=h, seed=1)) for h in (0.5, 0.8)}
    assert abs(est[0.5] - 0.5) < 0.12 and abs(est[0.8] - 0.8) < 0.12
    assert est[0.8] > est[0.5] + 0.15


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"shape": (1, 10)}, "shape"),
        ({"shape": (10.5, 10)}, "shape"),
        ({"spacing": 0.0}, "spacing"),
        ({"spacing": (30.0, float("nan"))}, "spacing"),
        ({"relief": -1.0}, "relief"),
        ({"hurst": 0.0}, "hurst"),
        ({"hurst": 1.5}, "hurst"),
    ],
)
def test_bad_arguments(kwargs: dict, match: str) -> None:
    with pytest.raises(NeuralMapError, match=match):
        synthetic_tile(**kwargs)
