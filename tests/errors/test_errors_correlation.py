"""Autocorrelation, partial autocorrelation and Ljung–Box whiteness against closed forms."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import chi2

from neuralmap.errors import (
    arma_moments,
    autocorrelation,
    confidence_band,
    ljung_box,
    partial_autocorrelation,
    sample_autocovariance,
    simulate_ar,
)


def test_acf_and_pacf_match_moment_definitions() -> None:
    x = simulate_ar(2000, phi=(0.44417, 0.16430), seed=1)
    gamma = sample_autocovariance(x, 5)
    np.testing.assert_allclose(autocorrelation(x, nlags=5), gamma / gamma[0], atol=1e-12)
    pacf = partial_autocorrelation(x, nlags=5)
    # the lag-k partial autocorrelation is the last coefficient of the order-k Yule–Walker fit
    for k in (1, 2, 3):
        assert pacf[k] == pytest.approx(arma_moments(gamma, k, 0).phi[-1], abs=1e-10)
    # AR(2): partial autocorrelation cuts off after lag 2
    band = confidence_band(x.size)
    assert abs(pacf[2]) > 2 * band
    assert np.all(np.abs(pacf[3:]) < 1.5 * band)


def test_ljung_box_statistic_and_verdicts() -> None:
    rng = np.random.default_rng(2)
    white = rng.standard_normal(1000)
    correlated = simulate_ar(1000, phi=(0.9,), seed=2)
    lb = ljung_box(white, lags=10)
    rho = autocorrelation(white, nlags=10)[1:]
    k = np.arange(1, 11)
    q = 1000 * 1002 * np.sum(rho**2 / (1000 - k))
    assert lb.statistic == pytest.approx(q, rel=1e-10)
    assert lb.p_value == pytest.approx(chi2.sf(q, 10), rel=1e-10)
    assert lb.white
    strong = ljung_box(correlated, lags=10)
    assert not strong.white and strong.p_value < 1e-10
    # model_df removes degrees of freedom
    assert ljung_box(white, lags=10, model_df=2).p_value == pytest.approx(chi2.sf(q, 8), rel=1e-10)


def test_ljung_box_false_alarm_rate_near_alpha() -> None:
    rng = np.random.default_rng(4)
    rejections = sum(not ljung_box(rng.standard_normal(300), lags=10).white for _ in range(200))
    # 5 % nominal; binomial(200, 0.05) has 99.9 % of its mass in [2, 22]
    assert 2 <= rejections <= 22
