"""``neural_region`` inside a filter run: the R it adds is the exact tangent-plane miss.

A quadratic terrain ``h(x) = c + g.(x - x0) + (x - x0)^T A (x - x0) / 2`` is flown by a
constant-velocity filter (``BatchedEKF``, state ``[px, py, vx, vy]``) that measures the
terrain height under the vehicle. At each step the linearizer gets the prior horizontal
covariance ``P_xy``; for a quadratic the tangent plane misses by ``d^T A d / 2`` and, for
``d ~ N(0, P_xy)``, ``E[(d^T A d / 2)^2] = (2 tr((A P)^2) + tr(A P)^2) / 4`` (Gaussian fourth
moments, computed in NumPy). The 3 x 3 Gauss-Hermite rule is exact for it, so the R added
per step must match to round-off (1e-9 relative, float64), and the filter's innovation
variance ``S`` must contain exactly that R.
"""

from __future__ import annotations

import numpy as np
import torch

from neuralmap.filters import BatchedEKF
from neuralmap.linearize import make_linearizer
from neuralmap.linearize.region_variance import ROOT_CHOLESKY
from neuralmap.terrain.base import TerrainModel

CURVATURE = np.array([[2.0e-3, -0.8e-3], [-0.8e-3, 1.2e-3]])  # A, 1/m
GRADIENT = np.array([0.05, -0.03])
CENTRE = np.array([1000.0, -500.0])
R_ALTIMETER = 4.0  # m^2
FIT_VARIANCE = 0.25  # m^2


class QuadraticTerrain(TerrainModel):
    """The quadratic terrain above on a 40 km square map."""

    def __init__(self) -> None:
        super().__init__()
        self.extent = (-20_000.0, 20_000.0, -20_000.0, 20_000.0)

    def forward(self, xy: torch.Tensor) -> torch.Tensor:
        u, v = xy[..., 0] - CENTRE[0], xy[..., 1] - CENTRE[1]
        a, b, c = CURVATURE[0, 0], CURVATURE[0, 1], CURVATURE[1, 1]
        return 300.0 + GRADIENT[0] * u + GRADIENT[1] * v + 0.5 * (a * u * u + 2 * b * u * v + c * v * v)


def closed_form_miss_variance(pos_cov: np.ndarray) -> np.ndarray:
    """``(N,)`` E[(d^T A d / 2)^2] for ``d ~ N(0, pos_cov[k])``."""
    ap = np.einsum("ij,njk->nik", CURVATURE, pos_cov)
    tr = np.trace(ap, axis1=1, axis2=2)
    tr_sq = np.einsum("nij,nji->n", ap, ap)
    return 0.25 * (2.0 * tr_sq + tr**2)


def test_neural_region_adds_the_exact_miss_variance_at_every_step() -> None:
    n, steps, dt = 12, 25, 1.0
    gen = torch.Generator().manual_seed(7)
    dtype = torch.float64
    terrain = QuadraticTerrain()
    linearizer = make_linearizer(
        "neural_region", tile=None, terrain=terrain, fit_variance=FIT_VARIANCE
    )
    F = torch.eye(4, dtype=dtype)
    F[0, 2] = F[1, 3] = dt
    Q = torch.diag(torch.tensor([1.0, 1.0, 0.05, 0.05], dtype=dtype))
    P0 = torch.tensor(
        [[150.0**2, 0.4 * 150 * 90, 0, 0], [0.4 * 150 * 90, 90.0**2, 0, 0],
         [0, 0, 4.0, 0], [0, 0, 0, 4.0]], dtype=dtype,
    )
    truth = torch.zeros(n, 4, dtype=dtype)
    truth[:, :2] = torch.tensor(CENTRE) + 2000.0 * (torch.rand(n, 2, generator=gen, dtype=dtype) - 0.5)
    truth[:, 2:] = torch.tensor([40.0, 25.0]) + 5.0 * torch.randn(n, 2, generator=gen, dtype=dtype)
    x0 = truth + torch.randn(n, 4, generator=gen, dtype=dtype) @ torch.linalg.cholesky(P0).T
    ekf = BatchedEKF(x0, P0)
    added_total, max_rel = 0.0, 0.0
    for _ in range(steps):
        truth = truth @ F.T
        ekf.predict(F, Q)
        x_prior, P_prior = ekf.x.clone(), ekf.P.clone()
        pos_cov = P_prior[:, :2, :2]
        lin = linearizer(x_prior[:, :2], pos_cov)
        report = linearizer.region_report
        assert report is not None
        assert (report.root == ROOT_CHOLESKY).all() and (report.nodes_used == 8).all()

        added = (lin.variance - FIT_VARIANCE).numpy()
        expected = closed_form_miss_variance(pos_cov.numpy())
        np.testing.assert_allclose(added, expected, rtol=1e-9, atol=0)
        max_rel = max(max_rel, float(np.max(np.abs(added / expected - 1.0))))
        added_total += float(expected.mean())

        z = terrain(truth[:, :2]) + R_ALTIMETER**0.5 * torch.randn(n, generator=gen, dtype=dtype)
        H = torch.zeros(n, 4, dtype=dtype)
        H[:, :2] = lin.slope
        diag = ekf.update(z - lin.height, H, R_ALTIMETER + lin.variance)
        assert diag.applied is None or bool(diag.applied.all())
        # The filter used exactly that R: S = h P h^T + R_alt + fit variance + miss variance.
        h = H.numpy()
        s_expected = (
            np.einsum("ni,nij,nj->n", h, P_prior.numpy(), h) + R_ALTIMETER + FIT_VARIANCE + expected
        )
        np.testing.assert_allclose(diag.S.reshape(-1).numpy(), s_expected, rtol=1e-12, atol=0)
    # The test exercises a real effect: the miss variance is a sizeable part of R.
    assert added_total / steps > R_ALTIMETER
    assert max_rel < 1e-9
