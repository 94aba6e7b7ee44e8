"""Batched strapdown INS mechanisation in the NED frame on the WGS-84 ellipsoid.

The continuous strapdown equations (SEEDS 003, eqs. 1–2 before perturbation; Groves ch. 5,
Titterton & Weston ch. 3)::

    L̇ = v_N / (R_M + h),   λ̇ = v_E / ((R_N + h) cos L),   ḣ = −v_D
    v̇ⁿ = C_b^n f^b − (2 ω_ieⁿ + ω_enⁿ) × vⁿ + gⁿ
    q̇ = ½ q ⊗ [0, ω_nb^b],   ω_nb^b = ω_ib^b − C_n^b (ω_ieⁿ + ω_enⁿ)

The IMU delivers instantaneous angular rate ``ω_ib^b`` (rad/s) and specific force ``f^b``
(m/s²) at its sample epochs; between two samples both are taken as linear in time.

`strapdown_step` is the production algorithm (the increment form used by KF-GINS
and PSINS, written for sampled rates): body rotation vector with the coning term
``φ = Δθ + (ω_k × ω_{k+1}) Δt²/12``; body velocity increment with the rotation and
sculling terms exact to second order for linear inputs; navigation-frame rotation
``ζ = ω_inⁿ Δt``; ``q_{k+1} = q(−ζ) ⊗ q_k ⊗ q(φ)``; velocity
``v_{k+1} = v_k + (I − ½[ζ×]) C_b^n Δv_b + (gⁿ − (2ω_ie + ω_en) × v_mid) Δt``; position by
the trapezoid of the velocities. `strapdown_step_rk4` integrates the continuous
equations above with classical RK4 (a slower reference for tests).
"""

from __future__ import annotations

import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.ins.earth import (
    WGS84_A,
    WGS84_E2,
    WGS84_OMEGA,
    earth_rate_ned,
    normal_gravity,
    radii,
    transport_rate_ned,
)
from neuralmap.ins.rotation import quat_normalize
from neuralmap.ins.state import NavState

__all__ = ["mechanize", "navigation_derivative", "strapdown_step", "strapdown_step_rk4"]


