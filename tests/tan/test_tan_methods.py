"""The built-in navigation methods flown through the lab's `fly` (one `Navigator` per
method): on a tilted plane (linear-Gaussian: the Bayes posterior is Gaussian and the bilinear
EKF is the Kalman filter) the point-mass grid and the one-component EKF bank against the
EKF; the EKF bank's prior against the Gaussian it splits; the point-mass grid on any map
against its bilinear fast path; the map's support; the progress callback."""

from __future__ import annotations

import dataclasses
from typing import Any

import pytest
import torch

from neuralmap.lab.monte_carlo import fly, study_navigator_config
from neuralmap.linearize.factory import make_linearizer
from neuralmap.nav.fix import STATUS_CODE
from neuralmap.tan.method import MethodContext
from neuralmap.tan.methods.ekf_bank import EkfBank, EkfBankOptions
from neuralmap.tan.model import TanModel
from neuralmap.terrain.base import inside_extent


@pytest.fixture(scope="module")
def tiny(tiny_wide_prior: tuple[Any, ...]) -> tuple[Any, ...]:
    """The tiny scenario with a 120 m prior, 8 runs of 40 s (conftest), with the bilinear
    linearizer."""
    scenario, tile, truth, grid = tiny_wide_prior
    return scenario, tile, truth, grid, make_linearizer("bilinear", tile=tile)


def _fly(scenario: Any, truth: Any, terrain: Any, method: dict[str, Any],  # noqa: ANN401
         **kwargs: Any) -> Any:  # noqa: ANN401
    model = TanModel.from_scenario(scenario)
    return fly(truth, terrain, study_navigator_config(scenario, method), model=model,
               map_error_variance=model.fit_variance, name=method["method"], **kwargs)


@pytest.fixture(scope="module")
def tilted_plane(tiny_scenario: Any, plane_flight: Any) -> Any:  # noqa: ANN401
    """`PlaneFlight` of 20 s (6 runs, σ0 = 60 m)."""
    return plane_flight(tiny_scenario, duration_s=20.0)


def test_the_reference_is_the_kalman_filter(tilted_plane: Any) -> None:  # noqa: ANN401
    """The plane's EKF reference updates at every epoch after the prior and stays consistent."""
    kalman = tilted_plane.kalman
    assert bool(kalman.updated[:, 1:].all()) and not bool(kalman.updated[:, 0].any())
    assert bool(kalman.healthy.all())


def test_point_mass_matches_the_kalman_filter_on_a_plane(tilted_plane: Any) -> None:  # noqa: ANN401
    """96² cells over ±4σ0: estimate within 1 m (grid spacing ~5 m) and the horizontal
    covariance within 0.5 % of the Kalman filter's at every step (measured: 0.44 m, 0.14 %)."""
    res = tilted_plane.fly({"method": "point_mass",
                            "point_mass": {"cells": 96, "dtype": "float64"}})
    kalman = tilted_plane.kalman
    assert bool(res.updated[:, 1:].all())
    torch.testing.assert_close(res.err[..., :2], kalman.err[..., :2], atol=1.0, rtol=0)
    ref = kalman.P[..., :2, :2]
    scale = float(ref.abs().max())
    torch.testing.assert_close(res.P[..., :2, :2], ref, atol=5e-3 * scale, rtol=0)


def test_single_component_bank_is_the_kalman_filter(tilted_plane: Any) -> None:  # noqa: ANN401
    """A bank of one EKF (1 component per axis, at the prior) is the EKF itself."""
    res = tilted_plane.fly({"method": "ekf_bank",
                            "ekf_bank": {"per_axis": 1, "linearizer": tilted_plane.lin}})
    kalman = tilted_plane.kalman
    torch.testing.assert_close(res.err, kalman.err, atol=1e-9, rtol=0)
    torch.testing.assert_close(res.P, kalman.P, atol=1e-9, rtol=0)


