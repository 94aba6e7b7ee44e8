"""Compiled loops of the GNSS/INS hot path: strapdown over a block of IMU samples, bias walk.

The batched torch mechanisation (`strapdown_step`)
costs about a hundred small tensor operations per IMU step, so at 200 Hz over a few
hundred runs the time goes into per-operation overhead, not arithmetic. Between two
GNSS epochs nothing but the IMU samples enters the mechanisation, so the whole block of
samples is integrated in one call here: a loop over runs and samples compiled by numba
(optional extra ``fast``: ``pip install 'neuralmap[fast]'``). Without numba the same
block interface runs the torch step sample by sample (bit-identical to the per-step
filter).

The arithmetic is `strapdown_step` operation by
operation (same expression order, no fused multiply-add, no fast-math); only ``sin``,
``cos`` come from the C library instead of torch's vectorised ones, so results agree with
the torch step to a few units in the last place per step (the tests check 1e-12 relative
over a drive).
"""

from __future__ import annotations

import math

import numpy as np
import torch

from neuralmap.ins.earth import WGS84_A, WGS84_E2, WGS84_OMEGA

__all__ = ["HAVE_NUMBA", "gauss_markov_block", "mechanize_block"]

try:  # optional accelerator
    import numba

    HAVE_NUMBA = True
except ImportError:  # pragma: no cover - exercised where numba is missing
    numba = None
    HAVE_NUMBA = False

_LAT_LIMIT = math.radians(89.0)


def njit(fn):  # type: ignore[no-untyped-def]
    if numba is None:
        return fn
    return numba.njit(cache=True, fastmath=False, error_model="numpy")(fn)


@njit
def _cross(a0, a1, a2, b0, b1, b2):  # type: ignore[no-untyped-def]
    return a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0


@njit
def _rotvec_quat(p0, p1, p2):  # type: ignore[no-untyped-def]
    angle2 = (p0 * p0 + p1 * p1) + p2 * p2
    angle = math.sqrt(angle2)
    if angle < 1e-4:
        scale = 0.5 - angle2 / 48.0
    else:
        scale = math.sin(0.5 * angle) / angle
    return math.cos(0.5 * angle), scale * p0, scale * p1, scale * p2


@njit
def _qmul(p0, p1, p2, p3, q0, q1, q2, q3):  # type: ignore[no-untyped-def]
    c0, c1, c2 = _cross(p1, p2, p3, q1, q2, q3)
    return (p0 * q0 - ((p1 * q1 + p2 * q2) + p3 * q3),
            (p0 * q1 + q0 * p1) + c0, (p0 * q2 + q0 * p2) + c1, (p0 * q3 + q0 * p3) + c2)


