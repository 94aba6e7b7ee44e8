"""Compiled covariance propagation of the 15-state ψ-angle model, vectorised over runs.

The propagation point of `propagate_block` (error model,
``Φ = I + FT + (FT)²/2``, ``Q_d = ½ (Φ G Q_c Gᵀ Φᵀ + G Q_c Gᵀ) T`` and
``P ← Φ P Φᵀ + Q_d``; `neuralmap.ins.error_model`, SEEDS 003 eqs. 1–2) computed for
a group of `LANES` = 8 runs at once: every matrix is stored ``(15, 15, 8)`` with the
runs (lanes) innermost, each multiply-add of the matrix products works on the 8 lanes at
once (kept in registers; numba's SLP vectoriser, switched on while these kernels compile,
turns it into vector instructions), and the index bookkeeping is paid once per group
instead of once per run. A last, partial group repeats its last run in the spare lanes
(their results are dropped).

Only the structural nonzeros of ``F`` and ``Φ`` enter the products (`F_PATTERN`,
`PHI_PATTERN`, from the block structure of the error equations); every element is
summed over the same terms in the same ascending order as the per-run loop
(`_propagate_nb`, which skips the numerical zeros of
``Φ``). The terms one of them has and the other lacks are products with an exact zero,
``±0.0``, and adding ``±0.0`` leaves a sum unchanged, so the numbers are the same (at
most the sign of an exact zero differs; a test checks equality on random inputs and the
study's results are unchanged).
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

import numpy as np
import torch

from neuralmap.filters.stats import symmetrize
from neuralmap.ins import kernels
from neuralmap.ins.error_model import continuous_noise, discretize, error_dynamics
from neuralmap.ins.kernels import HAVE_NUMBA, error_model_nb, njit, propagation_scratch

__all__ = ["F_PATTERN", "LANES", "PHI_PATTERN", "propagate_block", "propagate_lanes"]

#: Runs propagated together (SIMD lanes: 8 doubles = one AVX-512 or two AVX2 registers);
#: the kernels below spell out 8 lanes.
LANES = 8


def _f_pattern() -> np.ndarray:
    """Structural nonzeros of ``F`` ``(15, 15)`` bool, block by block (error_model eqs.).

    ``δṙ``: ``−ω_en×`` (off-diagonal skew) and ``I`` on δv; ``δv̇``: the gravity
    diagonal on δr, ``−(2ω_ie + ω_en)×`` and ``fⁿ×`` (off-diagonal), ``−C`` on δb_a;
    ``ψ̇``: ``−ω_in×`` (off-diagonal) and ``C`` on δb_g; the bias diagonals.
    """
    skew = ~np.eye(3, dtype=bool)
    full = np.ones((3, 3), dtype=bool)
    eye = np.eye(3, dtype=bool)
    F = np.zeros((15, 15), dtype=bool)
    F[0:3, 0:3], F[0:3, 3:6] = skew, eye
    F[3:6, 0:3], F[3:6, 3:6], F[3:6, 6:9], F[3:6, 12:15] = eye, skew, skew, full
    F[6:9, 6:9], F[6:9, 9:12] = skew, full
    F[9:15, 9:15] = np.eye(6, dtype=bool)
    return F


#: Structural nonzeros of the continuous error dynamics ``F``.
F_PATTERN = _f_pattern()
_SQUARE = (F_PATTERN.astype(np.int64) @ F_PATTERN.astype(np.int64)) > 0
#: Structural nonzeros of ``Φ = I + FT + (FT)²/2``.
PHI_PATTERN = np.eye(15, dtype=bool) | F_PATTERN | _SQUARE


def _rows(pattern: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Column indices of each row's nonzeros ``(15, 15)`` (ascending, padded) and counts."""
    idx = np.zeros((15, 15), dtype=np.int64)
    count = np.zeros(15, dtype=np.int64)
    for i in range(15):
        cols = np.flatnonzero(pattern[i])
        idx[i, :cols.size] = cols
        count[i] = cols.size
    return idx, count


