"""The Navigator's acquisition pipeline: the hand-off test's two parts on constructed
posteriors (the largest σ against NumPy's eigenvalues, the grid's unimodality against a NumPy
Bhattacharyya coefficient), the point-mass EKF handed off by the grid and sent back to it by
the lost-lock test (only the vehicles whose altimeter is biased), and bad input."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
import pytest
import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.lab.monte_carlo import FilterRun, fly, study_navigator_config
from neuralmap.nav.fix import STATUS_CODE
from neuralmap.nav.integrity import largest_sigma
from neuralmap.nav.navigator import Navigator
from neuralmap.tan.method import MethodContext
from neuralmap.tan.methods.point_mass import PointMassGrid, PointMassOptions
from neuralmap.tan.model import TanModel

D = torch.float64
ACQ, TRK, LOST, OFF = (STATUS_CODE[k] for k in ("acquiring", "tracking", "lost", "off_map"))


@pytest.fixture(scope="module")
def tiny(tiny_wide_prior: tuple[Any, ...]) -> tuple[Any, ...]:
    """The tiny scenario with a 120 m prior, 8 runs of 40 s (conftest)."""
    return tiny_wide_prior


def test_largest_sigma_equals_numpy_eigenvalues() -> None:
    """The hand-off's size test reads the largest principal σ of the horizontal block."""
    gen = torch.Generator().manual_seed(0)
    a = torch.randn(6, 5, 5, generator=gen, dtype=D)
    cov = a @ a.transpose(1, 2) * 100.0
    cov[0, :2, :2] = torch.diag(torch.tensor([100.0, 400.0], dtype=D))  # 20 m
    cov[1, :2, :2] = torch.diag(torch.tensor([2500.0, 100.0], dtype=D))  # 50 m
    ref = np.sqrt(np.linalg.eigvalsh(cov[:, :2, :2].numpy())[:, -1])
    np.testing.assert_allclose(largest_sigma(cov).numpy(), ref, rtol=1e-12)
    assert largest_sigma(cov)[:2].tolist() == pytest.approx([20.0, 50.0], rel=1e-12)


def test_unimodality_on_constructed_posteriors(tiny: tuple[Any, ...]) -> None:  # noqa: ANN401
    """`PointMassGrid.unimodality`: the Bhattacharyya coefficient ``Σ sqrt(w g)`` between the
    grid masses and their Gaussian fit ``N(s̄, Σ + D/12)`` on the same cells (NumPy): near
    1 for the Gaussian prior, near ``1/√2`` for two separate modes; 0 where not asked."""
    scenario, tile, _, grid_map = tiny
    model = TanModel.from_scenario(scenario)
    ctx = MethodContext(terrain=grid_map, extent=grid_map.extent, model=model, R=9.0,
                        R_altimeter=9.0, n_vehicles=3, device=torch.device("cpu"))
    grid = PointMassGrid(ctx, PointMassOptions(cells=48, dtype="float64"))
    on = torch.tensor([True, True, False])
    grid.load(on, torch.zeros(3, 5, dtype=D), model.filter_prior().expand(3, 5, 5))
    pm = grid.pm
    pts = pm.points()
    w = pm.weights.clone()
    bump = ((pts[1] - torch.tensor([-150.0, 0.0], dtype=D)).square().sum(-1) / -800.0).exp()
    bump = bump + ((pts[1] - torch.tensor([150.0, 0.0], dtype=D)).square().sum(-1)
                   / -800.0).exp()
    w[1] = bump / bump.sum()  # vehicle 1: two equal modes 300 m apart
    pm.set_state(w, pm.lin_mean, pm.lin_cov, pm.centre, pm.axes)
    got = grid.unimodality(torch.ones(3, dtype=torch.bool))
    for r in range(2):
        wr = w[r].numpy().ravel()
        s = pts[r].numpy().reshape(-1, 2)
        m = wr @ s
        d = s - m
        sp = pm.spacing[r].numpy()
        cov = (wr[:, None] * d).T @ d + np.diag(sp**2 / 12.0)
        g = np.exp(-0.5 * np.einsum("ki,ij,kj->k", d, np.linalg.inv(cov), d))
        g /= g.sum()
        assert float(got[r]) == pytest.approx(np.sqrt(wr * g).sum(), rel=1e-9)
    assert float(got[0]) > 0.99 and 0.4 < float(got[1]) < 0.8  # 0.9 = the hand-off's
    assert float(got[2]) == 0.0  # not on the grid
    assert float(grid.unimodality(torch.tensor([True, False, False]))[1]) == 0.0


