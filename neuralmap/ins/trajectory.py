"""Land-vehicle reference trajectories with exact IMU outputs.

A drive is a list of `Segment` s (hold, speed change, turn, or both at once) on a
level road at constant ellipsoidal height, roll = pitch = 0. Inside a segment the
longitudinal acceleration and the yaw rate follow raised-cosine pulses,
``a(τ) = (Δv/T)(1 − cos 2πτ/T)`` and ``ψ̇(τ) = (Δψ/T)(1 − cos 2πτ/T)``, so speed, heading,
acceleration and yaw rate are continuous everywhere (no jumps in the specific force).

Exact IMU outputs follow from the strapdown equations solved for the sensors (SEEDS 003,
the mechanisation of eqs. 1–2 inverted)::

    f^b    = C_n^b (v̇ⁿ + (2 ω_ieⁿ + ω_enⁿ) × vⁿ − gⁿ)
    ω_ib^b = [0, 0, ψ̇] + C_n^b (ω_ieⁿ + ω_enⁿ)

with ``vⁿ = v [cos ψ, sin ψ, 0]`` and ``v̇ⁿ = a [cos ψ, sin ψ, 0] + v ψ̇ [−sin ψ, cos ψ, 0]``;
latitude and longitude are integrated from the analytic velocity with RK4 (exact to
rounding at IMU rates). `urban_drive` gives a default resembling paper 003's urban
test drive (1527 s, 8.7 km, stops, 90° turns, speed changes).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.ins.earth import (
    WGS84_A,
    WGS84_E2,
    earth_rate_ned,
    gravity_ned,
    radii,
    transport_rate_ned,
)
from neuralmap.ins.rotation import quat_from_euler

__all__ = ["Segment", "Trajectory", "check_continuity", "generate", "short_drive", "urban_drive"]


@dataclass(frozen=True)
class Segment:
    """One manoeuvre of a land-vehicle drive.

    Attributes:
        duration: Length (s), > 0.
        dspeed: Speed change over the segment (m/s); 0 = constant speed (or stopped).
        dheading: Heading change (rad, positive = clockwise seen from above, i.e. right).
    """

    duration: float
    dspeed: float = 0.0
    dheading: float = 0.0


@dataclass(frozen=True)
class Trajectory:
    """A reference trajectory sampled at the IMU epochs (single run, shared by all runs).

    Attributes:
        time: ``(K,)`` sample epochs (s), uniform with interval ``dt``.
        states: ``(K, 10)`` packed true states ``[lat, lon, h, v_NED, q(C_b^n)]``.
        gyro: ``(K, 3)`` true angular rate ``ω_ib^b`` (rad/s).
        accel: ``(K, 3)`` true specific force ``f^b`` (m/s²).
        dt: IMU interval (s).
    """

    time: torch.Tensor
    states: torch.Tensor
    gyro: torch.Tensor
    accel: torch.Tensor
    dt: float

    def to(self, device: torch.device | str) -> Trajectory:
        """The same trajectory with its tensors on ``device``."""
        return Trajectory(time=self.time.to(device), states=self.states.to(device),
                          gyro=self.gyro.to(device), accel=self.accel.to(device), dt=self.dt)

    @property
    def n_samples(self) -> int:
        """Number of IMU samples K."""
        return self.time.shape[0]

    @property
    def duration(self) -> float:
        """Length (s)."""
        return float(self.time[-1] - self.time[0])

    @property
    def distance(self) -> float:
        """Travelled distance (m), trapezoid over the speed."""
        speed = torch.linalg.vector_norm(self.states[:, 3:6], dim=-1)
        return float(torch.trapezoid(speed, dx=self.dt))


def _profiles(
    segments: Sequence[Segment], t: torch.Tensor, heading0: float
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Speed, acceleration, heading and yaw rate at times ``t`` ``(M,)`` each."""
    dtype = t.dtype
    dur = torch.tensor([s.duration for s in segments], dtype=dtype)
    dv = torch.tensor([s.dspeed for s in segments], dtype=dtype)
    dpsi = torch.tensor([s.dheading for s in segments], dtype=dtype)
    start = torch.cumsum(dur, 0) - dur
    v_start = torch.cumsum(dv, 0) - dv
    psi_start = heading0 + torch.cumsum(dpsi, 0) - dpsi
    idx = torch.clamp(torch.searchsorted(start, t, right=True) - 1, 0, len(segments) - 1)
    tau = torch.clamp(t - start[idx], min=0.0)
    length = dur[idx]
    tau = torch.minimum(tau, length)
    x = 2.0 * math.pi * tau / length
    ramp = tau / length - torch.sin(x) / (2.0 * math.pi)  # ∫ pulse, 0 → 1
    pulse = (1.0 - torch.cos(x)) / length  # d ramp / dτ
    speed = v_start[idx] + dv[idx] * ramp
    acc = dv[idx] * pulse
    heading = psi_start[idx] + dpsi[idx] * ramp
    rate = dpsi[idx] * pulse
    return speed, acc, heading, rate


