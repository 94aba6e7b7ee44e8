"""The windowed-NIS lost-lock test: the mean NIS of the last W updates against ``χ²_p(W)/W``.

A filter that still tracks the truth produces NIS values distributed as ``χ²₁`` (scalar
measurements); their mean over a window of ``W`` updates exceeds ``χ²_p(W) / W`` with
probability ``1 − p``. A filter that has locked onto a wrong terrain match produces large
NIS values at every update, and the test fires once the window fills. With a ``cap`` a
single outlier cannot fire it: every NIS entering the window is capped at twice the
threshold, so it takes many outliers in one window (8 in 20 at ``p = 0.99999``) while a lost
lock (every NIS large) still fires it.

Batched over N filters (batch first); each filter's window advances only when it is
updated.
"""

from __future__ import annotations

import math

import torch

from neuralmap.filters.stats import chi2_mean_threshold

__all__ = ["NisWindow"]


class NisWindow:
    """The last ``window`` NIS values of N filters and the lost-lock test on their mean.

    Args:
        n: Filters N.
        window: W, updates averaged (0 disables the test; the mean is still kept over 1).
        prob: χ² probability of the threshold ``χ²_p(W)/W``.
        capped: Cap each NIS entering the window at twice the threshold.
        dtype, device: Of the stored values.
    """

    def __init__(self, n: int, window: int, prob: float, *, capped: bool = False,
                 dtype: torch.dtype = torch.float64, device: torch.device | None = None) -> None:
        self.w = max(int(window), 1)
        self.enabled = window > 0
        self.threshold = chi2_mean_threshold(prob, self.w) if self.enabled else math.inf
        self.cap = 2.0 * self.threshold if capped else math.inf
        self.values = torch.zeros(n, self.w, dtype=dtype, device=device)
        self.count = torch.zeros(n, dtype=torch.long, device=device)
        self.slot = torch.zeros(n, dtype=torch.long, device=device)
        self._rows = torch.arange(n, device=device)

    def add(self, nis: torch.Tensor, updated: torch.Tensor) -> None:
        """Appends ``nis (N,)`` for the filters ``updated (N,)`` (others unchanged)."""
        cur = self.values[self._rows, self.slot]
        nis = nis.to(self.values.dtype).clamp(max=self.cap)
        self.values[self._rows, self.slot] = torch.where(updated, nis, cur)
        self.slot = torch.where(updated, (self.slot + 1) % self.w, self.slot)
        self.count = self.count + updated.long()

    def mean(self) -> torch.Tensor:
        """``(N,)`` mean NIS over the filled part of the window (NaN before any update)."""
        k = self.count.clamp(max=self.w)
        total = self.values.sum(1)  # unfilled slots hold 0
        return torch.where(k > 0, total / k.clamp_min(1).to(total.dtype), math.nan)

    def fired(self) -> torch.Tensor:
        """``(N,)`` bool: the window is full and its mean is past the threshold."""
        if not self.enabled:
            return torch.zeros_like(self.count, dtype=torch.bool)
        return (self.count >= self.w) & (self.values.mean(1) > self.threshold)

    def clear(self, mask: torch.Tensor) -> None:
        """Empties the windows of the filters ``mask (N,)``."""
        self.values = torch.where(mask[:, None], 0.0, self.values)
        self.count = torch.where(mask, 0, self.count)
        self.slot = torch.where(mask, 0, self.slot)
