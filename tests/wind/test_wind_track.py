"""Dead reckoning with and without the wind correction."""

from __future__ import annotations

import math

import pytest
import torch

from neuralmap.wind import TrackConfig, dead_reckon


def _const_wind(n, t, east, north):
    w = torch.zeros(n, t, 2, dtype=torch.float64)
    w[..., 0], w[..., 1] = east, north
    return w


def test_uncorrected_error_is_wind_times_time_split_along_and_cross():
    # heading north at 20 m/s, wind 3 m/s east + 4 m/s north, no sensor noise:
    # ground velocity (3, 24); the DR error after k steps is −(3, 4)·k·Δt.
    cfg = TrackConfig(airspeed=20.0, heading_deg=0.0, dt=0.5, airspeed_noise_std=0.0,
                      heading_noise_std_deg=0.0)
    wind = _const_wind(2, 11, 3.0, 4.0)
    res = dead_reckon(wind, cfg, generator=torch.Generator().manual_seed(0))
    k = torch.arange(11, dtype=torch.float64)
    err = res.position - res.true_position
    assert torch.allclose(err[..., 0], -3.0 * 0.5 * k) and torch.allclose(err[..., 1],
                                                                           -4.0 * 0.5 * k)
    t_hat = torch.tensor([3.0, 24.0], dtype=torch.float64) / math.hypot(3.0, 24.0)
    along = -(3.0 * t_hat[0] + 4.0 * t_hat[1]) * 0.5 * k
    cross = -(4.0 * t_hat[0] - 3.0 * t_hat[1]) * 0.5 * k  # e_n t_e − e_e t_n
    assert torch.allclose(res.along[0], along) and torch.allclose(res.cross[0], cross)
    assert torch.allclose(res.error[0], 5.0 * 0.5 * k)


def test_full_correction_with_true_wind_is_exact_and_partial_step_scales():
    cfg = TrackConfig(airspeed=15.0, heading_deg=30.0, turn_rate_deg=2.0,
                      airspeed_noise_std=0.0, heading_noise_std_deg=0.0)
    gen = torch.Generator().manual_seed(1)
    wind = torch.randn(3, 40, 2, generator=gen, dtype=torch.float64) + 5.0
    res = dead_reckon(wind, cfg, wind_estimate=wind, generator=gen)
    assert res.error.abs().max().item() < 1e-10
    half = TrackConfig(airspeed=15.0, heading_deg=30.0, turn_rate_deg=2.0, dt=1.0,
                       correction_step=0.5, airspeed_noise_std=0.0, heading_noise_std_deg=0.0)
    res_half = dead_reckon(wind, half, wind_estimate=wind, generator=gen)
    res_none = dead_reckon(wind, half, generator=gen)
    err_half = res_half.position - res_half.true_position
    err_none = res_none.position - res_none.true_position
    assert torch.allclose(err_half, 0.5 * err_none, atol=1e-10)


def test_same_draws_and_fixes_reset_the_error():
    cfg = TrackConfig(fix_interval=10, fix_std=2.0)
    wind = _const_wind(200, 31, 8.0, 0.0)
    a = dead_reckon(wind, cfg, generator=torch.Generator().manual_seed(3))
    b = dead_reckon(wind, cfg, generator=torch.Generator().manual_seed(3))
    assert torch.equal(a.position, b.position)
    err = a.position - a.true_position
    # at a fix the error is the fix noise (std 2 m per axis) whatever came before
    assert err[:, 10].std().item() == pytest.approx(2.0, rel=0.15)
    assert err[:, 9].norm(dim=-1).mean().item() > 60.0  # 8 m/s for 9 s without correction
