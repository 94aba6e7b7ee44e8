"""The point-mass tracker method's lattice floor (cells no finer than the transition blur):
the floor against its closed form, and the prediction kernels it keeps short on a sharp
posterior (flown through the lab's `fly`) against the same flight without it; the
transition blur and the covariance floor against closed forms / NumPy."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import neuralmap.filters.lattice.kernels as tracker_module
from neuralmap.dem.tile import DemTile
from neuralmap.exceptions import NeuralMapError
from neuralmap.lab.monte_carlo import fly, study_navigator_config
from neuralmap.lab.scenario import Scenario
from neuralmap.lab.simulator import simulate
from neuralmap.tan.methods.tracker import TrackerOptions, spd_floor, transition_blur
from neuralmap.tan.model import TanModel
from neuralmap.terrain.grid import GridTerrain


def test_floor_is_the_blur_times_the_half_lattice() -> None:
    cfg = TrackerOptions(cells=33, min_cell_blur=1.5).lattice_config(blur_m=2.0)
    assert cfg.min_half_width == pytest.approx(1.5 * 2.0 * 16.0)
    off = TrackerOptions(cells=33, min_cell_blur=0.0).lattice_config(blur_m=2.0)
    assert off.min_half_width == 0.0
    wide = TrackerOptions(cells=33, min_half_width=500.0).lattice_config(blur_m=2.0)
    assert wide.min_half_width == 500.0  # the floor never narrows a wider setting
    with pytest.raises(NeuralMapError, match="min_cell_blur"):
        TrackerOptions(min_cell_blur=-1.0).validate()
    with pytest.raises(NeuralMapError, match="dtype"):
        TrackerOptions(dtype="float16").validate()


def test_transition_blur_and_spd_floor_closed_forms() -> None:
    """``b = sqrt(λ_max(Q_s) + T² λ_max(P0_v))``; the floor clips eigenvalues at ``rel`` × the
    largest (NumPy eigen-decomposition)."""
    model = TanModel(dt=2.0, P0=(400.0, 400.0, 100.0, 0.09, 0.25),
                     Q=(1.0, 4.0, 1.0, 0.0025, 0.0025), R_altimeter=9.0)
    assert transition_blur(model) == pytest.approx(math.sqrt(4.0 + 4.0 * 0.25), rel=1e-12)
    a = np.array([[4.0, 2.0, 0.0], [2.0, 1.0, 0.0], [0.0, 0.0, 9.0]])  # singular block
    lam, vec = np.linalg.eigh(a)
    ref = (vec * np.maximum(lam, 1e-6 * lam.max())) @ vec.T
    got = spd_floor(torch.tensor(a), rel=1e-6).numpy()
    np.testing.assert_allclose(got, ref, rtol=0, atol=1e-12)
    assert np.linalg.eigvalsh(got).min() > 0


def test_prediction_kernels_stay_short_on_a_sharp_posterior(monkeypatch) -> None:  # noqa: ANN001
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
    model = TanModel.from_scenario(scenario)
    grid = GridTerrain(tile, method="bilinear")

    def run(floor: float) -> None:
        options = {"cells": 32, "min_cell_blur": floor}
        cfg = study_navigator_config(scenario, {"method": "point_mass_tracker",
                                                "point_mass_tracker": options})
        res = fly(truth, grid, cfg, model=model, map_error_variance=0.0)
        assert bool(res.updated[:, 1:].all()) and res.counts["handoffs"] == 0

    run(1.5)
    assert lengths and max(lengths) <= 4, max(lengths)
    lengths.clear()
    run(0.0)
    assert max(lengths) > 4  # without the floor the kernels grow (the test can fail)