_F_IDX, _F_COUNT = _rows(F_PATTERN)
_PHI_IDX, _PHI_COUNT = _rows(PHI_PATTERN)


@contextlib.contextmanager
def _slp_vectorize() -> Iterator[None]:
    """Compiles what is first called inside with LLVM's SLP vectoriser on.

    numba leaves it off by default (``NUMBA_SLP_VECTORIZE``); the lane kernels need it to
    pack the 8 lanes' scalar multiply-adds into vector instructions (2–3× faster). It
    packs identical IEEE operations and never reassociates (no fast-math flags), so the
    numbers are those of the scalar code. Only compilation reads the flag; it is restored
    afterwards.
    """
    if not HAVE_NUMBA:
        yield
        return
    from numba.core import config

    before = config.SLP_VECTORIZE
    config.SLP_VECTORIZE = 1
    try:
        yield
    finally:
        config.SLP_VECTORIZE = before


def _njit_inline(fn):  # type: ignore[no-untyped-def]
    if not HAVE_NUMBA:
        return fn
    import numba

    return numba.njit(cache=True, fastmath=False, error_model="numpy", inline="always")(fn)


@_njit_inline
def _madd(acc, x, y):  # type: ignore[no-untyped-def]
    """``acc + x y`` on the 8 lanes (a tuple of 8 floats; x, y: 8-element rows). Kept in
    registers, so the compiler turns it into two 4-wide (or one 8-wide) multiply and add
    instructions (separate, no fused multiply-add)."""
    return (acc[0] + x[0] * y[0], acc[1] + x[1] * y[1], acc[2] + x[2] * y[2],
            acc[3] + x[3] * y[3], acc[4] + x[4] * y[4], acc[5] + x[5] * y[5],
            acc[6] + x[6] * y[6], acc[7] + x[7] * y[7])


@_njit_inline
def _store(dst, acc):  # type: ignore[no-untyped-def]
    """Writes the 8 lanes of ``acc`` into the 8-element row ``dst``."""
    dst[0], dst[1], dst[2], dst[3] = acc[0], acc[1], acc[2], acc[3]
    dst[4], dst[5], dst[6], dst[7] = acc[4], acc[5], acc[6], acc[7]


_ZERO = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)


@njit
def _load_lane(F, G, w, Fl, Gl, f_idx, f_count):  # type: ignore[no-untyped-def]
    """Copies one run's F (structural nonzeros) and G (its blocks) into lane w."""
    for i in range(15):
        for c in range(f_count[i]):
            k = f_idx[i, c]
            Fl[i, k, w] = F[i, k]
    for base in (3, 6):
        for i in range(3):
            for j in range(3):
                Gl[base + i, base + j, w] = G[base + i, base + j]
    for d in range(9, 15):
        Gl[d, d, w] = G[d, d]


@njit
def _discretize_lanes(Fl, Gl, T, ft, phi, pg, qd, f_idx, f_count, p_idx, p_count):  # type: ignore[no-untyped-def]
    """Φ and Q_d of the 8 lanes (as kernels.discretize_nb, element by element).

    ``ft``, ``phi``, ``pg`` and ``qd`` are ``(15, 15, 8)`` work arrays whose entries
    outside the patterns are zero.
    """
    for i in range(15):  # FT
        for c in range(f_count[i]):
            k = f_idx[i, c]
            for w in range(LANES):
                ft[i, k, w] = Fl[i, k, w] * T
    for i in range(15):  # Φ = (FT + ½ (FT)²) + I on Φ's pattern
        for c in range(p_count[i]):
            j = p_idx[i, c]
            acc = _ZERO
            for a in range(f_count[i]):  # (FT)²_ij over ascending k
                k = f_idx[i, a]
                acc = _madd(acc, ft[i, k], ft[k, j])
            for w in range(LANES):
                phi[i, j, w] = ft[i, j, w] + 0.5 * acc[w]
        for w in range(LANES):
            phi[i, i, w] += 1.0
    for i in range(15):  # pg = Φ G (columns 3..14; G is zero elsewhere)
        for base in (3, 6):
            for j in range(3):
                for w in range(LANES):
                    pg[i, base + j, w] = ((phi[i, base, w] * Gl[base, base + j, w]
                                           + phi[i, base + 1, w] * Gl[base + 1, base + j, w])
                                          + phi[i, base + 2, w] * Gl[base + 2, base + j, w])
        for d in range(9, 15):
            for w in range(LANES):
                pg[i, d, w] = phi[i, d, w] * Gl[d, d, w]
    for i in range(15):  # Q_d = ½ (Φ (Φ G)ᵀ + G) T, lower triangle, mirrored
        for j in range(i + 1):
            acc = _ZERO
            for c in range(p_count[i]):
                k = p_idx[i, c]
                if k >= 3:
                    acc = _madd(acc, phi[i, k], pg[j, k])
            for w in range(LANES):
                v = 0.5 * (acc[w] + Gl[i, j, w]) * T
                qd[i, j, w] = v
                qd[j, i, w] = v


