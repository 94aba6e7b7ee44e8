"""Measured R of the EKF methods (map table + pilot flights) against independent references.

* the non-decreasing fit equals SciPy's isotonic regression;
* the tent-weighted binning puts node samples on their node and splits the rest linearly;
* the in-flight miss on a plane whose truth lies a constant above the map is that constant
  at every step (closed form: the tangent plane is exact, only the offset is left);
* a consistent linear case (plane, no map error) whose scenario carries a wrong hand map
  variance: the derived R is the altimeter variance alone and the run-averaged NEES lies in
  its 95 % band in >= 90 % of the steps, while the hand R leaves the band (the test can fail).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
from scipy.optimize import isotonic_regression

from neuralmap.dem.tile import DemTile
from neuralmap.lab.metrics import navigation_metrics
from neuralmap.lab.monte_carlo import run_filter
from neuralmap.lab.noise_calibration import (
    binned_mean_square,
    derive_method_noise,
    flight_miss,
    isotonic_increasing,
)
from neuralmap.lab.pcrb import pcrb, pcrb_position
from neuralmap.lab.scenario import Scenario
from neuralmap.lab.simulator import simulate
from neuralmap.lab.truth_terrain import true_terrain
from neuralmap.linearize.factory import make_linearizer
from neuralmap.tan.model import TanModel
from neuralmap.terrain.grid import GridTerrain

SPACING = 100.0


@pytest.fixture(scope="module")
def plane_case() -> tuple[Scenario, DemTile]:
    yy, xx = np.mgrid[0:120, 0:120]
    tile = DemTile(heights=0.08 * xx * SPACING - 0.05 * yy * SPACING + 500.0,
                   spacing=(SPACING, SPACING), name="plane")
    scenario = Scenario(
        name="plane-consistent", tile="plane", dt=1.0, duration_s=60.0,
        start_xy=[3000.0, 3000.0], start_spread_m=200.0, speed_mps=80.0, heading_deg=60.0,
        altitude_agl_m=500.0, init_pos_sigma_m=50.0, init_alt_sigma_m=10.0,
        init_vel_sigma_mps=0.5, vel_random_walk=0.05, pos_noise_sigma_m=1.0,
        alt_noise_sigma_m=1.0, altimeter_sigma_m=5.0, truth_model="dem", dem_error_sigma_m=0.0,
        P0_diag=[2500.0, 2500.0, 100.0, 0.25, 0.25], Q_diag=[1.0, 1.0, 1.0, 0.0025, 0.0025],
        # a hand map variance the map does not have: R 45 m² instead of the altimeter's 25
        R_m2=25.0, fit_variance_m2=20.0,
    ).validate()
    return scenario, tile


def test_isotonic_fit_equals_scipy() -> None:
    rng = np.random.default_rng(4)
    values = np.cumsum(rng.normal(0.5, 2.0, size=14))
    weights = rng.uniform(0.5, 5.0, size=14)
    expected = isotonic_regression(values, weights=weights, increasing=True).x
    np.testing.assert_allclose(isotonic_increasing(values, weights), expected, rtol=1e-12)


def test_tent_binning_splits_samples_between_nodes() -> None:
    nodes = (0.0, 10.0, 30.0)
    sigma = torch.tensor([10.0, 10.0, 20.0, 50.0], dtype=torch.float64)
    value = torch.tensor([2.0, 4.0, 8.0, 16.0], dtype=torch.float64)
    mean, weight = binned_mean_square(sigma, value, nodes)
    # node 10: samples 2, 4 (weight 1 each) and 8 (weight 1/2); node 30: 8 (1/2) and 16 (1)
    np.testing.assert_allclose(weight, [0.0, 2.5, 1.5])
    np.testing.assert_allclose(mean[1:], [(2 + 4 + 4) / 2.5, (4 + 16) / 1.5])
    assert np.isnan(mean[0])


def test_flight_miss_on_a_plane_is_the_map_offset(plane_case) -> None:
    scenario, tile = plane_case
    truth = simulate(scenario, tile, n_runs=20, seed=2)
    linearizer = make_linearizer("bilinear", tile=tile, variance="zero")
    run = run_filter(truth, linearizer, scenario)
    grid = GridTerrain(tile, method="bilinear", dtype=torch.float64)
    sigma, miss, own = flight_miss(run, truth, linearizer, TanModel.from_scenario(scenario),
                              lambda xy: grid(xy) + 3.0)
    assert miss.numel() == 20 * scenario.n_steps
    np.testing.assert_allclose(miss.numpy(), 3.0, atol=1e-6)
    assert bool((sigma > 0).all()) and bool((own == 0).all())


def test_derived_r_makes_a_consistent_linear_case_consistent(plane_case) -> None:
    scenario, tile = plane_case
    world = true_terrain(scenario, tile, seed=0)
    methods = {"bilinear": make_linearizer("bilinear", tile=tile, variance="zero")}
    wrapped, filter_scenario, info = derive_method_noise(
        methods, scenario=scenario, tile=tile, truth_terrain=world, seed=0, n_pilot=100,
        iterations=1, n_points=500, draws=2, sigmas=(0.0, 10.0, 50.0, 100.0))
    table = info["methods"]["bilinear"]
    np.testing.assert_allclose(table["R_m2"], 25.0, atol=1e-9)  # altimeter variance only
    assert filter_scenario.fit_variance_m2 == 0.0 and info["pilot_runs"] == 100
    truth = simulate(scenario, tile, n_runs=1000, seed=5, truth_terrain=world)
    bound = pcrb_position(pcrb(truth, scenario, world.model))
    derived = navigation_metrics(run_filter(truth, wrapped["bilinear"], filter_scenario), bound)
    hand = navigation_metrics(run_filter(truth, methods["bilinear"], scenario), bound)
    assert derived["nees_in_band"] >= 0.9, derived["nees_in_band"]
    assert hand["nees_in_band"] < 0.5, hand["nees_in_band"]
    assert derived["pcrb_ratio_all"] == pytest.approx(1.0, abs=0.05)


def test_derive_without_pilot_keeps_the_map_table(plane_case) -> None:
    scenario, tile = plane_case
    world = true_terrain(scenario, tile, seed=0)
    shifted = dataclasses.replace(scenario, R_m2=16.0)
    _, _, info = derive_method_noise(
        {"nine_point": make_linearizer("nine_point", tile=tile)}, scenario=shifted, tile=tile,
        truth_terrain=world, seed=0, n_pilot=0, iterations=1, n_points=300, draws=2,
        sigmas=(0.0, 50.0))
    table = info["methods"]["nine_point"]
    assert info["iterations"] == 0 and table["flight_samples"] == [0.0, 0.0]
    np.testing.assert_allclose(table["R_m2"], 16.0, atol=1e-9)
