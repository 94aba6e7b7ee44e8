"""End-to-end Monte Carlo on a linear-Gaussian problem: the protocol must say "consistent".

A plane terrain makes the TAN measurement linear (constant slope), and the filter is tuned
exactly like the simulated truth (P0, Q, R), so the EKF is the optimal Kalman filter and
its covariance is the PCRB. The real simulator, batched filter, metrics and PCRB must then
give RMSE / PCRB ≈ 1 over all runs and a time-averaged NEES inside its 99 % band; a filter
tuned wrong must fall out of the band (the test can fail).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from neuralmap.dem.tile import DemTile
from neuralmap.lab.metrics import navigation_metrics
from neuralmap.lab.monte_carlo import run_filter
from neuralmap.lab.pcrb import pcrb, pcrb_position
from neuralmap.lab.scenario import Scenario
from neuralmap.lab.simulator import simulate
from neuralmap.linearize.factory import make_linearizer
from neuralmap.terrain.grid import GridTerrain

SPACING = 100.0


@pytest.fixture(scope="module")
def plane_problem() -> tuple[Scenario, DemTile]:
    yy, xx = np.mgrid[0:120, 0:120]
    tile = DemTile(heights=0.08 * xx * SPACING - 0.05 * yy * SPACING + 500.0,
                   spacing=(SPACING, SPACING), name="plane")
    scenario = Scenario(
        name="linear-gaussian", tile="plane", dt=1.0, duration_s=60.0, start_xy=[3000.0, 3000.0],
        start_spread_m=200.0, speed_mps=80.0, heading_deg=60.0, altitude_agl_m=500.0,
        init_pos_sigma_m=50.0, init_alt_sigma_m=10.0, init_vel_sigma_mps=0.5,
        vel_random_walk=0.05, pos_noise_sigma_m=1.0, alt_noise_sigma_m=1.0,
        altimeter_sigma_m=5.0, truth_model="dem",
        # consistent: P0 = truth spread², Q = truth driving noise, R = altimeter variance
        P0_diag=[2500.0, 2500.0, 100.0, 0.25, 0.25], Q_diag=[1.0, 1.0, 1.0, 0.0025, 0.0025],
        R_m2=25.0, fit_variance_m2=0.0,
    ).validate()
    assert scenario.Q_diag == pytest.approx(scenario.truth_process_noise())
    return scenario, tile


def _metrics(scenario: Scenario, tile: DemTile, seed: int) -> dict:
    truth = simulate(scenario, tile, n_runs=2000, seed=seed)
    run = run_filter(truth, make_linearizer("bilinear", tile=tile, variance="zero"), scenario)
    bound = pcrb(truth, scenario, GridTerrain(tile, method="bicubic", dtype=torch.float64))
    return navigation_metrics(run, pcrb_position(bound), nees_confidence=0.99)


def test_consistent_linear_gaussian_filter_reaches_the_bound(plane_problem) -> None:
    scenario, tile = plane_problem
    m = _metrics(scenario, tile, seed=1)
    assert m["n_diverged"] == 0 and m["n_unhealthy"] == 0 and m["n_off_map"] == 0
    assert 0.95 <= m["pcrb_ratio_all"] <= 1.05, m["pcrb_ratio_all"]
    assert m["pcrb_ratio_converged"] == pytest.approx(m["pcrb_ratio_all"])
    lo, hi = m["nees_time_band_runs"]
    assert lo < 5.0 < hi and m["nees_time_in_band"], (m["nees_time_avg"], lo, hi)


def test_mistuned_filter_leaves_the_nees_band(plane_problem) -> None:
    scenario, tile = plane_problem
    pessimistic = dataclasses.replace(scenario, R_m2=250.0).validate()  # R 10x too large
    m = _metrics(pessimistic, tile, seed=1)
    assert m["nees_time_avg"] < m["nees_time_band_runs"][0]
    assert not m["nees_time_in_band"]
