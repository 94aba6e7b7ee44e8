"""The linearisation result and the interface of every linearisation method."""

from __future__ import annotations

from typing import NamedTuple

import torch
from torch import nn


class Linearization(NamedTuple):
    """Terrain height, slope and linearisation-error variance at a batch of points.

    Attributes:
        height: ``(N,)`` terrain height in metres.
        slope: ``(N, 2)`` terrain slope ``(dh/dx, dh/dy)``, metres per metre.
        variance: ``(N,)`` linearisation-error variance in m^2, added to R by the filter.
    """

    height: torch.Tensor
    slope: torch.Tensor
    variance: torch.Tensor


class Linearizer(nn.Module):
    """Base class: ``forward(xy, pos_cov=None) -> Linearization``."""

    def forward(
        self, xy: torch.Tensor, pos_cov: torch.Tensor | None = None
    ) -> Linearization:  # pragma: no cover - interface
        """Linearises the terrain at ``xy``.

        Args:
            xy: ``(N, 2)`` metric points (the filter's horizontal position estimate).
            pos_cov: ``(N, 2, 2)`` horizontal position covariance (m^2), used by the
                covariance-adaptive methods; ignored by the others.

        Returns:
            `Linearization` with shapes ``(N,)``, ``(N, 2)``, ``(N,)``.
        """
        raise NotImplementedError
