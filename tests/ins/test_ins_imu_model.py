"""MEMS IMU error model: noise statistics against the grade parameters."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.ins.imu_model import IMU_GRADES, ImuErrorProcess, imu_grade


def test_white_noise_and_gauss_markov_statistics() -> None:
    """Sample σ of the white noise = ARW/√Δt; GM lag-1 correlation e^{-Δt/τ}, variance σ²."""
    g = dataclasses.replace(IMU_GRADES["consumer_mems"], gyro_turn_on=0.0, accel_turn_on=0.0,
                            gyro_corr_time=2.0, accel_corr_time=4.0)
    dt, n, steps = 0.1, 4000, 60
    gen = torch.Generator().manual_seed(0)
    imu = ImuErrorProcess(g, n_runs=n, dt=dt, generator=gen, scale_factor=False)
    zero = torch.zeros(3, dtype=torch.float64)
    meas, gm = [], []
    for _ in range(steps):
        gm.append(imu.gyro_gm.clone())
        meas.append(imu.measure(zero, zero))
    w = torch.stack([m[0] for m in meas]) - torch.stack(gm)  # white part of the gyro
    assert w.std().item() == pytest.approx(g.gyro_arw_si / math.sqrt(dt), rel=0.01)
    b = torch.stack(gm)  # (steps, N, 3)
    assert b.std().item() == pytest.approx(g.gyro_bias_sigma_si, rel=0.02)
    rho = (b[1:] * b[:-1]).mean() / b.square().mean()
    assert rho.item() == pytest.approx(math.exp(-dt / 2.0), abs=0.01)
    a = torch.stack([m[1] for m in meas])
    assert a.std().item() == pytest.approx(
        math.sqrt(g.accel_vrw_si**2 / dt + g.accel_bias_sigma_si**2), rel=0.01)


def test_turn_on_and_scale_factor() -> None:
    g = IMU_GRADES["tactical_mems"]
    gen = torch.Generator().manual_seed(1)
    imu = ImuErrorProcess(g, n_runs=20000, dt=0.01, generator=gen)
    assert imu.gyro_turn_on.std().item() == pytest.approx(g.gyro_turn_on_si, rel=0.02)
    assert imu.accel_scale.std().item() == pytest.approx(g.accel_scale_ppm * 1e-6, rel=0.02)
    truth = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    w, _ = imu.measure(truth, truth)
    expected = imu.gyro_scale[:, 2] + 1.0 + imu.gyro_bias[:, 2]
    # the white noise is the only difference
    assert (w[:, 2] - expected).std().item() == pytest.approx(g.gyro_arw_si / 0.1, rel=0.03)


@pytest.mark.parametrize("field,value", [("gyro_arw", 0.0), ("accel_vrw", -0.1),
                                         ("gyro_corr_time", 0.0), ("gyro_turn_on", -1.0),
                                         ("accel_vrw", float("nan"))])
def test_bad_grades(field: str, value: float) -> None:
    bad = dataclasses.replace(IMU_GRADES["tactical_mems"], **{field: value})
    with pytest.raises(NeuralMapError, match=field):
        imu_grade(bad)
    with pytest.raises(NeuralMapError, match="unknown IMU grade"):
        imu_grade("navigation_grade_fog")