@njit
def mechanize_step_nb(y, w0, f0, w1, f1, dt):  # type: ignore[no-untyped-def]
    """One increment-algorithm step of one run, in place on ``y`` (10,)."""
    lat, lon, h = y[0], y[1], y[2]
    v0, v1, v2 = y[3], y[4], y[5]
    q0, q1, q2, q3 = y[6], y[7], y[8], y[9]
    s = math.sin(lat)
    c = math.cos(lat)
    w = 1.0 - WGS84_E2 * s * s
    rn = WGS84_A / math.sqrt(w)
    rm_h = rn * ((1.0 - WGS84_E2) / w) + h
    rn_h = rn + h
    s2 = s * s
    g = (9.7803267715 * (1.0 + 0.0052790414 * s2 + 0.0000232718 * s2 * s2)
         + h * (0.0000000043977311 * s2 - 0.0000030876910891) + 0.0000000000007211 * h * h)
    ve_rn = v1 / rn_h
    ie0, ie1, ie2 = WGS84_OMEGA * c, 0.0, -WGS84_OMEGA * s
    en0, en1, en2 = ve_rn, -v0 / rm_h, -ve_rn * s / c
    z0, z1, z2 = (ie0 + en0) * dt, (ie1 + en1) * dt, (ie2 + en2) * dt
    # body increments: coning, rotation + sculling
    dw0, dw1, dw2 = w1[0] - w0[0], w1[1] - w0[1], w1[2] - w0[2]
    df0, df1, df2 = f1[0] - f0[0], f1[1] - f0[1], f1[2] - f0[2]
    k12 = dt * dt / 12.0
    cw0, cw1, cw2 = _cross(w0[0], w0[1], w0[2], w1[0], w1[1], w1[2])
    ph0 = (w0[0] + 0.5 * dw0) * dt + cw0 * k12
    ph1 = (w0[1] + 0.5 * dw1) * dt + cw1 * k12
    ph2 = (w0[2] + 0.5 * dw2) * dt + cw2 * k12
    a0, a1, a2 = _cross(w0[0], w0[1], w0[2], 0.5 * f0[0] + df0 / 3.0, 0.5 * f0[1] + df1 / 3.0,
                        0.5 * f0[2] + df2 / 3.0)
    b0, b1, b2 = _cross(dw0, dw1, dw2, f0[0] / 6.0 + 0.125 * df0, f0[1] / 6.0 + 0.125 * df1,
                        f0[2] / 6.0 + 0.125 * df2)
    dtt = dt * dt
    db0 = (f0[0] + 0.5 * df0) * dt + (a0 + b0) * dtt
    db1 = (f0[1] + 0.5 * df1) * dt + (a1 + b1) * dtt
    db2 = (f0[2] + 0.5 * df2) * dt + (a2 + b2) * dtt
    # dv_n = C(q) dv_b = v + q0 t + u × t, t = 2 u × v
    t0, t1, t2 = _cross(q1, q2, q3, db0, db1, db2)
    t0, t1, t2 = 2.0 * t0, 2.0 * t1, 2.0 * t2
    u0, u1, u2 = _cross(q1, q2, q3, t0, t1, t2)
    n0, n1, n2 = (db0 + q0 * t0) + u0, (db1 + q0 * t1) + u1, (db2 + q0 * t2) + u2
    x0, x1, x2 = _cross(z0, z1, z2, n0, n1, n2)
    n0, n1, n2 = n0 - 0.5 * x0, n1 - 0.5 * x1, n2 - 0.5 * x2
    g_dt = g * dt
    m0, m1, m2 = v0 + 0.5 * (n0 + 0.0), v1 + 0.5 * (n1 + 0.0), v2 + 0.5 * (n2 + g_dt)
    c0, c1, c2 = _cross(2.0 * ie0 + en0, 2.0 * ie1 + en1, 2.0 * ie2 + en2, m0, m1, m2)
    nv0 = (v0 + n0) + 0.0 - c0 * dt
    nv1 = (v1 + n1) + 0.0 - c1 * dt
    nv2 = (v2 + n2) + g_dt - c2 * dt
    # attitude: q(−ζ) ⊗ q ⊗ q(φ)
    r0, r1, r2, r3 = _rotvec_quat(-z0, -z1, -z2)
    p0, p1, p2, p3 = _qmul(r0, r1, r2, r3, q0, q1, q2, q3)
    e0, e1, e2, e3 = _rotvec_quat(ph0, ph1, ph2)
    p0, p1, p2, p3 = _qmul(p0, p1, p2, p3, e0, e1, e2, e3)
    inv = 1.0 / math.sqrt(((p0 * p0 + p1 * p1) + p2 * p2) + p3 * p3)
    # position: trapezoid of the velocities, mid-interval radii
    va0, va1, va2 = 0.5 * (v0 + nv0), 0.5 * (v1 + nv1), 0.5 * (v2 + nv2)
    h_new = h - va2 * dt
    h_mid = 0.5 * (h + h_new)
    lat_new = lat + va0 * dt / (rm_h + (h_mid - h))
    lon_new = lon + va1 * dt / ((rn_h + (h_mid - h)) * math.cos(0.5 * (lat + lat_new)))
    y[0], y[1], y[2] = lat_new, lon_new, h_new
    y[3], y[4], y[5] = nv0, nv1, nv2
    y[6], y[7], y[8], y[9] = p0 * inv, p1 * inv, p2 * inv, p3 * inv


