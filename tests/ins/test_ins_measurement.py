"""Lever-arm GNSS measurement Jacobians against finite differences."""

from __future__ import annotations

import pytest
import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.ins.error_state import inject
from neuralmap.ins.measurement import (
    antenna_position,
    antenna_velocity,
    check_lever_arm,
    gnss_measurement_model,
)
from neuralmap.ins.trajectory import short_drive

SCALES = torch.tensor([1.0] * 3 + [0.01] * 3 + [1e-3] * 3 + [1e-4] * 3 + [1e-3] * 3,
                      dtype=torch.float64)


@pytest.mark.parametrize("arm", [[0.8, -0.4, -1.5], [0.0, 0.0, 0.0]])
def test_jacobian_matches_finite_differences(arm: list[float]) -> None:
    traj = short_drive(dt=0.01)
    k = 1500  # turning: ω × l is not zero
    lever = torch.tensor(arm, dtype=torch.float64)
    true, gyro = traj.states[k:k + 1], traj.gyro[k:k + 1]
    zp, zv = antenna_position(true, lever), antenna_velocity(true, gyro, lever)
    dx = torch.cat([torch.diag(SCALES), -torch.diag(SCALES)])
    comp = inject(true.expand(30, 10), dx[:, :9])
    z, _ = gnss_measurement_model(comp, gyro - dx[:, 9:12], lever, zp.expand(30, 3),
                                  zv.expand(30, 3))
    fd = ((z[:15] - z[15:]) / (2 * SCALES[:, None])).t()
    resid, H = gnss_measurement_model(true, gyro, lever, zp, zv)
    assert resid.abs().max() < 1e-9  # zero innovation at the truth
    # measured max |H − H_fd| = 2.9e-7 (entries up to 1.5: lever-arm attitude/bias terms)
    assert (fd - H[0]).abs().max() < 2e-6
    if arm[0] != 0.0:
        assert H[0, 0:3, 6:9].abs().max() > 0.5  # attitude enters through the lever arm
        assert H[0, 3:6, 9:12].abs().max() > 0.5  # gyro bias through ω × l


def test_lever_arm_checks() -> None:
    with pytest.raises(NeuralMapError, match=r"shape \(2,\)"):
        check_lever_arm([1.0, 2.0], where="test")
    with pytest.raises(NeuralMapError, match="shape"):
        check_lever_arm([[1.0, 2.0, 3.0]], where="test")
    with pytest.raises(NeuralMapError, match="non-finite"):
        check_lever_arm([1.0, float("nan"), 0.0], where="test")
