"""Synthetic region generator: the jacksboro spectrum, written memory-mapped."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from neuralmap.dem import load_tile
from neuralmap.dem.region import (
    JACKSBORO_SPECTRUM,
    JACKSBORO_STD_M,
    corner_wavenumber,
    synthetic_region,
)
from neuralmap.lab.truth_terrain import spectral_slope


def test_jacksboro_constants_match_the_sample() -> None:
    tile = load_tile("jacksboro")
    amplitude, beta = spectral_slope(tile.heights, tile.spacing)
    assert (amplitude, beta) == pytest.approx(JACKSBORO_SPECTRUM, rel=1e-9)
    assert float(np.nanstd(tile.heights)) == pytest.approx(JACKSBORO_STD_M, rel=1e-9)


def test_corner_wavenumber_closed_form() -> None:
    a, beta, std = 2e-7, 4.0, 100.0
    k_c = corner_wavenumber(a, beta, std)
    # sigma^2 = 2 pi A k_c^(2-beta) (1/(beta-2) + 1/2) by direct radial integration
    k = np.geomspace(k_c, 1e3, 200_001)
    integrand = 2 * np.pi * k * a * k ** (-beta)
    tail = np.trapezoid(integrand, k)
    flat = np.pi * k_c**2 * a * k_c ** (-beta)
    assert tail + flat == pytest.approx(std**2, rel=1e-4)


def test_region_has_the_spectrum_and_is_memory_mapped(tmp_path: Path) -> None:
    info = synthetic_region(tmp_path / "r.npy", shape=(384, 512), spacing=100.0, seed=3)
    array = np.load(tmp_path / "r.npy", mmap_mode="r")
    assert isinstance(array, np.memmap) and array.dtype == np.float32
    assert array.shape == (384, 512)
    amplitude, beta = spectral_slope(np.asarray(array, dtype=np.float64), (100.0, 100.0))
    assert beta == pytest.approx(JACKSBORO_SPECTRUM[1], abs=0.3)
    assert 0.4 < amplitude / JACKSBORO_SPECTRUM[0] < 2.5
    assert float(array.std()) == pytest.approx(JACKSBORO_STD_M, rel=0.3)
    assert json.loads((tmp_path / "r.npy.json").read_text())["seed"] == 3
    assert info["shape"] == [384, 512]
    again = synthetic_region(tmp_path / "s.npy", shape=(384, 512), spacing=100.0, seed=3)
    np.testing.assert_array_equal(np.load(tmp_path / "s.npy"), array)
    assert again["measured_std_m"] == info["measured_std_m"]
