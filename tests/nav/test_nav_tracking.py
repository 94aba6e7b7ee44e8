"""The TAN point-mass tracker's lattice floor (cells no finer than the transition blur)."""

from __future__ import annotations

import pytest
import torch

import neuralmap.filters.lattice.kernels as tracker_module
from neuralmap.dem.tile import DemTile
from neuralmap.exceptions import NeuralMapError
from neuralmap.nav.scenario import Scenario
from neuralmap.nav.simulator import simulate
from neuralmap.nav.tracking import TrackerOptions, run_tracker
from neuralmap.terrain.grid import GridTerrain


def test_floor_is_the_blur_times_the_half_lattice() -> None:
    cfg = TrackerOptions(cells=33, min_cell_blur=1.5).tracker_config(blur_m=2.0)
    assert cfg.min_half_width == pytest.approx(1.5 * 2.0 * 16.0)
    assert TrackerOptions(cells=33, min_cell_blur=0.0).tracker_config(blur_m=2.0).min_half_width == 0.0
    with pytest.raises(NeuralMapError, match="min_cell_blur"):
        TrackerOptions(min_cell_blur=-1.0).tracker_config()


def test_prediction_kernels_stay_short_on_a_sharp_posterior(monkeypatch) -> None:
    # steep sine terrain + a precise altimeter: the posterior gets a few metres wide, finer
    # than one step's transition blur; the floor keeps every blur kernel at <= 9 taps
    import numpy as np

    yy, xx = np.mgrid[0:80, 0:80]
    heights = 200.0 * np.sin(xx / 3.0) * np.cos(yy / 4.0) + 1000.0
    tile = DemTile(heights=heights, spacing=(50.0, 50.0), name="sharp")
    scenario = Scenario(
        name="sharp", tile="sharp", dt=1.0, duration_s=30.0, start_xy=[1500.0, 1500.0],
        start_spread_m=0.0, speed_mps=60.0, heading_deg=45.0, altitude_agl_m=500.0,
        init_pos_sigma_m=20.0, init_alt_sigma_m=5.0, init_vel_sigma_mps=0.5,
        vel_random_walk=0.05, pos_noise_sigma_m=1.0, alt_noise_sigma_m=1.0,
        altimeter_sigma_m=1.0, truth_model="dem", dem_error_sigma_m=0.0,
        P0_diag=[400.0, 400.0, 25.0, 0.25, 0.25], Q_diag=[1.0, 1.0, 1.0, 0.0025, 0.0025],
        R_m2=1.0).validate()
    truth = simulate(scenario, tile, n_runs=8, seed=0)
    lengths: list[int] = []
    original = tracker_module.convolve_axis

    def spy(x, kernels, half_len, dim):
        lengths.append(half_len)
        return original(x, kernels, half_len, dim)

    monkeypatch.setattr(tracker_module, "convolve_axis", spy)
    P0 = torch.diag(torch.tensor(scenario.P0_diag, dtype=torch.float64))
    Q = torch.diag(torch.tensor(scenario.Q_diag, dtype=torch.float64))
    run_tracker(truth, GridTerrain(tile, method="bilinear"), P0=P0, Q=Q, R=1.0, dt=1.0,
                options=TrackerOptions(cells=32))
    assert lengths and max(lengths) <= 4, max(lengths)
    lengths.clear()
    run_tracker(truth, GridTerrain(tile, method="bilinear"), P0=P0, Q=Q, R=1.0, dt=1.0,
                options=TrackerOptions(cells=32, min_cell_blur=0.0))
    assert max(lengths) > 4  # without the floor the kernels grow (the test can fail)
