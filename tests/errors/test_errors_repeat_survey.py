"""The simulated repeat survey (61 nodes × 10 passes) and recovery of its error model."""

from __future__ import annotations

import numpy as np
import pytest

from neuralmap.errors import DEM_ERROR_AR2, repeat_survey, survey_recovery


def test_survey_sample_layout() -> None:
    heights = np.linspace(100.0, 160.0, 61)
    survey = repeat_survey(true_heights=heights, seed=1)
    assert survey.measurements.shape == (10, 61)
    assert survey.errors.shape == (610,)
    # deviations from the per-node mean sum to zero at every node
    np.testing.assert_allclose(survey.errors.reshape(10, 61).sum(axis=0), 0.0, atol=1e-9)
    np.testing.assert_allclose(
        survey.errors.reshape(10, 61), survey.true_errors - survey.true_errors.mean(0), atol=1e-9
    )
    batch = repeat_survey(batch=300, seed=2)
    # default σ makes the sample's σ the paper's 1.0435 m
    assert np.mean(np.std(batch.errors, axis=-1)) == pytest.approx(1.0435, rel=0.02)


def test_identification_recovers_ar1() -> None:
    out = survey_recovery(n_trials=40, seed=3)
    assert out["ar1_phi_mean"][0] == pytest.approx(0.5315, abs=0.02)  # measured: ±0.035/√40
    assert 0.02 < out["ar1_phi_std"][0] < 0.05
    assert out["chosen_counts"].get("AR(1)", 0) >= 34
    assert out["first"]["chosen"]["name"] == "AR(1)"


def test_identification_recovers_ar2() -> None:
    out = survey_recovery(n_trials=40, phi=DEM_ERROR_AR2, seed=4)
    np.testing.assert_allclose(out["ar2_phi_mean"], DEM_ERROR_AR2, atol=0.03)
