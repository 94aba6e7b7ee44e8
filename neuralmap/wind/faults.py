"""Measurement faults of the wind measurement: patches of consecutive outliers, spikes.

SEEDS 002 (figures 3–4): the measured wind contains "patches" of consecutive outliers
(sensor drop-outs, transmission faults, shear). A patch is ``patch_length`` consecutive
samples whose measurement is replaced by ``truth-measurement + patch_std·n`` with ``n``
standard normal per sample and axis (so the differenced measurement is corrupted along the
whole patch, not only at its edges). Isolated spikes add ``± spike_magnitude`` to single
samples with probability ``spike_rate``.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.wind.checks import require_in_range, require_nonnegative

__all__ = ["FaultConfig", "draw_faults"]


@dataclass
class FaultConfig:
    """Outlier patches and spikes.

    Attributes:
        patch_count: Patches per run (0 = none).
        patch_length: Samples per patch.
        patch_std: Standard deviation of the outliers added inside a patch (m/s).
        patch_window: ``(start, end)`` fractions of the run inside which patches start
            (drawn uniformly per run and patch).
        spike_rate: Probability of a spike per sample (0 = none).
        spike_magnitude: Size of a spike (m/s), random sign.
    """

    patch_count: int = 0
    patch_length: int = 20
    patch_std: float = 10.0
    patch_window: tuple[float, float] = (0.3, 0.7)
    spike_rate: float = 0.0
    spike_magnitude: float = 15.0

    def validate(self) -> FaultConfig:
        """Checks the fields; returns ``self``.

        Raises:
            NeuralMapError: Negative counts or magnitudes, a rate outside [0, 1], a
                patch window outside [0, 1] or reversed.
        """
        where = "FaultConfig"
        require_nonnegative(self.patch_count, "patch_count", where)
        if int(self.patch_length) < 1:
            raise NeuralMapError(f"{where}: 'patch_length' = {self.patch_length!r} must be >= 1.")
        require_nonnegative(self.patch_std, "patch_std", where)
        require_in_range(self.spike_rate, "spike_rate", where, 0.0, 1.0)
        require_nonnegative(self.spike_magnitude, "spike_magnitude", where)
        lo, hi = (float(v) for v in self.patch_window)
        if not 0.0 <= lo <= hi <= 1.0:
            raise NeuralMapError(
                f"{where}: 'patch_window' = {self.patch_window!r} must be (start, end) "
                "fractions with 0 <= start <= end <= 1."
            )
        return self


def draw_faults(
    config: FaultConfig,
    *,
    n_runs: int,
    n_steps: int,
    generator: torch.Generator,
    dtype: torch.dtype = torch.float64,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Draws the additive fault signal and the outlier mask.

    Args:
        config: Fault parameters (validated here).
        n_runs: ``N``.
        n_steps: ``T``.
        generator: Random generator.
        dtype: Dtype of the fault signal.

    Returns:
        ``(fault (N, T, 2), outlier (N, T) bool)``: what to add to the measurement and
        where a sample is an outlier (patch or spike).
    """
    config.validate()
    n, t = int(n_runs), int(n_steps)
    fault = torch.zeros(n, t, 2, dtype=dtype)
    outlier = torch.zeros(n, t, dtype=torch.bool)
    steps = torch.arange(t)
    lo, hi = config.patch_window
    length = int(config.patch_length)
    for _ in range(int(config.patch_count)):
        u = torch.rand(n, generator=generator, dtype=torch.float64)
        first = int(lo * (t - 1))
        last = max(first, int(hi * (t - 1)) - length + 1)
        start = (first + u * (last - first + 1)).floor().long().clamp(max=t - 1)
        inside = (steps[None, :] >= start[:, None]) & (steps[None, :] < start[:, None] + length)
        noise = torch.randn(n, t, 2, generator=generator, dtype=dtype) * config.patch_std
        fault = fault + torch.where(inside[..., None], noise, 0.0)
        outlier = outlier | inside
    if config.spike_rate > 0.0:
        hit = torch.rand(n, t, generator=generator, dtype=torch.float64) < config.spike_rate
        sign = torch.randint(0, 2, (n, t, 2), generator=generator).to(dtype) * 2.0 - 1.0
        fault = fault + torch.where(hit[..., None], sign * config.spike_magnitude, 0.0)
        outlier = outlier | hit
    return fault, outlier
