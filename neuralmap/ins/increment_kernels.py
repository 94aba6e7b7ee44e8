"""Compiled loops for a recorded IMU log: increments over a block, covariance with its σ.

A logged IMU gives one increment per interval, entered as the constant rate
``Δθ_k / Δt_k`` over ``(t_{k−1}, t_k]`` (intervals may differ). The mechanisation step is
the one of `neuralmap.ins.kernels` (``mechanize_step_nb`` with equal rates at both ends, i.e.
`strapdown_step` ``(y, w, f, w, f, Δt_k)``), looped over
the block of intervals between two GNSS epochs; the covariance propagation is that of
`propagate_block` (same error model, discretisation and
``Φ P Φᵀ``), which also returns the σ after every propagation point, since a log solution
is written at every IMU record. Without numba (extra ``fast``) the same interfaces run
the torch functions step by step.
"""

from __future__ import annotations

import numpy as np
import torch

from neuralmap.filters.stats import symmetrize
from neuralmap.ins import kernels
from neuralmap.ins.kernels import (
    discretize_nb,
    error_model_nb,
    mechanize_step_nb,
    njit,
    propagation_scratch,
    sandwich_nb,
)

__all__ = ["mechanize_increments", "propagate_with_sigma"]


@njit
def _mechanize_increments_nb(y, gyro, accel, bg, ba, dt, stops, out):  # type: ignore[no-untyped-def]
    n_runs, n_steps = gyro.shape[0], gyro.shape[1]
    w = np.empty(3)
    f = np.empty(3)
    for r in range(n_runs):
        yr = y[r]
        stop = 0
        for k in range(n_steps):
            for i in range(3):
                w[i] = gyro[r, k, i] - bg[r, i]
                f[i] = accel[r, k, i] - ba[r, i]
            mechanize_step_nb(yr, w, f, w, f, dt[k])
            if stop < stops.shape[0] and stops[stop] == k + 1:
                for i in range(10):
                    out[r, stop, i] = yr[i]
                stop += 1


def mechanize_increments(
    y: torch.Tensor,
    gyro: torch.Tensor,
    accel: torch.Tensor,
    bg: torch.Tensor,
    ba: torch.Tensor,
    dt: torch.Tensor,
    stops: list[int],
) -> tuple[torch.Tensor, torch.Tensor]:
    """Strapdown over L intervals of constant bias-corrected rates (SEEDS 003).

    Args:
        y: ``(N, 10)`` packed states at the block start.
        gyro, accel: ``(N, L, 3)`` measured rates of the intervals (rad/s, m/s²).
        bg, ba: ``(N, 3)`` bias estimates subtracted from the rates.
        dt: ``(L,)`` interval lengths (s).
        stops: Increasing step counts in ``1..L`` at which the state is returned.

    Returns:
        ``(states after the stops (N, S, 10), final state (N, 10))`` (the final state is
        the state after L steps).
    """
    if kernels.HAVE_NUMBA and y.device.type == "cpu" and y.dtype == torch.float64:
        yn = y.detach().numpy().copy()
        out = np.empty((y.shape[0], len(stops), 10))
        _mechanize_increments_nb(yn, gyro.detach().contiguous().numpy(),
                                 accel.detach().contiguous().numpy(), bg.detach().numpy(),
                                 ba.detach().numpy(), dt.detach().contiguous().numpy(),
                                 np.asarray(stops, dtype=np.int64), out)
        return torch.from_numpy(out), torch.from_numpy(yn)
    from neuralmap.ins.mechanization import strapdown_step

    wanted = set(stops)
    kept = []
    for k in range(gyro.shape[1]):
        w, f = gyro[:, k] - bg, accel[:, k] - ba
        y = strapdown_step(y, w, f, w, f, float(dt[k]))
        if k + 1 in wanted:
            kept.append(y)
    states = torch.stack(kept, 1) if kept else y.new_empty(y.shape[0], 0, 10)
    return states, y


@njit
def _propagate_sigma_nb(P, healthy, states, accel, intervals, qc, tau_g, tau_a, var):  # type: ignore[no-untyped-def]
    n_runs, n_points = states.shape[0], states.shape[1]
    F, G, phi, qd, tmp, tmp2, idx, count, C, fn = propagation_scratch()
    for r in range(n_runs):
        for s in range(n_points):
            if healthy[r]:
                error_model_nb(states[r, s], accel[r, s], qc, tau_g, tau_a, F, G, C, fn)
                discretize_nb(F, G, intervals[s], phi, qd, tmp, idx, count)
                sandwich_nb(phi, P[r], tmp2, tmp, idx, count)
                for i in range(15):
                    for j in range(i + 1):
                        v = tmp2[i, j] + qd[i, j]
                        P[r, i, j] = v
                        P[r, j, i] = v
            for i in range(15):
                var[r, s, i] = P[r, i, i]


def propagate_with_sigma(
    P: torch.Tensor,
    healthy: torch.Tensor,
    states: torch.Tensor,
    accel: torch.Tensor,
    intervals: list[float],
    qc: torch.Tensor,
    tau_g: float,
    tau_a: float,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Error covariance through S propagation points, with the variances after each.

    For each point s: ``F``, ``G Q_c Gᵀ`` of the solution there, ``Φ_s, Q_d,s`` over the
    interval and ``P ← Φ P Φᵀ + Q_d`` (symmetric) on healthy samples, as
    `propagate_block` (which leaves the last point to the
    filter's predict; here every point is applied).

    Args:
        P: ``(N, 15, 15)`` covariance at the first point's start.
        healthy: ``(N,)`` bool; unhealthy samples keep their P.
        states: ``(N, S, 10)`` solutions at the points.
        accel: ``(N, S, 3)`` bias-corrected specific forces there.
        intervals: S propagation intervals (s).
        qc: ``(12,)`` noise densities; tau_g, tau_a: bias correlation times (s).

    Returns:
        ``(P after the S points, variances diag P after each point (N, S, 15))``.
    """
    n, points = states.shape[0], states.shape[1]
    if kernels.HAVE_NUMBA and P.device.type == "cpu" and P.dtype == torch.float64:
        p = P.detach().contiguous().numpy().copy()
        var = np.empty((n, points, 15))
        _propagate_sigma_nb(p, healthy.numpy(), states.contiguous().numpy(),
                            accel.contiguous().numpy(), np.asarray(intervals, dtype=np.float64),
                            qc.numpy(), float(tau_g), float(tau_a), var)
        return torch.from_numpy(p), torch.from_numpy(var)
    from neuralmap.ins.error_model import continuous_noise, discretize, error_dynamics

    ok = healthy.reshape(-1, 1, 1)
    var = []
    for s in range(points):
        F = error_dynamics(states[:, s], accel[:, s], gyro_corr_time=tau_g,
                           accel_corr_time=tau_a)
        phi, qd = discretize(F, continuous_noise(states[:, s], qc), intervals[s])
        fpf = torch.matmul(torch.matmul(phi, P), phi.transpose(1, 2))
        P = torch.where(ok, symmetrize(fpf) + qd, P)
        var.append(P.diagonal(dim1=-2, dim2=-1))
    return P, (torch.stack(var, 1) if var else P.new_empty(n, 0, 15))
