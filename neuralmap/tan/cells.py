"""The map on a point-mass lattice's cells: heights, the map's support, the height spread.

Shared by the point-mass methods (the acquisition grid, `neuralmap.tan.methods.point_mass`,
and the whole-flight tracker, `neuralmap.tan.methods.tracker`). The measurement of cell
``s`` (a horizontal INS error) reads the map at ``p_ins − s`` (SEEDS 004: ``y = t(p_ins −
δp) + δh − v``); cells whose position lies off the map get no likelihood (NaN height).
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import torch

from neuralmap.filters.lattice.kernels import cell_reach, mass_radius, sorted_mass
from neuralmap.terrain.base import inside_extent

__all__ = ["cell_height_variance", "cell_heights", "cells_on_map", "heights_on_cells",
           "is_bilinear_grid", "lattice_bilinear", "lattice_protection_radius", "map_dtype",
           "mask_voids"]


def is_bilinear_grid(terrain: Any) -> bool:
    """The map is a bilinear `neuralmap.terrain.grid.GridTerrain` (the separable fast path
    of `lattice_bilinear` applies)."""
    return getattr(terrain, "method", None) == "bilinear" and hasattr(terrain, "heights")


def heights_on_cells(terrain: Any, ins_xy: torch.Tensor, extent: tuple[float, ...], *,
                     mask_off_map: bool = True) -> Callable[[torch.Tensor], torch.Tensor]:
    """``g(s) = t(p_ins − s)`` on any lattice's cells, NaN off the map.

    Args:
        terrain: The map (``forward(xy (M, 2)) -> (M,)``): a grid, a neural map, any
            `neuralmap.terrain.base.TerrainModel`.
        ins_xy: ``(N, 2)`` INS horizontal positions.
        extent: Map extent ``(xmin, xmax, ymin, ymax)``.
        mask_off_map: False keeps the map's own value off its extent (a grid clamps to its
            border) for a caller that masks later.

    Returns:
        Callable on cell coordinates ``(N, G, G, 2)`` returning ``(N, G, G)`` heights in
        their dtype (the map is evaluated in its own parameters' dtype).
    """
    own = map_dtype(terrain)

    def g(points: torch.Tensor) -> torch.Tensor:
        return cell_heights(terrain, ins_xy, extent, own, points, mask_off_map=mask_off_map)

    return g


def map_dtype(terrain: Any) -> torch.dtype | None:
    """The dtype a neural map is evaluated in (its parameters'); None for a grid (it takes
    its queries' dtype) or a map without parameters."""
    param = next(iter(terrain.parameters()), None) if hasattr(terrain, "parameters") else None
    return param.dtype if param is not None and not hasattr(terrain, "heights") else None


def cell_heights(terrain: Any, ins_xy: torch.Tensor, extent: tuple[float, ...],
                 own: torch.dtype | None, points: torch.Tensor, *,
                 mask_off_map: bool = True) -> torch.Tensor:
    """``g(s) = t(p_ins − s)`` at the cells ``points (N, G, G, 2)``: ``(N, G, G)`` in their
    dtype, NaN off the map and over its voids (`heights_on_cells`, whose callable this is;
    a module-level function, so that a compiled tracking epoch takes it as its map lookup:
    `neuralmap.filters.point_mass_tracker.PointMassTracker.track`).

    Args:
        terrain: The map.
        ins_xy: ``(N, 2)`` INS horizontal positions.
        extent: Map extent ``(xmin, xmax, ymin, ymax)``.
        own: The map's own dtype (`map_dtype`), None to query it in the cells' dtype.
        points: ``(N, G, G, 2)`` cell coordinates ``s``.
        mask_off_map: As `heights_on_cells`.
    """
    xy = ins_xy[:, None, None, :].to(points.dtype) - points  # p_ins − s
    flat = xy.reshape(-1, 2)
    with torch.no_grad():
        h = terrain(flat if own is None else flat.to(own))
    h = h.to(points.dtype).reshape(points.shape[:-1])
    h = mask_voids(terrain, xy, h)
    return torch.where(inside_extent(xy, extent), h, torch.nan) if mask_off_map else h


def mask_voids(terrain: Any, xy: torch.Tensor, heights: torch.Tensor) -> torch.Tensor:
    """``heights`` with NaN where the map reads a void of its DEM at ``xy (..., 2)`` (a
    filled no-data node is not a measured height: no likelihood there); unchanged for a map
    without voids or one that does not report them (``void_at``)."""
    if not getattr(terrain, "n_filled", 0) or not callable(getattr(terrain, "void_at", None)):
        return heights
    return heights.masked_fill(terrain.void_at(xy), torch.nan)


def _cell_axes(ins_xy: torch.Tensor, centre: torch.Tensor, spacing: torch.Tensor,
               offsets: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(N, G)`` map x of the grid's columns and map y of its rows (``p_ins − s``)."""
    dt = centre.dtype
    xs = ins_xy[:, 0:1].to(dt) - (centre[:, 0:1] + spacing[:, 0:1] * offsets)
    ys = ins_xy[:, 1:2].to(dt) - (centre[:, 1:2] + spacing[:, 1:2] * offsets)
    return xs, ys


def lattice_bilinear(heights: torch.Tensor, origin: tuple[float, float],
                     spacing_m: tuple[float, float], ins_xy: torch.Tensor, centre: torch.Tensor,
                     spacing: torch.Tensor, offsets: torch.Tensor) -> torch.Tensor:
    """Bilinear map heights at ``p_ins − s`` for every cell of axis-aligned grids (fast path).

    Equals ``GridTerrain(tile, method="bilinear")(ins_xy − points)`` (border clamping
    included), but the cell arithmetic runs per grid row and column ``(N, G)`` and only the
    four corner gathers and the blend run per cell.

    Args:
        heights: ``(ny, nx)`` DEM heights (rows along y), in the dtype wanted.
        origin: DEM origin ``(x0, y0)``, m.
        spacing_m: DEM node spacing ``(dx, dy)``, m.
        ins_xy: ``(N, 2)`` INS horizontal positions.
        centre: ``(N, 2)`` grid centres (state space: INS − truth).
        spacing: ``(N, 2)`` grid spacings.
        offsets: ``(G,)`` cell offsets ``j − (G − 1)/2``.

    Returns:
        ``(N, G, G)`` heights in the dtype of ``centre``.
    """
    ny, nx = heights.shape
    (x0, y0), (dx, dy) = origin, spacing_m
    xs, ys = _cell_axes(ins_xy, centre, spacing, offsets)
    u = ((xs - x0) / dx).clamp(0.0, nx - 1.0)
    v = ((ys - y0) / dy).clamp(0.0, ny - 1.0)
    jf = u.floor().clamp(max=nx - 2.0)
    i_f = v.floor().clamp(max=ny - 2.0)
    fu, fv = (u - jf)[:, None, :], (v - i_f)[:, :, None]
    idx = (i_f.long() * nx)[:, :, None] + jf.long()[:, None, :]
    flat = heights.reshape(-1)
    if flat.dtype != centre.dtype:
        flat = flat.to(centre.dtype)
    shape = idx.shape
    idx = idx.reshape(-1)
    h00 = flat.index_select(0, idx).view(shape)
    h01 = flat[1:].index_select(0, idx).view(shape)
    south = torch.lerp(h00, h01, fu)
    h10 = flat[nx:].index_select(0, idx).view(shape)
    h11 = flat[nx + 1:].index_select(0, idx).view(shape)
    return torch.lerp(south, torch.lerp(h10, h11, fu), fv)


def cells_on_map(ins_xy: torch.Tensor, centre: torch.Tensor, spacing: torch.Tensor,
                 offsets: torch.Tensor, extent: tuple[float, ...]) -> torch.Tensor:
    """``(N, G, G)`` bool: the cell's position ``p_ins − s`` lies on the map.

    Separable (rows ``i`` along y, columns ``j`` along x, as `lattice_bilinear`): the test
    runs per grid row and column ``(N, G)`` and one outer product per cell.

    Args:
        ins_xy: ``(N, 2)`` INS horizontal positions.
        centre: ``(N, 2)`` grid centres (state space: INS − truth).
        spacing: ``(N, 2)`` grid spacings.
        offsets: ``(G,)`` cell offsets.
        extent: Map extent ``(xmin, xmax, ymin, ymax)``.
    """
    xmin, xmax, ymin, ymax = extent
    xs, ys = _cell_axes(ins_xy, centre, spacing, offsets)
    inx = (xs >= xmin) & (xs <= xmax)
    iny = (ys >= ymin) & (ys <= ymax)
    return iny[:, :, None] & inx[:, None, :]


def cell_height_variance(heights: torch.Tensor) -> torch.Tensor:
    """Spread of the map height over each lattice cell, ``(N, G, G)`` m².

    ``(Δ_x² + Δ_y²) / 12`` with ``Δ`` the central height differences between neighbouring
    cells (one-sided at the border): the variance of a height that changes linearly by
    ``Δ`` across the cell. It measures the terrain's variation at the lattice's own scale,
    large while the lattice is coarse and negligible once it is fine ("likelihood
    flattening": a coarse lattice cannot step over a likelihood peak narrower than a cell).

    Args:
        heights: ``(N, G, G)`` map heights on the cells, m.

    Returns:
        ``(N, G, G)`` variances, m².
    """
    gy, gx = torch.gradient(heights, dim=(1, 2))
    return (gx.square() + gy.square()) * (1.0 / 12.0)  # uniform slope over a cell: Δ²/12


def lattice_protection_radius(points: torch.Tensor, weights: torch.Tensor, axes: torch.Tensor,
                              centre: torch.Tensor, risk: float, gaussian: torch.Tensor
                              ) -> torch.Tensor:
    """Horizontal protection radius of a point-mass posterior around ``centre``, m.

    The lattice holds the posterior as masses ``w`` on cells, each spread over its cell:
    a cell at distance ``d`` from the fix lies within ``d + h`` of it, ``h`` the half
    diagonal of the cell (`axes`). The radius is the larger of

    * ``r_w``: the smallest radius whose ``d + h`` ball holds at least ``1 − risk`` of the
      lattice's mass (a multi-modal posterior, a heavy tail: the lattice's own answer);
    * ``gaussian``: the Gaussian protection level of the same posterior's moments
      (`neuralmap.nav.integrity`), which also bounds the tail beyond the lattice's
      ``± span`` (mass the lattice cannot hold, e.g. beyond 5 σ).

    Cheap where the two agree: the lattice mass outside ``gaussian`` is one masked sum; the
    weighted quantile (a sort over the cells) runs only for vehicles where that mass
    exceeds the risk.

    Args:
        points: ``(N, G, G, 2)`` cell coordinates (state space).
        weights: ``(N, G, G)`` normalised cell masses.
        axes: ``(N, 2, 2)`` cell steps (columns).
        centre: ``(N, 2)`` the fix's position error estimate (the posterior mean).
        risk: Integrity risk in ``(0, 0.5)``.
        gaussian: ``(N,)`` the Gaussian protection level, m.

    Returns:
        ``(N,)`` radii, m (float64).
    """
    reach = cell_reach(points, axes, centre)
    w = weights.flatten(1).double()
    outside = torch.where(reach > gaussian[:, None], w, 0.0).sum(1)
    out = gaussian.double().clone()
    rows = (outside > risk).nonzero().reshape(-1)
    if rows.numel() > 0:  # the lattice's quantile: the (1 − risk) point of w over d + h
        r, cum = sorted_mass(reach.index_select(0, rows), w.index_select(0, rows))
        out[rows] = torch.maximum(out[rows], mass_radius(r, cum, risk))
    return out
