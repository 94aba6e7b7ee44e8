"""A run the filter declared lost counts as diverged (metrics, the report table, figures).

The point-mass tracker flags a run ``lost`` when it widened beyond recovery; its estimate
is held, so its final error may even be small. Such a run is a divergence, not a
numerical failure and not a converged run.
"""

from __future__ import annotations

import torch

from neuralmap.nav.metrics import diverged_runs, navigation_metrics
from neuralmap.nav.monte_carlo import FilterRun

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
    assert "declared it lost" in lost["divergence_rule"]


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


def test_tracker_run_carries_its_lost_flag_and_stays_healthy(monkeypatch) -> None:
    """`run_tracker` puts the tracker's ``lost`` into the `FilterRun` (not into ``healthy``)."""
    from neuralmap.nav import tracking
    from neuralmap.nav.model import TanModel
    from neuralmap.nav.scenario import load_scenario, scenario_tile
    from neuralmap.nav.simulator import simulate
    from neuralmap.terrain.grid import GridTerrain

    scenario = load_scenario("tiny")
    tile = scenario_tile(scenario)
    truth = simulate(scenario, tile, n_runs=3, seed=0, dtype=F64)
    real = tracking.PointMassTracker

    class Losing(real):  # flags run 1 lost at the first update
        def update(self, *args, **kwargs):
            out = super().update(*args, **kwargs)
            self.lost[1] = True
            return out

    monkeypatch.setattr(tracking, "PointMassTracker", Losing)
    model = TanModel.from_scenario(scenario)
    result = tracking.run_tracker(truth, GridTerrain(tile, method="bilinear"),
                                  P0=model.filter_prior(), Q=model.filter_process_noise(),
                                  R=float(scenario.R_m2), dt=scenario.dt)
    assert result.lost.tolist() == [False, True, False]
    assert result.run.lost.tolist() == [False, True, False]
    assert bool(result.run.healthy.all())
    metrics = navigation_metrics(result.run, torch.full((truth.n_steps + 1,), 1e6, dtype=F64),
                                 divergence_sigma=1e6)
    assert metrics["diverged"][1] and metrics["n_unhealthy"] == 0