def generate(
    segments: Sequence[Segment],
    *,
    dt: float = 0.005,
    lat0_deg: float = 30.5,
    lon0_deg: float = 114.3,
    h0: float = 20.0,
    heading0_deg: float = 0.0,
    dtype: torch.dtype = torch.float64,
) -> Trajectory:
    """Builds a trajectory and its exact IMU record from manoeuvre segments.

    Args:
        segments: The drive, in order; the vehicle starts at rest.
        dt: IMU interval (s) (default 200 Hz as in paper 003).
        lat0_deg, lon0_deg, h0: Start position (degrees, metres; default near Wuhan).
        heading0_deg: Initial heading (degrees from north, clockwise).
        dtype: Floating dtype (float64 recommended).

    Returns:
        The `Trajectory` (CPU tensors).

    Raises:
        NeuralMapError: No segments, a non-positive duration or ``dt``, or a speed that
            becomes negative.
    """
    if not segments:
        raise NeuralMapError("generate: 'segments' is empty; give at least one Segment.")
    if not dt > 0:
        raise NeuralMapError(f"generate: 'dt' = {dt!r} must be > 0 (IMU interval in s).")
    speed_now = 0.0
    for i, seg in enumerate(segments):
        if not seg.duration > 0 or not math.isfinite(seg.duration):
            raise NeuralMapError(
                f"generate: segment {i} has duration {seg.duration!r}; durations must be "
                "finite and > 0."
            )
        speed_now += seg.dspeed
        if speed_now < -1e-9:
            raise NeuralMapError(
                f"generate: the speed becomes {speed_now:.3f} m/s after segment {i}; a land "
                "vehicle drives forwards (decrease 'dspeed')."
            )
    total = sum(s.duration for s in segments)
    k_total = int(math.floor(total / dt + 1e-9)) + 1
    t = torch.arange(k_total, dtype=dtype) * dt
    psi0 = math.radians(heading0_deg)
    speed, acc, heading, rate = _profiles(segments, t, psi0)
    speed_mid, _, heading_mid, _ = _profiles(segments, t + 0.5 * dt, psi0)

    def ne_vel(v: torch.Tensor, psi: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        return v * torch.cos(psi), v * torch.sin(psi)

    vn, ve = ne_vel(speed, heading)
    vn_m, ve_m = ne_vel(speed_mid, heading_mid)
    # RK4 of L̇ = v_N/(R_M+h), λ̇ = v_E/((R_N+h) cos L) with the analytic velocity.
    lat = torch.empty(k_total, dtype=dtype)
    lon = torch.empty(k_total, dtype=dtype)
    lat[0], lon[0] = math.radians(lat0_deg), math.radians(lon0_deg)
    h = torch.full((k_total,), float(h0), dtype=dtype)

    def rates(la: float, v_n: float, v_e: float) -> tuple[float, float]:
        w = 1.0 - WGS84_E2 * math.sin(la) ** 2
        rn = WGS84_A / math.sqrt(w)
        rm = rn * (1.0 - WGS84_E2) / w
        return v_n / (rm + h0), v_e / ((rn + h0) * math.cos(la))

    # scalar loop over samples of the single reference trajectory (not a hot path)
    vn_l, ve_l, vnm_l, vem_l = vn.tolist(), ve.tolist(), vn_m.tolist(), ve_m.tolist()
    la, lo = float(lat[0]), float(lon[0])
    lat_l, lon_l = [la], [lo]
    for k in range(k_total - 1):
        a1 = rates(la, vn_l[k], ve_l[k])
        a2 = rates(la + 0.5 * dt * a1[0], vnm_l[k], vem_l[k])
        a3 = rates(la + 0.5 * dt * a2[0], vnm_l[k], vem_l[k])
        a4 = rates(la + dt * a3[0], vn_l[k + 1], ve_l[k + 1])
        la += dt / 6.0 * (a1[0] + 2 * a2[0] + 2 * a3[0] + a4[0])
        lo += dt / 6.0 * (a1[1] + 2 * a2[1] + 2 * a3[1] + a4[1])
        lat_l.append(la)
        lon_l.append(lo)
    lat = torch.tensor(lat_l, dtype=dtype)
    lon = torch.tensor(lon_l, dtype=dtype)
    zero = torch.zeros_like(speed)
    vel = torch.stack([vn, ve, zero], dim=-1)
    cos_p, sin_p = torch.cos(heading), torch.sin(heading)
    vdot = torch.stack(
        [acc * cos_p - speed * rate * sin_p, acc * sin_p + speed * rate * cos_p, zero], dim=-1
    )
    w_ie = earth_rate_ned(lat)
    w_en = transport_rate_ned(lat, h, vel)
    f_n = vdot + torch.linalg.cross(2.0 * w_ie + w_en, vel, dim=-1) - gravity_ned(lat, h)
    w_in = w_ie + w_en

    def to_body(x: torch.Tensor) -> torch.Tensor:  # C_n^b = R_z(ψ)ᵀ
        return torch.stack(
            [cos_p * x[:, 0] + sin_p * x[:, 1], -sin_p * x[:, 0] + cos_p * x[:, 1], x[:, 2]],
            dim=-1,
        )

    accel = to_body(f_n)
    gyro = to_body(w_in) + torch.stack([zero, zero, rate], dim=-1)
    quat = quat_from_euler(torch.stack([zero, zero, heading], dim=-1))
    states = torch.cat([lat[:, None], lon[:, None], h[:, None], vel, quat], dim=1)
    return Trajectory(time=t, states=states, gyro=gyro, accel=accel, dt=float(dt))


def urban_drive(
    *,
    duration: float = 1527.0,
    distance: float = 8700.0,
    blocks: int = 12,
    dt: float = 0.005,
    **kwargs: float,
) -> Trajectory:
    """A drive resembling paper 003's urban test: stops, 90° turns, speed changes.

    60 s at rest (initial alignment), then ``blocks`` city blocks, each: accelerate from
    rest (10 s), cruise, slow to 4 m/s (6 s), turn 90° (8 s; turns alternate in a
    right-right-left pattern), accelerate (8 s), cruise, stop (8 s), wait at a light (20 s);
    the rest of ``duration`` is spent at rest. The cruise time and speed are solved so that
    the drive lasts ``duration`` and covers ``distance``.

    Args:
        duration: Total length (s) (paper: 1527 s).
        distance: Travelled distance (m) (paper: about 8.7 km).
        blocks: Number of city blocks.
        dt: IMU interval (s).
        **kwargs: Passed to `generate` (start position, heading, dtype).

    Raises:
        NeuralMapError: The duration/distance pair needs a cruise time ≤ 0 or a cruise speed
            ≤ 4 m/s (change ``blocks``).
    """
    tail = 27.0
    cruise_t = ((duration - 60.0 - tail) / blocks - 60.0) / 2.0
    if cruise_t <= 0:
        raise NeuralMapError(
            f"urban_drive: duration {duration} s is too short for {blocks} blocks; use fewer "
            "blocks or a longer drive."
        )
    cruise_v = (distance / blocks - 60.0) / (16.0 + 2.0 * cruise_t)
    if cruise_v <= 4.0:
        raise NeuralMapError(
            f"urban_drive: distance {distance} m over {blocks} blocks needs a cruise speed of "
            f"{cruise_v:.2f} m/s (must exceed the 4 m/s turning speed); raise 'distance'."
        )
    turn_signs = [1.0, 1.0, -1.0]
    segments = [Segment(60.0)]
    for b in range(blocks):
        turn = turn_signs[b % 3] * math.pi / 2.0
        segments += [
            Segment(10.0, dspeed=cruise_v),
            Segment(cruise_t),
            Segment(6.0, dspeed=4.0 - cruise_v),
            Segment(8.0, dheading=turn),
            Segment(8.0, dspeed=cruise_v - 4.0),
            Segment(cruise_t),
            Segment(8.0, dspeed=-cruise_v),
            Segment(20.0),
        ]
    segments.append(Segment(tail))
    return generate(segments, dt=dt, **kwargs)


def short_drive(*, duration: float = 60.0, dt: float = 0.01, **kwargs: float) -> Trajectory:
    """A short drive for tests: rest, accelerate, turn right while speeding up, cruise,
    slow down while turning left, cruise (lengths scaled to ``duration``)."""
    u = duration / 60.0
    segments = [
        Segment(5.0 * u),
        Segment(8.0 * u, dspeed=10.0),
        Segment(10.0 * u, dspeed=2.0, dheading=math.pi / 2),
        Segment(12.0 * u),
        Segment(10.0 * u, dspeed=-6.0, dheading=-math.pi / 3),
        Segment(15.0 * u),
    ]
    return generate(segments, dt=dt, **kwargs)


def check_continuity(
    traj: Trajectory, *, position_tol: float = 0.05, attitude_tol: float = 0.01
) -> None:
    """Checks that a (user-supplied) trajectory has no jumps.

    The position step between samples must match the trapezoid of the velocities to within
    ``position_tol`` (m), and the attitude change between samples must not exceed what the
    gyro allows by more than ``attitude_tol`` (rad); the time axis must be uniform.

    Raises:
        NeuralMapError: Naming the first sample at which the trajectory jumps.
    """
    t = traj.time
    if t.ndim != 1 or t.shape[0] < 2:
        raise NeuralMapError("check_continuity: the trajectory needs at least two samples.")
    steps = torch.diff(t)
    bad = (steps - traj.dt).abs() > 1e-6 * max(traj.dt, 1.0)
    if bool(bad.any()):
        k = int(torch.nonzero(bad)[0, 0])
        raise NeuralMapError(
            f"check_continuity: time step {float(steps[k])!r} s between samples {k} and {k + 1} "
            f"differs from dt = {traj.dt}; resample the trajectory to a uniform IMU rate."
        )
    s = traj.states
    rm, rn = radii(s[:-1, 0])
    h = s[:-1, 2]
    dn = torch.diff(s[:, 0]) * (rm + h)
    de = torch.diff(s[:, 1]) * (rn + h) * torch.cos(s[:-1, 0])
    dd = -torch.diff(s[:, 2])
    v_mid = 0.5 * (s[1:, 3:6] + s[:-1, 3:6]) * traj.dt
    gap = torch.linalg.vector_norm(torch.stack([dn, de, dd], -1) - v_mid, dim=-1)
    q = s[:, 6:10]
    dot = (q[1:] * q[:-1]).sum(-1).abs().clamp(max=1.0)
    turn = 2.0 * torch.acos(dot)
    allowed = torch.linalg.vector_norm(traj.gyro[:-1], dim=-1) * traj.dt * 1.5
    jumps = (gap > position_tol) | (turn > allowed + attitude_tol) | ~torch.isfinite(gap)
    if bool(jumps.any()):
        k = int(torch.nonzero(jumps)[0, 0])
        raise NeuralMapError(
            f"check_continuity: the trajectory jumps between samples {k} and {k + 1} "
            f"(t = {float(t[k]):.3f} s): position step mismatch {float(gap[k]):.3f} m "
            f"(tolerance {position_tol}), attitude change {float(turn[k]):.4f} rad. Remove the "
            "discontinuity or split the trajectory."
        )
