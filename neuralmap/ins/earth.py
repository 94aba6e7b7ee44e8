"""WGS-84 Earth model in the north-east-down (NED) local-level frame.

Radii of curvature, normal gravity, Earth rate and transport rate as used by the strapdown
mechanisation and the error-state model of SEEDS 003 (the standard forms of the GNSS/INS
literature, e.g. Groves, *Principles of GNSS, Inertial, and Multisensor Integrated
Navigation Systems*, ch. 2 and 5; the same formulas as the KF-GINS mechanisation).

Conventions: latitude ``lat`` and longitude ``lon`` in radians, ellipsoidal height ``h``
in metres; NED vectors ``(..., 3)`` ordered north, east, down. Every function broadcasts
over leading dimensions and keeps the dtype/device of its inputs.
"""

from __future__ import annotations

import math

import torch

__all__ = [
    "WGS84_A",
    "WGS84_E2",
    "WGS84_F",
    "WGS84_OMEGA",
    "earth_rate_ned",
    "gravity_ned",
    "normal_gravity",
    "position_offset_ned",
    "radii",
    "schuler_period",
    "transport_rate_ned",
]

#: Semi-major axis (m).
WGS84_A = 6378137.0
#: Flattening.
WGS84_F = 1.0 / 298.257223563
#: First eccentricity squared.
WGS84_E2 = WGS84_F * (2.0 - WGS84_F)
#: Earth rotation rate (rad/s).
WGS84_OMEGA = 7.2921151467e-5


def radii(lat: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Meridian and prime-vertical radii of curvature.

    ``R_M = a(1−e²)/(1−e² sin²L)^{3/2}``, ``R_N = a/(1−e² sin²L)^{1/2}``.

    Args:
        lat: ``(...)`` geodetic latitude (rad).

    Returns:
        ``(R_M, R_N)``, each ``(...)`` metres.
    """
    s2 = torch.sin(lat).square()
    w = 1.0 - WGS84_E2 * s2
    rn = WGS84_A / torch.sqrt(w)
    rm = rn * (1.0 - WGS84_E2) / w
    return rm, rn


def normal_gravity(lat: torch.Tensor, h: torch.Tensor) -> torch.Tensor:
    """Magnitude of WGS-84 normal gravity (Somigliana with a height correction).

    ``g = 9.7803267715 (1 + 0.0052790414 s² + 0.0000232718 s⁴)
    + h (0.0000000043977311 s² − 0.0000030876910891) + 0.0000000000007211 h²``,
    ``s = sin L`` (the KF-GINS / Groves form; gravity including the centrifugal part).

    Args:
        lat: ``(...)`` latitude (rad).
        h: ``(...)`` ellipsoidal height (m).

    Returns:
        ``(...)`` gravity magnitude (m/s²), pointing down the ellipsoid normal.
    """
    s2 = torch.sin(lat).square()
    g0 = 9.7803267715 * (1.0 + 0.0052790414 * s2 + 0.0000232718 * s2.square())
    return g0 + h * (0.0000000043977311 * s2 - 0.0000030876910891) + 0.0000000000007211 * h * h


def gravity_ned(lat: torch.Tensor, h: torch.Tensor) -> torch.Tensor:
    """Normal gravity vector ``g^n = [0, 0, g]`` (down positive), ``(..., 3)``."""
    g = normal_gravity(lat, h)
    zero = torch.zeros_like(g)
    return torch.stack([zero, zero, g], dim=-1)


def earth_rate_ned(lat: torch.Tensor) -> torch.Tensor:
    """Earth rate in the NED frame ``ω_ie^n = Ω [cos L, 0, −sin L]``, ``(..., 3)``."""
    return torch.stack(
        [WGS84_OMEGA * torch.cos(lat), torch.zeros_like(lat), -WGS84_OMEGA * torch.sin(lat)],
        dim=-1,
    )


def transport_rate_ned(
    lat: torch.Tensor, h: torch.Tensor, vel: torch.Tensor
) -> torch.Tensor:
    """Transport rate ``ω_en^n = [v_E/(R_N+h), −v_N/(R_M+h), −v_E tan L/(R_N+h)]``.

    Args:
        lat: ``(...)`` latitude (rad).
        h: ``(...)`` height (m).
        vel: ``(..., 3)`` NED velocity (m/s).

    Returns:
        ``(..., 3)`` rad/s.
    """
    rm, rn = radii(lat)
    ve_rn = vel[..., 1] / (rn + h)
    return torch.stack([ve_rn, -vel[..., 0] / (rm + h), -ve_rn * torch.tan(lat)], dim=-1)


def position_offset_ned(
    lat: torch.Tensor,
    lon: torch.Tensor,
    h: torch.Tensor,
    lat_ref: torch.Tensor,
    lon_ref: torch.Tensor,
    h_ref: torch.Tensor,
) -> torch.Tensor:
    """Small geodetic differences as NED metres about a reference point (first order).

    ``δr = [(R_M+h) δL, (R_N+h) cos L δλ, −δh]`` with the radii at the reference; exact to
    first order in the offset (use for errors of metres to kilometres, not for long baselines).

    Returns:
        ``(..., 3)`` metres, ``position − reference``.
    """
    rm, rn = radii(lat_ref)
    return torch.stack(
        [
            (lat - lat_ref) * (rm + h_ref),
            (lon - lon_ref) * (rn + h_ref) * torch.cos(lat_ref),
            -(h - h_ref),
        ],
        dim=-1,
    )


def schuler_period(lat: float, h: float = 0.0) -> float:
    """Schuler period ``2π √(R/g)`` with ``R = √(R_M R_N)`` at a latitude (s)."""
    t = torch.tensor(lat, dtype=torch.float64)
    rm, rn = radii(t)
    radius = float(torch.sqrt(rm * rn)) + h
    return 2.0 * math.pi * math.sqrt(radius / float(normal_gravity(t, torch.tensor(h))))
