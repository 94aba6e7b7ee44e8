"""Method-of-moments ARMA estimates against the paper's Table 1, closed forms and statsmodels."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.signal import lfilter
from statsmodels.regression.linear_model import yule_walker
from statsmodels.tsa.arima_process import ArmaProcess
from statsmodels.tsa.stattools import acovf

from neuralmap.errors import (
    ArmaModel,
    MomentSolutionError,
    arma_moments,
    sample_autocovariance,
    simulate_ar,
)

# Autocorrelations implied by the paper's Table 1: ρ_1 = AR(1) φ, ρ_2 = ρ_1 · ARMA(1,1) φ.
PAPER_RHO = np.array([1.0, 0.53150, 0.53150 * 0.75330])


def test_paper_table1_parameters_from_its_autocorrelations() -> None:
    # The three low orders of Table 1 follow from ρ_1, ρ_2 alone; the moment equations
    # must reproduce the printed values to their 5 digits.
    ar1 = arma_moments(PAPER_RHO, 1, 0)
    ar2 = arma_moments(PAPER_RHO, 2, 0)
    arma11 = arma_moments(PAPER_RHO, 1, 1)
    assert ar1.phi == pytest.approx((0.53150,), abs=1e-5)
    assert ar2.phi == pytest.approx((0.44417, 0.16430), abs=1e-5)
    assert arma11.phi == pytest.approx((0.75330,), abs=1e-5)
    assert arma11.theta == pytest.approx((0.31867,), abs=1e-5)


def test_ma1_has_no_invertible_solution_when_rho1_exceeds_half() -> None:
    # Table 1 leaves the MA(1) residual empty: ρ_1 = 0.53 > 1/2 has no invertible MA(1).
    with pytest.raises(MomentSolutionError, match="no invertible moment solution"):
        arma_moments(PAPER_RHO, 0, 1)
    # Below 1/2 the closed form θ = (−1 + √(1 − 4ρ²)) / (2ρ) with ρ = −θ/(1+θ²).
    rho = -0.4
    model = arma_moments(np.array([1.0, rho]), 0, 1)
    assert model.theta[0] == pytest.approx((-1 + np.sqrt(1 - 4 * rho**2)) / (2 * rho), abs=1e-12)


def test_arma11_matches_closed_form_moment_equations() -> None:
    gamma = np.array([2.0, 1.1, 0.7])
    model = arma_moments(gamma, 1, 1)
    phi = gamma[2] / gamma[1]
    c0 = gamma[0] * (1 + phi**2) - 2 * phi * gamma[1]
    c1 = gamma[1] * (1 + phi**2) - phi * (gamma[0] + gamma[2])
    rho_w = c1 / c0
    theta = (-1 + np.sqrt(1 - 4 * rho_w**2)) / (2 * rho_w)
    assert model.phi[0] == pytest.approx(phi, abs=1e-12)
    assert model.theta[0] == pytest.approx(theta, abs=1e-12)
    assert model.sigma2 == pytest.approx(c0 / (1 + theta**2), rel=1e-12)


@pytest.mark.parametrize("order", [(1, 0), (1, 1), (2, 1), (2, 2), (0, 2)])
def test_theoretical_autocovariance_is_a_fixed_point(order: tuple[int, int]) -> None:
    # Moments of an exact ARMA autocovariance give back the model (statsmodels' acovf).
    p, q = order
    true = ArmaModel(phi=(0.6, -0.2)[:p], theta=(0.4, 0.25)[:q], sigma2=1.7)
    process = ArmaProcess(np.r_[1, -np.array(true.phi)], np.r_[1, -np.array(true.theta)])
    gamma_sm = process.acovf(p + q + 1) * true.sigma2
    np.testing.assert_allclose(true.autocovariance(p + q), gamma_sm, rtol=1e-10)
    model = arma_moments(gamma_sm, p, q)
    np.testing.assert_allclose(model.phi, true.phi, atol=1e-9)
    np.testing.assert_allclose(model.theta, true.theta, atol=1e-9)
    assert model.sigma2 == pytest.approx(true.sigma2, rel=1e-9)


@pytest.mark.filterwarnings("ignore::FutureWarning")
@pytest.mark.parametrize("phi", [(0.5315,), (0.44417, 0.16430), (1.2, -0.5)])
def test_ar_equals_statsmodels_yule_walker(phi: tuple[float, ...]) -> None:
    x = simulate_ar(3000, phi=phi, sigma=1.0435, seed=7)
    np.testing.assert_allclose(sample_autocovariance(x, 3), acovf(x, nlag=3), rtol=1e-12)
    model = arma_moments(sample_autocovariance(x, len(phi)), len(phi), 0)
    rho, sigma = yule_walker(x, order=len(phi), method="mle")
    np.testing.assert_allclose(model.phi, rho, atol=1e-10)
    assert model.sigma2 == pytest.approx(sigma**2, rel=1e-10)
    # and recovers the true coefficients: 3000 samples, tolerance ≈ 4 standard errors
    np.testing.assert_allclose(model.phi, phi, atol=0.07)


def test_arma11_recovered_and_close_to_statsmodels_arima() -> None:
    from statsmodels.tsa.arima.model import ARIMA

    rng = np.random.default_rng(3)
    a = rng.standard_normal(6000 + 500)
    x = lfilter([1.0, -0.3], [1.0, -0.75], a)[500:]  # φ = 0.75, θ = 0.3
    model = arma_moments(sample_autocovariance(x, 2), 1, 1)
    fit = ARIMA(x, order=(1, 0, 1), trend="n").fit()
    # Moment estimates are less efficient than maximum likelihood: the tolerance is
    # about three times the ML standard error at n = 6000.
    assert model.phi[0] == pytest.approx(0.75, abs=0.05)
    assert model.theta[0] == pytest.approx(0.3, abs=0.06)
    assert model.phi[0] == pytest.approx(fit.arparams[0], abs=0.05)
    assert model.theta[0] == pytest.approx(-fit.maparams[0], abs=0.06)  # statsmodels: +θ
