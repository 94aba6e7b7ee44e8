"""Where the tiles of a latent tileset lie, and the C² partition of unity across their seams.

A region of ``NY x NX`` nodes (one metric frame: ``origin``, ``spacing``) is cut into a
rectangular grid of tiles: tile column ``j`` owns the core node columns
``columns[j] = (c0, c1)`` (inclusive), tile row ``i`` the core rows ``rows[i]``. Adjacent
cores touch or share their edge node line (SRTM tiles share one), and the **seam** between
columns ``j`` and ``j + 1`` lies halfway between the last core column of ``j`` and the first
of ``j + 1``: ``s_j = (c1_j + c0_{j+1}) / 2`` nodes.

**Overlap blending.** Each tile is fitted on its core grown by ``overlap_nodes + 1`` nodes
on every side that has a neighbour (`TilesetLayout.window`; the extra node covers a seam
halfway between two abutting cores). Across a seam ``s`` the two tiles
are blended over ``[s - w, s + w]`` with ``w = overlap_nodes * spacing``, the upper tile
weighted by the quintic smoothstep ``S(t) = 6t^5 - 15t^4 + 10t^3``,
``t = (u - (s - w)) / 2w`` (`neuralmap.terrain.block_layout.smoothstep`, as the blockwise
maps blend their blocks), the lower by ``1 - S(t)``. The 2-D weight of tile ``(i, j)`` is
``phi_ij(x, y) = psi_j(x) chi_i(y)``; per axis the weights sum to one, so
``sum_ij phi_ij = 1`` and each ``phi_ij`` is C² (``S' = S'' = 0`` at both ends of the zone).
The weight of a tile is zero outside its window, so a tile is only ever evaluated where it
was fitted. Blend zones of one axis must not overlap: seams lie at least ``2 overlap_nodes``
node intervals apart, and ``overlap_nodes`` from the region's edge.

Why blending and not shared border coefficients: the tiles are fitted independently (any
order, any process, one tile's data in memory), a tile's bitstream is the existing latent
map file unchanged, and the blend is C² whatever the fits; sharing border coefficients would
couple the fits of neighbours (a joint solve, or a fixed border that the second tile must
honour) and change the file format. The price is ``overlap_nodes`` extra nodes per side per
tile and up to four tile evaluations in the blend zones (one elsewhere).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import torch

from neuralmap.dem.tile import DemTile
from neuralmap.exceptions import NeuralMapError
from neuralmap.terrain.block_layout import smoothstep

__all__ = ["AxisWeights", "TilesetLayout", "regular_ranges", "smoothstep_slope", "window_tile"]


def smoothstep_slope(t: torch.Tensor) -> torch.Tensor:
    """``dS/dt = 30 t^2 (1 - t)^2`` of the quintic smoothstep, ``t`` clamped to [0, 1]."""
    t = t.clamp(0.0, 1.0)
    return 30.0 * (t * (1.0 - t)) ** 2


def regular_ranges(nodes: int, tile_nodes: int) -> list[tuple[int, int]]:
    """Core ranges of tiles ``tile_nodes`` node intervals wide, sharing their edge node.

    Args:
        nodes: Nodes along the axis.
        tile_nodes: Node intervals per tile (the last tile takes the remainder, merged into
            the one before it when shorter than half a tile).

    Returns:
        ``[(c0, c1), ...]`` inclusive, ``c0 = 0`` first, ``c1 = nodes - 1`` last.
    """
    if int(tile_nodes) < 2:
        raise NeuralMapError(f"--data.tile_nodes must be >= 2 node intervals, got {tile_nodes}.")
    step = int(tile_nodes)
    starts = list(range(0, max(1, nodes - 1), step))
    if len(starts) > 1 and (nodes - 1) - starts[-1] < step / 2:
        starts.pop()
    ends = [*starts[1:], nodes - 1]
    return list(zip(starts, ends, strict=True))


@dataclass(frozen=True)
class AxisWeights:
    """The two tiles along one axis on either side of each coordinate's nearest seam.

    Attributes:
        lower: ``(P,)`` index of the tile below (west / south of) the nearest seam.
        offset: ``(P,)`` ``u - s_k``, metres from the nearest seam ``s_k`` (``inf`` when the
            axis has a single tile).
        half: Blend half-width ``w``, metres.
    """

    lower: torch.Tensor
    offset: torch.Tensor
    half: float

    @property
    def upper(self) -> torch.Tensor:
        """``(P,)`` index of the tile above the nearest seam."""
        return self.lower + 1

    @property
    def own(self) -> torch.Tensor:
        """``(P,)`` the tile whose core holds the coordinate (weight 1 off the blend zone)."""
        return self.lower + (self.offset >= 0).long()

    @property
    def blending(self) -> torch.Tensor:
        """``(P,)`` bool: inside the blend zone ``|u - s_k| < w`` (both tiles weigh)."""
        return self.offset.abs() < self.half

    def weight(self, index: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """``S(t)``, the weight of the upper tile (the lower one has ``1 - S``), and
        ``dS/du`` per metre, with ``t = (u - s_k) / 2w + 1/2``; at ``index`` only when given.
        """
        offset = self.offset if index is None else self.offset.index_select(0, index)
        t = offset * (0.5 / self.half) + 0.5  # 0 -> 1 across [s - w, s + w]
        return smoothstep(t), smoothstep_slope(t) * (0.5 / self.half)


@dataclass(frozen=True)
class TilesetLayout:
    """The tile grid of a region and its blending geometry (module docstring).

    Attributes:
        shape: ``(NY, NX)`` region nodes.
        spacing: ``(dx, dy)`` metres.
        origin: ``(x0, y0)`` metric position of region node ``[0, 0]``.
        columns: Inclusive core node-column range of every tile column, west to east.
        rows: Inclusive core node-row range of every tile row, south to north.
        overlap_nodes: Overlap margin and blend half-width, in node intervals (>= 1).

    Raises:
        NeuralMapError: Ranges that leave gaps, do not cover the region, or seams too close
            for the overlap.
    """

    shape: tuple[int, int]
    spacing: tuple[float, float]
    origin: tuple[float, float]
    columns: tuple[tuple[int, int], ...]
    rows: tuple[tuple[int, int], ...]
    overlap_nodes: int

    def __post_init__(self) -> None:
        if not isinstance(self.overlap_nodes, int) or self.overlap_nodes < 1:
            raise NeuralMapError(
                f"--data.overlap_nodes must be a whole number >= 1 (the overlap margin and "
                f"blend half-width in nodes), got {self.overlap_nodes!r}.")
        for axis, (ranges, n, what) in enumerate(((self.columns, self.shape[1], "column"),
                                                   (self.rows, self.shape[0], "row"))):
            self._check_axis(ranges, n, what, axis)

    def _check_axis(self, ranges: tuple[tuple[int, int], ...], n: int, what: str,
                    axis: int) -> None:
        if not ranges or ranges[0][0] != 0 or ranges[-1][1] != n - 1:
            raise NeuralMapError(
                f"latent tileset: the tile {what}s {list(ranges)} do not cover the region's "
                f"{n} node {what}s (0 .. {n - 1}).")
        for k, (lo, hi) in enumerate(ranges):
            if hi <= lo:
                raise NeuralMapError(f"latent tileset: tile {what} {k} has an empty core "
                                     f"({lo} .. {hi}).")
            if k and not (ranges[k - 1][0] < lo <= ranges[k - 1][1] + 1 and hi > ranges[k - 1][1]):
                raise NeuralMapError(
                    f"latent tileset: tile {what}s {k - 1} ({ranges[k - 1]}) and {k} ({lo}, "
                    f"{hi}) neither touch nor share their edge; the tiles do not form one "
                    "region (a gap or a nested tile).")
        seams = [0.0, *self.seam_nodes(axis), float(n - 1)]
        ov = self.overlap_nodes
        for k in range(1, len(seams) - 1):
            room = min(seams[k] - seams[k - 1] - (0 if k == 1 else ov),
                       seams[k + 1] - seams[k] - (0 if k == len(seams) - 2 else ov))
            if room < ov:
                raise NeuralMapError(
                    f"latent tileset: the seam between tile {what}s {k - 1} and {k} (node "
                    f"{seams[k]:g}) leaves only {room:g} node intervals for a blend half-width "
                    f"of {ov} (--data.overlap_nodes); use a smaller overlap or larger tiles.")

    @property
    def grid(self) -> tuple[int, int]:
        """``(tile rows, tile columns)``."""
        return len(self.rows), len(self.columns)

    @property
    def count(self) -> int:
        """Number of tiles; tile id = ``row * columns + col``."""
        return len(self.rows) * len(self.columns)

    @property
    def extent(self) -> tuple[float, float, float, float]:
        """``(xmin, xmax, ymin, ymax)`` of the region's nodes, metres."""
        (x0, y0), (dx, dy), (ny, nx) = self.origin, self.spacing, self.shape
        return (x0, x0 + (nx - 1) * dx, y0, y0 + (ny - 1) * dy)

    @property
    def blend_width(self) -> tuple[float, float]:
        """``(wx, wy)`` blend half-widths, metres."""
        return (self.overlap_nodes * self.spacing[0], self.overlap_nodes * self.spacing[1])

    def seam_nodes(self, axis: int) -> list[float]:
        """Seam positions in node units along ``axis`` (0 = x / columns, 1 = y / rows)."""
        ranges = self.columns if axis == 0 else self.rows
        return [0.5 * (ranges[k][1] + ranges[k + 1][0]) for k in range(len(ranges) - 1)]

    def seams(self, axis: int) -> list[float]:
        """Seam positions in metres along ``axis``."""
        return [self.origin[axis] + s * self.spacing[axis] for s in self.seam_nodes(axis)]

    def window(self, row: int, col: int) -> tuple[int, int, int, int]:
        """``(r0, r1, c0, c1)`` inclusive node box a tile is fitted on: its core grown by
        ``overlap_nodes + 1`` on every side with a neighbour (it holds the tile's blend
        zones)."""
        ov, (ny, nx) = self.overlap_nodes + 1, self.shape
        (r0, r1), (c0, c1) = self.rows[row], self.columns[col]
        grow = (row > 0, row < len(self.rows) - 1, col > 0, col < len(self.columns) - 1)
        return (max(0, r0 - ov * grow[0]), min(ny - 1, r1 + ov * grow[1]),
                max(0, c0 - ov * grow[2]), min(nx - 1, c1 + ov * grow[3]))

    def axis_weights(self, u: torch.Tensor, axis: int) -> AxisWeights:
        """The nearest seam of every coordinate along one axis (differentiable in ``u``).

        The nearest seam ``s_k`` comes from the midpoints between seams (one
        ``searchsorted``); `AxisWeights.weight` gives the blend weights. Off the region the
        weights clamp to the border tile.

        Args:
            u: ``(P,)`` metric coordinates along ``axis`` (finite).
            axis: 0 (x, tile columns) or 1 (y, tile rows).

        Returns:
            The lower tile of the nearest seam and the offset from it.
        """
        seams = self.seams(axis)
        if not seams:
            idx = torch.zeros(u.shape, dtype=torch.long, device=u.device)
            return AxisWeights(idx, torch.full_like(u, -float("inf")), 1.0)
        s = torch.tensor(seams, dtype=u.dtype, device=u.device)
        mids = 0.5 * (s[1:] + s[:-1])
        lower = torch.searchsorted(mids, u.detach().contiguous(), right=True)  # nearest seam
        return AxisWeights(lower, u - s.index_select(0, lower), self.blend_width[axis])

    def describe(self) -> dict[str, Any]:
        """JSON-serialisable form (`from_description` reads it back)."""
        return {"shape": list(self.shape), "spacing": list(self.spacing),
                "origin": list(self.origin), "columns": [list(c) for c in self.columns],
                "rows": [list(r) for r in self.rows], "overlap_nodes": self.overlap_nodes,
                "x_seams_m": self.seams(0), "y_seams_m": self.seams(1),
                "blend_width_m": list(self.blend_width)}

    @classmethod
    def from_description(cls, data: dict[str, Any]) -> TilesetLayout:
        """The layout `describe` wrote."""
        return cls(shape=(int(data["shape"][0]), int(data["shape"][1])),
                   spacing=(float(data["spacing"][0]), float(data["spacing"][1])),
                   origin=(float(data["origin"][0]), float(data["origin"][1])),
                   columns=tuple((int(a), int(b)) for a, b in data["columns"]),
                   rows=tuple((int(a), int(b)) for a, b in data["rows"]),
                   overlap_nodes=int(data["overlap_nodes"]))


def window_tile(region: DemTile, box: tuple[int, int, int, int], name: str,
                source: str = "") -> DemTile:
    """The part ``(r0, r1, c0, c1)`` (inclusive nodes) of the region as a tile in the region's
    frame (same georeference, origin moved to the box's first node).

    Raises:
        NeuralMapError: A box with no finite height (all void).
    """
    r0, r1, c0, c1 = box
    (x0, y0), (dx, dy) = region.origin, region.spacing
    meta = {k: region.meta[k] for k in ("units", "units_reason", "crs", "nodata")
            if k in region.meta}
    return DemTile(heights=region.heights[r0:r1 + 1, c0:c1 + 1].copy(), spacing=region.spacing,
                   origin=(x0 + c0 * dx, y0 + r0 * dy), name=name, geo=region.geo,
                   source=source or region.source, meta=meta, projected=region.projected)
