"""The Navigator's altimeter spike gate: the lattice filters' predictive NIS
(`LatticeFilter.predictive_nis`) against a NumPy reference, and through the Navigator a
gated spike equal, bit for bit, to an epoch without a measurement (counted as a spike), for
the point-mass tracker and for the point-mass grid with its ``spike_gate`` on."""

from __future__ import annotations

import dataclasses
from typing import Any

import numpy as np
import pytest
import torch
from scipy.stats import chi2

from neuralmap.exceptions import NeuralMapError
from neuralmap.filters.point_mass import PointMassConfig, PointMassFilter
from neuralmap.filters.point_mass_tracker import PointMassTracker, TrackerConfig
from neuralmap.lab.monte_carlo import FilterRun, fly, study_navigator_config
from neuralmap.lab.scenario import scenario_tile
from neuralmap.lab.simulator import simulate
from neuralmap.nav.config import load_navigator_config
from neuralmap.nav.fix import STATUS_CODE
from neuralmap.tan.model import TanModel
from neuralmap.terrain.grid import GridTerrain

D = torch.float64


def _grid_filter(n: int, g: int) -> PointMassFilter:
    return PointMassFilter(torch.zeros(n, 2, dtype=D), torch.eye(2, dtype=D) * 900.0,
                           config=PointMassConfig(cells=g), dtype=D)


