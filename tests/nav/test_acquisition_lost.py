"""A run the hand-off tracker declares lost counts as diverged in the acquisition study's
metrics (as in the whole-flight tracker study), not as a numerical failure."""

from __future__ import annotations

import dataclasses

import torch

from neuralmap.nav import tracker_handoff
from neuralmap.nav.acquisition import AcquisitionConfig, run_acquisition, tan_inputs
from neuralmap.nav.metrics import navigation_metrics
from neuralmap.nav.scenario import scenario_tile
from neuralmap.nav.simulator import simulate
from neuralmap.terrain.grid import GridTerrain


def _flight(tiny_scenario):  # noqa: ANN001, ANN202
    sig = 120.0
    scenario = dataclasses.replace(
        tiny_scenario, init_pos_sigma_m=sig, start_xy=[900.0, 900.0], start_spread_m=50.0,
        P0_diag=[sig**2, sig**2] + list(tiny_scenario.P0_diag[2:]), duration_s=30.0,
    ).validate()
    tile = scenario_tile(scenario)
    truth = simulate(scenario, tile, n_runs=4, seed=3)
    return tan_inputs(truth, scenario), GridTerrain(tile, method="bilinear")


CFG = AcquisitionConfig(cells=48, handoff_sigma_m=30.0, fallback_window=5, min_acquire_steps=3)


def test_a_lost_tracker_run_counts_as_diverged(tiny_scenario, monkeypatch) -> None:  # noqa: ANN001
    inputs, grid = _flight(tiny_scenario)
    base = run_acquisition(inputs, method="point_mass_tracker", terrain=grid, config=CFG)
    assert bool((base.handoff_step > 0).all())
    assert base.run.lost is not None and not bool(base.run.lost.any())
    real = tracker_handoff.PointMassTracker

    class Losing(real):  # flags run 1 lost at its first update as a member of the pool
        def update(self, *args, **kwargs):  # noqa: ANN002, ANN003, ANN202
            out = super().update(*args, **kwargs)
            mask = kwargs.get("mask")
            if mask is not None and bool(mask[1]):
                self.lost[1] = True
            return out

    monkeypatch.setattr(tracker_handoff, "PointMassTracker", Losing)
    res = run_acquisition(inputs, method="point_mass_tracker", terrain=grid, config=CFG)
    assert res.run.lost.tolist() == [False, True, False, False]
    bound = torch.full((inputs.radar.shape[1],), 1e6, dtype=torch.float64)
    m0 = navigation_metrics(base.run, bound, divergence_sigma=1e6)
    m1 = navigation_metrics(res.run, bound, divergence_sigma=1e6)
    assert m0["n_diverged"] == 0 and m0["n_unhealthy"] == 0
    # run 1: diverged (not a numerical failure) whatever its final error
    assert m1["diverged"] == [False, True, False, False]
    assert m1["n_diverged"] == 1 and m1["n_unhealthy"] == 0

