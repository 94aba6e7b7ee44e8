"""Rate-distortion helpers: BD-rate and bytes at equal error against closed forms."""

from __future__ import annotations

import math

import pytest

from neuralmap.studies.rate_distortion import bd_rate, bytes_at_error


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
