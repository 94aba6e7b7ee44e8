"""MEMS IMU error model with named grades, drawn per run and streamed sample by sample.

Each of the N runs has its own IMU whose measurements are (SEEDS 003; Groves ch. 4.4)::

    ω̃ = (1 + s_g) ω + b_g,on + b_g,GM(t) + n_g,    n_g ~ N(0, ARW²/Δt)
    f̃ = (1 + s_a) f + b_a,on + b_a,GM(t) + n_a,    n_a ~ N(0, VRW²/Δt)

with a random constant turn-on bias, a first-order Gauss–Markov bias
``b_{k+1} = e^{−Δt/τ} b_k + σ √(1 − e^{−2Δt/τ}) w_k`` (stationary standard deviation σ
= the bias instability, correlation time τ) and an optional random constant scale-factor
error. The white noises are those of instantaneous rate samples: ARW (rad/√s) and VRW
(m/s/√s) are the square roots of the two-sided power spectral densities, so a sample has
the standard deviation ``ARW/√Δt``.

The record is generated one sample at a time (`ImuErrorProcess.measure`) so that a
1527 s, 200 Hz drive over N = 1000 runs never holds the ``(N, K, 6)`` record in memory.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from neuralmap.exceptions import NeuralMapError

__all__ = ["IMU_GRADES", "ImuErrorProcess", "ImuGrade", "imu_grade"]

_DEG = math.pi / 180.0
_HOUR = 3600.0
_MG = 9.80665e-3


@dataclass(frozen=True)
class ImuGrade:
    """Error parameters of an IMU grade in datasheet units.

    Attributes:
        name: Grade name.
        gyro_arw: Angle random walk (deg/√h), > 0.
        accel_vrw: Velocity random walk (m/s/√h), > 0.
        gyro_bias_instability: Gauss–Markov bias standard deviation (deg/h), ≥ 0.
        accel_bias_instability: Gauss–Markov bias standard deviation (mg), ≥ 0.
        gyro_corr_time: Gyro bias correlation time (s), > 0.
        accel_corr_time: Accelerometer bias correlation time (s), > 0.
        gyro_turn_on: Turn-on bias standard deviation (deg/h), ≥ 0.
        accel_turn_on: Turn-on bias standard deviation (mg), ≥ 0.
        gyro_scale_ppm: Scale-factor error standard deviation (ppm), ≥ 0.
        accel_scale_ppm: Scale-factor error standard deviation (ppm), ≥ 0.
    """

    name: str
    gyro_arw: float
    accel_vrw: float
    gyro_bias_instability: float
    accel_bias_instability: float
    gyro_corr_time: float = 3600.0
    accel_corr_time: float = 3600.0
    gyro_turn_on: float = 0.0
    accel_turn_on: float = 0.0
    gyro_scale_ppm: float = 0.0
    accel_scale_ppm: float = 0.0

    def validate(self) -> ImuGrade:
        """Checks the parameters; returns self.

        Raises:
            NeuralMapError: A noise density or correlation time that is not finite and > 0,
                or a negative / non-finite bias or scale-factor standard deviation.
        """
        positive = ("gyro_arw", "accel_vrw", "gyro_corr_time", "accel_corr_time")
        for name in positive:
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value > 0):
                raise NeuralMapError(
                    f"ImuGrade '{self.name}': '{name}' = {value!r} must be finite and > 0 "
                    "(noise densities and correlation times are positive; use a tiny value "
                    "for an almost ideal sensor)."
                )
        for name in ("gyro_bias_instability", "accel_bias_instability", "gyro_turn_on",
                     "accel_turn_on", "gyro_scale_ppm", "accel_scale_ppm"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value >= 0):
                raise NeuralMapError(
                    f"ImuGrade '{self.name}': '{name}' = {value!r} must be finite and >= 0."
                )
        return self

    # SI values -------------------------------------------------------------------
    @property
    def gyro_arw_si(self) -> float:
        """ARW in rad/√s."""
        return self.gyro_arw * _DEG / math.sqrt(_HOUR)

    @property
    def accel_vrw_si(self) -> float:
        """VRW in m/s/√s."""
        return self.accel_vrw / math.sqrt(_HOUR)

    @property
    def gyro_bias_sigma_si(self) -> float:
        """Gauss–Markov gyro bias σ in rad/s."""
        return self.gyro_bias_instability * _DEG / _HOUR

    @property
    def accel_bias_sigma_si(self) -> float:
        """Gauss–Markov accelerometer bias σ in m/s²."""
        return self.accel_bias_instability * _MG

    @property
    def gyro_turn_on_si(self) -> float:
        """Turn-on gyro bias σ in rad/s."""
        return self.gyro_turn_on * _DEG / _HOUR

    @property
    def accel_turn_on_si(self) -> float:
        """Turn-on accelerometer bias σ in m/s²."""
        return self.accel_turn_on * _MG


#: Named grades. ``tactical_mems`` is the class of the paper 003 IMU (an industrial /
#: tactical MEMS unit, e.g. ADIS1646x-class datasheet values); ``consumer_mems`` a
#: smartphone-class unit.
IMU_GRADES: dict[str, ImuGrade] = {
    "tactical_mems": ImuGrade(
        name="tactical_mems", gyro_arw=0.15, accel_vrw=0.06, gyro_bias_instability=3.0,
        accel_bias_instability=0.05, gyro_corr_time=3600.0, accel_corr_time=3600.0,
        gyro_turn_on=10.0, accel_turn_on=1.0, gyro_scale_ppm=300.0, accel_scale_ppm=300.0,
    ),
    "consumer_mems": ImuGrade(
        name="consumer_mems", gyro_arw=0.6, accel_vrw=0.15, gyro_bias_instability=20.0,
        accel_bias_instability=0.3, gyro_corr_time=300.0, accel_corr_time=300.0,
        gyro_turn_on=200.0, accel_turn_on=15.0, gyro_scale_ppm=3000.0, accel_scale_ppm=3000.0,
    ),
}


def imu_grade(grade: str | ImuGrade) -> ImuGrade:
    """Looks up a named grade (or validates a given one).

    Raises:
        NeuralMapError: Unknown name (the message lists the known grades).
    """
    if isinstance(grade, ImuGrade):
        return grade.validate()
    if grade not in IMU_GRADES:
        raise NeuralMapError(
            f"imu_grade: unknown IMU grade {grade!r}; choose one of {sorted(IMU_GRADES)} or "
            "pass an ImuGrade."
        )
    return IMU_GRADES[grade].validate()


class ImuErrorProcess:
    """N independent IMUs of one grade, corrupting a true IMU record sample by sample.

    Args:
        grade: Grade name or `ImuGrade`.
        n_runs: Number of runs N.
        dt: IMU interval (s).
        generator: Torch random generator (seeded by the caller for reproducibility), on
            ``device``.
        dtype, device: Of the generated tensors.
        scale_factor: Draw the scale-factor errors (default True).

    Attributes:
        gyro_turn_on, accel_turn_on, gyro_scale, accel_scale: ``(N, 3)`` per-run constants.
        gyro_gm, accel_gm: ``(N, 3)`` current Gauss–Markov biases.
    """

    def __init__(
        self,
        grade: str | ImuGrade,
        *,
        n_runs: int,
        dt: float,
        generator: torch.Generator,
        dtype: torch.dtype = torch.float64,
        device: torch.device | str = "cpu",
        scale_factor: bool = True,
    ) -> None:
        self.grade = imu_grade(grade)
        if not dt > 0:
            raise NeuralMapError(f"ImuErrorProcess: 'dt' = {dt!r} must be > 0.")
        self.n_runs, self.dt = int(n_runs), float(dt)
        self._gen = generator
        self._kw = {"dtype": dtype, "device": device}
        g = self.grade

        def draw(sigma: float) -> torch.Tensor:
            return sigma * self._randn()

        self.gyro_turn_on = draw(g.gyro_turn_on_si)
        self.accel_turn_on = draw(g.accel_turn_on_si)
        self.gyro_scale = draw(g.gyro_scale_ppm * 1e-6 if scale_factor else 0.0)
        self.accel_scale = draw(g.accel_scale_ppm * 1e-6 if scale_factor else 0.0)
        self.gyro_gm = draw(g.gyro_bias_sigma_si)
        self.accel_gm = draw(g.accel_bias_sigma_si)
        self._phi_g = math.exp(-dt / g.gyro_corr_time)
        self._phi_a = math.exp(-dt / g.accel_corr_time)
        self._drive_g = g.gyro_bias_sigma_si * math.sqrt(1.0 - self._phi_g**2)
        self._drive_a = g.accel_bias_sigma_si * math.sqrt(1.0 - self._phi_a**2)
        self._white_g = g.gyro_arw_si / math.sqrt(dt)
        self._white_a = g.accel_vrw_si / math.sqrt(dt)

    def _randn(self) -> torch.Tensor:
        return torch.randn(self.n_runs, 3, generator=self._gen, **self._kw)

    @property
    def gyro_bias(self) -> torch.Tensor:
        """``(N, 3)`` current total gyro bias (turn-on + Gauss–Markov), rad/s."""
        return self.gyro_turn_on + self.gyro_gm

    @property
    def accel_bias(self) -> torch.Tensor:
        """``(N, 3)`` current total accelerometer bias, m/s²."""
        return self.accel_turn_on + self.accel_gm

    def measure(
        self, gyro: torch.Tensor, accel: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Measured sample of the current epoch; then advances the biases by one interval.

        Args:
            gyro: ``(3,)`` or ``(N, 3)`` true angular rate (rad/s).
            accel: ``(3,)`` or ``(N, 3)`` true specific force (m/s²).

        Returns:
            ``(gyro_measured, accel_measured)``, ``(N, 3)`` each.
        """
        noise = torch.randn(self.n_runs, 6, generator=self._gen, **self._kw)
        w = gyro * (1.0 + self.gyro_scale) + self.gyro_bias + self._white_g * noise[:, :3]
        f = accel * (1.0 + self.accel_scale) + self.accel_bias + self._white_a * noise[:, 3:]
        drive = torch.randn(self.n_runs, 6, generator=self._gen, **self._kw)
        self.gyro_gm = self._phi_g * self.gyro_gm + self._drive_g * drive[:, :3]
        self.accel_gm = self._phi_a * self.accel_gm + self._drive_a * drive[:, 3:]
        return w, f

    def measure_block(
        self, gyro: torch.Tensor, accel: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """L consecutive samples at once: the same numbers as L calls of `measure`.

        The random draws come from the generator in the same order (noise, then bias
        drive, per sample); torch fills normal draws in blocks of 16 values, so one call
        for the whole block gives the same numbers exactly when a sample's 6 N draws are a
        whole number of blocks (N a multiple of 8); otherwise each sample's draws are made
        separately into one buffer. The bias walk runs as a compiled loop where numba is
        installed (`gauss_markov_block`).

        Args:
            gyro: ``(L, 3)`` true angular rates (rad/s).
            accel: ``(L, 3)`` true specific forces (m/s²).

        Returns:
            ``(gyro_measured, accel_measured)``, ``(N, L, 3)`` each.
        """
        from neuralmap.ins.kernels import gauss_markov_block

        n, steps = self.n_runs, gyro.shape[0]
        if (6 * n) % 16 == 0:
            draws = torch.randn(steps, 2, n, 6, generator=self._gen, **self._kw)
        else:
            draws = torch.empty(steps, 2, n, 6, **self._kw)
            for t in range(steps):
                torch.randn(n, 6, generator=self._gen, out=draws[t, 0])
                torch.randn(n, 6, generator=self._gen, out=draws[t, 1])
        kw = self._kw
        phi = torch.tensor([self._phi_g] * 3 + [self._phi_a] * 3, **kw)
        sigma = torch.tensor([self._drive_g] * 3 + [self._drive_a] * 3, **kw)
        hist, gm = gauss_markov_block(torch.cat([self.gyro_gm, self.accel_gm], 1), phi, sigma,
                                      draws[:, 1])
        self.gyro_gm, self.accel_gm = gm[:, :3].contiguous(), gm[:, 3:].contiguous()
        noise = draws[:, 0]
        w = (gyro[:, None, :] * (1.0 + self.gyro_scale) + (self.gyro_turn_on + hist[..., :3])
             + self._white_g * noise[..., :3])
        f = (accel[:, None, :] * (1.0 + self.accel_scale) + (self.accel_turn_on + hist[..., 3:])
             + self._white_a * noise[..., 3:])
        return w.transpose(0, 1), f.transpose(0, 1)
