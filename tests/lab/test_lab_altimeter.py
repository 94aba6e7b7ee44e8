"""Radar-altimeter faults and quality record against their specification."""

from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.lab.altimeter import FAULT_CODES, altimeter_faults, footprint_roughness
from neuralmap.lab.scenario import load_scenario, scenario_tile
from neuralmap.lab.simulator import simulate


def _faulty(**kw):  # noqa: ANN003, ANN202
    return dataclasses.replace(load_scenario("tiny"), **kw).validate()


def test_spike_rate_sizes_and_signs() -> None:
    scenario = _faulty(spike_prob=0.05, spike_min_m=50.0, spike_max_m=300.0)
    gen = torch.Generator().manual_seed(0)
    error, code = altimeter_faults(scenario, (400, 201), generator=gen)
    spikes = code == FAULT_CODES["spike"]
    rate = float(spikes.double().mean())
    assert abs(rate - 0.05) < 4 * math.sqrt(0.05 * 0.95 / spikes.numel())  # binomial, 4σ
    size = error[spikes].abs()
    assert float(size.min()) >= 50.0 and float(size.max()) <= 300.0
    assert abs(float((error[spikes] > 0).double().mean()) - 0.5) < 0.03
    assert torch.equal(error[~spikes], torch.zeros_like(error[~spikes]))


def test_patches_are_consecutive_biased_runs_of_the_stated_length() -> None:
    scenario = _faulty(patch_prob=0.01, patch_min_s=5.0, patch_max_s=20.0,
                       patch_bias_min_m=-40.0, patch_bias_max_m=-10.0)
    gen = torch.Generator().manual_seed(1)
    error, code = altimeter_faults(scenario, (300, 400), generator=gen)
    patch = (code == FAULT_CODES["patch"]).numpy()
    assert not patch[:, 0].any()
    lengths, biases = [], []
    for row, err in zip(patch, error.numpy(), strict=True):
        edges = np.flatnonzero(np.diff(np.r_[0, row.astype(int), 0]))
        for start, stop in zip(edges[::2], edges[1::2], strict=True):
            biases.append(err[start:stop])
            if stop < len(row):  # a patch cut by the end of the flight is shorter
                lengths.append(stop - start)
    assert lengths and min(lengths) >= 5
    # back-to-back patches can chain; a single one never exceeds 20 epochs, most are alone
    assert np.median(lengths) <= 20
    for values in biases:
        assert np.all((values >= -40.0) & (values <= -10.0))


def test_lock_loss_is_a_missing_measurement_and_reported_in_quality() -> None:
    scenario = _faulty(lock_loss_prob=0.1)
    tile = scenario_tile(scenario)
    truth = simulate(scenario, tile, n_runs=50, seed=2)
    lost = truth.fault == FAULT_CODES["lock_loss"]
    assert bool(lost.any())
    assert torch.isnan(truth.radar[lost]).all() and torch.isfinite(truth.radar[~lost]).all()
    assert torch.equal(truth.quality[..., 2] == 0, lost)
    clean = simulate(load_scenario("tiny"), tile, n_runs=50, seed=2)
    assert torch.equal(clean.ins_error, truth.ins_error)  # faults never change the draws
    keep = ~lost
    torch.testing.assert_close(truth.radar[keep], clean.radar[keep])


def test_footprint_roughness_of_a_plane_is_its_slope_spread() -> None:
    """Plane h = a x: heights on the ring are a·r·cos(θ); std over 9 points by hand."""
    a, r = 0.2, 100.0 * math.tan(math.radians(20.0))

    def plane(xy: torch.Tensor) -> torch.Tensor:
        return a * xy[..., 0]

    rough = footprint_roughness(plane, torch.zeros(3, 2, dtype=torch.float64),
                                torch.full((3,), 100.0, dtype=torch.float64), 20.0)
    ring = a * r * np.cos(np.arange(8) * np.pi / 4)
    expected = np.std(np.r_[0.0, ring])
    np.testing.assert_allclose(rough.numpy(), expected, rtol=1e-12)


def test_bad_fault_parameters() -> None:
    with pytest.raises(NeuralMapError, match="spike_prob"):
        _faulty(spike_prob=1.5)
    with pytest.raises(NeuralMapError, match="patch_min_s"):
        _faulty(patch_min_s=30.0, patch_max_s=20.0)
    with pytest.raises(NeuralMapError, match="patch_bias_min_m"):
        _faulty(patch_bias_min_m=-5.0, patch_bias_max_m=-10.0)
