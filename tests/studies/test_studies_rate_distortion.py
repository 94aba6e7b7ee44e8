"""Rate-distortion helpers: BD-rate and bytes at equal error against closed forms."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.fft import idctn

from neuralmap.studies.rate_distortion import bd_rate, bytes_at_error, gaussian_rd_bytes


def test_bd_rate_of_a_curve_at_half_the_bytes_is_minus_fifty_percent() -> None:
    errors = [0.5, 1.0, 2.0, 5.0]
    sizes = [8000.0, 5000.0, 3000.0, 1500.0]
    assert bd_rate(sizes, errors, [s / 2 for s in sizes], errors) == pytest.approx(-0.5)
    assert bd_rate(sizes, errors, [3 * s for s in sizes], errors) == pytest.approx(2.0)
    assert bd_rate(sizes, errors, sizes, errors) == pytest.approx(0.0, abs=1e-12)


def test_bd_rate_between_power_laws_is_the_mean_log_ratio() -> None:
    """A: R = 1000 e^-1, B: R = 600 e^-1.5 over log e in [0, log 4]: the mean of
    log(R_B / R_A) = log 0.6 - 0.5 log e is log 0.6 - 0.25 log 4 (closed form)."""
    grid = [1.0, 1.25, 1.5, 2.0, 2.5, 3.0, 3.5, 4.0]
    dense = [1.0 + 3.0 * k / 400 for k in range(401)]
    sizes_a = [1000.0 / e for e in grid]
    sizes_b = [600.0 / e**1.5 for e in dense]
    expected = math.expm1(math.log(0.6) - 0.25 * math.log(4.0))
    # A is exact in log-log (a line); B is sampled densely, so linear interpolation is exact
    # to 1e-5 relative
    assert bd_rate(sizes_a, grid, sizes_b, dense) == pytest.approx(expected, rel=1e-4)


def test_bd_rate_without_overlap_or_points_is_none() -> None:
    assert bd_rate([100.0, 50.0], [1.0, 2.0], [10.0, 5.0], [3.0, 4.0]) is None
    assert bd_rate([100.0], [1.0], [10.0, 5.0], [1.0, 2.0]) is None


def test_bytes_at_error_interpolates_in_log_log_and_never_extrapolates() -> None:
    sizes, errors = [4000.0, 1000.0], [1.0, 4.0]  # R = 4000 / e
    assert bytes_at_error(sizes, errors, 2.0) == pytest.approx(2000.0)
    assert bytes_at_error(sizes, errors, 1.0) == pytest.approx(4000.0)
    assert bytes_at_error(sizes, errors, 0.5) is None
    assert bytes_at_error(sizes, errors, 8.0) is None
    # a dominated point (larger and less accurate) is not on the front and is ignored
    assert bytes_at_error([*sizes, 9000.0], [*errors, 3.0], 2.0) == pytest.approx(2000.0)


def test_gaussian_rd_of_white_noise_is_the_closed_form() -> None:
    """White Gaussian noise of variance σ²: R(D) = n/2 log2(σ²/D) bits for D < σ²
    (Cover & Thomas, Thm. 10.3.2); the smoothed spectrum is flat up to sampling noise."""
    rng = np.random.default_rng(0)
    field = 10.0 * rng.standard_normal((128, 160))
    n, var = field.size, float(np.var(field))
    expected = n / 2 * math.log2(var / 1.0) / 8
    assert gaussian_rd_bytes(field, 1.0) == pytest.approx(expected, rel=1e-2)
    assert gaussian_rd_bytes(field, 20.0) == 0.0


def test_gaussian_rd_oracle_water_fills_two_variances_exactly() -> None:
    """DCT coefficients ±a on the low quarter, ±b elsewhere (oracle variances a², b²):
    below b² every coefficient gets ½ log2(σ²/D); above it the water level θ solves
    f·θ + (1 - f)·b² = D and only the low coefficients are coded."""
    ny, nx, a, b = 64, 96, 20.0, 2.0
    ky, kx = np.meshgrid(np.arange(ny) / ny, np.arange(nx) / nx, indexing="ij")
    low = np.hypot(ky, kx) < 0.25
    low[0, 0] = False  # the mean: removed by the function
    signs = np.where(np.random.default_rng(1).random((ny, nx)) < 0.5, -1.0, 1.0)
    coefficients = signs * np.where(low, a, b)
    coefficients[0, 0] = 0.0
    field = idctn(coefficients, norm="ortho") + 300.0
    n, f = field.size, low.mean()
    small = 1.0  # D < b²: every coefficient but the (zero-power) mean is coded at θ
    theta = small * n / (n - 1)  # (n - 1)/n · θ = D
    expected = ((low.sum() * 0.5 * math.log2(a**2 / theta))
                + ((~low).sum() - 1) * 0.5 * math.log2(b**2 / theta)) / 8
    assert gaussian_rd_bytes(field, math.sqrt(small), oracle=True) == pytest.approx(expected, rel=1e-9)
    d = 10.0  # b² < D: θ = (D - (1 - f) b²) / f, with the DC term at zero variance in the mean
    theta = (d - ((~low).sum() - 1) / n * b**2) / f
    expected = low.sum() * 0.5 * math.log2(a**2 / theta) / 8
    assert gaussian_rd_bytes(field, math.sqrt(d), oracle=True) == pytest.approx(expected, rel=1e-6)


def test_gaussian_rd_refuses_bad_input() -> None:
    with pytest.raises(ValueError, match="fill voids"):
        gaussian_rd_bytes(np.array([[1.0, float("nan")], [0.0, 1.0]]), 1.0)
    with pytest.raises(ValueError, match="rmse_m must be > 0"):
        gaussian_rd_bytes(np.zeros((4, 4)), 0.0)


def test_innovation_entropy_of_white_gaussian_and_laplace_fields_is_the_closed_form() -> None:
    """h = ½ log2(2πe σ²) for white Gaussian noise, log2(2e b) for white Laplace noise
    (Cover & Thomas, Table 17.1); the estimate is within 0.02 bit of it at 25 000 nodes."""
    from neuralmap.studies.rate_distortion import innovation_entropy_bits

    rng = np.random.default_rng(0)
    gauss = 10.0 * rng.standard_normal((128, 200))
    assert innovation_entropy_bits(gauss) == pytest.approx(
        0.5 * math.log2(2 * math.pi * math.e * 100.0), abs=0.02)
    laplace = rng.laplace(0.0, 3.0, (128, 200))
    assert innovation_entropy_bits(laplace) == pytest.approx(math.log2(2 * math.e * 3.0),
                                                             abs=0.02)


def test_innovation_entropy_of_a_gauss_markov_field_is_its_driving_noise() -> None:
    """x[i, j] = 0.9 x[i, j−1] + w, w ~ N(0, 1): the entropy rate is h(w) = ½ log2(2πe),
    0.7 bit below the marginal entropy ½ log2(2πe / (1 − 0.81)) the predictor removes."""
    from neuralmap.studies.rate_distortion import innovation_entropy_bits

    rng = np.random.default_rng(1)
    w = rng.standard_normal((160, 240))
    x = np.zeros_like(w)
    x[:, 0] = w[:, 0] / math.sqrt(1 - 0.81)
    for j in range(1, w.shape[1]):
        x[:, j] = 0.9 * x[:, j - 1] + w[:, j]
    assert innovation_entropy_bits(x) == pytest.approx(0.5 * math.log2(2 * math.pi * math.e),
                                                       abs=0.02)


def test_shannon_lower_bound_meets_and_undercuts_the_gaussian_function() -> None:
    """White Gaussian noise: the Shannon lower bound is the Gaussian R(D) (equal for
    D < σ²). White Laplace noise of the same variance: it lies ½ log2(π/e) = 0.104 bit per
    node below the Gaussian function — the Gaussian R(D) is an upper bound, not a floor."""
    from neuralmap.studies.rate_distortion import shannon_lower_bound_bytes

    rng = np.random.default_rng(2)
    gauss = 10.0 * rng.standard_normal((128, 160))
    assert shannon_lower_bound_bytes(gauss, 1.0) == pytest.approx(
        gaussian_rd_bytes(gauss, 1.0), rel=5e-3)
    b = 10.0 / math.sqrt(2.0)
    laplace = rng.laplace(0.0, b, (128, 160))
    n = laplace.size
    gap_bits = (gaussian_rd_bytes(laplace, 1.0) - shannon_lower_bound_bytes(laplace, 1.0)) * 8
    assert gap_bits / n == pytest.approx(0.5 * math.log2(math.pi / math.e), abs=0.02)
    assert shannon_lower_bound_bytes(gauss, 1e3) == 0.0
    with pytest.raises(ValueError, match="rmse_m must be > 0"):
        shannon_lower_bound_bytes(gauss, 0.0)
    with pytest.raises(ValueError, match="fill voids"):
        shannon_lower_bound_bytes(np.full((8, 8), np.nan), 1.0)


def test_the_roughness_context_finds_the_entropy_rate_of_a_non_stationary_field() -> None:
    """White Gaussian noise with σ = 1 m on the left half and 10 m on the right: the entropy
    rate is the mean of ½ log2(2πe σ²) over the halves; the marginal entropy of the mixture
    is 0.6 bit higher, and the causal roughness context removes that excess (to 0.06 bit)."""
    from neuralmap.studies.rate_distortion import innovation_entropy_bits

    rng = np.random.default_rng(3)
    field = rng.standard_normal((160, 240))
    field[:, 120:] *= 10.0
    rate = 0.5 * (0.5 * math.log2(2 * math.pi * math.e) + 0.5 * math.log2(
        2 * math.pi * math.e * 100.0))
    marginal = innovation_entropy_bits(field, context_bins=1)
    conditional = innovation_entropy_bits(field)
    assert marginal > rate + 0.5
    assert conditional == pytest.approx(rate, abs=0.06)
    with pytest.raises(ValueError, match="context_bins"):
        innovation_entropy_bits(field, context_bins=0)
