"""Bootstrap intervals of Monte Carlo RMSE figures, paired across methods.

Every method of a Monte Carlo study flies the same truth runs, so two methods are compared
run by run: the runs are resampled with replacement (one draw of run indices shared by
every method, a *paired* bootstrap) and each method's RMSE, and the ratio of two methods'
RMSE, is recomputed on every resample. The percentile interval of those resamples is the
interval of the figure (Efron & Tibshirani, *An Introduction to the Bootstrap*, ch. 13).

RMSE over a subset of runs: ``sqrt(sum_r w_r m_r / sum_r w_r)`` with ``m_r`` the run's mean
squared position error over the scored samples and ``w_r`` 1 for runs in the subset (all
included runs, or the converged ones), so that resampling a run resamples all its samples.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch

from neuralmap.exceptions import NeuralMapError

__all__ = ["BootstrapRmse", "bootstrap_rmse", "paired_ratio"]


@dataclass(frozen=True)
class BootstrapRmse:
    """A bootstrap RMSE figure.

    Attributes:
        value: The RMSE on the runs as drawn (m); None when the subset is empty.
        low: Lower end of the percentile interval (m).
        high: Upper end.
        n_runs: Runs in the subset.
    """

    value: float | None
    low: float | None
    high: float | None
    n_runs: int


def _check(msq: torch.Tensor, mask: torch.Tensor) -> None:
    if msq.ndim != 1 or mask.shape != msq.shape:
        raise NeuralMapError(
            f"bootstrap: per-run mean squared errors (R,) and a mask (R,) expected, got "
            f"{tuple(msq.shape)} and {tuple(mask.shape)}."
        )


def _resample_rmse(msq: torch.Tensor, mask: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
    """``(B,)`` RMSE of the subset on each resample ``index (B, R)`` (NaN when empty)."""
    weight = mask.to(msq.dtype)[index]
    values = torch.where(mask, msq, torch.zeros_like(msq))[index]
    count = weight.sum(-1)
    return torch.where(count > 0, (values.sum(-1) / count.clamp(min=1)).sqrt(),
                       torch.full_like(count, math.nan))


def resample_index(n_runs: int, n_boot: int, seed: int) -> torch.Tensor:
    """``(n_boot, n_runs)`` run indices drawn with replacement (shared by every method)."""
    generator = torch.Generator().manual_seed(int(seed))
    return torch.randint(int(n_runs), (int(n_boot), int(n_runs)), generator=generator)


def _interval(samples: torch.Tensor, confidence: float) -> tuple[float | None, float | None]:
    good = samples[torch.isfinite(samples)]
    if good.numel() == 0:
        return None, None
    alpha = 0.5 * (1.0 - confidence)
    q = torch.quantile(good.double(), torch.tensor([alpha, 1.0 - alpha], dtype=torch.float64))
    return float(q[0]), float(q[1])


def bootstrap_rmse(
    msq: torch.Tensor, mask: torch.Tensor, index: torch.Tensor, *, confidence: float = 0.95
) -> BootstrapRmse:
    """RMSE of the runs in ``mask`` with its percentile bootstrap interval.

    Args:
        msq: ``(R,)`` per-run mean squared position error over the scored samples, m².
        mask: ``(R,)`` bool, runs in the subset.
        index: ``(B, R)`` resampled run indices (`resample_index`).
        confidence: Two-sided coverage of the interval.

    Returns:
        `BootstrapRmse`.
    """
    _check(msq, mask)
    msq = msq.double()
    n = int(mask.sum())
    if n == 0:
        return BootstrapRmse(None, None, None, 0)
    value = float(msq[mask].mean().sqrt())
    low, high = _interval(_resample_rmse(msq, mask, index), confidence)
    return BootstrapRmse(value, low, high, n)


def paired_ratio(
    msq: torch.Tensor, mask: torch.Tensor, ref_msq: torch.Tensor, ref_mask: torch.Tensor,
    index: torch.Tensor, *, confidence: float = 0.95,
) -> tuple[float | None, float | None, float | None]:
    """RMSE of a method over the reference's, with a paired bootstrap interval.

    Both RMSEs are recomputed on the same resampled runs (each over its own subset).

    Returns:
        ``(ratio, low, high)``; Nones when either subset is empty.
    """
    _check(msq, mask)
    _check(ref_msq, ref_mask)
    if not bool(mask.any()) or not bool(ref_mask.any()):
        return None, None, None
    msq, ref_msq = msq.double(), ref_msq.double()
    ratio = float(msq[mask].mean().sqrt() / ref_msq[ref_mask].mean().sqrt())
    samples = _resample_rmse(msq, mask, index) / _resample_rmse(ref_msq, ref_mask, index)
    low, high = _interval(samples, confidence)
    return ratio, low, high
