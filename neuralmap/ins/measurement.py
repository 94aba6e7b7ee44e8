"""GNSS position and velocity measurement models with the lever arm (SEEDS 003, eqs. 3–10).

The antenna sits at the lever arm ``l^b`` (m, body frame, from the IMU to the antenna
phase centre). Its position and velocity follow from the INS solution::

    r_antⁿ = rⁿ + C_b^n l^b
    v_antⁿ = vⁿ + C_b^n (ω_ib^b × l^b) − ω_inⁿ × (C_b^n l^b)

The innovation is the INS-predicted minus the GNSS-measured antenna position (NED metres
about the measurement) and velocity, ``δz = [r̂_ant − r̃_ant, v̂_ant − ṽ_ant]`` (m = 6).
To first order in the ψ-angle error state (``φ = ψ + T δr``, see
`neuralmap.ins.error_state`) its Jacobian is::

    H_r = [I + [(Ĉl)×] T, 0, [(Ĉl)×], 0, 0]
    H_v = [([v×] + ([a×] − [ω_in×][(Ĉl)×]) T), I, [a×] − [ω_in×][(Ĉl)×], Ĉ [l×], 0]

with ``a = Ĉ (ω̂_ib × l)``; the terms through the position dependence of ``ω_in``
(of order ``|l|·|v|/R²``) are dropped.
"""

from __future__ import annotations

import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.ins.earth import earth_rate_ned, position_offset_ned, radii, transport_rate_ned
from neuralmap.ins.error_state import frame_tilt_matrix
from neuralmap.ins.rotation import dcm_from_quat, skew

__all__ = ["antenna_position", "antenna_velocity", "check_lever_arm", "gnss_measurement_model"]


def check_lever_arm(lever_arm: object, *, where: str) -> torch.Tensor:
    """Validates a lever arm: a finite ``(3,)`` body-frame vector in metres.

    Raises:
        NeuralMapError: Wrong shape or non-finite entries.
    """
    arm = torch.as_tensor(lever_arm, dtype=torch.float64)
    if arm.shape != (3,):
        raise NeuralMapError(
            f"{where}: 'lever_arm' has shape {tuple(arm.shape)}, expected (3,) = the IMU-to-"
            "antenna vector [forward, right, down] in metres in the body frame."
        )
    if not bool(torch.isfinite(arm).all()):
        raise NeuralMapError(f"{where}: 'lever_arm' {arm.tolist()} has non-finite entries.")
    return arm


def antenna_position(states: torch.Tensor, lever_arm: torch.Tensor) -> torch.Tensor:
    """Geodetic antenna position ``(N, 3)`` [lat, lon, h] of packed states ``(N, 10)``."""
    lat, h = states[:, 0], states[:, 2]
    rm, rn = radii(lat)
    off = (dcm_from_quat(states[:, 6:10]) @ lever_arm.to(states)).reshape(-1, 3)
    return torch.stack(
        [lat + off[:, 0] / (rm + h), states[:, 1] + off[:, 1] / ((rn + h) * torch.cos(lat)),
         h - off[:, 2]], dim=-1,
    )


def antenna_velocity(
    states: torch.Tensor, gyro: torch.Tensor, lever_arm: torch.Tensor
) -> torch.Tensor:
    """NED antenna velocity ``(N, 3)`` from packed states and ``ω_ib^b`` ``(N, 3)``."""
    lat, h, vel = states[:, 0], states[:, 2], states[:, 3:6]
    c = dcm_from_quat(states[:, 6:10])
    arm = lever_arm.to(states).expand_as(vel)
    w_in = earth_rate_ned(lat) + transport_rate_ned(lat, h, vel)
    a = (c @ torch.linalg.cross(gyro.expand_as(vel), arm, dim=-1).unsqueeze(-1)).squeeze(-1)
    b = (c @ arm.unsqueeze(-1)).squeeze(-1)
    return vel + a - torch.linalg.cross(w_in, b, dim=-1)


def gnss_measurement_model(
    states: torch.Tensor,
    gyro: torch.Tensor,
    lever_arm: torch.Tensor,
    gnss_position: torch.Tensor,
    gnss_velocity: torch.Tensor,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Innovation and Jacobian of a GNSS position + velocity epoch.

    Args:
        states: ``(N, 10)`` computed packed INS states at the GNSS epoch.
        gyro: ``(N, 3)`` bias-corrected angular rate at the epoch (rad/s).
        lever_arm: ``(3,)`` IMU-to-antenna vector (m, body frame).
        gnss_position: ``(N, 3)`` measured antenna [lat, lon, h] (rad, rad, m).
        gnss_velocity: ``(N, 3)`` measured antenna NED velocity (m/s).

    Returns:
        ``(innovation (N, 6), H (N, 6, 15))``; innovation = predicted − measured.
    """
    n = states.shape[0]
    lat, h, vel = states[:, 0], states[:, 2], states[:, 3:6]
    arm = lever_arm.to(states)
    pred_pos = antenna_position(states, arm)
    dz_r = position_offset_ned(
        pred_pos[:, 0], pred_pos[:, 1], pred_pos[:, 2],
        gnss_position[:, 0], gnss_position[:, 1], gnss_position[:, 2],
    )
    dz_v = antenna_velocity(states, gyro, arm) - gnss_velocity
    c = dcm_from_quat(states[:, 6:10])
    b = (c @ arm).reshape(n, 3)
    w_in = earth_rate_ned(lat) + transport_rate_ned(lat, h, vel)
    a = (c @ torch.linalg.cross(gyro.expand(n, 3), arm.expand(n, 3), dim=-1).unsqueeze(-1))
    a = a.squeeze(-1)
    t = frame_tilt_matrix(lat, h)
    eye = torch.eye(3, dtype=states.dtype, device=states.device).expand(n, 3, 3)
    b_x = skew(b)
    att_v = skew(a) - skew(w_in) @ b_x
    H = states.new_zeros(n, 6, 15)
    H[:, 0:3, 0:3] = eye + b_x @ t
    H[:, 0:3, 6:9] = b_x
    H[:, 3:6, 0:3] = (skew(vel) + att_v) @ t
    H[:, 3:6, 3:6] = eye
    H[:, 3:6, 6:9] = att_v
    H[:, 3:6, 9:12] = c @ skew(arm.expand(n, 3))
    return torch.cat([dz_r, dz_v], dim=1), H