@njit
def _mechanize_block_nb(y, y_good, failed, gyro, accel, bg, ba, dt, stops, out):  # type: ignore[no-untyped-def]
    n_runs, n_samples = gyro.shape[0], gyro.shape[1]
    w0 = np.empty(3)
    f0 = np.empty(3)
    w1 = np.empty(3)
    f1 = np.empty(3)
    for r in range(n_runs):
        yr = y[r]
        stop = 0
        for i in range(3):
            w1[i] = gyro[r, 0, i] - bg[r, i]
            f1[i] = accel[r, 0, i] - ba[r, i]
        for k in range(1, n_samples):
            for i in range(3):
                w0[i], f0[i] = w1[i], f1[i]
                w1[i] = gyro[r, k, i] - bg[r, i]
                f1[i] = accel[r, k, i] - ba[r, i]
            mechanize_step_nb(yr, w0, f0, w1, f1, dt)
            if stop < stops.shape[0] and stops[stop] == k:
                bad = False
                for i in range(10):
                    if not math.isfinite(yr[i]):
                        bad = True
                if not bad and abs(yr[0]) >= _LAT_LIMIT:
                    bad = True
                if bad:
                    failed[r] = True
                    for i in range(10):
                        yr[i] = y_good[r, i]
                else:
                    for i in range(10):
                        y_good[r, i] = yr[i]
                for i in range(10):
                    out[r, stop, i] = yr[i]
                stop += 1


@njit
def _gauss_markov_nb(gm, phi, drive_sigma, drive, hist):  # type: ignore[no-untyped-def]
    n_steps, n_runs, width = drive.shape
    for t in range(n_steps):
        for r in range(n_runs):
            for i in range(width):
                hist[t, r, i] = gm[r, i]
                gm[r, i] = phi[i] * gm[r, i] + drive_sigma[i] * drive[t, r, i]


