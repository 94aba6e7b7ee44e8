"""First-order (Dryden-type) turbulence discretised exactly: coefficients and statistics.

Continuous model per axis: a first-order Gauss-Markov process with correlation time
``τ = L / V`` (turbulence scale ``L`` in metres flown at airspeed ``V``) and standard
deviation ``σ`` (turbulence intensity). Sampled every ``Δt`` its exact discretisation is
the AR(1) recursion (SEEDS 002, reconstructed simulator)

    v_t(k+1) = φ v_t(k) + σ·sqrt(1 − φ²)·w_k,     φ = exp(−V Δt / L) = exp(−h / L),

with ``h = V Δt`` the distance flown between samples (the paper's step ``h = 20``; SEEDS
writes the exponent as ``h V / L`` with ``h`` the sample period, the same number when
``h`` is given in seconds) and ``w_k`` white with variance ``Σ`` (the paper's ``Σ = 1``).
Stationary statistics: variance ``σ² Σ``, autocorrelation ``φ^|j|`` at lag ``j`` samples,
correlation time ``L / V`` seconds (``L / h`` samples).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from neuralmap.wind.checks import require_positive

__all__ = ["TurbulenceCoefficients", "turbulence_coefficients"]


@dataclass(frozen=True)
class TurbulenceCoefficients:
    """Exact AR(1) discretisation of the first-order turbulence of one axis.

    Attributes:
        phi: ``φ = exp(−h / L)``, one-step autocorrelation.
        gain: ``σ·sqrt(1 − φ²)``, multiplies the white driver ``w`` (variance ``Σ``).
        variance: Stationary variance ``σ² Σ``.
        correlation_steps: Correlation time in samples, ``L / h`` (``φ^k = e^{-1}``).
    """

    phi: float
    gain: float
    variance: float
    correlation_steps: float

    def autocorrelation(self, lag: int) -> float:
        """Analytic autocorrelation ``φ^|lag|`` of the stationary process."""
        return self.phi ** abs(int(lag))


def turbulence_coefficients(
    *, intensity: float, scale: float, step: float, driver_var: float = 1.0
) -> TurbulenceCoefficients:
    """Coefficients of the exact discretisation (SEEDS 002, eq. 31 reconstructed).

    Args:
        intensity: Turbulence intensity ``σ`` (m/s); paper 1.75.
        scale: Turbulence scale ``L`` (m); paper 100.
        step: Distance flown between samples ``h = V Δt`` (m); paper 20.
        driver_var: Variance ``Σ`` of the white driver; paper 1.

    Returns:
        `TurbulenceCoefficients`.

    Raises:
        NeuralMapError: A non-positive scale, step, intensity or variance.
    """
    where = "turbulence_coefficients"
    sigma = require_positive(intensity, "intensity", where)
    length = require_positive(scale, "scale", where,
                              "The turbulence scale L is a length in metres (paper: 100).")
    h = require_positive(step, "step", where)
    var = require_positive(driver_var, "driver_var", where)
    phi = math.exp(-h / length)
    return TurbulenceCoefficients(
        phi=phi,
        gain=sigma * math.sqrt(1.0 - phi * phi),
        variance=sigma * sigma * var,
        correlation_steps=length / h,
    )
