"""Batched horizontal wind simulator: random-walk mean wind plus first-order turbulence.

SEEDS 002 (eqs. 30–31, reconstructed): per axis (east, north)

    v_m(k+1) = v_m(k) + w_m,                 w_m ~ N(0, Σ_vm)       (mean wind)
    v_t(k+1) = φ v_t(k) + σ sqrt(1 − φ²) w,  w ~ N(0, Σ)            (turbulence)
    v(k)     = v_m(k) + v_t(k) [+ gust(k)]

with the paper's row ``[Σ_vm Σ σ L h v_m(0) v_t(0)] = [0.01 1 1.75 100 20 10 0]`` as the
defaults of `WindSimConfig`. Optional: a shear step (the mean wind jumps by a
vector at one sample) and a "1 − cos" discrete gust. All N runs are drawn at once from
one seeded generator (loops only over time steps).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.wind.checks import require_nonnegative, require_positive
from neuralmap.wind.turbulence import TurbulenceCoefficients, turbulence_coefficients

__all__ = ["WindSimConfig", "WindTruth", "simulate_wind"]


@dataclass
class WindSimConfig:
    """Wind-field simulator parameters (defaults: the paper's parameter row).

    Attributes:
        mean_walk_var: ``Σ_vm``, variance of the mean-wind random-walk increment per
            sample (m²/s²); paper 0.01.
        driver_var: ``Σ``, variance of the white turbulence driver; paper 1.
        intensity: ``σ``, turbulence intensity (m/s); paper 1.75.
        scale: ``L``, turbulence scale (m); paper 100.
        step: ``h``, distance flown between samples (m); paper 20.
        airspeed: ``V`` (m/s); the sample period is ``Δt = h / V`` (1 s by default).
        mean0: ``v_m(0)``, initial mean wind speed (m/s); paper 10.
        turb0: ``v_t(0)`` (m/s); paper 0. None draws it from the stationary law.
        mean_direction_deg: Direction the mean wind blows towards, degrees from north,
            clockwise (90 = towards east).
        shear_step: Size of a step in the mean wind (m/s); 0 = no shear.
        shear_time: Sample index of the shear step.
        shear_direction_deg: Direction of the shear step (as ``mean_direction_deg``;
            default north, across the default eastward mean wind, as the wind study).
        gust_amplitude: Peak of a "1 − cos" discrete gust (m/s); 0 = no gust.
        gust_time: First sample of the gust.
        gust_length: Gust duration in samples.
        gust_direction_deg: Gust direction (as ``mean_direction_deg``).
    """

    mean_walk_var: float = 0.01
    driver_var: float = 1.0
    intensity: float = 1.75
    scale: float = 100.0
    step: float = 20.0
    airspeed: float = 20.0
    mean0: float = 10.0
    turb0: float | None = 0.0
    mean_direction_deg: float = 90.0
    shear_step: float = 0.0
    shear_time: int = 0
    shear_direction_deg: float = 0.0
    gust_amplitude: float = 0.0
    gust_time: int = 0
    gust_length: int = 20
    gust_direction_deg: float = 90.0

    @property
    def dt(self) -> float:
        """Sample period ``Δt = h / V`` in seconds."""
        return self.step / self.airspeed

    def validate(self) -> WindSimConfig:
        """Checks every field; returns ``self``.

        Raises:
            NeuralMapError: Non-positive variances, intensity, scale, step or airspeed,
                negative shear/gust times, a gust shorter than one sample.
        """
        where = "WindSimConfig"
        require_positive(self.mean_walk_var, "mean_walk_var", where)
        require_positive(self.driver_var, "driver_var", where)
        require_positive(self.intensity, "intensity", where)
        require_positive(self.scale, "scale", where,
                         "The turbulence scale L is a length in metres (paper: 100).")
        require_positive(self.step, "step", where)
        require_positive(self.airspeed, "airspeed", where)
        require_nonnegative(self.shear_time, "shear_time", where)
        require_nonnegative(self.gust_time, "gust_time", where)
        if int(self.gust_length) < 1:
            raise NeuralMapError(
                f"{where}: 'gust_length' = {self.gust_length!r} must be >= 1 sample."
            )
        for name in ("mean0", "shear_step", "gust_amplitude", "mean_direction_deg",
                     "shear_direction_deg", "gust_direction_deg"):
            if not math.isfinite(float(getattr(self, name))):
                raise NeuralMapError(f"{where}: '{name}' must be finite.")
        if self.turb0 is not None and not math.isfinite(float(self.turb0)):
            raise NeuralMapError(f"{where}: 'turb0' must be finite or None (stationary).")
        return self

    def turbulence(self) -> TurbulenceCoefficients:
        """The exact AR(1) coefficients of the turbulence (see `.turbulence`)."""
        return turbulence_coefficients(intensity=self.intensity, scale=self.scale,
                                       step=self.step, driver_var=self.driver_var)


@dataclass
class WindTruth:
    """Simulated wind, batch first.

    Attributes:
        wind: ``(N, T, 2)`` total wind (east, north) in m/s.
        mean: ``(N, T, 2)`` mean wind (random walk plus shear step).
        turbulence: ``(N, T, 2)`` turbulence component.
        gust: ``(T, 2)`` deterministic gust (zeros when disabled).
        dt: Sample period (s).
    """

    wind: torch.Tensor
    mean: torch.Tensor
    turbulence: torch.Tensor
    gust: torch.Tensor
    dt: float


def _unit(direction_deg: float, dtype: torch.dtype) -> torch.Tensor:
    rad = math.radians(direction_deg)
    return torch.tensor([math.sin(rad), math.cos(rad)], dtype=dtype)


def simulate_wind(
    config: WindSimConfig,
    *,
    n_runs: int,
    n_steps: int,
    generator: torch.Generator | None = None,
    seed: int | None = None,
    dtype: torch.dtype = torch.float64,
) -> WindTruth:
    """Draws ``n_runs`` wind histories of ``n_steps`` samples (SEEDS 002, eqs. 30–31).

    Args:
        config: Simulator parameters (validated here).
        n_runs: Number of Monte Carlo runs ``N``.
        n_steps: Samples per run ``T`` (including the initial one).
        generator: Random generator (takes precedence over ``seed``).
        seed: Seed of a fresh CPU generator when ``generator`` is None.
        dtype: Floating dtype of the result.

    Returns:
        `WindTruth` with ``(N, T, 2)`` tensors.

    Raises:
        NeuralMapError: Bad config, ``n_runs < 1`` or ``n_steps < 2``.
    """
    config.validate()
    if int(n_runs) < 1 or int(n_steps) < 2:
        raise NeuralMapError(
            f"simulate_wind: need n_runs >= 1 and n_steps >= 2, got {n_runs!r}, {n_steps!r}."
        )
    if generator is None:
        generator = torch.Generator().manual_seed(0 if seed is None else int(seed))
    n, t = int(n_runs), int(n_steps)
    coef = config.turbulence()
    # mean wind: initial vector plus cumulated random-walk increments
    increments = torch.randn(n, t - 1, 2, generator=generator, dtype=dtype)
    increments = increments * math.sqrt(config.mean_walk_var)
    mean = torch.zeros(n, t, 2, dtype=dtype)
    mean[:, 1:] = torch.cumsum(increments, dim=1)
    mean = mean + config.mean0 * _unit(config.mean_direction_deg, dtype)
    if config.shear_step != 0.0 and int(config.shear_time) < t:
        shear = config.shear_step * _unit(config.shear_direction_deg, dtype)
        mean[:, int(config.shear_time):] += shear
    # turbulence: exact AR(1) recursion, a loop over time only
    drivers = torch.randn(n, t, 2, generator=generator, dtype=dtype) * math.sqrt(
        config.driver_var
    )
    turb = torch.empty(n, t, 2, dtype=dtype)
    if config.turb0 is None:
        turb[:, 0] = math.sqrt(coef.variance) * drivers[:, 0] / math.sqrt(config.driver_var)
    else:
        turb[:, 0] = float(config.turb0)
    for k in range(t - 1):
        turb[:, k + 1] = coef.phi * turb[:, k] + coef.gain * drivers[:, k + 1]
    gust = torch.zeros(t, 2, dtype=dtype)
    if config.gust_amplitude != 0.0:
        k = torch.arange(t, dtype=dtype) - int(config.gust_time)
        inside = (k >= 0) & (k < int(config.gust_length))
        shape = 0.5 * (1.0 - torch.cos(2.0 * math.pi * k / int(config.gust_length)))
        gust = (torch.where(inside, shape, 0.0) * config.gust_amplitude)[:, None] * _unit(
            config.gust_direction_deg, dtype
        )
    return WindTruth(wind=mean + turb + gust, mean=mean, turbulence=turb, gust=gust,
                     dt=config.dt)
