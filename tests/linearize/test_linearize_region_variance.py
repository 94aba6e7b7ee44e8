"""Region variance of the tangent plane: nodes off the map, non-PD covariances, dtypes.

Reference: for a quadratic terrain ``h(x) = c + g.x + x^T H x / 2`` the tangent plane at ``p``
misses by ``e(d) = d^T H d / 2`` and, for ``d ~ N(0, S)``, the Gaussian fourth moments give
``E[e^2] = (2 tr((HS)^2) + tr(HS)^2) / 4`` (computed here in NumPy, float64).
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from neuralmap.linearize import AutogradLinearizer, RegionReport
from neuralmap.linearize.region_variance import (
    ROOT_CHOLESKY,
    ROOT_EIGEN_CLAMPED,
    ROOT_NONE,
    covariance_root,
)
from neuralmap.terrain.base import TerrainModel

HESSIAN = np.array([[0.02, 0.012], [0.012, -0.01]])
GRADIENT = np.array([0.3, -0.2])
CENTRE = (2500.0, 2500.0)


class QuadraticMap(TerrainModel):
    """The quadratic above (about CENTRE) on a finite extent, NaN outside it (no data)."""

    def __init__(self, extent: tuple[float, float, float, float]) -> None:
        super().__init__()
        self.extent = extent

    def forward(self, xy: torch.Tensor) -> torch.Tensor:
        x, y = xy[..., 0] - CENTRE[0], xy[..., 1] - CENTRE[1]
        a, b, c = HESSIAN[0, 0], HESSIAN[0, 1], HESSIAN[1, 1]
        h = 100.0 + GRADIENT[0] * x + GRADIENT[1] * y + 0.5 * (a * x * x + 2 * b * x * y + c * y * y)
        return torch.where(self.contains(xy), h, torch.full_like(h, float("nan")))


def closed_form(cov: np.ndarray) -> float:
    hs = HESSIAN @ cov
    return 0.25 * (2.0 * np.trace(hs @ hs) + np.trace(hs) ** 2)


def miss(d: np.ndarray) -> float:
    return 0.5 * float(d @ HESSIAN @ d)


def run(
    xy: list[list[float]], cov: np.ndarray, dtype: torch.dtype,
    extent: tuple[float, float, float, float] = (0.0, 5000.0, 0.0, 5000.0),
) -> tuple[np.ndarray, RegionReport]:
    lin = AutogradLinearizer(QuadraticMap(extent), region_variance=True)
    points = torch.tensor(xy, dtype=dtype)
    pos_cov = torch.as_tensor(cov, dtype=dtype)
    if pos_cov.ndim == 2:
        pos_cov = pos_cov.expand(len(xy), 2, 2)
    out = lin(points, pos_cov)
    assert out.variance.dtype == dtype
    assert lin.region_report is not None
    return out.variance.double().numpy(), lin.region_report


#: float32: heights up to ~5e4 m carry ~3e-3 m rounding, so the miss (~10 m) and its square
#: are good to a few 1e-4 relative.
TOL = {torch.float64: dict(rtol=1e-10, atol=1e-12), torch.float32: dict(rtol=3e-3, atol=1e-3)}
DTYPES = [torch.float64, torch.float32]


@pytest.mark.parametrize("dtype", DTYPES)
def test_full_rule_inside_the_map_is_exact(dtype: torch.dtype) -> None:
    cov = np.array([[300.0**2, 0.3 * 300 * 200], [0.3 * 300 * 200, 200.0**2]])
    variance, report = run([[2500.0, 2500.0], [1200.0, 3100.0]], cov, dtype)
    np.testing.assert_allclose(variance, closed_form(cov), **TOL[dtype])
    assert report.nodes_used.tolist() == [8, 8]
    np.testing.assert_allclose(report.coverage.double().numpy(), 1.0, rtol=0, atol=1e-6)
    assert report.root.tolist() == [ROOT_CHOLESKY] * 2


@pytest.mark.parametrize("dtype", DTYPES)
def test_nodes_off_one_side_are_mirrored_and_stay_exact(dtype: torch.dtype) -> None:
    """Estimate 200 m from the west border, sqrt(3) sigma_x = 520 m: the three western
    nodes fall off the map (where it returns NaN); their mirror images stand in for them."""
    cov = np.array([[300.0**2, 0.3 * 300 * 200], [0.3 * 300 * 200, 200.0**2]])
    variance, report = run([[200.0, 2500.0]], cov, dtype)
    assert np.isfinite(variance).all()
    np.testing.assert_allclose(variance, closed_form(cov), **TOL[dtype])
    assert report.nodes_used.tolist() == [5]
    np.testing.assert_allclose(report.coverage.double().numpy(), 1.0, rtol=0, atol=1e-6)


@pytest.mark.parametrize("dtype", DTYPES)
def test_pairs_entirely_off_the_map_are_dropped_and_weights_renormalised(
    dtype: torch.dtype,
) -> None:
    """A map 600 m wide, estimate in its middle, sigma_x = 300 m: every node at
    x +- 520 m is off the map; only the pair (0, +-sqrt(3) sigma_y) is left. With the
    centre (weight 4/9, zero miss) and that pair (2/9), the renormalised rule gives
    (2/9 e^2) / (6/9) = e^2 / 3."""
    sx, sy = 300.0, 200.0
    cov = np.diag([sx**2, sy**2])
    variance, report = run([[300.0, 2500.0]], cov, dtype, extent=(0.0, 600.0, 0.0, 5000.0))
    e = miss(np.array([0.0, math.sqrt(3.0) * sy]))
    np.testing.assert_allclose(variance, [e**2 / 3.0], **TOL[dtype])
    assert report.nodes_used.tolist() == [2]
    np.testing.assert_allclose(report.coverage.double().numpy(), [6.0 / 9.0], rtol=1e-6)


@pytest.mark.parametrize("dtype", DTYPES)
def test_no_usable_node_gives_zero_and_says_so(dtype: torch.dtype) -> None:
    # Estimate far off the map: every node (and the height itself) is NaN there.
    variance, report = run([[-9000.0, -9000.0]], np.diag([300.0**2, 200.0**2]), dtype)
    assert variance.tolist() == [0.0]
    assert report.nodes_used.tolist() == [0]
    np.testing.assert_allclose(report.coverage.double().numpy(), [4.0 / 9.0], rtol=1e-6)


@pytest.mark.parametrize("dtype", DTYPES)
def test_singular_and_indefinite_covariances_use_the_clamped_root(dtype: torch.dtype) -> None:
    singular = 100.0 * np.array([[4.0, 2.0], [2.0, 1.0]])  # rank 1: Cholesky breaks down
    indefinite = np.array([[100.0, 300.0], [300.0, 100.0]])  # eigenvalues 400, -200
    clamped = np.full((2, 2), 200.0)  # 400 v v^T with v = (1, 1) / sqrt(2)
    diagonal_negative = np.array([[400.0, 0.0], [0.0, -100.0]])
    covs = np.stack([singular, indefinite, diagonal_negative])
    variance, report = run([[2500.0, 2500.0]] * 3, covs, dtype)
    assert np.isfinite(variance).all()
    expected = [closed_form(singular), closed_form(clamped), closed_form(np.diag([400.0, 0.0]))]
    np.testing.assert_allclose(variance, expected, **TOL[dtype])
    assert report.root.tolist() == [ROOT_EIGEN_CLAMPED] * 3


@pytest.mark.parametrize("dtype", DTYPES)
def test_non_finite_covariance_gives_zero_variance_and_a_flag(dtype: torch.dtype) -> None:
    good = np.diag([300.0**2, 200.0**2])
    bad = np.array([[np.nan, 0.0], [0.0, 1.0]])
    infinite = np.array([[np.inf, 0.0], [0.0, 1.0]])
    variance, report = run([[2500.0, 2500.0]] * 3, np.stack([good, bad, infinite]), dtype)
    np.testing.assert_allclose(variance, [closed_form(good), 0.0, 0.0], **TOL[dtype])
    assert report.root.tolist() == [ROOT_CHOLESKY, ROOT_NONE, ROOT_NONE]


def test_covariance_root_reproduces_the_psd_part() -> None:
    covs = torch.tensor(
        [[[9.0, 3.0], [3.0, 5.0]], [[4.0, 2.0], [2.0, 1.0]], [[1.0, 3.0], [3.0, 1.0]]],
        dtype=torch.float64,
    )
    root, status = covariance_root(covs)
    assert status.tolist() == [ROOT_CHOLESKY, ROOT_EIGEN_CLAMPED, ROOT_EIGEN_CLAMPED]
    # Nearest PSD matrix in NumPy: eigenvalues clamped at zero.
    values, vectors = np.linalg.eigh(covs.numpy())
    psd = np.einsum("nij,nj,nkj->nik", vectors, np.clip(values, 0.0, None), vectors)
    np.testing.assert_allclose((root @ root.transpose(-1, -2)).numpy(), psd, rtol=0, atol=1e-12)
