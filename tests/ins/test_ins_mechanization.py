"""Strapdown mechanisation: Schuler oscillation and the noise-free round trip."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.ins.earth import earth_rate_ned, normal_gravity, position_offset_ned, schuler_period
from neuralmap.ins.error_state import inject
from neuralmap.ins.mechanization import mechanize, strapdown_step, strapdown_step_rk4
from neuralmap.ins.state import NavState
from neuralmap.ins.trajectory import short_drive

LAT = math.radians(30.0)


def _stationary(tilt_east: float, *, dt: float, duration: float) -> tuple[np.ndarray, float]:
    """North velocity error of a stationary, level IMU started with a tilt about east.

    The height is held (ideal height aiding) because the free-inertial vertical channel
    diverges within hours; the horizontal Schuler loop is untouched.
    """
    lat = torch.tensor([LAT], dtype=torch.float64)
    h = torch.tensor([50.0], dtype=torch.float64)
    truth = NavState.from_parts(lat=lat, lon=torch.tensor([2.0], dtype=torch.float64), h=h,
                                vel=torch.zeros(1, 3, dtype=torch.float64),
                                euler=torch.zeros(1, 3, dtype=torch.float64))
    # exact IMU of a stationary, level, north-pointing body: f^b = -g^n, ω^b = ω_ie^n
    accel = torch.tensor([0.0, 0.0, -float(normal_gravity(lat, h))], dtype=torch.float64)
    gyro = earth_rate_ned(lat)[0]
    err = torch.zeros(1, 9, dtype=torch.float64)
    err[0, 7] = tilt_east
    start = NavState(inject(truth.packed, err))
    k = int(duration / dt) + 1
    out = mechanize(start, gyro.expand(k, 3), accel.expand(k, 3), dt, hold_height=True)
    return out[0, :, 3].numpy(), float(h)


def _crossings(v: np.ndarray, dt: float) -> np.ndarray:
    s = np.nonzero(np.sign(v[1:]) != np.sign(v[:-1]))[0]
    return (s + v[s] / (v[s] - v[s + 1])) * dt  # linear interpolation


def test_schuler_period_from_tilt() -> None:
    """Two Schuler periods of a stationary IMU: period measured from zero crossings."""
    dt = 10.0
    vn, h = _stationary(1e-4, dt=dt, duration=2.2 * 5070.0)
    crossings = _crossings(vn[1:], dt) + dt  # skip the exact zero at t = 0
    assert crossings.size >= 4
    # mean of two full periods from alternate crossings (cancels the slow Earth-rate offset
    # of v_N that shifts up- and down-crossings in opposite directions); measured 5052 s
    period = 0.5 * ((crossings[2] - crossings[0]) + (crossings[3] - crossings[1]))
    assert period / 60.0 == pytest.approx(84.4, rel=0.02)
    assert period == pytest.approx(schuler_period(LAT, h), rel=5e-3)


def test_schuler_closed_form_first_20_minutes() -> None:
    """δv_N(t) = ψ_E √(gR) sin(ω_s t) over 20 min (Earth-rate coupling < 1 %)."""
    dt = 5.0
    vn, h = _stationary(2e-4, dt=dt, duration=1200.0)
    period = schuler_period(LAT, h)
    ws = 2 * math.pi / period
    t = np.arange(vn.size) * dt
    expected = 2e-4 * 9.7934 / ws * np.sin(ws * t)  # ψ √(gR) = ψ g / ω_s
    amp = 2e-4 * 9.7934 / ws
    assert np.abs(vn - expected).max() < 0.01 * amp


def test_noise_free_round_trip() -> None:
    """Trajectory → exact IMU → mechanisation → trajectory (60 s drive at 50 Hz).

    Tolerances (measured: 2.4 mm, 7e-5 m/s, 1.6e-6 rad): position 5 mm, velocity
    2e-4 m/s, attitude quaternion 5e-6.
    """
    traj = short_drive(duration=60.0, dt=0.02)
    out = mechanize(NavState(traj.states[:1].clone()), traj.gyro, traj.accel, traj.dt)[0]
    s = traj.states
    dp = position_offset_ned(out[:, 0], out[:, 1], out[:, 2], s[:, 0], s[:, 1], s[:, 2])
    assert traj.distance > 400.0
    assert dp.norm(dim=-1).max() < 5e-3
    assert (out[:, 3:6] - s[:, 3:6]).norm(dim=-1).max() < 2e-4
    assert (out[:, 6:] - s[:, 6:]).norm(dim=-1).max() < 5e-6


def test_increment_step_matches_rk4_reference() -> None:
    traj = short_drive(duration=60.0, dt=0.01)
    k = 1500  # in the turn
    y = traj.states[k:k + 1]
    a = strapdown_step(y, traj.gyro[k], traj.accel[k], traj.gyro[k + 1], traj.accel[k + 1], 0.01)
    b = strapdown_step_rk4(y, traj.gyro[k], traj.accel[k], traj.gyro[k + 1],
                           traj.accel[k + 1], 0.01)
    assert (a[:, :2] - b[:, :2]).abs().max() < 1e-13  # rad (≈ 1e-6 m)
    assert (a[:, 2:6] - b[:, 2:6]).abs().max() < 1e-7
    assert (a[:, 6:] - b[:, 6:]).abs().max() < 1e-10


def test_batched_runs_are_independent() -> None:
    traj = short_drive(duration=10.0, dt=0.05)
    y = traj.states[:1].repeat(3, 1)
    gyro = traj.gyro.expand(3, -1, 3).clone()
    gyro[1] += 1e-3
    out = mechanize(NavState(y), gyro, traj.accel.expand(3, -1, 3), traj.dt)
    single = mechanize(NavState(y[:1]), gyro[1], traj.accel, traj.dt)
    assert torch.equal(out[0], out[2])
    assert torch.allclose(out[1], single[0], rtol=0, atol=1e-12)


def test_mechanize_bad_input() -> None:
    traj = short_drive(duration=10.0, dt=0.05)
    start = NavState(traj.states[:1])
    with pytest.raises(NeuralMapError, match="dt"):
        mechanize(start, traj.gyro, traj.accel, 0.0)
    with pytest.raises(NeuralMapError, match="gyro"):
        mechanize(start, traj.gyro[:, :2], traj.accel[:, :2], 0.05)
    with pytest.raises(NeuralMapError, match="packed"):
        NavState(torch.zeros(2, 9))