def _tracker(n: int, g: int) -> PointMassTracker:
    E = torch.tensor([[0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], dtype=D)
    return PointMassTracker(torch.zeros(n, 5, dtype=D),
                            torch.diag(torch.tensor([900.0, 900.0, 100.0, 0.04, 0.04],
                                                    dtype=D)),
                            E=E, F=torch.eye(3, dtype=D), c=torch.tensor([1.0, 0.0, 0.0],
                                                                         dtype=D),
                            config=TrackerConfig(cells=g), dtype=D)


@pytest.mark.parametrize("make", [_grid_filter, _tracker], ids=["grid", "tracker"])
def test_predictive_nis_equals_a_numpy_reference_with_cells_off_the_map(
        make: Any) -> None:  # noqa: ANN401
    """``ŷ = Σ w (g + c·μ)``, ``S = Σ w (g + c·μ − ŷ)² + cᵀPc + R`` over the cells on the
    map (masses renormalised), NIS ``(y − ŷ)²/S``; NaN where no cell is on the map or the
    clearance is missing."""
    gen = torch.Generator().manual_seed(0)
    n, g = 4, 12
    f = make(n, g)
    nz = f.nz
    w = torch.rand(n, g, g, generator=gen, dtype=D)
    w = w / w.sum((1, 2), keepdim=True)
    mu = torch.randn(n, nz, g, g, generator=gen, dtype=D) * 3.0
    a = torch.randn(n, nz, nz, generator=gen, dtype=D)
    P = a @ a.transpose(1, 2) + torch.eye(nz, dtype=D)
    f.set_state(w, mu, P, f.centre.clone(), f.axes.clone())
    h = 100.0 * torch.rand(n, g, g, generator=gen, dtype=D)
    h[1, :2] = float("nan")  # two rows of run 1 off the map
    h[2] = float("nan")  # run 2 entirely off the map
    y = torch.tensor([60.0, 20.0, 50.0, float("nan")], dtype=D)
    got = f.predictive_nis(y, h, 25.0)
    c = f.c.numpy()
    for r in range(2):
        ok = np.isfinite(h[r].numpy()).ravel()
        wr = w[r].numpy().ravel()[ok]
        wr = wr / wr.sum()
        yc = (h[r].numpy() + np.einsum("z,zij->ij", c, mu[r].numpy())).ravel()[ok]
        yhat = wr @ yc
        s = wr @ (yc - yhat) ** 2 + c @ P[r].numpy() @ c + 25.0
        assert float(got[r]) == pytest.approx((float(y[r]) - yhat) ** 2 / s, rel=1e-12)
    assert bool(torch.isnan(got[2:]).all())
    with pytest.raises(NeuralMapError, match="predictive_nis"):
        f.predictive_nis(y, h[:, :3], 25.0)


@pytest.fixture(scope="module")
def flight(tiny_scenario: Any) -> tuple[Any, ...]:  # noqa: ANN401
    sig = 120.0
    scenario = dataclasses.replace(
        tiny_scenario, init_pos_sigma_m=sig, start_xy=[900.0, 900.0], start_spread_m=50.0,
        P0_diag=[sig**2, sig**2] + list(tiny_scenario.P0_diag[2:]), duration_s=25.0,
    ).validate()
    tile = scenario_tile(scenario)
    truth = simulate(scenario, tile, n_runs=4, seed=3)
    return scenario, truth, GridTerrain(tile, method="bilinear")


METHODS = {"point_mass_tracker": {"method": "point_mass_tracker"},
           "point_mass": {"method": "point_mass",
                          "point_mass": {"cells": 48, "spike_gate": True}}}


def _run(flight: tuple[Any, ...], method: str, radar: torch.Tensor, prob: float) -> FilterRun:
    scenario, truth, grid = flight
    cfg = study_navigator_config(scenario, METHODS[method], overrides={
        "integrity": {"spike_gate_prob": prob, "lost_window": 0}})
    model = TanModel.from_scenario(scenario)
    return fly(dataclasses.replace(truth, radar=radar), grid, cfg, model=model,
               map_error_variance=0.0, name=method)


@pytest.mark.parametrize("method", sorted(METHODS))
def test_a_gated_spike_equals_a_missing_measurement_and_is_counted(
        flight: tuple[Any, ...], method: str) -> None:
    """A 150 m spike on run 0 at epoch 12: with the gate, the run is exactly as if that
    clearance were missing (bit-identical, status ``no_measurement``), the spike is counted
    and its predictive NIS reported; without the gate the spike moves the estimate."""
    radar = flight[1].radar
    k = 12
    spiked = radar.clone()
    spiked[0, k] += 150.0
    missing = radar.clone()
    missing[0, k] = float("nan")
    gated = _run(flight, method, spiked, 0.9999)
    reference = _run(flight, method, missing, 0.9999)
    assert gated.vehicle_counts["spikes"].tolist() == [1, 0, 0, 0]
    assert reference.vehicle_counts["spikes"].tolist() == [0, 0, 0, 0]
    assert reference.counts["missing_radar"] == 1 and gated.counts["missing_radar"] == 0
    assert torch.equal(gated.err, reference.err)
    assert torch.equal(gated.P, reference.P)
    assert torch.equal(gated.status, reference.status)
    assert torch.equal(gated.updated, reference.updated) and not bool(gated.updated[0, k])
    assert int(gated.status[0, k]) == STATUS_CODE["no_measurement"]
    assert float(gated.nis[0, k]) > chi2.ppf(0.9999, 1)  # the NIS that refused it
    assert bool(torch.isnan(reference.nis[0, k]))
    ungated = _run(flight, method, spiked, 0.0)
    assert ungated.counts["spikes"] == 0 and bool(ungated.updated[0, k])
    assert float((ungated.err[0, k:, :2] - gated.err[0, k:, :2]).abs().max()) > 1.0
    clean_off, clean_on = _run(flight, method, radar, 0.0), _run(flight, method, radar, 0.9999)
    assert clean_on.counts["spikes"] == 0  # nothing gated on clean data ...
    assert torch.equal(clean_off.err, clean_on.err)  # ... so the gate changes nothing


def test_the_grid_gates_only_with_its_spike_gate_on(flight: tuple[Any, ...]) -> None:
    """The point-mass grid's ``spike_gate`` is off by default: the spike is then used."""
    scenario, truth, grid = flight
    spiked = truth.radar.clone()
    spiked[0, 12] += 150.0
    cfg = study_navigator_config(scenario, {"method": "point_mass",
                                            "point_mass": {"cells": 48}},
                                 overrides={"integrity": {"spike_gate_prob": 0.9999}})
    res = fly(dataclasses.replace(truth, radar=spiked), grid, cfg,
              model=TanModel.from_scenario(scenario), map_error_variance=0.0)
    assert res.counts["spikes"] == 0 and bool(res.updated[0, 12])


def test_spike_gate_prob_out_of_range_is_refused() -> None:
    with pytest.raises(NeuralMapError, match="spike_gate_prob"):
        load_navigator_config({"integrity": {"spike_gate_prob": 1.0}})