def _fly(tiny: tuple[Any, ...], truth: Any = None,  # noqa: ANN401
         method: str = "point_mass_ekf") -> FilterRun:
    scenario, tile, truth0, grid = tiny
    cfg = study_navigator_config(
        scenario, {"method": method} | ({method: {"linearizer": "bilinear"}}
                                        if method == "point_mass_ekf" else {}),
        overrides={"point_mass": {"cells": 48}, "point_mass_tracker": {"dtype": "float64"},
                   "acquisition": {"handoff_sigma_m": 30.0, "min_acquire_steps": 3},
                   "integrity": {"lost_window": 5, "lost_prob": 0.99999}})
    model = TanModel.from_scenario(scenario)
    return fly(truth0 if truth is None else truth, grid, cfg, model=model,
               map_error_variance=0.0, tile=tile, name="point_mass_ekf")


def test_point_mass_ekf_hands_off_and_falls_back(tiny: tuple[Any, ...]) -> None:  # noqa: ANN401
    """Every run hands off (the grid's status ``acquiring``, then ``tracking``); a 150 m
    altimeter bias on runs 0 and 1 after the hand-off makes their NIS fail the lost-lock
    test and sends them (only them) back to the acquisition grid."""
    truth = tiny[2]
    res = _fly(tiny)
    assert torch.isfinite(res.err).all() and torch.isfinite(res.P).all()
    handoff = res.vehicle_counts["first_handoff"]
    assert bool((handoff > 0).all()) and res.counts["handoffs"] == 8
    assert res.counts["lost"] == 0 and not bool(res.lost.any())
    for i, k in enumerate(handoff.tolist()):  # on the grid until the hand-off
        assert bool((res.status[i, :k] == ACQ).all())
    assert bool((res.status[:, -1] == TRK).all())
    final = res.err[:, -1, :2].norm(dim=1)
    assert float(final.max()) < 30.0
    k_bias = int(handoff.max()) + 2
    radar = truth.radar.clone()
    radar[:2, k_bias:] += 150.0
    res2 = _fly(tiny, dataclasses.replace(truth, radar=radar))
    lost = res2.vehicle_counts["lost"]
    assert bool((lost[:2] >= 1).all()) and int(lost[2:].sum()) == 0
    assert res2.counts["reacquisitions"] == res2.counts["lost"]
    for i in range(2):  # lost, then back on the grid (acquiring)
        first = int((res2.status[i] == LOST).nonzero()[0])
        assert k_bias < first <= k_bias + 5  # within the window of 5 updates
        assert int(res2.status[i, first + 1]) == ACQ
    assert not bool((res2.status[2:, k_bias:] == ACQ).any())
    assert torch.equal(res2.err[2:], res.err[2:])  # the other vehicles are untouched


def test_bad_input(tiny: tuple[Any, ...]) -> None:  # noqa: ANN401
    grid = tiny[3]
    with pytest.raises(NeuralMapError, match="unknown navigation method 'particle'"):
        Navigator(grid, {"method": "particle"})
    with pytest.raises(NeuralMapError, match="n_vehicles"):
        Navigator(grid, None, n_vehicles=0)
    with pytest.raises(NeuralMapError, match="no extent"):
        Navigator(torch.nn.Identity(), None)
    with pytest.raises(NeuralMapError, match="handoff_affinity"):
        Navigator(grid, {"acquisition": {"handoff_affinity": 0.0}})


@pytest.mark.parametrize("method", ["bilinear", "point_mass", "point_mass_tracker",
                                    "point_mass_ekf"])
def test_a_start_off_the_map_is_predicted_only(tiny: tuple[Any, ...],  # noqa: ANN401
                                               method: str) -> None:
    """A vehicle whose INS starts (and stays) 5 km off the map is predicted only: status
    ``off_map`` at every epoch (counted), never updated; the others fly as without it."""
    truth = tiny[2]
    ins = truth.ins_pos.clone()
    ins[3, :, 0] -= 5000.0
    off = _fly(tiny, dataclasses.replace(truth, ins_pos=ins), method)
    assert not bool(off.updated[3].any())
    keep = torch.tensor([0, 1, 2, 4, 5, 6, 7])
    ref = _fly(tiny, method=method)
    # the float32 acquisition grid diffuses the batch in one pass or row by row depending on
    # which rows are due: the others agree to float32 round-off (1e-4 m), else to 1e-9
    atol = 1e-3 if method == "point_mass_ekf" else 1e-9
    torch.testing.assert_close(off.err[keep], ref.err[keep], rtol=0, atol=atol)
    assert int(off.vehicle_counts["off_map_epochs"][3]) == truth.t.shape[0]
    assert bool((off.status[3] == OFF).all())
