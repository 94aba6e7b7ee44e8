"""Runs test against statsmodels and stationarity verdicts on known sequences."""

from __future__ import annotations

import numpy as np
import pytest
from statsmodels.sandbox.stats.runs import runstest_1samp

from neuralmap.errors import adf_test, check_stationarity, runs_test, simulate_ar


def test_runs_test_equals_statsmodels() -> None:
    rng = np.random.default_rng(0)
    # even lengths: no value equals the median (statsmodels counts ties as above, we drop them)
    for x in (rng.standard_normal(300), simulate_ar(400, phi=(0.9,), seed=1)):
        ours = runs_test(x)
        z, p = runstest_1samp(x, cutoff="median", correction=False)
        assert ours.z == pytest.approx(z, rel=1e-10)
        assert ours.p_value == pytest.approx(p, rel=1e-10)


def test_runs_test_verdicts_white_vs_correlated() -> None:
    rng = np.random.default_rng(1)
    assert runs_test(rng.standard_normal(500)).random
    strong = runs_test(simulate_ar(500, phi=(0.9,), seed=1))
    assert not strong.random and strong.z < -5  # too few runs: positive correlation


def test_stationary_ar1_accepted() -> None:
    result = check_stationarity(simulate_ar(2000, seed=3))
    assert result.stationary, result.to_dict()


def test_shrinking_variance_rejected_by_run_test() -> None:
    # the paper's adaptive-region linearisation error: variance decays, then small and white
    rng = np.random.default_rng(4)
    t = np.arange(2000)
    x = (0.5 + 10 * np.exp(-t / 400)) * rng.standard_normal(2000)
    result = check_stationarity(x)
    assert not result.mean_square_runs.random
    assert not result.stationary


def test_adf_random_walk_vs_ar1() -> None:
    rng = np.random.default_rng(5)
    assert not adf_test(np.cumsum(rng.standard_normal(1000))).stationary
    assert adf_test(simulate_ar(1000, seed=5)).stationary
