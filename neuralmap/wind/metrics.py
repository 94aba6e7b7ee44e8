"""Error metrics of wind estimates over Monte Carlo runs (batch first).

All metrics compare an estimate ``ŵ`` ``(N, T, 2)`` with the true wind ``w``; the error is
the horizontal vector error ``ŵ − w`` (m/s).

* RMSE: ``sqrt(mean |ŵ − w|²)`` over the kept runs and all samples after the first;
* divergence: a run diverges when the RMS of its error over the last ``tail_fraction`` of
  the samples exceeds ``divergence_threshold`` (or any estimate is not finite, or the
  filter flagged it numerically broken);
* NEES: time-averaged ``(ŵ_i − w_i)² / P_ii`` per axis (1 for a consistent filter);
* outlier-patch metrics: the mean over runs of the largest error and of the largest
  one-sample change of the error inside the outlier samples (a "jump" of the estimate).
"""

from __future__ import annotations

import math

import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.wind.checks import require_in_range, require_positive
from neuralmap.wind.filtering import WindEstimate

__all__ = ["wind_error_metrics", "diverged_runs", "rmse_over_time", "track_error_metrics"]


def _check(truth: torch.Tensor, estimate: WindEstimate) -> None:
    if truth.ndim != 3 or truth.shape[-1] != 2 or estimate.wind.shape != truth.shape:
        raise NeuralMapError(
            f"wind metrics: truth {tuple(truth.shape)} and estimate "
            f"{tuple(estimate.wind.shape)} must both be (N, T, 2)."
        )


def diverged_runs(
    truth: torch.Tensor,
    estimate: WindEstimate,
    *,
    divergence_threshold: float = 5.0,
    tail_fraction: float = 0.1,
) -> torch.Tensor:
    """``(N,)`` bool, runs whose final error RMS exceeds the threshold (see module doc).

    Raises:
        NeuralMapError: Bad shapes, threshold ≤ 0 or tail fraction outside (0, 1].
    """
    _check(truth, estimate)
    require_positive(divergence_threshold, "divergence_threshold", "diverged_runs")
    frac = require_in_range(tail_fraction, "tail_fraction", "diverged_runs", 1e-9, 1.0)
    t = truth.shape[1]
    tail = max(1, int(math.ceil(frac * t)))
    err = (estimate.wind - truth)[:, -tail:]
    tail_rms = err.square().sum(-1).mean(-1).sqrt()
    finite = torch.isfinite(estimate.wind).flatten(1).all(-1)
    return ~finite | ~torch.isfinite(tail_rms) | (tail_rms > divergence_threshold) | ~(
        estimate.healthy.to(finite.device))


def rmse_over_time(truth: torch.Tensor, estimate: WindEstimate,
                   keep: torch.Tensor | None = None) -> torch.Tensor:
    """``(T,)`` RMS of the vector error over the kept runs (all runs by default)."""
    _check(truth, estimate)
    sq = (estimate.wind - truth).square().sum(-1)
    if keep is not None:
        sq = sq[keep]
    return sq.mean(0).sqrt()


def wind_error_metrics(
    truth: torch.Tensor,
    estimate: WindEstimate,
    *,
    outlier: torch.Tensor | None = None,
    divergence_threshold: float = 5.0,
    tail_fraction: float = 0.1,
) -> dict[str, float]:
    """Summary metrics of one filter on one condition.

    Args:
        truth: ``(N, T, 2)`` true wind.
        estimate: The filter's `WindEstimate` (``(N, T, 2)`` fields).
        outlier: ``(N, T)`` bool outlier samples (None = no patch metrics).
        divergence_threshold: Final-error RMS (m/s) above which a run counts as diverged.
        tail_fraction: Fraction of the run used for the divergence test.

    Returns:
        ``rmse`` (non-diverged runs), ``rmse_all`` (all runs), ``median_run_rmse``,
        ``divergence_rate``, ``nees`` (non-diverged runs; ideal 1), and with ``outlier``
        ``patch_max_error`` and ``patch_max_jump`` (m/s, mean over runs with outliers).
    """
    diverged = diverged_runs(truth, estimate, divergence_threshold=divergence_threshold,
                             tail_fraction=tail_fraction)
    keep = ~diverged
    err = (estimate.wind - truth)[:, 1:]
    sq = err.square().sum(-1)  # (N, T-1)
    run_rmse = sq.mean(-1).sqrt()
    nees = (err.square() / estimate.variance[:, 1:]).mean((-1, -2))
    out = {
        "rmse": float(sq[keep].mean().sqrt()) if bool(keep.any()) else float("nan"),
        "rmse_all": float(sq.mean().sqrt()),
        "median_run_rmse": float(run_rmse.median()),
        "divergence_rate": float(diverged.double().mean()),
        "nees": float(nees[keep].mean()) if bool(keep.any()) else float("nan"),
    }
    if outlier is not None:
        if outlier.shape != truth.shape[:2]:
            raise NeuralMapError(f"wind_error_metrics: 'outlier' must be (N, T) = "
                                 f"{tuple(truth.shape[:2])}, got {tuple(outlier.shape)}.")
        full = (estimate.wind - truth).norm(dim=-1)  # (N, T)
        jump = torch.zeros_like(full)
        jump[:, 1:] = (estimate.wind - truth).diff(dim=1).norm(dim=-1)
        has = outlier.any(-1)
        if bool(has.any()):
            inside = outlier[has]
            out["patch_max_error"] = float(torch.where(inside, full[has], 0.0).amax(-1).mean())
            out["patch_max_jump"] = float(torch.where(inside, jump[has], 0.0).amax(-1).mean())
    return out


def track_error_metrics(along: torch.Tensor, cross: torch.Tensor) -> dict[str, float]:
    """Summary of dead-reckoning errors ``(N, T)`` along and across the track (m).

    Returns:
        ``final_along_rms``, ``final_cross_rms``, ``final_rms`` (RMS over runs at the last
        sample), ``max_rms`` (largest over time of the RMS over runs of the horizontal
        error), ``mean_rms`` (its time average) and ``p95_max`` (95th percentile over runs
        of each run's largest error).
    """
    if along.shape != cross.shape or along.ndim != 2:
        raise NeuralMapError(f"track_error_metrics: along {tuple(along.shape)} and cross "
                             f"{tuple(cross.shape)} must both be (N, T).")
    sq = along.square() + cross.square()
    rms_t = sq.mean(0).sqrt()
    return {
        "final_along_rms": float(along[:, -1].square().mean().sqrt()),
        "final_cross_rms": float(cross[:, -1].square().mean().sqrt()),
        "final_rms": float(rms_t[-1]),
        "max_rms": float(rms_t.max()),
        "mean_rms": float(rms_t.mean()),
        "p95_max": float(torch.quantile(sq.sqrt().amax(-1), 0.95)),
    }
