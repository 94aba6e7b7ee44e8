"""Inverse-function weights, innovations and fit residual against closed forms and ARIMA."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.signal import lfilter

from neuralmap.errors import ArmaModel, fit_residual, innovations, inverse_function_weights
from neuralmap.exceptions import NeuralMapError


def test_weights_closed_forms() -> None:
    np.testing.assert_allclose(
        inverse_function_weights(ArmaModel(phi=(0.44, 0.16)), 5), [0.44, 0.16, 0, 0, 0],
        atol=1e-15,
    )
    phi, theta = 0.7533, 0.31867
    j = np.arange(1, 9)
    np.testing.assert_allclose(
        inverse_function_weights(ArmaModel(phi=(phi,), theta=(theta,)), 8),
        (phi - theta) * theta ** (j - 1),
        rtol=1e-12,
    )


def test_innovations_invert_the_model_exactly_and_equal_the_loop() -> None:
    rng = np.random.default_rng(0)
    model = ArmaModel(phi=(0.6, 0.1), theta=(0.3, -0.2), sigma2=1.0)
    a = rng.standard_normal((3, 400))
    x = lfilter([1, -0.3, 0.2], [1, -0.6, -0.1], a, axis=-1)  # zero pre-sample values
    np.testing.assert_allclose(innovations(x, model, demean=False), a, atol=1e-10)
    # explicit recursion a_t = x_t − Σ φ_i x_{t-i} + Σ θ_j a_{t-j}
    ref = np.zeros(400)
    for t in range(400):
        ref[t] = x[0, t]
        for i, f in enumerate(model.phi, 1):
            ref[t] -= f * x[0, t - i] if t - i >= 0 else 0.0
        for i, th in enumerate(model.theta, 1):
            ref[t] += th * ref[t - i] if t - i >= 0 else 0.0
    np.testing.assert_allclose(innovations(x[0], model, demean=False), ref, atol=1e-12)


def test_residual_matches_arima_sigma2() -> None:
    from statsmodels.tsa.arima.model import ARIMA

    rng = np.random.default_rng(5)
    x = lfilter([1.0, -0.3], [1.0, -0.75], 0.8 * rng.standard_normal(4500))[500:]
    fit = ARIMA(x, order=(1, 0, 1), trend="n").fit()
    model = ArmaModel(phi=tuple(fit.arparams), theta=tuple(-fit.maparams))
    # the conditional (zero-start) residual after 20 samples ≈ the exact ML σ² (1 %)
    assert fit_residual(x, model, start=20) == pytest.approx(fit.params[-1], rel=0.01)
    assert fit_residual(x, model, start=20) == pytest.approx(0.64, rel=0.05)


def test_non_invertible_model_is_refused() -> None:
    with pytest.raises(NeuralMapError, match="not invertible"):
        innovations(np.arange(10.0), ArmaModel(theta=(1.5,)))
