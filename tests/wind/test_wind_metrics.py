"""Wind and track error metrics on hand-made data with known answers."""

from __future__ import annotations

import math

import pytest
import torch

from neuralmap.wind import WindEstimate
from neuralmap.wind.metrics import (
    diverged_runs,
    rmse_over_time,
    track_error_metrics,
    wind_error_metrics,
)


def _estimate(wind: torch.Tensor, variance: float = 1.0) -> WindEstimate:
    n, t, _ = wind.shape
    return WindEstimate(wind=wind, variance=torch.full_like(wind, variance),
                        nis=torch.zeros_like(wind), coefficient=torch.ones_like(wind),
                        healthy=torch.ones(n, dtype=torch.bool))


def test_constant_errors_give_exact_rmse_nees_and_divergence():
    truth = torch.zeros(4, 50, 2, dtype=torch.float64)
    est = truth.clone()
    est[0] += torch.tensor([3.0, 4.0], dtype=torch.float64)  # |error| 5
    est[1, 45:] += 20.0  # diverges at the end only
    m = wind_error_metrics(truth, _estimate(est, variance=4.0), divergence_threshold=10.0)
    assert m["divergence_rate"] == pytest.approx(0.25)
    # kept runs 0, 2, 3: squared vector errors 25, 0, 0 -> RMSE sqrt(25/3)
    assert m["rmse"] == pytest.approx(math.sqrt(25.0 / 3.0))
    # NEES per axis: run 0 has (9 + 16)/2/4 per sample; mean over kept runs
    assert m["nees"] == pytest.approx((25.0 / 8.0) / 3.0)
    sq_run1 = 5 * 800.0 / 49  # 5 samples of |(20, 20)|² = 800 over 49 samples
    assert m["rmse_all"] == pytest.approx(math.sqrt((25.0 + sq_run1) / 4.0))
    assert diverged_runs(truth, _estimate(est), divergence_threshold=10.0).tolist() == [
        False, True, False, False]
    curve = rmse_over_time(truth, _estimate(est))
    assert curve[0].item() == pytest.approx(math.sqrt(25.0 / 4.0))


def test_outlier_patch_metrics_and_nonfinite_runs():
    truth = torch.zeros(2, 10, 2, dtype=torch.float64)
    est = truth.clone()
    est[0, 4, 0] = 6.0  # inside the patch: max error 6, jumps 6
    est[1, 3, 1] = float("nan")
    outlier = torch.zeros(2, 10, dtype=torch.bool)
    outlier[0, 3:6] = True
    m = wind_error_metrics(truth, _estimate(est), outlier=outlier)
    assert m["patch_max_error"] == pytest.approx(6.0)
    assert m["patch_max_jump"] == pytest.approx(6.0)
    # a non-finite estimate anywhere counts as diverged, a large finite one early does not
    assert diverged_runs(truth, _estimate(est)).tolist() == [False, True]
    assert diverged_runs(truth, _estimate(torch.where(torch.isnan(est), 1e3, est))).tolist() == [
        False, False]
    assert m["divergence_rate"] == pytest.approx(0.5)


def test_track_metrics():
    along = torch.tensor([[0.0, 3.0], [0.0, -3.0]], dtype=torch.float64)
    cross = torch.tensor([[0.0, 4.0], [0.0, 4.0]], dtype=torch.float64)
    m = track_error_metrics(along, cross)
    assert m["final_along_rms"] == pytest.approx(3.0)
    assert m["final_cross_rms"] == pytest.approx(4.0)
    assert m["final_rms"] == pytest.approx(5.0) and m["max_rms"] == pytest.approx(5.0)
    assert m["mean_rms"] == pytest.approx(2.5)
