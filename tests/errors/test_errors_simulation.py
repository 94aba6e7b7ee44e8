"""AR sequences and fields against theoretical autocovariances; the DEM error tile."""

from __future__ import annotations

import numpy as np
import pytest
from statsmodels.tsa.arima_process import ArmaProcess

from neuralmap.dem import synthetic_tile
from neuralmap.errors import (
    DEM_ERROR_AR1,
    DEM_ERROR_AR2,
    DEM_ERROR_SIGMA,
    add_dem_error,
    ar_error_field,
    simulate_ar,
)


@pytest.mark.parametrize("phi", [DEM_ERROR_AR1, DEM_ERROR_AR2, (1.2, -0.5)])
def test_batched_sequences_have_the_model_autocovariance(phi: tuple[float, ...]) -> None:
    x = simulate_ar(200, phi=phi, sigma=2.0, batch=4000, seed=1)
    assert x.shape == (4000, 200)
    # ensemble statistics at the start and at the end: stationary from the first sample
    acf = ArmaProcess(np.r_[1, -np.array(phi)], [1]).acf(3)
    for t in (0, 150):
        var = np.mean(x[:, t] ** 2)
        assert var == pytest.approx(4.0, rel=0.07)  # 4000 draws: ±2.2 % std
        for k in (1, 2):
            rho = np.mean(x[:, t] * x[:, t + k]) / var
            assert rho == pytest.approx(acf[k], abs=0.04)


def test_seeding() -> None:
    np.testing.assert_array_equal(simulate_ar(50, seed=3), simulate_ar(50, seed=3))
    assert not np.allclose(simulate_ar(50, seed=3), simulate_ar(50, seed=4))
    assert simulate_ar(50).shape == (50,)


def test_field_is_separable_ar_along_grid_lines() -> None:
    f = ar_error_field((40, 50), phi=(0.5315,), phi_north=(0.2,), batch=400, seed=2)
    assert f.shape == (400, 40, 50)
    var = np.mean(f**2)
    assert var == pytest.approx(DEM_ERROR_SIGMA**2, rel=0.03)
    east = np.mean(f[..., 1:] * f[..., :-1]) / var
    north = np.mean(f[:, 1:] * f[:, :-1]) / var
    diag = np.mean(f[:, 1:, 1:] * f[:, :-1, :-1]) / var
    assert east == pytest.approx(0.5315, abs=0.02)
    assert north == pytest.approx(0.2, abs=0.02)
    assert diag == pytest.approx(0.5315 * 0.2, abs=0.02)
    # corner node variance (the start of both recursions) is right too
    assert np.mean(f[:, 0, 0] ** 2) == pytest.approx(DEM_ERROR_SIGMA**2, rel=0.2)


def test_add_dem_error_returns_new_tile() -> None:
    tile = synthetic_tile((60, 80), spacing=100.0, seed=0)
    tile.heights[3, 4] = np.nan
    before = tile.heights.copy()
    noisy = add_dem_error(tile, seed=5)
    np.testing.assert_array_equal(tile.heights, before)  # the truth is untouched
    assert noisy is not tile and noisy.shape == tile.shape
    assert noisy.spacing == tile.spacing and noisy.origin == tile.origin
    assert np.isnan(noisy.heights[3, 4])
    err = (noisy.heights - tile.heights)[np.isfinite(before)]
    assert np.std(err) == pytest.approx(DEM_ERROR_SIGMA, rel=0.1)
    field = ar_error_field(tile.shape, seed=5)
    d = noisy.heights - tile.heights
    ok = np.isfinite(d)
    np.testing.assert_allclose(d[ok], field[ok], atol=1e-9)
    assert noisy.meta["dem_error"]["phi_east"] == list(DEM_ERROR_AR1)


def test_correlation_length_conversion_and_tile_option() -> None:
    from neuralmap.errors import ar1_coefficient, correlation_length

    length = correlation_length(0.5315)
    assert length == pytest.approx(158.2, abs=0.1)
    assert ar1_coefficient(length, 100.0) == pytest.approx(0.5315, rel=1e-12)
    tile = synthetic_tile((200, 100), spacing=(30.0, 60.0), seed=1)
    noisy = add_dem_error(tile, correlation_length_m=length, seed=2)
    d = noisy.heights - tile.heights
    var = np.mean(d**2)
    assert np.mean(d[:, 1:] * d[:, :-1]) / var == pytest.approx(np.exp(-30 / length), abs=0.03)
    assert np.mean(d[1:] * d[:-1]) / var == pytest.approx(np.exp(-60 / length), abs=0.03)
