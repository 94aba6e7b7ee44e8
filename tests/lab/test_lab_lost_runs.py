"""A run the navigator declared lost counts as diverged (metrics on hand-built runs with
known answers, and a Navigator flight through the lab's `fly`).

The Navigator's lost-lock test re-acquires a vehicle from its open-loop prior; a vehicle
still lost (or re-acquiring) at the last epoch is a lost run (`FilterRun.lost`), whatever
its final error. Such a run is a divergence, not a numerical failure and not a converged
run; a vehicle that lost lock and was re-acquired before the end is not lost.
"""

from __future__ import annotations

import torch

from neuralmap.lab.metrics import diverged_runs, navigation_metrics
from neuralmap.lab.monte_carlo import FilterRun

F64 = torch.float64


def _run(lost: torch.Tensor | None, healthy: torch.Tensor | None = None) -> FilterRun:
    """Four runs, 3 samples: run 0 far off (diverged by the error rule), runs 1–3 close
    to the truth; run 3's truth left the map (excluded)."""
    n, k1 = 4, 3
    err = torch.zeros(n, k1, 5, dtype=F64)
    err[:, :, 0] = 1.0
    err[0, -1, 0] = 500.0
    P = torch.eye(5, dtype=F64).expand(n, k1, 5, 5).clone() * 100.0
    off_map = torch.tensor([False, False, False, True])
    return FilterRun(method="pm", t=torch.arange(k1, dtype=F64), err=err, P=P,
                     nis=torch.zeros(n, k1, dtype=F64), residual=torch.zeros(n, k1, dtype=F64),
                     updated=torch.ones(n, k1, dtype=torch.bool),
                     est_on_map=torch.ones(n, k1, dtype=torch.bool), off_map=off_map,
                     healthy=torch.ones(n, dtype=torch.bool) if healthy is None else healthy,
                     lost=lost)


PCRB = torch.tensor([10.0, 10.0, 10.0], dtype=F64)


def test_lost_run_with_a_small_error_counts_as_diverged() -> None:
    base = navigation_metrics(_run(None), PCRB)
    lost = navigation_metrics(_run(torch.tensor([False, True, False, True])), PCRB)
    assert base["diverged"] == [True, False, False, False]
    # run 1 (lost, final error 1 m) diverged; run 3 (lost, truth off the map) stays excluded
    assert lost["diverged"] == [True, True, False, False]
    assert lost["n_diverged"] == 2 and lost["n_converged"] == 1 and lost["n_unhealthy"] == 0
    assert lost["divergence_rate"] == 2 / 3
    assert "navigator lost it" in lost["divergence_rule"]


def test_no_lost_flag_leaves_the_metrics_unchanged() -> None:
    """``lost`` None (every EKF method) or all False gives the same metrics field by field."""
    base = navigation_metrics(_run(None), PCRB)
    none_lost = navigation_metrics(_run(torch.zeros(4, dtype=torch.bool)), PCRB)
    assert base == none_lost


def test_a_lost_run_that_also_failed_numerically_counts_once_as_diverged() -> None:
    m = navigation_metrics(_run(torch.tensor([False, True, False, False]),
                                healthy=torch.tensor([True, False, True, True])), PCRB)
    assert m["n_diverged"] == 2 and m["n_unhealthy"] == 0


def test_diverged_runs_rule_with_lost() -> None:
    got = diverged_runs(torch.tensor([1.0, 1.0, 1.0]), torch.tensor([10.0, 10.0, 10.0]),
                        included=torch.tensor([True, True, False]),
                        healthy=torch.ones(3, dtype=torch.bool),
                        est_left=torch.zeros(3, dtype=torch.bool), pcrb_final=10.0,
                        lost=torch.tensor([False, True, True]))
    assert got.tolist() == [False, True, False]


def test_a_lost_lock_not_reacquired_by_the_end_is_a_lost_run() -> None:
    """Point-mass EKF (acquisition grid, hand-off, lost lock back to the grid): a 40 m
    altimeter bias on vehicle 1 from epoch 34 fires the lost-lock test too late for the grid
    to hand it off again (lost at the end); a 2-epoch bias on vehicle 2 at epochs 8-9 fires
    it early and the grid re-acquires it (not lost). `filter_run` puts the flag into
    ``lost`` (not into ``healthy``) and the metrics count only vehicle 1 diverged."""
    import dataclasses

    from neuralmap.lab.monte_carlo import fly, study_navigator_config
    from neuralmap.lab.scenario import load_scenario, scenario_tile
    from neuralmap.lab.simulator import simulate
    from neuralmap.nav.fix import STATUS_CODE
    from neuralmap.tan.model import TanModel
    from neuralmap.terrain.grid import GridTerrain

    scenario = load_scenario("tiny")
    tile = scenario_tile(scenario)
    truth = simulate(scenario, tile, n_runs=4, seed=0, dtype=F64)
    cfg = study_navigator_config(
        scenario, {"method": "point_mass_ekf", "point_mass_ekf": {"linearizer": "bilinear"}},
        overrides={"integrity": {"lost_window": 5, "lost_prob": 0.9999},
                   "point_mass": {"cells": 48}})
    model = TanModel.from_scenario(scenario)
    grid = GridTerrain(tile, method="bilinear")
    clean = fly(truth, grid, cfg, model=model, map_error_variance=0.0)
    assert clean.lost is not None and not bool(clean.lost.any())
    assert clean.counts["lost"] == 0
    radar = truth.radar.clone()
    radar[1, 34:] -= 40.0
    radar[2, 8:10] -= 40.0
    run = fly(dataclasses.replace(truth, radar=radar), grid, cfg, model=model,
              map_error_variance=0.0)
    assert run.vehicle_counts["lost"].tolist() == [0, 1, 1, 0]
    assert run.lost.tolist() == [False, True, False, False]
    assert int(run.status[1, -1]) == STATUS_CODE["acquiring"]
    assert int(run.status[2, -1]) == STATUS_CODE["tracking"]
    assert bool(run.healthy.all())
    bound = torch.full((truth.n_steps + 1,), 1e6, dtype=F64)
    m0 = navigation_metrics(clean, bound, divergence_sigma=1e6)
    m1 = navigation_metrics(run, bound, divergence_sigma=1e6)
    assert m0["n_diverged"] == 0 and m0["n_unhealthy"] == 0
    # vehicle 1: diverged (not a numerical failure) whatever its final error
    assert m1["diverged"] == [False, True, False, False]
    assert m1["n_diverged"] == 1 and m1["n_unhealthy"] == 0
    assert "navigator lost it" in m1["divergence_rule"]
