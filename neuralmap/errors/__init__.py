"""DEM-related error models: identification (stationarity, correlation, ARMA by moments,
inverse-function residual, F-test) and simulation of DEM-making errors (SEEDS 000).

Needs SciPy (filters, distributions); statsmodels for the correlation, whiteness and ADF
tests. Both come with the optional extra: ``pip install 'neuralmap[errors]'``.
"""

from neuralmap.errors.arma import ArmaModel, check_stationary, order_name
from neuralmap.errors.correlation import (
    autocorrelation,
    confidence_band,
    partial_autocorrelation,
)
from neuralmap.errors.dem_error import add_dem_error
from neuralmap.errors.f_test import f_quantile, f_statistic
from neuralmap.errors.identification import (
    ErrorModelIdentification,
    OrderRow,
    identify_error_model,
    minimum_length,
)
from neuralmap.errors.inverse_function import (
    fit_residual,
    innovations,
    inverse_function_weights,
)
from neuralmap.errors.linearization_error import linearization_error, summarise_error_sequences
from neuralmap.errors.moments import MomentSolutionError, arma_moments, sample_autocovariance
from neuralmap.errors.repeat_survey import RepeatSurvey, repeat_survey, survey_recovery
from neuralmap.errors.runs import RunsResult, runs_test
from neuralmap.errors.simulation import (
    DEM_ERROR_AR1,
    DEM_ERROR_AR2,
    DEM_ERROR_SIGMA,
    PAPER_GRID_SPACING,
    ar1_coefficient,
    ar_error_field,
    ar_filter,
    correlation_length,
    simulate_ar,
)
from neuralmap.errors.stationarity import (
    AdfResult,
    StationarityResult,
    adf_test,
    check_stationarity,
    run_stationarity_test,
)
from neuralmap.errors.whiteness import WhitenessResult, ljung_box

__all__ = [
    "DEM_ERROR_AR1",
    "DEM_ERROR_AR2",
    "DEM_ERROR_SIGMA",
    "PAPER_GRID_SPACING",
    "AdfResult",
    "ArmaModel",
    "ErrorModelIdentification",
    "MomentSolutionError",
    "OrderRow",
    "RepeatSurvey",
    "RunsResult",
    "StationarityResult",
    "WhitenessResult",
    "adf_test",
    "add_dem_error",
    "ar1_coefficient",
    "ar_error_field",
    "ar_filter",
    "arma_moments",
    "autocorrelation",
    "check_stationarity",
    "check_stationary",
    "confidence_band",
    "correlation_length",
    "f_quantile",
    "f_statistic",
    "fit_residual",
    "identify_error_model",
    "innovations",
    "inverse_function_weights",
    "linearization_error",
    "ljung_box",
    "minimum_length",
    "order_name",
    "partial_autocorrelation",
    "repeat_survey",
    "run_stationarity_test",
    "runs_test",
    "sample_autocovariance",
    "simulate_ar",
    "summarise_error_sequences",
    "survey_recovery",
]
