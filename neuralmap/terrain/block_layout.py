"""Regular block tiling of a map with a smooth partition of unity across block borders.

Blocks are laid on a regular ``nby x nbx`` grid over the map extent. Each block owns a core
cell; around every interior border there is a blending zone of half-width ``w`` metres in
which the two neighbouring blocks share the point with weights ``1 - s(t)`` and ``s(t)``,
``s`` the quintic smoothstep ``6t^5 - 15t^4 + 10t^3`` (C2), ``t`` running from 0 to 1 across
the zone. The 2-D weight is the product of the per-axis weights, so the weights of the (at
most four) blocks that see a point sum to one and are twice continuously differentiable:
height **and slope** of the blended map are continuous across borders, unlike the hard
gate of SEEDS 004.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from neuralmap.exceptions import NeuralMapError


def smoothstep(t: torch.Tensor) -> torch.Tensor:
    """Quintic smoothstep ``6t^5 - 15t^4 + 10t^3`` on ``t`` clamped to [0, 1]."""
    t = t.clamp(0.0, 1.0)
    return t * t * t * (t * (6.0 * t - 15.0) + 10.0)


@dataclass(frozen=True)
class BlockLayout:
    """Geometry of the block grid.

    Attributes:
        extent: ``(xmin, xmax, ymin, ymax)`` metres covered by the blocks.
        num_blocks: ``(nbx, nby)`` blocks along east and north.
        blend_width: ``(wx, wy)`` half-width in metres of the blending zone at each
            interior border (0 disables blending: a hard gate as in SEEDS 004).
    """

    extent: tuple[float, float, float, float]
    num_blocks: tuple[int, int]
    blend_width: tuple[float, float]

    @property
    def count(self) -> int:
        """Total number of blocks ``nbx * nby``; block id = ``iy * nbx + ix``."""
        return self.num_blocks[0] * self.num_blocks[1]

    @property
    def core_size(self) -> tuple[float, float]:
        """Core width of a block in metres along x and y."""
        xmin, xmax, ymin, ymax = self.extent
        return (xmax - xmin) / self.num_blocks[0], (ymax - ymin) / self.num_blocks[1]

    def block_bounds(self) -> np.ndarray:
        """``(B, 4)`` extended bounds ``(x0, x1, y0, y1)`` of each block (core + blend zone)."""
        xmin, _, ymin, _ = self.extent
        (cx, cy), (wx, wy) = self.core_size, self.blend_width
        nbx, nby = self.num_blocks
        ix = np.tile(np.arange(nbx), nby)
        iy = np.repeat(np.arange(nby), nbx)
        return np.stack(
            [
                xmin + ix * cx - wx,
                xmin + (ix + 1) * cx + wx,
                ymin + iy * cy - wy,
                ymin + (iy + 1) * cy + wy,
            ],
            axis=1,
        )

    def axis_candidates(
        self, u: torch.Tensor, axis: int
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """The two blocks along one axis that may see each coordinate, with their weights.

        Args:
            u: ``(P,)`` coordinates in metres along ``axis`` (0 = x, 1 = y).
            axis: 0 or 1.

        Returns:
            ``(i0, w0, i1, w1)``: own block index and weight, nearest neighbour block index
            (clamped into range) and its weight, each ``(P,)``; ``w0 + w1 = 1``.
        """
        lo = self.extent[2 * axis]
        n = self.num_blocks[axis]
        core = self.core_size[axis]
        half = self.blend_width[axis]
        s = (u - lo) / core
        i0 = s.floor().clamp(0, n - 1)
        frac = s - i0  # position inside the own core, in core units (may leave [0,1] off-map)
        upper = frac >= 0.5
        # Distance (metres) from the nearest interior border of the own block.
        border = torch.where(upper, (i0 + 1.0) * core, i0 * core) + lo
        neighbour = torch.where(upper, i0 + 1.0, i0 - 1.0)
        interior = (neighbour >= 0) & (neighbour <= n - 1)
        if half > 0:
            # t runs 0 -> 1 from (border - half) to (border + half); weight of the block on
            # the upper side of the border is s(t).
            t = (u - (border - half)) / (2.0 * half)
            s_up = smoothstep(t)
            w_neighbour = torch.where(upper, s_up, 1.0 - s_up)
            w_neighbour = torch.where(interior, w_neighbour, torch.zeros_like(w_neighbour))
        else:
            w_neighbour = torch.zeros_like(u)
        neighbour = neighbour.clamp(0, n - 1)
        return i0.long(), 1.0 - w_neighbour, neighbour.long(), w_neighbour

    def assign(self, xy: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Point-block pairs with non-zero blending weight.

        Args:
            xy: ``(P, 2)`` metric points.

        Returns:
            ``(point, block, weight)``: ``(Q,)`` point index, block id and weight for every
            pair with weight > 0; per point the weights sum to one. ``P <= Q <= 4P``.
        """
        ix0, wx0, ix1, wx1 = self.axis_candidates(xy[:, 0], 0)
        iy0, wy0, iy1, wy1 = self.axis_candidates(xy[:, 1], 1)
        nbx = self.num_blocks[0]
        block = torch.stack(
            [iy0 * nbx + ix0, iy0 * nbx + ix1, iy1 * nbx + ix0, iy1 * nbx + ix1], dim=1
        )
        weight = torch.stack([wy0 * wx0, wy0 * wx1, wy1 * wx0, wy1 * wx1], dim=1)
        keep = weight > 0
        point = torch.arange(xy.shape[0], device=xy.device).unsqueeze(1).expand(-1, 4)
        return point[keep], block[keep], weight[keep]


