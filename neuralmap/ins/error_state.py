"""The ψ-angle error state and its feedback correction (SEEDS 003, eqs. 1–2).

The 15-state error vector is ``δx = [δr, δv, ψ, δb_g, δb_a]`` with every error defined as
*computed minus true*:

* ``δr`` (m): position error in NED metres, ``[(R_M+h) δL, (R_N+h) cos L δλ, −δh]``;
* ``δv`` (m/s): velocity error of the ψ-angle formulation, the computed velocity minus the
  true velocity resolved in the computer frame: ``δv = (v̂ − v) + δθ × v``;
* ``ψ`` (rad): attitude error between the platform (computed body-to-navigation DCM) and
  the computer frame, ``ψ = φ − δθ``, where ``Ĉ_b^n = (I − [φ×]) C_b^n`` defines the
  total attitude error φ and ``δθ = [δr_E/(R_N+h), −δr_N/(R_M+h), −δr_E tan L/(R_N+h)]``
  is the small rotation from the true to the computed navigation frame;
* ``δb_g``, ``δb_a``: estimated minus true gyro and accelerometer biases.

The ψ-angle form decouples the attitude error from the position error (its equations
carry no ``δω_in`` terms), which is the attitude-drift model of paper 003. Feedback
(`correct`) subtracts an estimated error from the computed solution.
"""

from __future__ import annotations

import torch

from neuralmap.ins.earth import position_offset_ned, radii
from neuralmap.ins.rotation import dcm_from_quat, quat_from_rotvec, quat_multiply, rotvec_from_dcm

__all__ = [
    "correct",
    "frame_tilt",
    "frame_tilt_matrix",
    "inject",
    "navigation_error",
    "total_attitude_error",
]


def frame_tilt_matrix(lat: torch.Tensor, h: torch.Tensor) -> torch.Tensor:
    """``T`` with ``δθ = T δr``, ``(N, 3, 3)`` (true-to-computed navigation-frame rotation)."""
    rm, rn = radii(lat)
    z = torch.zeros_like(lat)
    inv_n = 1.0 / (rn + h)
    return torch.stack(
        [
            torch.stack([z, inv_n, z], -1),
            torch.stack([-1.0 / (rm + h), z, z], -1),
            torch.stack([z, -inv_n * torch.tan(lat), z], -1),
        ],
        dim=-2,
    )


def frame_tilt(lat: torch.Tensor, h: torch.Tensor, dr: torch.Tensor) -> torch.Tensor:
    """``δθ (N, 3)`` of position errors ``dr (N, 3)`` (NED metres)."""
    rm, rn = radii(lat)
    inv_n = 1.0 / (rn + h)
    return torch.stack(
        [dr[:, 1] * inv_n, -dr[:, 0] / (rm + h), -dr[:, 1] * inv_n * torch.tan(lat)], -1
    )


def navigation_error(true: torch.Tensor, computed: torch.Tensor) -> torch.Tensor:
    """ψ-formulation error ``[δr, δv, ψ]`` ``(N, 9)`` of computed vs true packed states.

    Args:
        true: ``(N, 10)`` true packed states.
        computed: ``(N, 10)`` computed packed states.

    Returns:
        ``(N, 9)``; exact position offsets to first order, exact rotation for the attitude.
    """
    lat, lon, h = true[:, 0], true[:, 1], true[:, 2]
    dr = position_offset_ned(computed[:, 0], computed[:, 1], computed[:, 2], lat, lon, h)
    dtheta = frame_tilt(lat, h, dr)
    v = true[:, 3:6]
    dv = computed[:, 3:6] - v + torch.linalg.cross(dtheta, v, dim=-1)
    c_hat = dcm_from_quat(computed[:, 6:10])
    c_true = dcm_from_quat(true[:, 6:10])
    phi = -rotvec_from_dcm(c_hat @ c_true.transpose(-1, -2))  # Ĉ Cᵀ = exp(−[φ×])
    return torch.cat([dr, dv, phi - dtheta], dim=1)


def total_attitude_error(true: torch.Tensor, computed: torch.Tensor) -> torch.Tensor:
    """Total attitude error φ ``(N, 3)`` (rad, NED axes): ``Ĉ_b^n = exp(−[φ×]) C_b^n``."""
    c_hat = dcm_from_quat(computed[:, 6:10])
    c_true = dcm_from_quat(true[:, 6:10])
    return -rotvec_from_dcm(c_hat @ c_true.transpose(-1, -2))


def inject(true: torch.Tensor, error: torch.Tensor) -> torch.Tensor:
    """Computed states that carry a given error ``[δr, δv, ψ]`` ``(N, 9)`` (inverse of
    `navigation_error` to first order in position, exact in attitude)."""
    lat, h = true[:, 0], true[:, 2]
    rm, rn = radii(lat)
    dr, dv, psi = error[:, :3], error[:, 3:6], error[:, 6:9]
    dtheta = frame_tilt(lat, h, dr)
    v = true[:, 3:6]
    out_lat = lat + dr[:, 0] / (rm + h)
    out_lon = true[:, 1] + dr[:, 1] / ((rn + h) * torch.cos(lat))
    out_h = h - dr[:, 2]
    out_v = v + dv - torch.linalg.cross(dtheta, v, dim=-1)
    q = quat_multiply(quat_from_rotvec(-(psi + dtheta)), true[:, 6:10])
    return torch.cat([out_lat[:, None], out_lon[:, None], out_h[:, None], out_v, q], dim=1)


def correct(computed: torch.Tensor, error: torch.Tensor) -> torch.Tensor:
    """Feedback correction: removes an estimated error ``[δr, δv, ψ]`` ``(N, 9)``.

    ``L = L̂ − δr_N/(R_M+h)``, ``λ = λ̂ − δr_E/((R_N+h) cos L)``, ``h = ĥ + δr_D``,
    ``v = v̂ − δv + δθ × v̂``, ``C = exp([(ψ + δθ)×]) Ĉ`` (all with the computed position).

    Returns:
        ``(N, 10)`` corrected packed states.
    """
    lat, h = computed[:, 0], computed[:, 2]
    rm, rn = radii(lat)
    dr, dv, psi = error[:, :3], error[:, 3:6], error[:, 6:9]
    dtheta = frame_tilt(lat, h, dr)
    v = computed[:, 3:6]
    out_lat = lat - dr[:, 0] / (rm + h)
    out_lon = computed[:, 1] - dr[:, 1] / ((rn + h) * torch.cos(lat))
    out_h = h + dr[:, 2]
    out_v = v - dv + torch.linalg.cross(dtheta, v, dim=-1)
    q = quat_multiply(quat_from_rotvec(psi + dtheta), computed[:, 6:10])
    q = q * torch.rsqrt((q * q).sum(-1, keepdim=True))
    return torch.cat([out_lat[:, None], out_lon[:, None], out_h[:, None], out_v, q], dim=1)
