"""Paired bootstrap of Monte Carlo RMSE: against a NumPy loop over the same resamples."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.lab.bootstrap import bootstrap_rmse, paired_ratio, resample_index


def _numpy_rmse(msq: np.ndarray, mask: np.ndarray, index: np.ndarray) -> np.ndarray:
    out = []
    for draw in index:  # the reference: one resample at a time
        chosen = [msq[r] for r in draw if mask[r]]
        out.append(np.sqrt(np.mean(chosen)) if chosen else np.nan)
    return np.asarray(out)


def test_interval_matches_a_numpy_loop_over_the_same_resamples() -> None:
    rng = np.random.default_rng(0)
    msq = rng.gamma(2.0, 50.0, 40)
    mask = rng.random(40) > 0.2
    index = resample_index(40, 500, seed=7)
    got = bootstrap_rmse(torch.from_numpy(msq), torch.from_numpy(mask), index)
    ref = _numpy_rmse(msq, mask, index.numpy())
    assert got.value == pytest.approx(np.sqrt(msq[mask].mean()), rel=1e-12)
    assert got.n_runs == int(mask.sum())
    lo, hi = np.quantile(ref, [0.025, 0.975])
    assert got.low == pytest.approx(lo, rel=1e-9) and got.high == pytest.approx(hi, rel=1e-9)
    assert got.low < got.value < got.high


def test_paired_ratio_of_a_method_with_itself_is_exactly_one() -> None:
    rng = np.random.default_rng(1)
    msq = torch.from_numpy(rng.gamma(2.0, 50.0, 30))
    mask = torch.ones(30, dtype=torch.bool)
    index = resample_index(30, 300, seed=0)
    assert paired_ratio(msq, mask, msq, mask, index) == pytest.approx((1.0, 1.0, 1.0))
    # twice the squared error everywhere: sqrt(2) on every resample
    ratio, lo, hi = paired_ratio(2 * msq, mask, msq, mask, index)
    assert ratio == pytest.approx(2**0.5) and lo == pytest.approx(2**0.5)
    assert hi == pytest.approx(2**0.5)


def test_empty_subset_and_bad_shapes() -> None:
    index = resample_index(5, 100, seed=0)
    msq = torch.ones(5, dtype=torch.float64)
    none = torch.zeros(5, dtype=torch.bool)
    assert bootstrap_rmse(msq, none, index).value is None
    assert paired_ratio(msq, none, msq, ~none, index) == (None, None, None)
    with pytest.raises(NeuralMapError, match="bootstrap"):
        bootstrap_rmse(msq, torch.ones(4, dtype=torch.bool), index)
