"""GNSS position/velocity simulation at 1 Hz with a quality record and urban effects.

Per epoch the receiver reports the antenna position (lat, lon, h) and NED velocity with a
quality record (SEEDS 003): PDOP, satellite count, ambiguity-fix ratio, fixed/float flag
and its own standard deviations σ_r, σ_v (NED). Urban effects are scheduled along the drive
(the environment is the same for every run; the errors are drawn per run):

* **outages**: no solution (the epoch is invalid; position and velocity are NaN);
* **degraded stretches**: float instead of fixed ambiguities, high PDOP, few satellites,
  a large reported σ and actual errors ``degraded_inflation`` times larger than reported
  (the paper's observation that the receiver σ is optimistic by 2–3×);
* **multipath jumps**: a position offset of metres (random direction per run) during an
  interval, not reflected in the reported σ.

Quality indicators given by a user may contain NaN: `sanitize_quality` treats them
(documented and counted) and `check_epochs` rejects epochs out of order.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.ins.earth import radii
from neuralmap.ins.measurement import antenna_position, antenna_velocity, check_lever_arm
from neuralmap.ins.trajectory import Trajectory

__all__ = [
    "GnssQuality",
    "GnssRecord",
    "UrbanEffects",
    "check_epochs",
    "sanitize_quality",
    "simulate_gnss",
]

Interval = tuple[float, float]


@dataclass(frozen=True)
class UrbanEffects:
    """Schedule of urban GNSS effects along a drive (times in seconds from the start).

    Attributes:
        outages: ``(start, end)`` intervals without a solution.
        degraded: ``(start, end)`` intervals with float solutions and high PDOP.
        multipath: ``(start, end, magnitude_m)`` position jumps.
        degraded_inflation: Actual / reported σ inside degraded stretches.
    """

    outages: tuple[Interval, ...] = ()
    degraded: tuple[Interval, ...] = ()
    multipath: tuple[tuple[float, float, float], ...] = ()
    degraded_inflation: float = 2.5

    @classmethod
    def urban(cls, duration: float = 1527.0) -> UrbanEffects:
        """A default urban schedule scaled to ``duration`` (two outages of 15–25 s, four
        degraded stretches covering about 20 % of the drive with a multipath jump of 3–8 m
        inside three of them)."""
        u = duration / 1527.0
        return cls(
            outages=((420 * u, 445 * u), (1105 * u, 1120 * u)),
            degraded=((230 * u, 300 * u), (640 * u, 720 * u), (930 * u, 980 * u),
                      (1250 * u, 1330 * u)),
            multipath=((255 * u, 268 * u, 5.0), (680 * u, 690 * u, 3.0),
                       (1280 * u, 1295 * u, 8.0)),
        )


@dataclass(frozen=True)
class GnssQuality:
    """Per-epoch quality record (shared by all runs).

    Attributes:
        time: ``(K,)`` epochs (s), strictly increasing.
        imu_index: ``(K,)`` IMU sample index of each epoch.
        valid: ``(K,)`` a solution exists.
        fixed: ``(K,)`` ambiguities fixed (False = float).
        pdop: ``(K,)`` position dilution of precision.
        n_sats: ``(K,)`` satellites used (float; NaN allowed before sanitising).
        fix_ratio: ``(K,)`` ambiguity-fix success ratio in [0, 1].
        sigma_pos: ``(K, 3)`` reported NED position σ (m).
        sigma_vel: ``(K, 3)`` reported NED velocity σ (m/s).
        degraded: ``(K,)`` inside a degraded stretch (truth label, for plots/tables).
        multipath: ``(K,)`` inside a multipath jump (truth label).
    """

    time: torch.Tensor
    imu_index: torch.Tensor
    valid: torch.Tensor
    fixed: torch.Tensor
    pdop: torch.Tensor
    n_sats: torch.Tensor
    fix_ratio: torch.Tensor
    sigma_pos: torch.Tensor
    sigma_vel: torch.Tensor
    degraded: torch.Tensor
    multipath: torch.Tensor

    @property
    def n_epochs(self) -> int:
        """Number of epochs K."""
        return self.time.shape[0]


@dataclass(frozen=True)
class GnssRecord:
    """Simulated GNSS solutions of N runs.

    Attributes:
        quality: The shared `GnssQuality`.
        position: ``(N, K, 3)`` antenna [lat, lon, h] (rad, rad, m); NaN in outages.
        velocity: ``(N, K, 3)`` antenna NED velocity (m/s); NaN in outages.
        lever_arm: ``(3,)`` IMU-to-antenna vector (m, body frame).
        position_error: ``(N, K, 3)`` actual NED position error of the solution (m).
    """

    quality: GnssQuality
    position: torch.Tensor
    velocity: torch.Tensor
    lever_arm: torch.Tensor
    position_error: torch.Tensor


def _inside(t: torch.Tensor, intervals: tuple) -> torch.Tensor:
    out = torch.zeros_like(t, dtype=torch.bool)
    for item in intervals:
        out |= (t >= item[0]) & (t < item[1])
    return out


def simulate_gnss(
    traj: Trajectory,
    *,
    n_runs: int,
    lever_arm: object,
    generator: torch.Generator,
    effects: UrbanEffects | None = None,
    interval: float = 1.0,
    sigma_fixed: tuple[float, float, float] = (0.02, 0.02, 0.05),
    sigma_float: tuple[float, float, float] = (0.4, 0.4, 0.8),
    sigma_vel: tuple[float, float, float] = (0.03, 0.03, 0.05),
    sigma_vel_degraded: tuple[float, float, float] = (0.1, 0.1, 0.2),
) -> GnssRecord:
    """Simulates GNSS antenna solutions along a trajectory.

    Args:
        traj: Reference trajectory (epochs fall on its IMU samples).
        n_runs: Number of runs N.
        lever_arm: ``(3,)`` IMU-to-antenna vector (m, body frame).
        generator: Random generator (the quality jitter and all errors).
        effects: Urban schedule (None = open sky).
        interval: GNSS interval (s), a multiple of the IMU interval (default 1 Hz).
        sigma_fixed, sigma_float: Reported NED position σ (m) of fixed / float solutions.
        sigma_vel, sigma_vel_degraded: Reported NED velocity σ (m/s), open sky / degraded.

    Returns:
        The `GnssRecord`.

    Raises:
        NeuralMapError: Bad lever arm, or an interval that is not a positive multiple of
            the IMU interval.
    """
    arm = check_lever_arm(lever_arm, where="simulate_gnss").to(traj.states)
    effects = effects or UrbanEffects()
    step = interval / traj.dt
    if not interval > 0 or abs(step - round(step)) > 1e-6 or round(step) < 1:
        raise NeuralMapError(
            f"simulate_gnss: 'interval' = {interval!r} s must be a positive multiple of the IMU "
            f"interval {traj.dt} s."
        )
    idx = torch.arange(0, traj.n_samples, int(round(step)))
    t = traj.time[idx]
    k = idx.shape[0]
    kw = {"dtype": traj.states.dtype}
    deg = _inside(t, effects.degraded)
    mp = _inside(t, tuple((a, b) for a, b, _ in effects.multipath))
    valid = ~_inside(t, effects.outages)
    u = torch.rand(k, 3, generator=generator, **kw)
    pdop = torch.where(deg | mp, 3.5 + 4.0 * u[:, 0], 1.3 + 0.4 * u[:, 0])
    n_sats = torch.where(deg | mp, 6.0 + torch.floor(5.0 * u[:, 1]), 16.0 + torch.floor(7 * u[:, 1]))
    fix_ratio = torch.where(deg | mp, 0.3 + 0.4 * u[:, 2], 0.97 + 0.03 * u[:, 2])
    fixed = ~(deg | mp)
    s_fix = torch.tensor(sigma_fixed, **kw)
    s_flt = torch.tensor(sigma_float, **kw)
    sigma_pos = torch.where(fixed[:, None], s_fix, s_flt) * torch.where(
        deg | mp, pdop / 3.5, torch.ones_like(pdop))[:, None]
    sigma_v = torch.where(fixed[:, None], torch.tensor(sigma_vel, **kw),
                          torch.tensor(sigma_vel_degraded, **kw))
    states = traj.states[idx]
    true_pos = antenna_position(states, arm)
    true_vel = antenna_velocity(states, traj.gyro[idx], arm)
    infl = torch.where(deg | mp, effects.degraded_inflation, 1.0)[:, None]
    err = torch.randn(n_runs, k, 3, generator=generator, **kw) * (sigma_pos * infl)
    for start, end, magnitude in effects.multipath:
        inside = ((t >= start) & (t < end))[None, :, None]
        ang = 2 * math.pi * torch.rand(n_runs, 1, generator=generator, **kw)
        mag = magnitude * (0.7 + 0.6 * torch.rand(n_runs, 1, generator=generator, **kw))
        sign = torch.where(torch.rand(n_runs, 1, generator=generator, **kw) < 0.5, -1.0, 1.0)
        jump = torch.cat([mag * torch.cos(ang), mag * torch.sin(ang), 0.5 * sign * mag], dim=1)
        err = err + inside * jump[:, None, :]
    verr = torch.randn(n_runs, k, 3, generator=generator, **kw) * (sigma_v * infl)
    rm, rn = radii(true_pos[:, 0])
    h = true_pos[:, 2]
    pos = true_pos.expand(n_runs, k, 3) + torch.stack(
        [err[..., 0] / (rm + h), err[..., 1] / ((rn + h) * torch.cos(true_pos[:, 0])),
         -err[..., 2]], dim=-1)
    vel = true_vel.expand(n_runs, k, 3) + verr
    nan = torch.tensor(float("nan"), **kw)
    pos = torch.where(valid[None, :, None], pos, nan)
    vel = torch.where(valid[None, :, None], vel, nan)
    quality = GnssQuality(
        time=t, imu_index=idx, valid=valid, fixed=fixed & valid, pdop=pdop, n_sats=n_sats,
        fix_ratio=fix_ratio, sigma_pos=sigma_pos, sigma_vel=sigma_v, degraded=deg | mp,
        multipath=mp,
    )
    return GnssRecord(quality=quality, position=pos, velocity=vel, lever_arm=arm,
                      position_error=err)


def check_epochs(time: torch.Tensor, *, where: str = "GNSS epochs") -> None:
    """Rejects epochs that are not strictly increasing or not finite.

    Raises:
        NeuralMapError: Naming the first epoch out of order.
    """
    if not bool(torch.isfinite(time).all()):
        i = int(torch.nonzero(~torch.isfinite(time))[0, 0])
        raise NeuralMapError(f"{where}: epoch {i} has a non-finite time {float(time[i])!r}.")
    d = torch.diff(time)
    if bool((d <= 0).any()):
        i = int(torch.nonzero(d <= 0)[0, 0])
        raise NeuralMapError(
            f"{where}: epochs are out of order: epoch {i + 1} (t = {float(time[i + 1])}) does "
            f"not come after epoch {i} (t = {float(time[i])}). Sort the record by time and "
            "drop duplicated epochs."
        )


#: Values that replace NaN quality indicators (the worst plausible quality).
WORST_QUALITY = {"pdop": 99.0, "n_sats": 0.0, "fix_ratio": 0.0}


def sanitize_quality(quality: GnssQuality) -> tuple[GnssQuality, dict[str, int]]:
    """Treats NaN quality indicators (counted, documented policy).

    * NaN (or non-positive) reported σ in a valid epoch: the epoch cannot be weighted, so
      it is marked invalid (no update) — counted as ``invalid_sigma``;
    * NaN PDOP, satellite count or fix ratio: replaced by the worst plausible value
      (PDOP 99, 0 satellites, fix ratio 0), so quality-based weighting distrusts the
      epoch — counted per indicator as ``nan_pdop``, ``nan_n_sats``, ``nan_fix_ratio``.

    Returns:
        ``(sanitised quality, counts)``.

    Raises:
        NeuralMapError: Epochs out of order (see `check_epochs`).
    """
    check_epochs(quality.time, where="sanitize_quality")
    counts: dict[str, int] = {}
    bad_sigma = ~(torch.isfinite(quality.sigma_pos).all(-1) & torch.isfinite(
        quality.sigma_vel).all(-1) & (quality.sigma_pos > 0).all(-1) & (
        quality.sigma_vel > 0).all(-1))
    bad_sigma = bad_sigma & quality.valid
    counts["invalid_sigma"] = int(bad_sigma.sum())
    ones = torch.ones_like(quality.sigma_pos)
    changes: dict[str, torch.Tensor] = {
        "valid": quality.valid & ~bad_sigma,
        "sigma_pos": torch.where(bad_sigma[:, None], ones, quality.sigma_pos),
        "sigma_vel": torch.where(bad_sigma[:, None], ones, quality.sigma_vel),
    }
    for name, worst in WORST_QUALITY.items():
        value = getattr(quality, name)
        nan = torch.isnan(value)
        counts[f"nan_{name}"] = int(nan.sum())
        changes[name] = torch.where(nan, torch.full_like(value, worst), value)
    return replace(quality, **changes), counts