def _cross(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    return torch.linalg.cross(a, b, dim=-1)


def navigation_derivative(
    y: torch.Tensor, gyro: torch.Tensor, accel: torch.Tensor
) -> torch.Tensor:
    """Time derivative of the packed navigation state.

    Args:
        y: ``(N, 10)`` packed state (see `NavState`).
        gyro: ``(N, 3)`` or ``(3,)`` angular rate ``ω_ib^b`` (rad/s).
        accel: ``(N, 3)`` or ``(3,)`` specific force ``f^b`` (m/s²).

    Returns:
        ``(N, 10)`` ``dy/dt``.
    """
    lat, h, vel, q = y[:, 0], y[:, 2], y[:, 3:6], y[:, 6:10]
    rm, rn = radii(lat)
    q0, q1, q2, q3 = q.unbind(-1)
    # C_b^n rows from the quaternion (not normalised inside the step; RK4 keeps |q| ≈ 1).
    c00 = q0 * q0 + q1 * q1 - q2 * q2 - q3 * q3
    c01 = 2 * (q1 * q2 - q0 * q3)
    c02 = 2 * (q1 * q3 + q0 * q2)
    c10 = 2 * (q1 * q2 + q0 * q3)
    c11 = q0 * q0 - q1 * q1 + q2 * q2 - q3 * q3
    c12 = 2 * (q2 * q3 - q0 * q1)
    c20 = 2 * (q1 * q3 - q0 * q2)
    c21 = 2 * (q2 * q3 + q0 * q1)
    c22 = q0 * q0 - q1 * q1 - q2 * q2 + q3 * q3
    f = accel.expand_as(vel)
    fx, fy, fz = f[:, 0], f[:, 1], f[:, 2]
    fn = torch.stack(
        [c00 * fx + c01 * fy + c02 * fz, c10 * fx + c11 * fy + c12 * fz,
         c20 * fx + c21 * fy + c22 * fz], dim=-1)
    w_ie = earth_rate_ned(lat)
    w_en = transport_rate_ned(lat, h, vel)
    w_in = w_ie + w_en
    g = normal_gravity(lat, h)
    vdot = fn - _cross(2.0 * w_ie + w_en, vel)
    vdot = torch.cat([vdot[:, :2], (vdot[:, 2] + g)[:, None]], dim=1)
    wx, wy, wz = w_in[:, 0], w_in[:, 1], w_in[:, 2]
    w = gyro.expand_as(vel)
    # ω_nb^b = ω_ib^b − C_n^b ω_in^n  (C_n^b = (C_b^n)ᵀ)
    bx = w[:, 0] - (c00 * wx + c10 * wy + c20 * wz)
    by = w[:, 1] - (c01 * wx + c11 * wy + c21 * wz)
    bz = w[:, 2] - (c02 * wx + c12 * wy + c22 * wz)
    qdot = 0.5 * torch.stack(
        [-q1 * bx - q2 * by - q3 * bz, q0 * bx + q2 * bz - q3 * by,
         q0 * by - q1 * bz + q3 * bx, q0 * bz + q1 * by - q2 * bx], dim=-1)
    pos_dot = torch.stack(
        [vel[:, 0] / (rm + h), vel[:, 1] / ((rn + h) * torch.cos(lat)), -vel[:, 2]], dim=-1)
    return torch.cat([pos_dot, vdot, qdot], dim=1)


def strapdown_step_rk4(
    y: torch.Tensor,
    gyro0: torch.Tensor,
    accel0: torch.Tensor,
    gyro1: torch.Tensor,
    accel1: torch.Tensor,
    dt: float,
) -> torch.Tensor:
    """One RK4 step of the continuous equations from IMU sample k to k+1 (reference).

    Args:
        y: ``(N, 10)`` packed state at sample k.
        gyro0, accel0: ``(N, 3)`` or ``(3,)`` IMU sample k (rad/s, m/s²).
        gyro1, accel1: IMU sample k+1.
        dt: Sample interval (s).

    Returns:
        ``(N, 10)`` state at sample k+1 (quaternion renormalised).
    """
    gm, am = 0.5 * (gyro0 + gyro1), 0.5 * (accel0 + accel1)
    k1 = navigation_derivative(y, gyro0, accel0)
    k2 = navigation_derivative(y + (0.5 * dt) * k1, gm, am)
    k3 = navigation_derivative(y + (0.5 * dt) * k2, gm, am)
    k4 = navigation_derivative(y + dt * k3, gyro1, accel1)
    out = y + (dt / 6.0) * (k1 + 2.0 * (k2 + k3) + k4)
    return torch.cat([out[:, :6], quat_normalize(out[:, 6:])], dim=1)


def _qmul(p: torch.Tensor, q: torch.Tensor) -> torch.Tensor:
    """Hamilton product with vector operations (fewer kernels than component form)."""
    p0, pv = p[:, :1], p[:, 1:]
    q0, qv = q[:, :1], q[:, 1:]
    return torch.cat(
        [p0 * q0 - (pv * qv).sum(-1, keepdim=True), p0 * qv + q0 * pv + _cross(pv, qv)], dim=1
    )


def _rotate(q: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """``C(q) v`` for unit quaternions: ``v + q0 t + u × t``, ``t = 2 u × v``."""
    u = q[:, 1:]
    t = 2.0 * _cross(u, v)
    return v + q[:, :1] * t + _cross(u, t)


def _rotvec_quat(phi: torch.Tensor) -> torch.Tensor:
    """Quaternion of rotation vectors ``(N, 3)`` (series below 1e-4 rad)."""
    angle2 = (phi * phi).sum(-1, keepdim=True)
    angle = torch.sqrt(angle2)
    small = angle < 1e-4
    safe = torch.where(small, 1.0, angle)
    scale = torch.where(small, 0.5 - angle2 / 48.0, torch.sin(0.5 * safe) / safe)
    return torch.cat([torch.cos(0.5 * angle), scale * phi], dim=1)


def strapdown_step(
    y: torch.Tensor,
    gyro0: torch.Tensor,
    accel0: torch.Tensor,
    gyro1: torch.Tensor,
    accel1: torch.Tensor,
    dt: float,
) -> torch.Tensor:
    """One mechanisation step from IMU sample k to k+1 (increment algorithm).

    Args:
        y: ``(N, 10)`` packed state at sample k.
        gyro0, accel0: ``(N, 3)`` or ``(3,)`` IMU sample k (rad/s, m/s²).
        gyro1, accel1: IMU sample k+1.
        dt: Sample interval (s).

    Returns:
        ``(N, 10)`` state at sample k+1 (quaternion renormalised).
    """
    n = y.shape[0]
    lat, lon, h = y[:, 0], y[:, 1], y[:, 2]
    v, q = y[:, 3:6], y[:, 6:10]
    w0, w1 = gyro0.expand(n, 3), gyro1.expand(n, 3)
    f0, f1 = accel0.expand(n, 3), accel1.expand(n, 3)
    # Earth model at sample k (changes negligibly within one IMU interval)
    s, c = torch.sin(lat), torch.cos(lat)
    w = 1.0 - WGS84_E2 * s * s
    rn = WGS84_A / torch.sqrt(w)
    rm_h = rn * ((1.0 - WGS84_E2) / w) + h
    rn_h = rn + h
    s2 = s * s
    g = (9.7803267715 * (1.0 + 0.0052790414 * s2 + 0.0000232718 * s2 * s2)
         + h * (0.0000000043977311 * s2 - 0.0000030876910891) + 0.0000000000007211 * h * h)
    ve_rn = v[:, 1] / rn_h
    w_ie = torch.stack([WGS84_OMEGA * c, torch.zeros_like(c), -WGS84_OMEGA * s], dim=1)
    w_en = torch.stack([ve_rn, -v[:, 0] / rm_h, -ve_rn * s / c], dim=1)
    zeta = (w_ie + w_en) * dt
    # body increments, coning, rotation + sculling (exact to 2nd order for linear inputs)
    dw, df = w1 - w0, f1 - f0
    phi = (w0 + 0.5 * dw) * dt + _cross(w0, w1) * (dt * dt / 12.0)
    dv_b = (f0 + 0.5 * df) * dt + (
        _cross(w0, 0.5 * f0 + df / 3.0) + _cross(dw, f0 / 6.0 + 0.125 * df)
    ) * (dt * dt)
    dv_n = _rotate(q, dv_b)
    dv_n = dv_n - 0.5 * _cross(zeta, dv_n)
    g_dt = torch.stack([torch.zeros_like(g), torch.zeros_like(g), g * dt], dim=1)
    v_mid = v + 0.5 * (dv_n + g_dt)
    v_new = v + dv_n + g_dt - _cross(2.0 * w_ie + w_en, v_mid) * dt
    # attitude: q(−ζ) ⊗ q_k ⊗ q(φ)
    q_new = _qmul(_qmul(_rotvec_quat(-zeta), q), _rotvec_quat(phi))
    q_new = q_new * torch.rsqrt((q_new * q_new).sum(1, keepdim=True))
    # position: trapezoid of the velocities, mid-interval radii
    v_avg = 0.5 * (v + v_new)
    h_new = h - v_avg[:, 2] * dt
    h_mid = 0.5 * (h + h_new)
    lat_new = lat + v_avg[:, 0] * dt / (rm_h + (h_mid - h))
    lon_new = lon + v_avg[:, 1] * dt / ((rn_h + (h_mid - h)) * torch.cos(0.5 * (lat + lat_new)))
    return torch.cat(
        [lat_new[:, None], lon_new[:, None], h_new[:, None], v_new, q_new], dim=1
    )


def mechanize(
    initial: NavState,
    gyro: torch.Tensor,
    accel: torch.Tensor,
    dt: float,
    *,
    every: int = 1,
    hold_height: bool = False,
) -> torch.Tensor:
    """Runs the mechanisation over a whole IMU record (pure INS, no aiding).

    Args:
        initial: N initial solutions at the first IMU sample.
        gyro: ``(K, 3)`` shared or ``(N, K, 3)`` per-run angular rates (rad/s).
        accel: ``(K, 3)`` or ``(N, K, 3)`` specific forces (m/s²).
        dt: IMU interval (s), > 0.
        every: Keep every ``every``-th state in the output.
        hold_height: Ideal height aiding: keep the initial height and zero vertical velocity
            after every step. The free-inertial vertical channel is unstable (error growth
            ``∝ e^{t/τ}``, ``τ = √(R/2g)`` ≈ 9.5 min), so runs of hours need it.

    Returns:
        ``(N, K', 10)`` packed states at samples ``0, every, 2·every, …`` (K' = ⌈K/every⌉).

    Raises:
        NeuralMapError: Shape mismatch or non-positive ``dt``.
    """
    if not dt > 0:
        raise NeuralMapError(f"mechanize: 'dt' = {dt!r} must be > 0 (IMU interval in s).")
    if gyro.shape != accel.shape or gyro.shape[-1] != 3 or gyro.ndim not in (2, 3):
        raise NeuralMapError(
            f"mechanize: 'gyro' {tuple(gyro.shape)} and 'accel' {tuple(accel.shape)} must both "
            "be (K, 3) or (N, K, 3)."
        )
    y = initial.packed
    if gyro.ndim == 3 and gyro.shape[0] != y.shape[0]:
        raise NeuralMapError(
            f"mechanize: per-run IMU has {gyro.shape[0]} runs but the initial state has "
            f"{y.shape[0]}."
        )
    gyro = gyro.to(y)
    accel = accel.to(y)
    k_total = gyro.shape[-2]
    out = [y]
    for k in range(k_total - 1):
        y = strapdown_step(
            y, gyro[..., k, :], accel[..., k, :], gyro[..., k + 1, :], accel[..., k + 1, :], dt
        )
        if hold_height:
            y = torch.cat([y[:, :2], initial.packed[:, 2:3], y[:, 3:5],
                           torch.zeros_like(y[:, 5:6]), y[:, 6:]], dim=1)
        if (k + 1) % every == 0:
            out.append(y)
    return torch.stack(out, dim=1)
