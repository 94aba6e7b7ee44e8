"""Rotation helpers for the strapdown mechanisation: quaternions, DCMs, Euler angles.

Quaternions are scalar-first ``(..., 4)`` = ``[q0, q1, q2, q3]`` and represent the
body-to-navigation rotation ``C_b^n`` (a vector ``x_b`` maps to ``C_b^n x_b``). Euler angles
are roll, pitch, yaw (rad) in the aerospace 3-2-1 sequence with ``C_b^n = R_z(ψ) R_y(θ)
R_x(φ)``. All functions broadcast over leading dimensions.
"""

from __future__ import annotations

import torch

__all__ = [
    "dcm_from_euler",
    "dcm_from_quat",
    "dcm_from_rotvec",
    "euler_from_dcm",
    "quat_from_dcm",
    "quat_from_euler",
    "quat_from_rotvec",
    "quat_multiply",
    "quat_normalize",
    "rotvec_from_dcm",
    "skew",
]


def skew(v: torch.Tensor) -> torch.Tensor:
    """Cross-product matrix ``[v×]`` of ``(..., 3)`` vectors, ``(..., 3, 3)``."""
    zero = torch.zeros_like(v[..., 0])
    x, y, z = v[..., 0], v[..., 1], v[..., 2]
    return torch.stack(
        [
            torch.stack([zero, -z, y], dim=-1),
            torch.stack([z, zero, -x], dim=-1),
            torch.stack([-y, x, zero], dim=-1),
        ],
        dim=-2,
    )


