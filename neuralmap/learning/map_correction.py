"""A learnable map correction: a coarse bilinear grid of height offsets added to a map.

The refined map is ``h'(p) = h(p) + c(p)``, ``c`` the bilinear interpolation of offsets on
a regular grid (``spacing_m``) over the map's extent, initialised at 0. Its height and
slope are analytic (no autograd through the base map), so a linearizer of the base map
(neural map or grid, without a graph) plus `CorrectedLinearizer` gives the refined
map's linearisation, differentiable in the offsets. `BiasedTerrain` builds a map
with a known systematic error for demonstrations and tests.
"""

from __future__ import annotations

import math
from typing import Any

import torch
from torch import nn

from neuralmap.exceptions import NeuralMapError
from neuralmap.linearize.base import Linearization
from neuralmap.terrain.base import TerrainModel

__all__ = ["BiasedTerrain", "CorrectedLinearizer", "CorrectedTerrain", "MapCorrection"]


class MapCorrection(nn.Module):
    """Bilinear grid of learnable height offsets over ``extent``.

    Args:
        extent: ``(xmin, xmax, ymin, ymax)`` of the map, m.
        spacing_m: Node spacing of the correction grid, m (> 0).

    Attributes:
        offsets: ``(ny, nx)`` learnable offsets, m (row = north index).
    """

    def __init__(self, extent: tuple[float, float, float, float], *, spacing_m: float) -> None:
        super().__init__()
        if not spacing_m > 0:
            raise NeuralMapError(f"MapCorrection: spacing_m must be > 0, got {spacing_m!r}.")
        self.extent = tuple(float(e) for e in extent)
        xmin, xmax, ymin, ymax = self.extent
        self.spacing = float(spacing_m)
        self.nx = max(int(math.ceil((xmax - xmin) / spacing_m)) + 1, 2)
        self.ny = max(int(math.ceil((ymax - ymin) / spacing_m)) + 1, 2)
        self.offsets = nn.Parameter(torch.zeros(self.ny, self.nx, dtype=torch.float64))

    def nodes(self) -> torch.Tensor:
        """``(ny, nx, 2)`` node coordinates, m."""
        xs = self.extent[0] + self.spacing * torch.arange(self.nx, dtype=torch.float64)
        ys = self.extent[2] + self.spacing * torch.arange(self.ny, dtype=torch.float64)
        yy, xx = torch.meshgrid(ys, xs, indexing="ij")
        return torch.stack([xx, yy], dim=-1)

    def forward(self, xy: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Offset ``(...)`` and its slope ``(..., 2)`` at ``(..., 2)`` points (clamped to the grid)."""
        c = self.offsets.to(xy.dtype)
        fx = ((xy[..., 0] - self.extent[0]) / self.spacing).clamp(0.0, self.nx - 1.000001)
        fy = ((xy[..., 1] - self.extent[2]) / self.spacing).clamp(0.0, self.ny - 1.000001)
        i = fx.detach().floor().long()
        j = fy.detach().floor().long()
        ax, ay = fx - i, fy - j
        c00, c01 = c[j, i], c[j, i + 1]
        c10, c11 = c[j + 1, i], c[j + 1, i + 1]
        low = c00 + ax * (c01 - c00)
        high = c10 + ax * (c11 - c10)
        value = low + ay * (high - low)
        dx = ((1 - ay) * (c01 - c00) + ay * (c11 - c10)) / self.spacing
        dy = (high - low) / self.spacing
        return value, torch.stack([dx, dy], dim=-1)


class CorrectedTerrain(TerrainModel):
    """``h'(p) = base(p) + correction(p)`` as a terrain model (evaluation, export)."""

    def __init__(self, base: nn.Module, correction: MapCorrection) -> None:
        super().__init__()
        self.base = base
        self.correction = correction
        self.extent = tuple(getattr(base, "extent", correction.extent))
        self.tile_name = getattr(base, "tile_name", "")
        self.tile_fingerprint = getattr(base, "tile_fingerprint", "")

    def forward(self, xy: torch.Tensor) -> torch.Tensor:
        """Heights ``(...)`` at ``(..., 2)`` points."""
        return self.base(xy).to(xy.dtype) + self.correction(xy)[0]


class CorrectedLinearizer(nn.Module):
    """The base map's linearisation plus the correction's height and slope (SEEDS 004 H).

    Args:
        base: Linearizer of the uncorrected map (its outputs need no graph).
        correction: The learnable offsets.
    """

    def __init__(self, base: Any, correction: MapCorrection) -> None:
        super().__init__()
        self.base = base
        self.correction = correction
        self.extent = getattr(base, "extent", None) or correction.extent

    def forward(self, xy: torch.Tensor, pos_cov: torch.Tensor | None = None) -> Linearization:
        """Linearises ``base + correction`` at ``(N, 2)`` points."""
        lin = self.base(xy, pos_cov)
        value, slope = self.correction(xy)
        return Linearization(lin.height.to(xy.dtype) + value, lin.slope.to(xy.dtype) + slope,
                             lin.variance.to(xy.dtype))


class BiasedTerrain(TerrainModel):
    """A map with a known systematic error: ``base + bias`` inside a rectangle.

    The bias ramps linearly to 0 over ``ramp_m`` outside the rectangle (a continuous map).

    Args:
        base: The map.
        box: ``(xmin, xmax, ymin, ymax)`` of the biased region, m.
        bias_m: The error added there, m.
        ramp_m: Width of the transition, m (> 0).
    """

    def __init__(self, base: nn.Module, box: tuple[float, float, float, float], *,
                 bias_m: float, ramp_m: float = 300.0) -> None:
        super().__init__()
        if not (box[0] < box[1] and box[2] < box[3]) or not ramp_m > 0:
            raise NeuralMapError(
                f"BiasedTerrain: box must be (xmin < xmax, ymin < ymax) and ramp_m > 0, got "
                f"{box} and {ramp_m}.")
        self.base = base
        self.box = tuple(float(b) for b in box)
        self.bias_m = float(bias_m)
        self.ramp_m = float(ramp_m)
        self.extent = tuple(base.extent)
        self.tile_name = getattr(base, "tile_name", "")
        self.tile_fingerprint = getattr(base, "tile_fingerprint", "")

    def error(self, xy: torch.Tensor) -> torch.Tensor:
        """The added error ``(...)`` at ``(..., 2)`` points, m."""
        xmin, xmax, ymin, ymax = self.box
        dx = torch.clamp(torch.maximum(xmin - xy[..., 0], xy[..., 0] - xmax), min=0.0)
        dy = torch.clamp(torch.maximum(ymin - xy[..., 1], xy[..., 1] - ymax), min=0.0)
        weight = torch.clamp(1.0 - torch.maximum(dx, dy) / self.ramp_m, min=0.0)
        return self.bias_m * weight

    def forward(self, xy: torch.Tensor) -> torch.Tensor:
        """Heights ``(...)`` at ``(..., 2)`` points."""
        return self.base(xy).to(xy.dtype) + self.error(xy)
