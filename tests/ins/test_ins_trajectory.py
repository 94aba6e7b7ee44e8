"""Trajectory generator: the paper-like urban drive, exact IMU, discontinuity checks."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.ins.earth import gravity_ned
from neuralmap.ins.rotation import dcm_from_quat
from neuralmap.ins.trajectory import (
    Segment,
    check_continuity,
    generate,
    short_drive,
    urban_drive,
)


def test_urban_drive_matches_paper_figures() -> None:
    traj = urban_drive(dt=0.1)
    assert traj.duration == pytest.approx(1527.0, abs=1e-9)
    assert traj.distance == pytest.approx(8700.0, rel=1e-3)
    speed = traj.states[:, 3:6].norm(dim=-1)
    assert (speed < 1e-9).float().mean() > 0.1  # stops at lights
    assert speed.max() < 14.0  # urban speeds (≈ 31 km/h cruise)
    check_continuity(traj)


def test_specific_force_at_rest_and_in_turn() -> None:
    traj = short_drive(duration=60.0, dt=0.05)
    # at rest: f^b = −C_n^b gⁿ + Coriolis-free (v = 0)
    c = dcm_from_quat(traj.states[0, 6:10])
    g = gravity_ned(traj.states[0, 0], traj.states[0, 2])
    assert torch.allclose(traj.accel[0], -(c.T @ g), atol=1e-12)
    # in the constant-speed cruise after the first turn: centripetal acceleration = v ψ̇
    # and the yaw rate is zero apart from Earth/transport rate (< 1e-4 rad/s)
    k = int(30.0 / 0.05)
    assert traj.gyro[k, 2].abs() < 1e-4
    assert traj.accel[k, :2].abs().max() < 1e-3


def test_generator_input_errors() -> None:
    with pytest.raises(NeuralMapError, match="empty"):
        generate([])
    with pytest.raises(NeuralMapError, match="duration"):
        generate([Segment(0.0)])
    with pytest.raises(NeuralMapError, match="speed becomes"):
        generate([Segment(5.0, dspeed=-1.0)])
    with pytest.raises(NeuralMapError, match="cruise speed"):
        urban_drive(distance=100.0)


def test_discontinuity_is_rejected() -> None:
    traj = short_drive(duration=20.0, dt=0.05)
    states = traj.states.clone()
    states[200:, 0] += 5.0 / 6.4e6  # a 5 m position jump at sample 200
    with pytest.raises(NeuralMapError, match="between samples 199 and 200"):
        check_continuity(dataclasses.replace(traj, states=states))
    states = traj.states.clone()
    states[150:, 6:10] = torch.tensor([math.cos(0.1), 0.0, 0.0, math.sin(0.1)],
                                      dtype=torch.float64)
    with pytest.raises(NeuralMapError, match="attitude change"):
        check_continuity(dataclasses.replace(traj, states=states))
    time = traj.time.clone()
    time[50:] += 0.01
    with pytest.raises(NeuralMapError, match="time step"):
        check_continuity(dataclasses.replace(traj, time=time))
