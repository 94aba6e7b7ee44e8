"""Airspeed-derived wind measurement with random-walk noise (SEEDS 002).

The measured wind is the INS ground velocity minus the air velocity from airspeed and
heading, ``Z_k = v_k + γ_k``. As in the paper, its error is a random walk,
``γ_{k+1} = γ_k + ν_{k+1}`` with ``ν`` white (variance ``walk_var``; physically the INS
velocity error), ``γ_0 ~ N(0, init_var)``. Faults (outlier patches, spikes) from
`.faults` are added on top. Differencing ``Z_{k+1} − Z_k`` turns the random walk into
the white ``ν_{k+1}`` (see `.tvar_model`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from neuralmap.wind.checks import require_nonnegative, require_positive
from neuralmap.wind.faults import FaultConfig, draw_faults
from neuralmap.wind.simulator import WindTruth

__all__ = ["MeasurementConfig", "WindMeasurement", "measure_wind"]


@dataclass
class MeasurementConfig:
    """Measurement-noise parameters.

    Attributes:
        walk_var: Variance of the random-walk increment ``ν`` per sample (m²/s²).
        init_var: Variance of the initial error ``γ_0`` (0 = start exact).
    """

    walk_var: float = 1.0e-3
    init_var: float = 0.0

    def validate(self) -> MeasurementConfig:
        """Checks the fields; returns ``self``.

        Raises:
            NeuralMapError: ``walk_var <= 0`` or ``init_var < 0``.
        """
        require_positive(self.walk_var, "walk_var", "MeasurementConfig")
        require_nonnegative(self.init_var, "init_var", "MeasurementConfig")
        return self


@dataclass
class WindMeasurement:
    """Measured wind, batch first.

    Attributes:
        z: ``(N, T, 2)`` measured wind (truth + random walk + faults).
        noise: ``(N, T, 2)`` random-walk error ``γ`` (without faults).
        fault: ``(N, T, 2)`` added fault signal.
        outlier: ``(N, T)`` bool, samples that carry an outlier.
    """

    z: torch.Tensor
    noise: torch.Tensor
    fault: torch.Tensor
    outlier: torch.Tensor


def measure_wind(
    truth: WindTruth,
    config: MeasurementConfig,
    faults: FaultConfig | None = None,
    *,
    generator: torch.Generator,
) -> WindMeasurement:
    """Draws the measured wind for every run of ``truth``.

    Args:
        truth: Simulated wind ``(N, T, 2)``.
        config: Random-walk noise parameters (validated here).
        faults: Outlier patches and spikes (None = clean).
        generator: Random generator.

    Returns:
        `WindMeasurement`.
    """
    config.validate()
    wind = truth.wind
    n, t, _ = wind.shape
    steps = torch.randn(n, t, 2, generator=generator, dtype=wind.dtype)
    steps[:, 0] *= math.sqrt(config.init_var)
    steps[:, 1:] *= math.sqrt(config.walk_var)
    noise = torch.cumsum(steps, dim=1)
    if faults is None:
        fault = torch.zeros_like(wind)
        outlier = torch.zeros(n, t, dtype=torch.bool)
    else:
        fault, outlier = draw_faults(faults, n_runs=n, n_steps=t, generator=generator,
                                     dtype=wind.dtype)
    return WindMeasurement(z=wind + noise + fault, noise=noise, fault=fault, outlier=outlier)
