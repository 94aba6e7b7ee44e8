"""The map's height spread over each cell of a point-mass lattice.

Shared by the acquisition grid (`neuralmap.nav.acquisition`) and the whole-flight
tracker (`neuralmap.nav.tracking`), so neither imports the other for it.
"""

from __future__ import annotations

import torch

__all__ = ["cell_height_variance"]


def cell_height_variance(heights: torch.Tensor) -> torch.Tensor:
    """Spread of the map height over each grid cell, ``(N, G, G)`` m².

    ``(Δ_x² + Δ_y²) / 12`` with ``Δ`` the central height differences between neighbouring
    cells (one-sided at the border): the variance of a height that changes linearly by
    ``Δ`` across the cell. It measures the terrain's variation at the grid's own scale,
    large while the grid is coarse and negligible once it is fine.

    Args:
        heights: ``(N, G, G)`` map heights on the cells, m.

    Returns:
        ``(N, G, G)`` variances, m².
    """
    gy, gx = torch.gradient(heights, dim=(1, 2))
    return (gx.square() + gy.square()) * (1.0 / 12.0)  # uniform slope over a cell: Δ²/12