def layout_for_tile(
    shape: tuple[int, int],
    spacing: tuple[float, float],
    extent: tuple[float, float, float, float],
    *,
    block_nodes: int | None,
    overlap_nodes: float,
    num_blocks: tuple[int, int] | None,
) -> BlockLayout:
    """Chooses the block grid for a tile, with blocks sized in grid nodes.

    Args:
        shape: ``(ny, nx)`` nodes of the tile.
        spacing: ``(dx, dy)`` metres.
        extent: ``(xmin, xmax, ymin, ymax)`` metres.
        block_nodes: Target core width of a block in node intervals (same on both axes);
            the count is ``ceil((n - 1) / block_nodes)`` per axis.
        overlap_nodes: Width of the blending zone across each border, in node intervals
            (0 = hard gate).
        num_blocks: ``(nbx, nby)``; overrides ``block_nodes`` when given.

    Raises:
        NeuralMapError: When the tile cannot feed that many blocks or the overlap is too wide.
    """
    ny, nx = shape
    if num_blocks is None:
        if block_nodes is None or block_nodes < 2:
            raise NeuralMapError(
                f"model.block_nodes must be an integer >= 2 (got {block_nodes}); or set "
                "model.num_blocks to [nbx, nby]."
            )
        num_blocks = (
            max(1, math.ceil((nx - 1) / block_nodes)),
            max(1, math.ceil((ny - 1) / block_nodes)),
        )
    nbx, nby = int(num_blocks[0]), int(num_blocks[1])
    if nbx < 1 or nby < 1:
        raise NeuralMapError(f"model.num_blocks must be >= 1 on both axes, got {num_blocks}.")
    core_nodes = ((nx - 1) / nbx, (ny - 1) / nby)
    if min(core_nodes) < 2.0:
        raise NeuralMapError(
            f"the tile ({nx} x {ny} nodes) cannot feed {nbx} x {nby} blocks: each block would "
            f"span only {min(core_nodes):.2f} node intervals (need >= 2). Use fewer blocks "
            "(larger model.block_nodes or smaller model.num_blocks)."
        )
    if overlap_nodes < 0 or overlap_nodes >= min(core_nodes):
        raise NeuralMapError(
            f"model.overlap_nodes = {overlap_nodes} must be >= 0 and smaller than the block "
            f"core ({min(core_nodes):.1f} node intervals); reduce it or use larger blocks."
        )
    blend = (0.5 * overlap_nodes * spacing[0], 0.5 * overlap_nodes * spacing[1])
    return BlockLayout(extent=tuple(float(e) for e in extent), num_blocks=(nbx, nby), blend_width=blend)  # type: ignore[arg-type]