def gauss_markov_block(
    gm: torch.Tensor, phi: torch.Tensor, drive_sigma: torch.Tensor, drive: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """First-order Gauss–Markov walk over a block: ``b_{t+1} = φ b_t + σ_d w_t``.

    Args:
        gm: ``(N, c)`` values at the first sample.
        phi: ``(c,)`` per-column factors ``e^{−Δt/τ}``.
        drive_sigma: ``(c,)`` per-column driving σ.
        drive: ``(L, N, c)`` standard normal draws.

    Returns:
        ``(values at each of the L samples (L, N, c), value after the block (N, c))``,
        the same numbers as L steps of ``φ·b + σ_d·w`` on tensors.
    """
    if HAVE_NUMBA and gm.device.type == "cpu" and gm.dtype == torch.float64:
        state = gm.detach().numpy().copy()
        hist = np.empty(tuple(drive.shape))
        _gauss_markov_nb(state, phi.numpy(), drive_sigma.numpy(), drive.numpy(), hist)
        return torch.from_numpy(hist), torch.from_numpy(state)
    out = []
    for t in range(drive.shape[0]):
        out.append(gm)
        gm = phi * gm + drive_sigma * drive[t]
    return torch.stack(out), gm


def mechanize_block(
    y: torch.Tensor,
    y_good: torch.Tensor,
    failed: torch.Tensor,
    gyro: torch.Tensor,
    accel: torch.Tensor,
    bg: torch.Tensor,
    ba: torch.Tensor,
    dt: float,
    stops: list[int],
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Strapdown over a block of raw IMU samples with bias correction and guards.

    Integrates from sample 0 to sample L of the block on ``gyro − bg``, ``accel − ba``;
    at each sample index in ``stops`` a run whose solution is non-finite or at
    ``|lat| ≥ 89°`` gets its last good solution back and is marked in ``failed`` (in
    place), else its solution becomes the last good one.

    Args:
        y: ``(N, 10)`` packed states at sample 0.
        y_good: ``(N, 10)`` last good states.
        failed: ``(N,)`` bool (updated in place).
        gyro, accel: ``(N, L + 1, 3)`` raw measured samples.
        bg, ba: ``(N, 3)`` bias estimates subtracted from the samples.
        dt: IMU interval (s).
        stops: Increasing sample indices in ``1..L``; the last one must be L.

    Returns:
        ``(states at the stops (N, S, 10), final y, final y_good)``.
    """
    if HAVE_NUMBA and y.device.type == "cpu" and y.dtype == torch.float64:
        yn = y.detach().numpy().copy()
        good = y_good.detach().numpy().copy()
        flags = failed.numpy()
        out = np.empty((y.shape[0], len(stops), 10))
        _mechanize_block_nb(yn, good, flags, gyro.detach().contiguous().numpy(),
                            accel.detach().contiguous().numpy(), bg.detach().numpy(),
                            ba.detach().numpy(), float(dt), np.asarray(stops, dtype=np.int64),
                            out)
        return torch.from_numpy(out), torch.from_numpy(yn), torch.from_numpy(good)
    from neuralmap.ins.mechanization import strapdown_step

    kept = []
    wanted = set(stops)
    w1, f1 = gyro[:, 0] - bg, accel[:, 0] - ba
    for k in range(1, gyro.shape[1]):
        w0, f0 = w1, f1
        w1, f1 = gyro[:, k] - bg, accel[:, k] - ba
        y = strapdown_step(y, w0, f0, w1, f1, dt)
        if k in wanted:
            bad = ~torch.isfinite(y).all(1) | (y[:, 0].abs() >= _LAT_LIMIT)
            if bool(bad.any()):
                failed |= bad
                y = torch.where(bad[:, None], y_good, y)
            y_good = y
            kept.append(y)
    return torch.stack(kept, dim=1), y, y_good


@njit
def _skew_into(M, r, c, x, y, z, sign):  # type: ignore[no-untyped-def]
    M[r, c + 1], M[r, c + 2] = -z * sign, y * sign
    M[r + 1, c], M[r + 1, c + 2] = z * sign, -x * sign
    M[r + 2, c], M[r + 2, c + 1] = -y * sign, x * sign


@njit
def error_model_nb(state, accel, qc, tau_g, tau_a, F, G, C, fn):  # type: ignore[no-untyped-def]
    """F and G Q_c Gᵀ (15, 15) of one solution (as error_dynamics / continuous_noise);
    ``C`` (3, 3) and ``fn`` (3,) are scratch buffers."""
    lat, h = state[0], state[2]
    v0, v1 = state[3], state[4]
    q0, q1, q2, q3 = state[6], state[7], state[8], state[9]
    C[0, 0] = q0 * q0 + q1 * q1 - q2 * q2 - q3 * q3
    C[0, 1] = 2 * (q1 * q2 - q0 * q3)
    C[0, 2] = 2 * (q1 * q3 + q0 * q2)
    C[1, 0] = 2 * (q1 * q2 + q0 * q3)
    C[1, 1] = q0 * q0 - q1 * q1 + q2 * q2 - q3 * q3
    C[1, 2] = 2 * (q2 * q3 - q0 * q1)
    C[2, 0] = 2 * (q1 * q3 - q0 * q2)
    C[2, 1] = 2 * (q2 * q3 + q0 * q1)
    C[2, 2] = q0 * q0 - q1 * q1 - q2 * q2 + q3 * q3
    s = math.sin(lat)
    s2 = s * s
    w = 1.0 - WGS84_E2 * s2
    rn = WGS84_A / math.sqrt(w)
    rm = rn * (1.0 - WGS84_E2) / w
    g = (9.7803267715 * (1.0 + 0.0052790414 * s2 + 0.0000232718 * s2 * s2)
         + h * (0.0000000043977311 * s2 - 0.0000030876910891) + 0.0000000000007211 * h * h)
    ie0, ie1, ie2 = WGS84_OMEGA * math.cos(lat), 0.0, -WGS84_OMEGA * s
    ve_rn = v1 / (rn + h)
    en0, en1, en2 = ve_rn, -v0 / (rm + h), -ve_rn * math.tan(lat)
    for i in range(3):
        fn[i] = C[i, 0] * accel[0] + C[i, 1] * accel[1] + C[i, 2] * accel[2]
    F[:, :] = 0.0
    _skew_into(F, 0, 0, en0, en1, en2, -1.0)
    for i in range(3):
        F[i, 3 + i] = 1.0
        F[9 + i, 9 + i] = -1.0 / tau_g
        F[12 + i, 12 + i] = -1.0 / tau_a
        for j in range(3):
            F[3 + i, 12 + j] = -C[i, j]
            F[6 + i, 9 + j] = C[i, j]
    F[3, 0] = -g / (rm + h)
    F[4, 1] = -g / (rn + h)
    F[5, 2] = 2.0 * g / (math.sqrt(rm * rn) + h)
    _skew_into(F, 3, 3, 2.0 * ie0 + en0, 2.0 * ie1 + en1, 2.0 * ie2 + en2, -1.0)
    _skew_into(F, 3, 6, fn[0], fn[1], fn[2], 1.0)
    _skew_into(F, 6, 6, ie0 + en0, ie1 + en1, ie2 + en2, -1.0)
    G[:, :] = 0.0
    for i in range(3):
        for j in range(3):
            a = 0.0
            b = 0.0
            for k in range(3):
                a += C[i, k] * qc[k] * C[j, k]
                b += C[i, k] * qc[3 + k] * C[j, k]
            G[3 + i, 3 + j] = a
            G[6 + i, 6 + j] = b
    for i in range(6):
        G[9 + i, 9 + i] = qc[6 + i]


@njit
def _matmul_into(A, B, out):  # type: ignore[no-untyped-def]
    """out = A B (15×15), skipping the zeros of A (i-k-j order: contiguous inner loop)."""
    for i in range(15):
        for j in range(15):
            out[i, j] = 0.0
        for k in range(15):
            a = A[i, k]
            if a != 0.0:
                for j in range(15):
                    out[i, j] += a * B[k, j]


@njit
def _nonzeros(A, idx, count):  # type: ignore[no-untyped-def]
    """Column indices of the nonzeros of each row of A (15×15) into idx, count."""
    for i in range(15):
        c = 0
        for k in range(15):
            if A[i, k] != 0.0:
                idx[i, c] = k
                c += 1
        count[i] = c


@njit
def sandwich_nb(A, B, out, tmp, idx, count):  # type: ignore[no-untyped-def]
    """out = A B Aᵀ (15×15) for a symmetric B: ``A (A B)ᵀ`` on the lower triangle, mirrored.

    ``idx``/``count``: the nonzeros of A's rows (`_nonzeros`). Both products run
    row by row (``out[i, :] += a · W[k, :]``, contiguous inner loops that vectorise), the
    second on ``W = (A B)ᵀ`` (``tmp`` transposed in place): each element is summed over
    the same k in the same ascending order as a dot product, so the numbers are those of
    ``acc += A[i, k] · (A B)[j, k]``.
    """
    for i in range(15):
        for j in range(15):
            tmp[i, j] = 0.0
        for c in range(count[i]):
            k = idx[i, c]
            a = A[i, k]
            for j in range(15):
                tmp[i, j] += a * B[k, j]
    _lower_products(A, tmp, out, idx, count, 0)
    for i in range(15):
        for j in range(i):
            out[j, i] = out[i, j]


@njit
def _lower_products(A, M, out, idx, count, first):  # type: ignore[no-untyped-def]
    """out[i, j] = Σ_k A[i, k] M[j, k] for j ≤ i over A's nonzeros with k ≥ ``first``
    (ascending k). Uses M's transpose, written into M's rows in place (M is scratch)."""
    for i in range(15):  # M ← Mᵀ
        for j in range(i):
            v = M[i, j]
            M[i, j] = M[j, i]
            M[j, i] = v
    for i in range(15):
        for j in range(i + 1):
            out[i, j] = 0.0
        for c in range(count[i]):
            k = idx[i, c]
            if k >= first:
                a = A[i, k]
                for j in range(i + 1):
                    out[i, j] += a * M[k, j]


@njit
def discretize_nb(F, G, T, phi, qd, tmp, idx, count):  # type: ignore[no-untyped-def]
    """Φ = I + FT + (FT)²/2, Q_d = ½ (Φ G Φᵀ + G) T (as discretize; G block diagonal).

    G = G Q_c Gᵀ is zero outside the 3×3 blocks at 3:6 and 6:9 and the diagonal 9:15,
    so ``Φ G`` is formed from those blocks only.
    """
    for i in range(15):
        for j in range(15):
            phi[i, j] = F[i, j] * T
    _nonzeros(phi, idx, count)
    for i in range(15):
        for j in range(15):
            tmp[i, j] = 0.0
        for c in range(count[i]):
            k = idx[i, c]
            a = phi[i, k]
            for j in range(15):
                tmp[i, j] += a * phi[k, j]
    for i in range(15):
        for j in range(15):
            phi[i, j] += 0.5 * tmp[i, j]
        phi[i, i] += 1.0
    _nonzeros(phi, idx, count)
    for i in range(15):  # tmp = Φ G
        for j in range(3):
            tmp[i, j] = 0.0
        for base in (3, 6):
            for j in range(3):
                tmp[i, base + j] = (phi[i, base] * G[base, base + j]
                                    + phi[i, base + 1] * G[base + 1, base + j]
                                    + phi[i, base + 2] * G[base + 2, base + j])
        for d in range(9, 15):
            tmp[i, d] = phi[i, d] * G[d, d]
    _lower_products(phi, tmp, qd, idx, count, 3)  # qd = ½ (Φ (Φ G)ᵀ + G) T, mirrored
    for i in range(15):
        for j in range(i + 1):
            v = 0.5 * (qd[i, j] + G[i, j]) * T
            qd[i, j] = v
            qd[j, i] = v


@njit
def propagation_scratch():  # type: ignore[no-untyped-def]
    """Work arrays of one covariance propagation point: F, G, Φ, Q_d, two 15 × 15 scratch
    matrices, the sparsity index and counts, the attitude matrix and the specific force."""
    return (np.empty((15, 15)), np.empty((15, 15)), np.empty((15, 15)), np.empty((15, 15)),
            np.empty((15, 15)), np.empty((15, 15)), np.empty((15, 15), dtype=np.int64),
            np.empty(15, dtype=np.int64), np.empty((3, 3)), np.empty(3))


@njit
def _propagate_nb(P, healthy, states, accel, intervals, qc, tau_g, tau_a, phi_last, qd_last):  # type: ignore[no-untyped-def]
    """The covariance propagation run by run (the reference of the lane-vectorised
    `propagate_lanes`, which gives the same
    numbers and is what `propagate_block` calls)."""
    n_runs, n_points = states.shape[0], states.shape[1]
    F, G, phi, qd, tmp, tmp2, idx, count, C, fn = propagation_scratch()
    for r in range(n_runs):
        for s in range(n_points):
            error_model_nb(states[r, s], accel[r, s], qc, tau_g, tau_a, F, G, C, fn)
            discretize_nb(F, G, intervals[s], phi, qd, tmp, idx, count)
            if s == n_points - 1:
                phi_last[r] = phi
                qd_last[r] = qd
            elif healthy[r]:
                sandwich_nb(phi, P[r], tmp2, tmp, idx, count)
                for i in range(15):
                    for j in range(i + 1):
                        v = tmp2[i, j] + qd[i, j]
                        P[r, i, j] = v
                        P[r, j, i] = v
