"""Bad input to the error-model toolkit raises NeuralMapError saying what, where and how."""

from __future__ import annotations

import sys

import numpy as np
import pytest

from neuralmap.errors import (
    ArmaModel,
    ar_error_field,
    arma_moments,
    autocorrelation,
    check_stationary,
    f_statistic,
    identify_error_model,
    ljung_box,
    repeat_survey,
    runs_test,
    simulate_ar,
)
from neuralmap.errors.optional import require_statsmodels
from neuralmap.exceptions import NeuralMapError


def test_too_short_for_the_order() -> None:
    x = simulate_ar(49, seed=0)
    with pytest.raises(NeuralMapError, match=r"49 samples; at least 50 .*ARMA\(2,2\)"):
        identify_error_model(x)
    with pytest.raises(NeuralMapError, match="at least 60"):
        identify_error_model(simulate_ar(55, seed=0), max_order=3, max_ma_order=2)
    with pytest.raises(NeuralMapError, match="lags up to lag 3|up to lag 3"):
        arma_moments(np.array([1.0, 0.5, 0.2]), 2, 1)


def test_constant_and_non_finite_sequences() -> None:
    with pytest.raises(NeuralMapError, match=r"constant \(2\.5 everywhere\)"):
        identify_error_model(np.full(100, 2.5))
    x = simulate_ar(100, seed=1)
    x[37] = np.nan
    with pytest.raises(NeuralMapError, match="first at index 37"):
        identify_error_model(x)
    x[37] = np.inf
    with pytest.raises(NeuralMapError, match="non-finite"):
        ljung_box(x)
    with pytest.raises(NeuralMapError, match="must be 1-D"):
        autocorrelation(np.zeros((2, 50)))
    with pytest.raises(NeuralMapError, match="2 values above and 2 below"):
        runs_test(np.array([0.0, 0.0, 0.0, 1.0, 0.0]))


@pytest.mark.parametrize(
    "phi", [(1.0,), (-1.2,), (0.6, 0.5), (0.2, -1.05), (1.3, -0.2)], ids=str
)
def test_non_stationary_ar_parameters(phi: tuple[float, ...]) -> None:
    with pytest.raises(NeuralMapError, match="not stationary: the roots"):
        check_stationary(phi, where="augmented map-error state")
    with pytest.raises(NeuralMapError, match="not stationary"):
        simulate_ar(10, phi=phi)
    with pytest.raises(NeuralMapError, match="not stationary"):
        ar_error_field((5, 5), phi=(0.5,), phi_north=phi)
    assert not ArmaModel(phi=phi).is_stationary


def test_stationary_boundary_accepted() -> None:
    np.testing.assert_allclose(check_stationary((0.999,), where="x"), [0.999])
    check_stationary((0.5, 0.49), where="x")  # φ1 + φ2 < 1


def test_other_bad_values() -> None:
    with pytest.raises(NeuralMapError, match="max_order ≥ 1"):
        identify_error_model(simulate_ar(100), max_order=0)
    with pytest.raises(NeuralMapError, match="n_params_small < n_params_large"):
        f_statistic(1.0, 0.9, n=100, n_params_small=2, n_params_large=2)
    with pytest.raises(NeuralMapError, match="sigma must be finite"):
        simulate_ar(10, sigma=-1.0)
    with pytest.raises(NeuralMapError, match="≥ 2 passes"):
        repeat_survey(n_passes=1)
    with pytest.raises(NeuralMapError, match="must exceed model_df"):
        ljung_box(simulate_ar(100), lags=2, model_df=2)


def test_missing_statsmodels_names_the_extra(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "statsmodels", None)
    with pytest.raises(NeuralMapError, match=r"pip install 'neuralmap\[errors\]'"):
        require_statsmodels("ljung_box")


def test_stationarity_check_needs_only_numpy() -> None:
    # SciPy is a core dependency (no optional-import guard); the stationarity condition
    # itself needs only NumPy (used by the navigation models)
    check_stationary((0.5,), where="x")
