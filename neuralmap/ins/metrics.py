"""Navigation metrics of a loosely coupled GNSS/INS Monte Carlo run (plain dicts).

Position, velocity and attitude errors per run and epoch are summarised as RMSE, 95th
percentile and the "spike" inside degraded GNSS stretches (paper 003 judges its tuning by
the position error spikes in the urban canyons), plus divergence, NEES and NIS.
"""

from __future__ import annotations

import math
from typing import Any

import torch
from scipy.stats import chi2

from neuralmap.ins.gnss import GnssQuality
from neuralmap.ins.loosely_coupled import LooselyCoupledResult

__all__ = ["navigation_summary"]

_DEG = 180.0 / math.pi


def _rms(x: torch.Tensor) -> float:
    x = x[torch.isfinite(x)]
    return float(x.square().mean().sqrt()) if x.numel() else float("nan")


def navigation_summary(
    result: LooselyCoupledResult,
    quality: GnssQuality,
    *,
    divergence_m: float,
    warmup_s: float,
) -> dict[str, Any]:
    """Summary numbers of one filter variant over N runs.

    Args:
        result: The filter run.
        quality: The GNSS quality record of the drive (degraded/outage labels).
        divergence_m: A run diverged when its horizontal error ever exceeds this, or when
            its filter became unhealthy.
        warmup_s: Epochs before this time are left out of the NEES/NIS and attitude
            statistics (initial transient).

    Returns:
        A JSON-ready dict (metres, m/s, degrees).
    """
    e = result.position_error
    horiz = e[..., :2].norm(dim=-1)  # (N, K)
    after = result.time >= warmup_s
    degraded = quality.degraded & quality.valid
    outage = ~quality.valid
    n = e.shape[0]
    spike = horiz[:, degraded].amax(1) if bool(degraded.any()) else torch.full((n,), math.nan)
    outage_max = horiz[:, outage].amax(1) if bool(outage.any()) else torch.full((n,), math.nan)
    att = result.attitude_error[:, after] * _DEG
    diverged = (horiz.amax(1) > divergence_m) | ~result.healthy
    nees = result.nees_position[:, after]
    lo, hi = chi2.ppf([0.025, 0.975], 3 * n) / n
    per_epoch = nees.mean(0)
    nis = result.nis[:, after]
    return {
        "n_runs": n,
        "rmse_horizontal_m": _rms(horiz),
        "rmse_vertical_m": _rms(e[..., 2]),
        "p95_horizontal_m": float(torch.quantile(horiz.flatten(), 0.95)),
        "rmse_horizontal_open_sky_m": _rms(horiz[:, quality.valid & ~quality.degraded]),
        "spike_degraded_mean_m": float(spike.mean()),
        "spike_degraded_max_m": float(spike.max()),
        "outage_max_mean_m": float(outage_max.mean()),
        "rmse_velocity_mps": _rms(result.velocity_error.norm(dim=-1)),
        "rmse_roll_deg": _rms(att[..., 0]),
        "rmse_pitch_deg": _rms(att[..., 1]),
        "rmse_heading_deg": _rms(att[..., 2]),
        "final_heading_rmse_deg": _rms(result.attitude_error[:, -1, 2] * _DEG),
        "divergence_rate": float(diverged.float().mean()),
        "nees_position_mean": float(nees.mean()),
        "nees_position_in_band": float(((per_epoch > lo) & (per_epoch < hi)).float().mean()),
        "nees_navigation_mean": float(result.nees_navigation[:, after].mean()),
        "nis_mean": float(nis[torch.isfinite(nis)].mean()) if bool(
            torch.isfinite(nis).any()) else float("nan"),
        "counts": dict(result.counts),
    }
