"""The linearisation error m2 (true terrain minus fitted plane at the estimate) and the
Table 2-style summary of error sequences."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from neuralmap.dem import DemTile
from neuralmap.errors import linearization_error, simulate_ar, summarise_error_sequences
from neuralmap.linearize.base import Linearization
from neuralmap.linearize.factory import make_linearizer
from neuralmap.terrain import GridTerrain


class _Plane(torch.nn.Module):
    """Stub linearizer: the plane h = 10 + 0.1 x (records the covariance it received)."""

    def forward(self, xy: torch.Tensor, pos_cov: torch.Tensor | None = None) -> Linearization:
        self.seen = pos_cov
        n = xy.shape[0]
        slope = torch.tensor([0.1, 0.0], dtype=xy.dtype).expand(n, 2)
        return Linearization(10 + 0.1 * xy[:, 0], slope, torch.zeros(n, dtype=xy.dtype))


def test_m2_is_truth_minus_plane() -> None:
    xy = torch.rand(3, 7, 2, dtype=torch.float64) * 100
    cov = torch.eye(2, dtype=torch.float64).expand(3, 7, 2, 2) * 4.0
    lin = _Plane()
    m2 = linearization_error(lin, lambda p: 0.01 * p[..., 0] ** 2, xy, pos_cov=cov)
    assert m2.shape == (3, 7)
    torch.testing.assert_close(m2, 0.01 * xy[..., 0] ** 2 - 10 - 0.1 * xy[..., 0])
    assert lin.seen.shape == (21, 2, 2)


@pytest.mark.parametrize("name", ["nine_point", "lsq_mean", "lsq_adaptive"])
def test_m2_vanishes_on_planar_terrain(name: str) -> None:
    yy, xx = np.mgrid[0:60, 0:60] * 100.0
    tile = DemTile(heights=300 + 0.05 * xx - 0.02 * yy, spacing=100.0, name="plane")
    truth = GridTerrain(tile, method="bicubic", dtype=torch.float64)
    lin = make_linearizer(name, tile=tile, dtype=torch.float64)
    xy = 2000 + 2000 * torch.rand(50, 2, dtype=torch.float64)
    cov = torch.diag(torch.tensor([200.0**2, 150.0**2], dtype=torch.float64)).expand(50, 2, 2)
    m2 = linearization_error(lin, truth, xy, pos_cov=cov)
    assert float(m2.abs().max()) < 1e-6


def test_summary_of_stationary_and_shrinking_sequences() -> None:
    ar = simulate_ar(400, phi=(0.6,), sigma=10.0, batch=6, seed=1)
    ar[0, :5] = np.nan  # off-map steps are dropped
    cell = summarise_error_sequences(ar, n_identify=6)
    assert cell["std"] == pytest.approx(10.0, rel=0.1)
    assert cell["n_identified"] == 6
    assert cell["stationary_fraction"] >= 0.66
    assert cell["chosen_counts"].get("AR(1)", 0) >= 4
    assert cell["ar1_phi_median"] == pytest.approx(0.6, abs=0.08)
    # the adaptive-region behaviour: large, shrinking, then small and white
    rng = np.random.default_rng(2)
    t = np.arange(400)
    shrinking = (1 + 30 * np.exp(-t / 60)) * rng.standard_normal((6, 400))
    cell = summarise_error_sequences(shrinking, n_identify=6)
    assert cell["stationary_fraction"] <= 0.25


def test_measurement_linearisation_error_closed_form() -> None:
    # h = 0.01 x² and the plane stub (f = 10 + 0.1 x, slope (0.1, 0)):
    # e_lin = h(p) − f(p̂) − 0.1 (x − x̂)
    xy = torch.rand(4, 5, 2, dtype=torch.float64) * 100
    true_xy = xy + torch.randn(4, 5, 2, dtype=torch.float64) * 10
    e = linearization_error(_Plane(), lambda p: 0.01 * p[..., 0] ** 2, xy, true_xy=true_xy)
    ref = (0.01 * true_xy[..., 0] ** 2 - (10 + 0.1 * xy[..., 0])
           - 0.1 * (true_xy[..., 0] - xy[..., 0]))
    torch.testing.assert_close(e, ref)
    # on a plane the slope term is exact: e_lin = m2 = 0 for a plane-fit method
    yy, xx = np.mgrid[0:60, 0:60] * 100.0
    tile = DemTile(heights=300 + 0.05 * xx - 0.02 * yy, spacing=100.0, name="plane")
    lin = make_linearizer("lsq_mean", tile=tile, dtype=torch.float64)
    est = 2000 + 2000 * torch.rand(20, 2, dtype=torch.float64)
    e = linearization_error(lin, GridTerrain(tile, method="bicubic", dtype=torch.float64), est,
                            true_xy=est + 150.0)
    assert float(e.abs().max()) < 1e-6
