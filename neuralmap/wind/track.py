"""Track correction with the wind estimate: a dead-reckoned vehicle (SEEDS 002, eq. 29).

The vehicle flies at airspeed ``V`` and heading ``ψ`` (degrees from north, clockwise, with
an optional constant turn rate) through the wind ``w``; its true ground velocity is
``V [sin ψ, cos ψ] + w``. Dead reckoning uses the measured airspeed and heading (white
errors) and integrates the air-relative velocity ``v̂``:

    uncorrected:  x̂_{k+1} = x̂_k + v̂_k Δt
    corrected:    x̂_{k+1} = x̂_k + v̂_k Δt + ŵ_k l,       0 ≤ l ≤ Δt,

the paper's ``x_{k+1} = x_k + (v̂ + ŵ)·l`` with the wind term applied over the correction
step ``l`` (``l = Δt`` is the full correction; ``l = 0`` is no correction). Optional
position fixes every ``fix_interval`` samples (an integrated navigation system) reset both
tracks to the true position plus white noise. Errors are split into along-track (along the
true ground velocity) and cross-track (to its left) components.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.wind.checks import require_in_range, require_nonnegative, require_positive

__all__ = ["TrackConfig", "TrackResult", "dead_reckon"]


@dataclass
class TrackConfig:
    """Dead-reckoning vehicle and correction step.

    Attributes:
        airspeed: ``V`` (m/s).
        heading_deg: Initial heading (degrees from north, clockwise).
        turn_rate_deg: Heading change per sample (degrees).
        dt: Sample period ``Δt`` (s); must match the wind samples.
        correction_step: ``l`` (s), ``0 ≤ l ≤ Δt``; None = ``Δt``.
        airspeed_noise_std: White airspeed error (m/s).
        heading_noise_std_deg: White heading error (degrees).
        fix_interval: Samples between position fixes (0 = pure dead reckoning).
        fix_std: Standard deviation of a fix per axis (m).
    """

    airspeed: float = 20.0
    heading_deg: float = 45.0
    turn_rate_deg: float = 0.0
    dt: float = 1.0
    correction_step: float | None = None
    airspeed_noise_std: float = 0.1
    heading_noise_std_deg: float = 0.1
    fix_interval: int = 0
    fix_std: float = 1.0

    @property
    def step(self) -> float:
        """The correction step ``l`` (``Δt`` when not given)."""
        return self.dt if self.correction_step is None else float(self.correction_step)

    def validate(self) -> TrackConfig:
        """Checks the fields; returns ``self``.

        Raises:
            NeuralMapError: Non-positive airspeed or period, a correction step outside
                ``[0, Δt]``, negative noise levels or fix interval.
        """
        where = "TrackConfig"
        require_positive(self.airspeed, "airspeed", where)
        dt = require_positive(self.dt, "dt", where)
        if self.correction_step is not None:
            require_in_range(self.correction_step, "correction_step", where, 0.0, dt)
        require_nonnegative(self.airspeed_noise_std, "airspeed_noise_std", where)
        require_nonnegative(self.heading_noise_std_deg, "heading_noise_std_deg", where)
        require_nonnegative(self.fix_interval, "fix_interval", where)
        require_nonnegative(self.fix_std, "fix_std", where)
        for name in ("heading_deg", "turn_rate_deg"):
            if not math.isfinite(float(getattr(self, name))):
                raise NeuralMapError(f"{where}: '{name}' must be finite.")
        return self


@dataclass
class TrackResult:
    """True and dead-reckoned tracks, batch first.

    Attributes:
        true_position: ``(N, T, 2)`` east/north position (m).
        position: ``(N, T, 2)`` dead-reckoned position.
        along: ``(N, T)`` along-track error (m), positive ahead of the truth.
        cross: ``(N, T)`` cross-track error (m), positive to the left.
    """

    true_position: torch.Tensor
    position: torch.Tensor
    along: torch.Tensor
    cross: torch.Tensor

    @property
    def error(self) -> torch.Tensor:
        """``(N, T)`` horizontal position error norm (m)."""
        return torch.hypot(self.along, self.cross)


def dead_reckon(
    wind: torch.Tensor,
    config: TrackConfig,
    *,
    wind_estimate: torch.Tensor | None = None,
    generator: torch.Generator,
) -> TrackResult:
    """Flies ``N`` vehicles through ``wind`` and dead-reckons them (SEEDS 002, eq. 29).

    The sensor errors and fixes are drawn from ``generator``: call with generators in the
    same state to compare the uncorrected (``wind_estimate=None``) and corrected tracks on
    the same draws.

    Args:
        wind: ``(N, T, 2)`` true wind (m/s).
        config: Vehicle and correction parameters (validated here).
        wind_estimate: ``(N, T, 2)`` wind estimate used for the correction; None = no
            correction.
        generator: Random generator of the sensor errors and fixes.

    Returns:
        `TrackResult`.

    Raises:
        NeuralMapError: Bad config or shapes.
    """
    config.validate()
    if wind.ndim != 3 or wind.shape[-1] != 2:
        raise NeuralMapError(f"dead_reckon: 'wind' must be (N, T, 2), got {tuple(wind.shape)}.")
    if wind_estimate is not None and wind_estimate.shape != wind.shape:
        raise NeuralMapError(
            f"dead_reckon: 'wind_estimate' has shape {tuple(wind_estimate.shape)}, expected "
            f"{tuple(wind.shape)} like 'wind'."
        )
    n, t, _ = wind.shape
    dtype = wind.dtype
    heading = torch.deg2rad(config.heading_deg + config.turn_rate_deg
                            * torch.arange(t, dtype=dtype))  # (T,)
    air = config.airspeed * torch.stack([torch.sin(heading), torch.cos(heading)], -1)
    ground = air + wind  # (N, T, 2)
    speed_meas = config.airspeed + config.airspeed_noise_std * torch.randn(
        n, t, generator=generator, dtype=dtype)
    heading_meas = heading + math.radians(config.heading_noise_std_deg) * torch.randn(
        n, t, generator=generator, dtype=dtype)
    air_meas = speed_meas[..., None] * torch.stack(
        [torch.sin(heading_meas), torch.cos(heading_meas)], -1)
    fix_noise = config.fix_std * torch.randn(n, t, 2, generator=generator, dtype=dtype)
    step = air_meas * config.dt
    if wind_estimate is not None:
        step = step + wind_estimate * config.step
    true_pos = torch.zeros(n, t, 2, dtype=dtype)
    true_pos[:, 1:] = torch.cumsum(ground[:, :-1] * config.dt, dim=1)
    pos = torch.empty_like(true_pos)
    pos[:, 0] = 0.0
    interval = int(config.fix_interval)
    for k in range(t - 1):
        nxt = pos[:, k] + step[:, k]
        if interval > 0 and (k + 1) % interval == 0:
            nxt = true_pos[:, k + 1] + fix_noise[:, k + 1]
        pos[:, k + 1] = nxt
    err = pos - true_pos
    direction = ground / ground.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    along = (err * direction).sum(-1)
    cross = err[..., 1] * direction[..., 0] - err[..., 0] * direction[..., 1]
    return TrackResult(true_position=true_pos, position=pos, along=along, cross=cross)
