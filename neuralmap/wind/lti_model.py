"""Linear time-invariant first-order Markov wind model (the usual choice, SEEDS 002).

One axis: ``v_{k+1} = φ v_k + w_k``, ``φ = exp(−Δt / τ)``, ``w ~ N(0, process_var)``, and
the raw measured wind ``Z_k = v_k + ε_k`` with ``ε`` assumed white (variance
``meas_var``). This is the model the paper improves upon: a fixed coefficient and white
noises, filtered with a plain Kalman filter on the raw measurement.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar

import torch

from neuralmap.wind.checks import require_positive

__all__ = ["LTIWindModel"]


@dataclass
class LTIWindModel:
    """First-order Gauss-Markov wind with white measurement noise.

    Attributes:
        correlation_time: ``τ`` (s) of the Markov wind.
        dt: Sample period (s).
        process_var: Variance of ``w`` per sample (paper start 0.01).
        meas_var: Assumed white measurement-noise variance (paper start 2).
        var_v0: Initial variance of ``v`` about the first measurement.
    """

    correlation_time: float = 300.0
    dt: float = 1.0
    process_var: float = 0.01
    meas_var: float = 2.0
    var_v0: float = 2.0

    num_states: ClassVar[int] = 1

    def validate(self) -> LTIWindModel:
        """Checks the fields; returns ``self``.

        Raises:
            NeuralMapError: A non-positive time constant, period or variance.
        """
        where = "LTIWindModel"
        for name in ("correlation_time", "dt", "process_var", "meas_var", "var_v0"):
            require_positive(getattr(self, name), name, where)
        return self

    @property
    def phi(self) -> float:
        """``φ = exp(−Δt / τ)``."""
        return math.exp(-self.dt / self.correlation_time)

    def initial(self, z0: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Initial state ``[Z_0]`` ``(N, 1)`` and covariance ``(N, 1, 1)``."""
        return z0.unsqueeze(-1).clone(), torch.full((z0.shape[0], 1, 1), self.var_v0,
                                                    dtype=z0.dtype, device=z0.device)
