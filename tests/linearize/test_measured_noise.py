"""The measured noise table of a linearisation method against closed forms.

``v(σ) = E[(t(p + d) − h(p) − slope(p) · d)²]``, ``d ~ N(0, σ² I)``, ``p`` uniform:

* quadratic terrain ``a x² + b y² + c x y``, map = truth, exact Taylor slope: the miss is
  ``a dx² + b dy² + c dx dy``, ``E[miss²] = σ⁴ (3a² + 3b² + 2ab + c²)`` at every ``p``;
* sine terrain ``A sin(k x)``: averaged over ``p`` (whole periods),
  ``E[miss²] = A² (1 + s − (1 + 2s) e^{−s})``, ``s = k² σ² / 2``;
* plane terrain with a map offset by ``b``: ``E[miss²] = b²`` for every σ (to rounding).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from torch import nn

from neuralmap.exceptions import NeuralMapError
from neuralmap.linearize.autograd import AutogradLinearizer
from neuralmap.linearize.measured_noise import (
    MeasuredNoiseLinearizer,
    fit_offset_scale,
    interpolate_table,
    measure_linearization_noise,
)


class _Quadratic(nn.Module):
    def __init__(self, a: float, b: float, c: float, offset: float = 0.0) -> None:
        super().__init__()
        self.a, self.b, self.c, self.offset = a, b, c, offset

    def forward(self, xy: torch.Tensor) -> torch.Tensor:
        x, y = xy[..., 0] - 5000.0, xy[..., 1] - 5000.0
        return self.a * x * x + self.b * y * y + self.c * x * y + self.offset


class _Sine(nn.Module):
    def __init__(self, amplitude: float, wavelength: float) -> None:
        super().__init__()
        self.amplitude, self.k = amplitude, 2.0 * math.pi / wavelength

    def forward(self, xy: torch.Tensor) -> torch.Tensor:
        return self.amplitude * torch.sin(self.k * xy[..., 0]) + 0.0 * xy[..., 1]


class _Plane(nn.Module):
    def __init__(self, offset: float) -> None:
        super().__init__()
        self.offset = offset

    def forward(self, xy: torch.Tensor) -> torch.Tensor:
        return 0.03 * xy[..., 0] - 0.02 * xy[..., 1] + 100.0 + self.offset


def test_quadratic_terrain_matches_the_closed_form() -> None:
    a, b, c = 2e-4, -1e-4, 1.5e-4
    terrain = _Quadratic(a, b, c)
    sigmas = (0.0, 20.0, 50.0, 100.0)
    table = measure_linearization_noise(AutogradLinearizer(terrain), terrain,
                                        extent=(0.0, 10000.0, 0.0, 10000.0), sigmas=sigmas,
                                        n_points=4000, draws=16, seed=3)
    closed = [s**4 * (3 * a * a + 3 * b * b + 2 * a * b + c * c) for s in sigmas]
    assert table.map_mse_m2[0] == pytest.approx(0.0, abs=1e-12)
    # 64 000 samples of a quartic in Gaussians: ~1.5 % standard error
    np.testing.assert_allclose(table.map_mse_m2[1:], closed[1:], rtol=0.05)
    assert table.variance_m2 == table.map_mse_m2


def test_sine_terrain_matches_the_closed_form_averaged_over_the_map() -> None:
    amplitude, wavelength = 10.0, 400.0
    terrain = _Sine(amplitude, wavelength)
    sigmas = (10.0, 50.0, 100.0, 250.0)
    # the points cover x in [1000, 39000] (margin 4 x 250 m): exactly 95 whole periods
    table = measure_linearization_noise(AutogradLinearizer(terrain), terrain,
                                        extent=(0.0, 40000.0, 0.0, 5000.0), sigmas=sigmas,
                                        n_points=20000, draws=8, seed=1)
    k = 2.0 * math.pi / wavelength
    closed = []
    for s in sigmas:
        q = 0.5 * k * k * s * s
        closed.append(amplitude**2 * (1.0 + q - (1.0 + 2.0 * q) * math.exp(-q)))
    np.testing.assert_allclose(table.map_mse_m2, closed, rtol=0.04)


def test_plane_with_a_map_offset_gives_the_offset_squared_at_every_sigma() -> None:
    truth = _Plane(0.0)
    table = measure_linearization_noise(AutogradLinearizer(_Plane(2.5)), truth,
                                        extent=(0.0, 8000.0, 0.0, 8000.0),
                                        sigmas=(0.0, 30.0, 300.0), n_points=500, draws=4)
    np.testing.assert_allclose(table.map_mse_m2, 6.25, rtol=1e-9)
    np.testing.assert_allclose(table.map_mean_m, -2.5, rtol=1e-9)


def test_interpolation_matches_numpy_and_is_constant_beyond_the_ends() -> None:
    nodes = torch.tensor([0.0, 10.0, 40.0, 100.0], dtype=torch.float64)
    values = torch.tensor([4.0, 6.0, 30.0, 300.0], dtype=torch.float64)
    query = torch.tensor([0.0, 3.0, 10.0, 25.0, 99.0, 100.0, 250.0], dtype=torch.float64)
    got = interpolate_table(nodes, values, query)
    np.testing.assert_allclose(got.numpy(), np.interp(query.numpy(), nodes.numpy(),
                                                      values.numpy()), rtol=1e-12)
    assert torch.isnan(interpolate_table(nodes, values, torch.tensor([float("nan")],
                                                                     dtype=torch.float64)))[0]


def test_wrapper_keeps_height_and_slope_and_reads_the_table_at_the_filter_sigma() -> None:
    terrain = _Quadratic(2e-4, -1e-4, 1.5e-4, offset=1.0)
    inner = AutogradLinearizer(terrain, fit_variance=6.0)
    table = measure_linearization_noise(inner, _Quadratic(2e-4, -1e-4, 1.5e-4),
                                        extent=(0.0, 10000.0, 0.0, 10000.0),
                                        sigmas=(0.0, 20.0, 60.0), n_points=200, draws=2)
    wrapped = MeasuredNoiseLinearizer(inner, table)
    xy = torch.tensor([[4000.0, 5200.0], [6100.0, 4800.0]], dtype=torch.float64)
    cov = torch.tensor([[[900.0, 50.0], [50.0, 700.0]], [[1e4, 0.0], [0.0, 1e4]]],
                       dtype=torch.float64)
    got, ref = wrapped(xy, cov), inner(xy, cov)
    torch.testing.assert_close(got.height, ref.height)
    torch.testing.assert_close(got.slope, ref.slope)
    sigma = np.sqrt([(900.0 + 700.0) / 2.0, 1e4])
    expected = np.interp(sigma, table.sigmas_m, table.variance_m2)
    np.testing.assert_allclose(got.variance.numpy(), expected, rtol=1e-12)
    assert wrapped.terrain is terrain  # the wrapped method's attributes stay reachable
    np.testing.assert_allclose(wrapped(xy).variance.numpy(), table.variance_m2[0])


def test_bad_sigmas_are_refused() -> None:
    terrain = _Plane(0.0)
    with pytest.raises(NeuralMapError, match="strictly increasing"):
        measure_linearization_noise(AutogradLinearizer(terrain), terrain,
                                    extent=(0.0, 1e4, 0.0, 1e4), sigmas=(10.0, 5.0))
    with pytest.raises(NeuralMapError, match="smaller than twice the margin"):
        measure_linearization_noise(AutogradLinearizer(terrain), terrain,
                                    extent=(0.0, 1e3, 0.0, 1e3), sigmas=(0.0, 300.0))


def test_offset_scale_fit_equals_weighted_least_squares() -> None:
    rng = np.random.default_rng(7)
    u = rng.uniform(0.0, 10.0, 500)
    e2 = 3.0 + 2.0 * u + rng.normal(0.0, 1.0, 500)
    w = rng.uniform(0.1, 1.0, 500)
    design = np.stack([np.ones_like(u), u], axis=1) * np.sqrt(w)[:, None]
    expected = np.linalg.lstsq(design, e2 * np.sqrt(w), rcond=None)[0]
    a, b = fit_offset_scale(torch.from_numpy(e2), torch.from_numpy(u), torch.from_numpy(w))
    np.testing.assert_allclose([a, b], expected, rtol=1e-9)
    # a negative offset is refused: a = 0 and the mean is kept
    a, b = fit_offset_scale(torch.tensor([0.0, 10.0]), torch.tensor([1.0, 2.0]))
    assert a == 0.0 and b == pytest.approx(5.0 / 1.5)


def test_local_table_scales_the_method_own_variance() -> None:
    terrain = _Sine(10.0, 2000.0)
    inner = AutogradLinearizer(terrain, region_variance=True)
    table = measure_linearization_noise(inner, terrain, extent=(0.0, 10000.0, 0.0, 10000.0),
                                        sigmas=(0.0, 30.0), n_points=400, draws=64, local=True)
    # σ ≪ wavelength: the terrain is locally quadratic, where the region variance is the
    # exact expected miss at each point (its curvature varies along x): e² ≈ 0 + 1 · u
    assert table.scale[1] == pytest.approx(1.0, rel=0.1)
    assert table.variance_m2[1] < 0.1 * table.map_mse_m2[1]
    xy = torch.tensor([[4000.0, 5200.0]], dtype=torch.float64)
    cov = torch.eye(2, dtype=torch.float64).unsqueeze(0) * 900.0
    got = MeasuredNoiseLinearizer(inner, table)(xy, cov).variance
    expected = table.variance_m2[1] + table.scale[1] * inner(xy, cov).variance
    torch.testing.assert_close(got, expected)
