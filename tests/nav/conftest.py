"""Fixtures shared by the navigation tests."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
import pytest


def _plane_flight(tiny_scenario: Any, *, duration_s: float, config: Any,  # noqa: ANN401
                 sigma_m: float = 60.0, n_runs: int = 6) -> tuple[Any, Any, Any, Any]:
    """The tiny scenario over a tilted plane with the DEM as truth: the radar measurement is
    linear in the position, so the Bayes posterior is Gaussian and the EKF with the bilinear
    linearizer (exact on a plane) is the Kalman filter, the reference.

    Returns:
        ``(inputs, grid, linearizer, kalman)``: the `TanInputs`, the bilinear plane,
        its linearizer and the EKF's `AcquisitionResult` under ``config``.
    """
    from neuralmap.dem.tile import DemTile
    from neuralmap.linearize.factory import make_linearizer
    from neuralmap.nav.acquisition import run_acquisition, tan_inputs
    from neuralmap.nav.simulator import simulate
    from neuralmap.terrain.grid import GridTerrain

    scenario = dataclasses.replace(
        tiny_scenario, truth_model="dem", init_pos_sigma_m=sigma_m, start_xy=[900.0, 900.0],
        start_spread_m=0.0, P0_diag=[sigma_m**2, sigma_m**2] + list(tiny_scenario.P0_diag[2:]),
        duration_s=duration_s,
    ).validate()
    xs = 30.0 * np.arange(96)
    x, y = np.meshgrid(xs, xs)
    tile = DemTile(heights=200.0 + 0.15 * x + 0.08 * y, spacing=(30.0, 30.0),
                   origin=(0.0, 0.0), name="plane")
    truth = simulate(scenario, tile, n_runs=n_runs, seed=1)
    grid = GridTerrain(tile, method="bilinear")
    lin = make_linearizer("bilinear", tile=tile)
    inputs = tan_inputs(truth, scenario)
    kalman = run_acquisition(inputs, method="ekf", terrain=grid, linearizer=lin, config=config)
    return inputs, grid, lin, kalman


@pytest.fixture(scope="session")
def plane_flight() -> Any:  # noqa: ANN401 - the flight builder
    """`_plane_flight`: the tilted-plane flight for a given duration and config."""
    return _plane_flight
