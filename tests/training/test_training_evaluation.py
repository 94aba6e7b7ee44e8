"""Fit evaluation: metrics, autocorrelation and the fit figures against independent references."""

from __future__ import annotations

import math

import numpy as np
import torch
from matplotlib.figure import Figure

from neuralmap.dem.tile import DemTile
from neuralmap.terrain.base import TerrainModel
from neuralmap.terrain.grid import GridTerrain
from neuralmap.training.evaluation import (
    FitAccumulator,
    evaluate_fit,
    height_and_slope,
    residual_autocorrelation,
)
from neuralmap.viz.fit import (
    figure_to_rgb,
    hillshade_comparison_figure,
    residual_autocorrelation_figure,
    residual_histogram_figure,
    residual_map_figure,
)


class _Plane(TerrainModel):
    """h = a x + b y + c + offset (float64), with one dummy parameter."""

    def __init__(self, a: float, b: float, c: float) -> None:
        super().__init__()
        self.a, self.b, self.c = a, b, c
        self.dummy = torch.nn.Parameter(torch.zeros((), dtype=torch.float64))
        self.extent = (0.0, 1.0, 0.0, 1.0)

    def forward(self, xy: torch.Tensor) -> torch.Tensor:
        return self.a * xy[..., 0] + self.b * xy[..., 1] + self.c + self.dummy


def test_height_and_slope_inside_inference_mode_matches_closed_form() -> None:
    plane = _Plane(0.01, -0.02, 5.0)
    xy = torch.rand(10, 2, dtype=torch.float64) * 100
    with torch.inference_mode():
        h, g = height_and_slope(plane, xy, chunk=3)
    expected = 0.01 * xy[:, 0] - 0.02 * xy[:, 1] + 5
    np.testing.assert_allclose(h.numpy(), expected.numpy(), atol=1e-12)
    np.testing.assert_allclose(g.numpy(), np.tile([0.01, -0.02], (10, 1)), atol=1e-12)


def test_accumulator_matches_direct_formulas_in_chunks() -> None:
    rng = np.random.default_rng(0)
    pred, target = rng.normal(size=1000), rng.normal(size=1000)
    sp, sr = rng.normal(size=(1000, 2)), rng.normal(size=(1000, 2))
    acc = FitAccumulator()
    for sl in (slice(0, 300), slice(300, 300), slice(300, 1000)):
        acc.update(*(torch.as_tensor(a[sl]) for a in (pred, target, sp, sr)))
    m = acc.metrics()
    err = pred - target
    assert m["n_nodes"] == 1000
    assert math.isclose(m["rmse_m"], float(np.sqrt(np.mean(err**2))), rel_tol=1e-12)
    assert math.isclose(m["max_abs_m"], float(np.abs(err).max()), rel_tol=1e-12)
    assert math.isclose(m["mean_m"], float(err.mean()), rel_tol=1e-9)
    assert math.isclose(m["std_m"], float(err.std()), rel_tol=1e-9)
    assert math.isclose(m["slope_rmse"], float(np.sqrt(np.mean(((sp - sr) ** 2).sum(1)))),
                        rel_tol=1e-12)
    # all-reduce round trip (single process: sums and maxima are the state itself)
    state = acc.as_tensor()
    assert FitAccumulator.from_tensors(state, state).metrics() == m


def test_autocorrelation_of_ar1_rows_and_white_columns() -> None:
    rng = np.random.default_rng(1)
    ny, nx, phi = 400, 400, 0.7
    e = np.zeros((ny, nx))
    noise = rng.normal(size=(ny, nx))
    e[:, 0] = noise[:, 0] / math.sqrt(1 - phi**2)
    for j in range(1, nx):  # AR(1) along each row (east), independent rows
        e[:, j] = phi * e[:, j - 1] + noise[:, j]
    e[10:20, 30:60] = np.nan
    acf_x, acf_y, n, _ = residual_autocorrelation(e, max_lag=5)
    assert n == ny * nx - 300
    np.testing.assert_allclose(acf_x, phi ** np.arange(6), atol=0.02)
    assert np.all(np.abs(acf_y[1:]) < 3 * 1.96 / math.sqrt(n))
    # independent reference for one lag: Pearson-like sum over valid pairs
    ec = e - np.nanmean(e)
    pairs = ec[:, :-2] * ec[:, 2:]
    ref = np.nanmean(pairs) / np.nanmean(ec**2)
    assert math.isclose(acf_x[2], ref, rel_tol=1e-10)