def test_bank_mixture_starts_at_the_prior(tilted_plane: Any) -> None:  # noqa: ANN401
    """The Gaussian-sum prior's moments are the prior's (mean and covariance: moment-matched,
    to round-off), for every vehicle loaded, whatever the prior's mean."""
    plane = tilted_plane
    n = 3
    model = plane.model
    ctx = MethodContext(terrain=plane.grid, extent=plane.grid.extent, model=model, R=9.0,
                        R_altimeter=9.0, n_vehicles=n, device=torch.device("cpu"),
                        tile=plane.tile)
    bank = EkfBank(ctx, EkfBankOptions(linearizer="bilinear", per_axis=3))
    assert bank.k == 9
    mean = torch.tensor([[10.0, -20.0, 1.0, 0.1, -0.1]] * n, dtype=torch.float64)
    cov = torch.diag(torch.tensor([900.0, 2500.0, 100.0, 0.04, 0.04], dtype=torch.float64))
    cov = cov.expand(n, 5, 5).clone()
    load = torch.tensor([True, False, True])
    bank.load(load, mean, cov)
    got_mean, got_cov = bank.estimate()
    torch.testing.assert_close(got_mean[load], mean[load], rtol=0, atol=1e-9)
    torch.testing.assert_close(got_cov[load], cov[load], rtol=1e-9, atol=1e-9)
    # the vehicle not loaded keeps the model's prior
    torch.testing.assert_close(got_cov[1], model.filter_prior(), rtol=1e-9, atol=1e-9)
    torch.testing.assert_close(got_mean[1], torch.zeros(5, dtype=torch.float64), rtol=0,
                               atol=1e-9)


def test_generic_terrain_model_path_matches_grid_fast_path(tiny: tuple[Any, ...]) -> None:
    """A terrain model without the lattice fast path (any TerrainModel: the neural map's
    route) gives the same point-mass run as the bilinear grid's fast path."""
    scenario, _, truth, grid, _ = tiny

    class Wrapped(torch.nn.Module):  # hides GridTerrain's attributes: generic forward only
        def __init__(self) -> None:
            super().__init__()
            self.inner = grid
            self.extent = grid.extent

        def forward(self, xy: torch.Tensor) -> torch.Tensor:
            return self.inner(xy)

    method = {"method": "point_mass", "point_mass": {"cells": 32, "dtype": "float64"}}
    fast = _fly(scenario, truth, grid, method)
    slow = _fly(scenario, truth, Wrapped(), method)
    assert bool(fast.updated[:, 1:].all())
    torch.testing.assert_close(fast.err, slow.err, atol=1e-6, rtol=0)
    torch.testing.assert_close(fast.P, slow.P, atol=1e-6, rtol=1e-9)


def test_map_support_keeps_the_grid_posterior_on_the_map(tiny: tuple[Any, ...]) -> None:
    """With off-map cells at zero likelihood, a grid's estimate never leaves the map (the
    posterior lives on the map, a convex set), although part of every grid is off it."""
    scenario, _, truth, grid, _ = tiny
    # move the INS near the west border so that part of every grid is off the map
    shift = torch.zeros_like(truth.ins_pos)
    shift[..., 0] = -float(truth.ins_pos[:, 0, 0].min()) + 150.0
    near = dataclasses.replace(truth, ins_pos=truth.ins_pos + shift)
    res = _fly(scenario, near, grid, {"method": "point_mass",
                                      "point_mass": {"cells": 48, "dtype": "float64"}})
    sigma0 = float(scenario.P0_diag[0]) ** 0.5
    assert float(near.ins_pos[:, 0, 0].min()) < grid.extent[0] + 4.0 * sigma0  # cut grids
    assert bool(res.updated[:, 1:].all())
    assert not bool((res.status == STATUS_CODE["off_map"]).any())
    est = near.ins_pos[..., :2] - (near.ins_error[..., :2] - res.err[..., :2])  # INS − δX̂
    assert bool(inside_extent(est, grid.extent).all())


@pytest.mark.parametrize("method", ["ekf_bank", "point_mass_ekf"])
def test_progress_is_reported_once_per_epoch_and_adds_up_to_one_run(
        tilted_plane: Any, method: str) -> None:  # noqa: ANN401
    """``progress`` gets ``1/K`` at each of the K epochs: the study's bar advances inside a
    row (heartbeat lines on long rows) and by exactly one row per method."""
    calls: list[float] = []
    tilted_plane.fly({"method": method, method: {"linearizer": tilted_plane.lin}},
                     progress=calls.append)
    assert len(calls) == tilted_plane.truth.t.shape[0]
    assert sum(calls) == pytest.approx(1.0, abs=1e-12)