def quat_multiply(p: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
    """Hamilton product ``p ⊗ q`` of ``(..., 4)`` quaternions."""
    p0, p1, p2, p3 = p.unbind(-1)
    q0, q1, q2, q3 = q.unbind(-1)
    return torch.stack(
        [
            p0 * q0 - p1 * q1 - p2 * q2 - p3 * q3,
            p0 * q1 + p1 * q0 + p2 * q3 - p3 * q2,
            p0 * q2 - p1 * q3 + p2 * q0 + p3 * q1,
            p0 * q3 + p1 * q2 - p2 * q1 + p3 * q0,
        ],
        dim=-1,
    )


def quat_normalize(q: torch.Tensor) -> torch.Tensor:
    """Unit quaternion with a non-negative scalar part (a unique representative)."""
    q = q / torch.linalg.vector_norm(q, dim=-1, keepdim=True)
    return torch.where(q[..., :1] < 0, -q, q)


def quat_from_rotvec(phi: torch.Tensor) -> torch.Tensor:
    """Quaternion ``[cos(|φ|/2), sin(|φ|/2) φ/|φ|]`` of a rotation vector ``(..., 3)``.

    Uses the series ``sin(x/2)/x ≈ 1/2 − x²/48`` below ``|φ| = 1e-4`` (no 0/0).
    """
    angle = torch.linalg.vector_norm(phi, dim=-1, keepdim=True)
    small = angle < 1e-4
    safe = torch.where(small, torch.ones_like(angle), angle)
    scale = torch.where(small, 0.5 - angle.square() / 48.0, torch.sin(0.5 * safe) / safe)
    return torch.cat([torch.cos(0.5 * angle), scale * phi], dim=-1)


def dcm_from_quat(q: torch.Tensor) -> torch.Tensor:
    """DCM ``C_b^n`` ``(..., 3, 3)`` of unit quaternions ``(..., 4)``."""
    q0, q1, q2, q3 = q.unbind(-1)
    return torch.stack(
        [
            torch.stack(
                [q0 * q0 + q1 * q1 - q2 * q2 - q3 * q3, 2 * (q1 * q2 - q0 * q3),
                 2 * (q1 * q3 + q0 * q2)], dim=-1),
            torch.stack(
                [2 * (q1 * q2 + q0 * q3), q0 * q0 - q1 * q1 + q2 * q2 - q3 * q3,
                 2 * (q2 * q3 - q0 * q1)], dim=-1),
            torch.stack(
                [2 * (q1 * q3 - q0 * q2), 2 * (q2 * q3 + q0 * q1),
                 q0 * q0 - q1 * q1 - q2 * q2 + q3 * q3], dim=-1),
        ],
        dim=-2,
    )


def dcm_from_rotvec(phi: torch.Tensor) -> torch.Tensor:
    """Rotation matrix ``exp([φ×])`` ``(..., 3, 3)`` of a rotation vector."""
    return dcm_from_quat(quat_from_rotvec(phi))


def quat_from_dcm(c: torch.Tensor) -> torch.Tensor:
    """Unit quaternion of a DCM ``(..., 3, 3)`` (Shepperd's method, numerically safe)."""
    tr = c[..., 0, 0] + c[..., 1, 1] + c[..., 2, 2]
    cands = torch.stack(
        [
            torch.stack([1 + tr, c[..., 2, 1] - c[..., 1, 2], c[..., 0, 2] - c[..., 2, 0],
                         c[..., 1, 0] - c[..., 0, 1]], dim=-1),
            torch.stack([c[..., 2, 1] - c[..., 1, 2], 1 + 2 * c[..., 0, 0] - tr,
                         c[..., 0, 1] + c[..., 1, 0], c[..., 0, 2] + c[..., 2, 0]], dim=-1),
            torch.stack([c[..., 0, 2] - c[..., 2, 0], c[..., 0, 1] + c[..., 1, 0],
                         1 + 2 * c[..., 1, 1] - tr, c[..., 1, 2] + c[..., 2, 1]], dim=-1),
            torch.stack([c[..., 1, 0] - c[..., 0, 1], c[..., 0, 2] + c[..., 2, 0],
                         c[..., 1, 2] + c[..., 2, 1], 1 + 2 * c[..., 2, 2] - tr], dim=-1),
        ],
        dim=-2,
    )  # row k = 4 q_k q (largest diagonal gives the best conditioning)
    diag = torch.stack([tr, c[..., 0, 0], c[..., 1, 1], c[..., 2, 2]], dim=-1)
    best = diag.argmax(-1, keepdim=True)
    row = torch.gather(cands, -2, best.unsqueeze(-1).expand(*best.shape, 4)).squeeze(-2)
    return quat_normalize(row)


def rotvec_from_dcm(c: torch.Tensor) -> torch.Tensor:
    """Rotation vector ``φ`` with ``exp([φ×]) = C`` (angle below π), ``(..., 3)``."""
    q = quat_from_dcm(c)
    vec = q[..., 1:]
    s = torch.linalg.vector_norm(vec, dim=-1, keepdim=True)
    angle = 2.0 * torch.atan2(s, q[..., :1])
    small = s < 1e-12
    scale = torch.where(small, 2.0 / q[..., :1], angle / torch.where(small, 1.0, s))
    return scale * vec


def dcm_from_euler(euler: torch.Tensor) -> torch.Tensor:
    """``C_b^n = R_z(yaw) R_y(pitch) R_x(roll)`` from ``(..., 3)`` roll, pitch, yaw (rad)."""
    cr, sr = torch.cos(euler[..., 0]), torch.sin(euler[..., 0])
    cp, sp = torch.cos(euler[..., 1]), torch.sin(euler[..., 1])
    cy, sy = torch.cos(euler[..., 2]), torch.sin(euler[..., 2])
    return torch.stack(
        [
            torch.stack([cp * cy, -cr * sy + sr * sp * cy, sr * sy + cr * sp * cy], dim=-1),
            torch.stack([cp * sy, cr * cy + sr * sp * sy, -sr * cy + cr * sp * sy], dim=-1),
            torch.stack([-sp, sr * cp, cr * cp], dim=-1),
        ],
        dim=-2,
    )


def quat_from_euler(euler: torch.Tensor) -> torch.Tensor:
    """Quaternion of ``(..., 3)`` roll, pitch, yaw (rad)."""
    return quat_from_dcm(dcm_from_euler(euler))


def euler_from_dcm(c: torch.Tensor) -> torch.Tensor:
    """Roll, pitch, yaw ``(..., 3)`` (rad) of ``C_b^n`` (pitch in [−π/2, π/2])."""
    roll = torch.atan2(c[..., 2, 1], c[..., 2, 2])
    pitch = torch.asin(torch.clamp(-c[..., 2, 0], -1.0, 1.0))
    yaw = torch.atan2(c[..., 1, 0], c[..., 0, 0])
    return torch.stack([roll, pitch, yaw], dim=-1)
