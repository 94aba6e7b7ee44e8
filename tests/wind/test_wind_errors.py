"""Bad input to the wind package raises NeuralMapError with a clear message."""

from __future__ import annotations

import pytest
import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.wind import (
    FaultConfig,
    LTIWindModel,
    MeasurementConfig,
    TrackConfig,
    TVARWindModel,
    WindSimConfig,
    dead_reckon,
    estimate_wind,
    run_tvar_filter,
    simulate_wind,
    turbulence_coefficients,
)
from neuralmap.wind.checks import require_open_unit


@pytest.mark.parametrize(
    ("config", "match"),
    [
        (WindSimConfig(scale=0.0), "'scale' = 0.0 must be > 0"),
        (WindSimConfig(scale=-100.0), "turbulence scale"),
        (WindSimConfig(mean_walk_var=-0.01), "'mean_walk_var'"),
        (WindSimConfig(driver_var=0.0), "'driver_var'"),
        (WindSimConfig(intensity=float("nan")), "'intensity' must be finite"),
        (WindSimConfig(step=0.0), "'step'"),
        (WindSimConfig(gust_length=0), "'gust_length'"),
        (MeasurementConfig(walk_var=0.0), "'walk_var'"),
        (MeasurementConfig(init_var=-1.0), "'init_var'"),
        (FaultConfig(spike_rate=1.5), "'spike_rate'"),
        (FaultConfig(patch_window=(0.8, 0.2)), "'patch_window'"),
        (TVARWindModel(meas_var=0.0), "'meas_var'"),
        (TVARWindModel(process_var=-1.0), "'process_var'"),
        (LTIWindModel(correlation_time=0.0), "'correlation_time'"),
        (TrackConfig(correction_step=1.5, dt=1.0), r"'correction_step' = 1.5 must lie in \[0.0, 1.0\]"),
        (TrackConfig(correction_step=-0.1), "'correction_step'"),
        (TrackConfig(airspeed=0.0), "'airspeed'"),
    ],
)
def test_bad_config_values(config, match):
    with pytest.raises(NeuralMapError, match=match):
        config.validate()


def test_bad_calls():
    with pytest.raises(NeuralMapError, match="turbulence scale"):
        turbulence_coefficients(intensity=1.75, scale=0.0, step=20.0)
    with pytest.raises(NeuralMapError, match="n_steps >= 2"):
        simulate_wind(WindSimConfig(), n_runs=2, n_steps=1)
    with pytest.raises(NeuralMapError, match=r"'z' must be \(N, T, 2\)"):
        estimate_wind(torch.zeros(3, 10), TVARWindModel())
    with pytest.raises(NeuralMapError, match=r"'z' must be a \(N, T\) tensor"):
        run_tvar_filter(torch.zeros(3), TVARWindModel())
    with pytest.raises(NeuralMapError, match="'meas_var'"):
        run_tvar_filter(torch.zeros(3, 5), TVARWindModel(meas_var=-2.0))
    with pytest.raises(NeuralMapError, match="'wind_estimate' has shape"):
        dead_reckon(torch.zeros(2, 5, 2), TrackConfig(), wind_estimate=torch.zeros(2, 4, 2),
                    generator=torch.Generator())


@pytest.mark.parametrize("value", [0.0, 1.0, -0.5, 1.2])
def test_forgetting_factor_outside_open_unit_interval(value):
    with pytest.raises(NeuralMapError, match=r"open interval \(0, 1\)"):
        require_open_unit(value, "forgetting", "SageHusa")
