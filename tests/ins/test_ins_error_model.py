"""The ψ-angle error model: Φ against finite differences of the mechanisation."""

from __future__ import annotations

import math

import pytest
import torch

from neuralmap.ins.error_model import (
    continuous_noise,
    discretize,
    error_dynamics,
    process_noise_density,
)
from neuralmap.ins.error_state import correct, inject, navigation_error
from neuralmap.ins.imu_model import IMU_GRADES
from neuralmap.ins.mechanization import strapdown_step
from neuralmap.ins.trajectory import short_drive

TAU = 3600.0
#: perturbation sizes: δr (m), δv (m/s), ψ (rad), δb_g (rad/s), δb_a (m/s²)
SCALES = torch.tensor([1.0] * 3 + [0.01] * 3 + [1e-4] * 3 + [1e-5] * 3 + [1e-3] * 3,
                      dtype=torch.float64)


def _fd_and_phi(dynamics=error_dynamics) -> tuple[torch.Tensor, torch.Tensor]:
    """Central-difference transition of the mechanisation over 1 s in a turn at 100 Hz,
    and the product of the per-step Φ (F averaged over each step's ends)."""
    traj = short_drive(dt=0.01)
    k0, steps, dt = 1500, 100, traj.dt
    dx = torch.cat([torch.diag(SCALES), -torch.diag(SCALES)])
    n = dx.shape[0]
    comp = inject(traj.states[k0].expand(n, 10), dx[:, :9])
    bg, ba = dx[:, 9:12], dx[:, 12:15]
    phi_chain = torch.eye(15, dtype=torch.float64)
    decay = math.exp(-dt / TAU)
    for k in range(k0, k0 + steps):
        F = 0.5 * sum(dynamics(traj.states[i:i + 1], traj.accel[i], gyro_corr_time=TAU,
                               accel_corr_time=TAU) for i in (k, k + 1))
        phi, _ = discretize(F, torch.zeros_like(F), dt)
        phi_chain = phi[0] @ phi_chain
        # corrected sensors read low by the bias estimation error (ω̂ = ω − δb_g)
        comp = strapdown_step(comp, traj.gyro[k] - bg, traj.accel[k] - ba,
                              traj.gyro[k + 1] - bg, traj.accel[k + 1] - ba, dt)
        bg, ba = bg * decay, ba * decay
    err = torch.cat([navigation_error(traj.states[k0 + steps].expand(n, 10), comp), bg, ba], 1)
    fd = ((err[:15] - err[15:]) / (2 * SCALES[:, None])).t()
    return fd, phi_chain


def _scaled(m: torch.Tensor) -> torch.Tensor:
    """Φ in units of the perturbation sizes (every entry is a relative response)."""
    return m * SCALES[None, :] / SCALES[:, None]


def test_transition_matches_finite_differences() -> None:
    """Scaled |Φ − Φ_fd| < 1e-5 (measured 1.1e-6); the f×ψ, gravity, Coriolis and bias
    couplings reach 1e-4 … 1 in these units, so every term that matters is checked."""
    fd, phi = _fd_and_phi()
    assert (_scaled(fd - phi)).abs().max() < 1e-5
    # large entries agree to 0.5 % relative as well (measured 0.2 %)
    big = phi.abs() > 0.05
    assert ((fd - phi)[big].abs() / phi[big].abs()).max() < 5e-3


def test_wrong_model_is_detected() -> None:
    """Flipping the sign of the specific-force coupling f×ψ breaks the comparison."""

    def wrong(states, accel, **kw):
        F = error_dynamics(states, accel, **kw)
        F[:, 3:6, 6:9] = -F[:, 3:6, 6:9]
        return F

    fd, phi = _fd_and_phi(wrong)
    assert _scaled(fd - phi).abs().max() > 1e-3


def test_inject_correct_round_trip() -> None:
    traj = short_drive(duration=20.0, dt=0.1)
    truth = traj.states[100:101].expand(4, 10)
    gen = torch.Generator().manual_seed(3)
    err = torch.randn(4, 9, generator=gen, dtype=torch.float64) * SCALES[:9] * 10
    comp = inject(truth, err)
    assert torch.allclose(navigation_error(truth, comp), err, rtol=1e-6, atol=1e-9)
    back = correct(comp, err)  # first-order inverse: residual O(|δr|²/R), measured 2e-5 m
    assert torch.allclose(navigation_error(truth, back), torch.zeros_like(err), atol=1e-4)


def test_process_noise_from_densities() -> None:
    g = IMU_GRADES["tactical_mems"]
    q = process_noise_density(g)
    assert q[0].item() == pytest.approx((0.06 / 60.0) ** 2)
    assert q[3].item() == pytest.approx((0.15 * math.pi / 180 / 60.0) ** 2)
    assert q[6].item() == pytest.approx(2 * (3.0 * math.pi / 180 / 3600) ** 2 / 3600.0)
    states = short_drive(duration=20.0, dt=0.1).states[50:52]
    gqg = continuous_noise(states, q)
    F = error_dynamics(states, torch.tensor([0.1, 0.2, -9.8], dtype=torch.float64),
                       gyro_corr_time=3600.0, accel_corr_time=3600.0)
    phi, qd = discretize(F, gqg, 0.1)
    assert torch.equal(qd, qd.transpose(-1, -2))
    assert torch.linalg.eigvalsh(qd).min() > 0
    # over a short interval Q_d ≈ G Q_c Gᵀ T (isotropic densities: C Q Cᵀ = Q)
    assert torch.allclose(qd[0].diagonal()[3:], q * 0.1, rtol=2e-3, atol=0.0)
