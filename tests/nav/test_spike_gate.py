"""Altimeter spike gate of the acquisition grid: the predictive NIS against a NumPy
reference, and a gated epoch equal to an epoch without a measurement."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.nav.acquisition import AcquisitionConfig, run_acquisition, tan_inputs
from neuralmap.nav.metrics import chi2_quantile
from neuralmap.nav.scenario import scenario_tile
from neuralmap.nav.simulator import simulate
from neuralmap.nav.spike_gate import predictive_nis, spike_gate_threshold, spiked
from neuralmap.terrain.grid import GridTerrain

D = torch.float64


def test_predictive_nis_equals_a_numpy_reference_with_cells_off_the_map() -> None:
    gen = torch.Generator().manual_seed(0)
    n, g = 3, 7
    w = torch.rand(n, g, g, generator=gen, dtype=D)
    w = w / w.sum((1, 2), keepdim=True)
    h = 100.0 * torch.rand(n, g, g, generator=gen, dtype=D)
    h[1, :2] = float("nan")  # two rows of run 1 off the map
    h[2] = float("nan")  # run 2 entirely off the map
    a = torch.randn(n, g, g, generator=gen, dtype=D)
    va = torch.tensor([4.0, 9.0, 1.0], dtype=D)
    y = torch.tensor([60.0, 20.0, 50.0], dtype=D)
    got = predictive_nis(y, w, h, a, va, 25.0)
    for r in range(2):
        ok = np.isfinite(h[r].numpy()).ravel()
        wr = w[r].numpy().ravel()[ok]
        wr = wr / wr.sum()
        yc = (h[r] + a[r]).numpy().ravel()[ok]
        yhat = wr @ yc
        s = wr @ (yc - yhat) ** 2 + float(va[r]) + 25.0
        assert float(got[r]) == pytest.approx((float(y[r]) - yhat) ** 2 / s, rel=1e-12)
    assert torch.isnan(got[2])
    assert spike_gate_threshold(0.0) == float("inf")
    assert spike_gate_threshold(0.999) == pytest.approx(chi2_quantile(0.999, 1))
    thr = spike_gate_threshold(0.999)
    assert spiked(torch.tensor([thr * 0.99, thr * 1.01, float("nan")]), 0.999).tolist() == [
        False, True, False]


@pytest.fixture(scope="module")
def flight(tiny_scenario):  # noqa: ANN001, ANN201
    sig = 120.0
    scenario = dataclasses.replace(
        tiny_scenario, init_pos_sigma_m=sig, start_xy=[900.0, 900.0], start_spread_m=50.0,
        P0_diag=[sig**2, sig**2] + list(tiny_scenario.P0_diag[2:]), duration_s=25.0,
    ).validate()
    tile = scenario_tile(scenario)
    truth = simulate(scenario, tile, n_runs=4, seed=3)
    return tan_inputs(truth, scenario), GridTerrain(tile, method="bilinear")


def _run(inputs, grid, prob: float):  # noqa: ANN001, ANN202
    cfg = AcquisitionConfig(cells=48, spike_gate_prob=prob)
    return run_acquisition(inputs, method="point_mass", terrain=grid, config=cfg)


def test_a_gated_spike_equals_a_missing_measurement_and_is_counted(flight) -> None:  # noqa: ANN001
    """A 150 m spike on run 0 at step 12: with the gate, the run is exactly as if that
    clearance were missing (bit-identical, same run); without it, the spike moves the grid."""
    inputs, grid = flight
    k = 12
    spiked_radar = inputs.radar.clone()
    spiked_radar[0, k] += 150.0
    missing = inputs.radar.clone()
    missing[0, k] = float("nan")
    with_spike = dataclasses.replace(inputs, radar=spiked_radar)
    gated = _run(with_spike, grid, 0.9999)
    reference = _run(dataclasses.replace(inputs, radar=missing), grid, 0.9999)
    assert gated.extra["spikes"].tolist() == [1, 0, 0, 0]
    assert reference.extra["spikes"].tolist() == [0, 0, 0, 0]
    assert torch.equal(gated.run.err, reference.run.err)
    assert torch.equal(gated.run.P, reference.run.P)
    ungated = _run(with_spike, grid, 0.0)
    assert "spikes" not in ungated.extra
    assert float((ungated.run.err[0, k:, :2] - gated.run.err[0, k:, :2]).abs().max()) > 1.0
    clean_off, clean_on = _run(inputs, grid, 0.0), _run(inputs, grid, 0.9999)
    assert int(clean_on.extra["spikes"].sum()) == 0  # nothing gated on clean data ...
    assert torch.equal(clean_off.run.err, clean_on.run.err)  # ... so the gate changes nothing


def test_spike_gate_prob_out_of_range_is_refused() -> None:
    with pytest.raises(NeuralMapError, match="spike_gate_prob"):
        AcquisitionConfig(spike_gate_prob=1.0).validate()