@njit
def _sandwich_lanes(phi, P, qd, tmp, p_idx, p_count):  # type: ignore[no-untyped-def]
    """``P ← Φ P Φᵀ + Q_d`` on the 8 lanes (lower triangle, mirrored), as kernels.sandwich_nb.

    ``tmp[k, j] = (Φ P)[j, k]`` (written transposed, so that both products read 8-lane
    rows); every element is a sum over ascending k.
    """
    for i in range(15):  # tmp[:, i] = (Φ P)[i, :]
        for j in range(15):
            acc = _ZERO
            for c in range(p_count[i]):
                k = p_idx[i, c]
                acc = _madd(acc, phi[i, k], P[k, j])
            _store(tmp[j, i], acc)
    for i in range(15):  # (Φ (Φ P)ᵀ)_ij = Σ_k Φ_ik (Φ P)_jk, j ≤ i
        for j in range(i + 1):
            acc = _ZERO
            for c in range(p_count[i]):
                k = p_idx[i, c]
                acc = _madd(acc, phi[i, k], tmp[k, j])
            for w in range(LANES):
                v = acc[w] + qd[i, j, w]
                P[i, j, w] = v
                P[j, i, w] = v


@njit
def _propagate_lanes_nb(P, healthy, states, accel, intervals, qc, tau_g, tau_a, phi_last,  # type: ignore[no-untyped-def]
                        qd_last, f_idx, f_count, p_idx, p_count):
    n_runs, n_points = states.shape[0], states.shape[1]
    F, G, _phi, _qd, _tmp, _tmp2, _idx, _count, C, fn = propagation_scratch()
    Fl = np.zeros((15, 15, LANES))
    Gl = np.zeros((15, 15, LANES))
    ft = np.zeros((15, 15, LANES))
    phi = np.zeros((15, 15, LANES))
    pg = np.zeros((15, 15, LANES))
    qd = np.zeros((15, 15, LANES))
    Pl = np.empty((15, 15, LANES))
    tmp = np.empty((15, 15, LANES))
    for r0 in range(0, n_runs, LANES):
        nw = min(LANES, n_runs - r0)
        for w in range(LANES):  # lanes past the last run repeat it (results dropped)
            r = r0 + min(w, nw - 1)
            for i in range(15):
                for j in range(15):
                    Pl[i, j, w] = P[r, i, j]
        for s in range(n_points):
            for w in range(LANES):
                r = r0 + min(w, nw - 1)
                error_model_nb(states[r, s], accel[r, s], qc, tau_g, tau_a, F, G, C, fn)
                _load_lane(F, G, w, Fl, Gl, f_idx, f_count)
            _discretize_lanes(Fl, Gl, intervals[s], ft, phi, pg, qd, f_idx, f_count,
                              p_idx, p_count)
            if s == n_points - 1:
                for w in range(nw):
                    for i in range(15):
                        for j in range(15):
                            phi_last[r0 + w, i, j] = phi[i, j, w]
                            qd_last[r0 + w, i, j] = qd[i, j, w]
            else:
                _sandwich_lanes(phi, Pl, qd, tmp, p_idx, p_count)
        for w in range(nw):
            if healthy[r0 + w]:
                for i in range(15):
                    for j in range(15):
                        P[r0 + w, i, j] = Pl[i, j, w]