def test_evaluate_fit_of_the_dem_itself_is_exact() -> None:
    rng = np.random.default_rng(2)
    heights = 200 + rng.normal(0, 30, (17, 23))
    heights[4, 5] = np.nan
    tile = DemTile(heights=heights, spacing=(25.0, 35.0), origin=(100.0, 200.0), name="x")
    grid = GridTerrain(tile, method="bicubic", dtype=torch.float64)
    grid.register_parameter("dummy", torch.nn.Parameter(torch.zeros((), dtype=torch.float64)))
    result = evaluate_fit(grid, tile, max_lag=3)
    m = result.metrics
    assert m["n_nodes"] == 17 * 23 - 1 and m["n_void"] == 1
    assert m["rmse_m"] < 1e-9 and m["max_abs_m"] < 1e-9 and m["slope_rmse"] < 1e-12
    assert np.isnan(result.residual[4, 5]) and np.isfinite(result.fitted).all()
    assert result.acf_x.shape == (4,) and result.acf_y.shape == (4,)


def test_evaluate_fit_known_offset_and_slope_error() -> None:
    y, x = np.mgrid[0:10, 0:12]
    tile = DemTile(heights=0.1 * x * 20.0 + 0.05 * y * 30.0 + 100, spacing=(20.0, 30.0), name="p")
    # model: plane with slope (0.12, 0.05), offset +0.5 m -> slope error 0.02, bias 0.5
    plane = _Plane(0.12, 0.05, 100.5)
    m = evaluate_fit(plane, tile).metrics
    err = 0.02 * x * 20.0 + 0.5
    assert math.isclose(m["rmse_m"], float(np.sqrt(np.mean(err**2))), rel_tol=1e-9)
    assert math.isclose(m["max_abs_m"], float(err.max()), rel_tol=1e-9)
    # bicubic slope of a plane is exact, so the slope error is exactly (0.02, 0)
    assert math.isclose(m["slope_rmse"], 0.02, rel_tol=1e-9)


def test_fit_figures_render() -> None:
    rng = np.random.default_rng(3)
    dem = 100 + rng.normal(size=(30, 40)).cumsum(1)
    dem[2:4, 5:9] = np.nan
    fitted = np.nan_to_num(dem, nan=100.0) + rng.normal(0, 0.5, dem.shape)
    residual = np.where(np.isfinite(dem), fitted - dem, np.nan)
    extent = (0.0, 39 * 30.0, 0.0, 29 * 30.0)
    acf_x, acf_y, n, _ = residual_autocorrelation(residual, 10)
    figures = [
        residual_map_figure(residual, extent),
        hillshade_comparison_figure(dem, fitted, (30.0, 30.0), extent),
        residual_histogram_figure(residual),
        residual_autocorrelation_figure(acf_x, acf_y, (30.0, 30.0), n),
    ]
    for figure in figures:
        assert isinstance(figure, Figure)
        rgb = figure_to_rgb(figure)
        assert rgb.ndim == 3 and rgb.shape[2] == 3 and rgb.dtype == np.uint8
        assert rgb.std() > 0  # something was drawn
    # the residual map uses symmetric limits (a high percentile of |residual|)
    image = figures[0].axes[0].images[0]
    lo, hi = image.get_clim()
    assert lo == -hi and math.isclose(hi, float(np.nanpercentile(np.abs(residual), 99.5)))
    full = residual_map_figure(residual, extent, percentile=100).axes[0].images[0]
    assert math.isclose(full.get_clim()[1], float(np.nanmax(np.abs(residual))))
    assert image.get_cmap().name.startswith("RdBu_r")
