"""The 15-state ψ-angle error model: continuous F, discrete Φ and Q (SEEDS 003).

Error state ``δx = [δr, δv, ψ, δb_g, δb_a]`` (see `neuralmap.ins.error_state`). The
ψ-angle (attitude drift) error equations of paper 003 (eqs. 1–2; Benson 1975, Titterton &
Weston ch. 12) with Gauss–Markov sensor biases::

    δṙ   = −ω_enⁿ × δr + δv
    δv̇   = fⁿ × ψ − (2ω_ieⁿ + ω_enⁿ) × δv + δg − C_b^n δb_a − C_b^n n_a
    ψ̇    = −ω_inⁿ × ψ + C_b^n δb_g + C_b^n n_g
    δḃ_g = −δb_g / τ_g + w_g,   δḃ_a = −δb_a / τ_a + w_a

with ``δg = [−g δr_N/(R_M+h), −g δr_E/(R_N+h), 2g δr_D/(√(R_M R_N)+h)]`` (the horizontal
gravity tilt that closes the Schuler loop and the vertical gradient). Estimated biases are
subtracted from the measurements, so a positive bias estimation error makes the corrected
sensor read low; the white sensor noises enter with the signs shown (irrelevant for Q).

Discretisation: ``Φ = I + F T + (F T)²/2`` (``order`` 1 or 2) over the propagation interval
T; ``Q_d = ½ (Φ G Q_c Gᵀ Φᵀ + G Q_c Gᵀ) T`` (trapezoid), with
``Q_c = diag(VRW², ARW², 2σ_g²/τ_g, 2σ_a²/τ_a)`` per axis from the IMU grade.
"""

from __future__ import annotations

import torch

from neuralmap.filters.stats import symmetrize
from neuralmap.ins.earth import earth_rate_ned, normal_gravity, radii, transport_rate_ned
from neuralmap.ins.imu_model import ImuGrade, imu_grade
from neuralmap.ins.rotation import dcm_from_quat, skew

__all__ = [
    "N_ERROR_STATES",
    "continuous_noise",
    "discretize",
    "error_dynamics",
    "process_noise_density",
]

#: Size of the error state.
N_ERROR_STATES = 15


def error_dynamics(
    states: torch.Tensor,
    accel: torch.Tensor,
    *,
    gyro_corr_time: float,
    accel_corr_time: float,
) -> torch.Tensor:
    """Continuous error dynamics matrix ``F`` ``(N, 15, 15)``.

    Args:
        states: ``(N, 10)`` computed packed states.
        accel: ``(N, 3)`` or ``(3,)`` bias-corrected specific force ``f^b`` (m/s²).
        gyro_corr_time, accel_corr_time: Bias correlation times τ (s).

    Returns:
        ``(N, 15, 15)`` F.
    """
    n = states.shape[0]
    lat, h, vel = states[:, 0], states[:, 2], states[:, 3:6]
    c = dcm_from_quat(states[:, 6:10])
    w_ie = earth_rate_ned(lat)
    w_en = transport_rate_ned(lat, h, vel)
    f_n = (c @ accel.expand(n, 3).unsqueeze(-1)).squeeze(-1)
    rm, rn = radii(lat)
    g = normal_gravity(lat, h)
    eye = torch.eye(3, dtype=states.dtype, device=states.device).expand(n, 3, 3)
    F = states.new_zeros(n, 15, 15)
    F[:, 0:3, 0:3] = -skew(w_en)
    F[:, 0:3, 3:6] = eye
    F[:, 3, 0] = -g / (rm + h)
    F[:, 4, 1] = -g / (rn + h)
    F[:, 5, 2] = 2.0 * g / (torch.sqrt(rm * rn) + h)
    F[:, 3:6, 3:6] = -skew(2.0 * w_ie + w_en)
    F[:, 3:6, 6:9] = skew(f_n)
    F[:, 3:6, 12:15] = -c
    F[:, 6:9, 6:9] = -skew(w_ie + w_en)
    F[:, 6:9, 9:12] = c
    F[:, 9:12, 9:12] = -eye / gyro_corr_time
    F[:, 12:15, 12:15] = -eye / accel_corr_time
    return F


def process_noise_density(grade: str | ImuGrade) -> torch.Tensor:
    """Diagonal of ``Q_c`` ``(12,)``: VRW², ARW², 2σ_g²/τ_g, 2σ_a²/τ_a per axis (SI)."""
    g = imu_grade(grade)
    values = (
        [g.accel_vrw_si**2] * 3
        + [g.gyro_arw_si**2] * 3
        + [2.0 * g.gyro_bias_sigma_si**2 / g.gyro_corr_time] * 3
        + [2.0 * g.accel_bias_sigma_si**2 / g.accel_corr_time] * 3
    )
    return torch.tensor(values, dtype=torch.float64)


def continuous_noise(states: torch.Tensor, q_diag: torch.Tensor) -> torch.Tensor:
    """``G Q_c Gᵀ`` ``(N, 15, 15)``: white noise mapped into the error state.

    ``G`` puts ``C_b^n n_a`` on δv, ``C_b^n n_g`` on ψ and the bias driving noises on the
    bias states; for per-axis equal densities ``C Q Cᵀ = Q`` but the general form is kept.
    """
    n = states.shape[0]
    c = dcm_from_quat(states[:, 6:10])
    q = q_diag.to(states)
    out = states.new_zeros(n, 15, 15)
    out[:, 3:6, 3:6] = (c * q[0:3]) @ c.transpose(-1, -2)
    out[:, 6:9, 6:9] = (c * q[3:6]) @ c.transpose(-1, -2)
    idx = torch.arange(9, 15, device=states.device)
    out[:, idx, idx] = q[6:12]
    return out


def discretize(
    F: torch.Tensor, gqg: torch.Tensor, interval: float, *, order: int = 2
) -> tuple[torch.Tensor, torch.Tensor]:
    """Transition matrix and discrete process noise over ``interval`` seconds.

    Args:
        F: ``(N, 15, 15)`` continuous dynamics.
        gqg: ``(N, 15, 15)`` continuous noise ``G Q_c Gᵀ``.
        interval: Propagation interval T (s), > 0.
        order: 1 → ``Φ = I + FT``; 2 → ``+ (FT)²/2``.

    Returns:
        ``(Φ, Q_d)``, ``(N, 15, 15)`` each; ``Q_d`` symmetric.
    """
    ft = F * interval
    eye = torch.eye(F.shape[-1], dtype=F.dtype, device=F.device)
    phi = eye + ft
    if order >= 2:
        phi = phi + 0.5 * ft @ ft
    q = 0.5 * (phi @ gqg @ phi.transpose(-1, -2) + gqg) * interval
    return phi, symmetrize(q)