def propagate_lanes(
    P: np.ndarray,
    healthy: np.ndarray,
    states: np.ndarray,
    accel: np.ndarray,
    intervals: np.ndarray,
    qc: np.ndarray,
    tau_g: float,
    tau_a: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Covariance over S propagation points for N runs, `LANES` runs at a time.

    Args:
        P: ``(N, 15, 15)`` float64 covariances at the first point's start; overwritten with
            P after S − 1 points on healthy runs (unhealthy runs keep theirs).
        healthy: ``(N,)`` bool.
        states: ``(N, S, 10)`` solutions at the points.
        accel: ``(N, S, 3)`` bias-corrected specific forces there.
        intervals: ``(S,)`` propagation intervals T (s).
        qc: ``(12,)`` noise densities; tau_g, tau_a: bias correlation times (s).

    Returns:
        ``(Φ_S (N, 15, 15), Q_d,S (N, 15, 15))`` of the last point.
    """
    n = P.shape[0]
    phi_last = np.empty((n, 15, 15))
    qd_last = np.empty((n, 15, 15))
    with _slp_vectorize():
        _propagate_lanes_nb(P, healthy, states, accel, intervals, qc, float(tau_g),
                            float(tau_a), phi_last, qd_last, _F_IDX, _F_COUNT, _PHI_IDX,
                            _PHI_COUNT)
    return phi_last, qd_last


def propagate_block(
    P: torch.Tensor,
    healthy: torch.Tensor,
    states: torch.Tensor,
    accel: torch.Tensor,
    intervals: list[float],
    qc: torch.Tensor,
    tau_g: float,
    tau_a: float,
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Error covariance over S propagation points; the last step is left to the filter.

    Compiled: `propagate_lanes` (8 runs per SIMD
    lane group). For each point s: ``F`` and ``G Q_c Gᵀ`` of the solution there
    (`error_dynamics`,
    `continuous_noise`), ``Φ_s, Q_d,s``
    (`discretize` over the interval), and for
    s < S: ``P ← ½(Φ P Φᵀ + (Φ P Φᵀ)ᵀ) + Q_d`` on healthy samples (the filter's predict).

    Args:
        P: ``(N, 15, 15)`` covariance at the first point's start.
        healthy: ``(N,)`` bool; unhealthy samples keep their P.
        states: ``(N, S, 10)`` solutions at the points.
        accel: ``(N, S, 3)`` bias-corrected specific forces there.
        intervals: S propagation intervals T (s).
        qc: ``(12,)`` noise densities; tau_g, tau_a: bias correlation times (s).

    Returns:
        ``(P after S − 1 points, Φ_S (N, 15, 15), Q_d,S (N, 15, 15))``.
    """
    points = states.shape[1]
    if kernels.HAVE_NUMBA and P.device.type == "cpu" and P.dtype == torch.float64:
        p = P.detach().contiguous().numpy().copy()
        phi_last, qd_last = propagate_lanes(
            p, healthy.numpy(), states.contiguous().numpy(), accel.contiguous().numpy(),
            np.asarray(intervals, dtype=np.float64), qc.numpy(), tau_g, tau_a)
        return torch.from_numpy(p), torch.from_numpy(phi_last), torch.from_numpy(qd_last)
    ok = healthy.reshape(-1, 1, 1)
    phi = qd = P
    for s in range(points):
        F = error_dynamics(states[:, s], accel[:, s], gyro_corr_time=tau_g,
                           accel_corr_time=tau_a)
        phi, qd = discretize(F, continuous_noise(states[:, s], qc), intervals[s])
        if s < points - 1:
            fpf = torch.matmul(torch.matmul(phi, P), phi.transpose(1, 2))
            P = torch.where(ok, symmetrize(fpf) + qd, P)
    return P, phi, qd
