"""Wind-field estimation and track correction (SEEDS 002).

* `.turbulence`, `.simulator`: batched wind simulator (random-walk mean wind
  plus exactly discretised first-order turbulence, shear steps, gusts);
* `.measurement`, `.faults`: airspeed-derived wind with random-walk noise,
  outlier patches and spikes;
* `.tvar_model`, `.correlated`, `.filtering`: the paper's time-varying AR
  model with differenced measurements and a correlated-noise EKF; the LTI first-order
  Markov model for comparison;
* `.track`: dead reckoning with and without the wind correction;
* `.metrics`, `.comparison`: error metrics and filters compared on common draws
  (the study is `neuralmap.studies.wind`).
"""

from neuralmap.wind.comparison import WindFilterSpec, make_policy, run_filters
from neuralmap.wind.correlated import CorrelatedNoiseEKF, DecorrelatedTransition, decorrelate
from neuralmap.wind.faults import FaultConfig, draw_faults
from neuralmap.wind.filtering import (
    WindEstimate,
    estimate_wind,
    run_lti_filter,
    run_tvar_filter,
)
from neuralmap.wind.lti_model import LTIWindModel
from neuralmap.wind.measurement import MeasurementConfig, WindMeasurement, measure_wind
from neuralmap.wind.metrics import (
    diverged_runs,
    rmse_over_time,
    track_error_metrics,
    wind_error_metrics,
)
from neuralmap.wind.simulator import WindSimConfig, WindTruth, simulate_wind
from neuralmap.wind.track import TrackConfig, TrackResult, dead_reckon
from neuralmap.wind.turbulence import TurbulenceCoefficients, turbulence_coefficients
from neuralmap.wind.tvar_model import TVARWindModel

__all__ = [
    "CorrelatedNoiseEKF",
    "DecorrelatedTransition",
    "FaultConfig",
    "LTIWindModel",
    "MeasurementConfig",
    "TVARWindModel",
    "TrackConfig",
    "TrackResult",
    "TurbulenceCoefficients",
    "WindEstimate",
    "WindFilterSpec",
    "WindMeasurement",
    "WindSimConfig",
    "WindTruth",
    "decorrelate",
    "diverged_runs",
    "dead_reckon",
    "draw_faults",
    "estimate_wind",
    "make_policy",
    "measure_wind",
    "rmse_over_time",
    "run_filters",
    "run_lti_filter",
    "run_tvar_filter",
    "simulate_wind",
    "track_error_metrics",
    "turbulence_coefficients",
    "wind_error_metrics",
]
