"""Grid terrain: bilinear and bicubic interpolation of a DEM tile as a `TerrainModel`.

The tile's heights live in a buffer (so ``.to(device, dtype)`` moves them); interpolation is
batched over any leading shape and built from plain tensor ops, so autograd gives slopes.
`GridTerrain.height_and_slope` computes the same slopes analytically (no autograd),
which is what the filter's hot path uses.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
import torch
from torch import nn

from neuralmap.dem.tile import DemTile
from neuralmap.exceptions import NeuralMapError
from neuralmap.terrain.base import TerrainModel

#: The interpolations of a grid map (`GridTerrain` ``method``).
INTERPOLATIONS = ("bilinear", "bicubic")


class BilinearParts(NamedTuple):
    """Bilinear height, slope and the pieces of the cell that the Taylor variance needs.

    Attributes:
        height: ``(M,)`` interpolated heights.
        slope: ``(M, 2)`` analytic ``(dh/dx, dh/dy)`` (zero across the border when clamped).
        twist: ``(M,)`` cell twist ``h00 - h01 - h10 + h11`` (zero on a plane).
        fu: ``(M,)`` fractional east position in the cell, ``[0, 1]``.
        fv: ``(M,)`` fractional north position in the cell, ``[0, 1]``.
    """

    height: torch.Tensor
    slope: torch.Tensor
    twist: torch.Tensor
    fu: torch.Tensor
    fv: torch.Tensor


def fill_voids_nearest(heights: np.ndarray, spacing: tuple[float, float]) -> np.ndarray:
    """Replaces NaN nodes by the value of the nearest valid node (metric distance).

    Uses `scipy.ndimage.distance_transform_edt` when scipy is installed, otherwise an
    exact chunked brute-force search in torch.

    Args:
        heights: ``(ny, nx)`` float64 heights, NaN = void; at least one valid node.
        spacing: ``(dx, dy)`` grid spacing in metres (distances are metric, not in nodes).

    Returns:
        ``(ny, nx)`` float64 heights without NaN (a copy).
    """
    heights = np.asarray(heights, dtype=np.float64)
    void = ~np.isfinite(heights)
    if not void.any():
        return heights.copy()
    dx, dy = spacing
    try:
        from scipy.ndimage import distance_transform_edt

        _, (ii, jj) = distance_transform_edt(void, sampling=(dy, dx), return_indices=True)
        return heights[ii, jj]
    except ImportError:  # pragma: no cover - scipy is a test dependency, normally present
        pass
    out = heights.copy()
    vi, vj = np.nonzero(void)
    gi, gj = np.nonzero(~void)
    good = torch.from_numpy(np.stack([gj * dx, gi * dy], axis=1).astype(np.float64))
    chunk = 4096
    for start in range(0, vi.size, chunk):
        ci, cj = vi[start : start + chunk], vj[start : start + chunk]
        query = torch.from_numpy(np.stack([cj * dx, ci * dy], axis=1).astype(np.float64))
        nearest = torch.cdist(query, good).argmin(dim=1).numpy()
        out[ci, cj] = heights[gi[nearest], gj[nearest]]
    return out


def _snap(u: torch.Tensor, tol: float, *, inplace: bool) -> torch.Tensor:
    """``u`` with the values within ``tol`` of an integer set to that integer; the gradient
    stays 1 (the snap is a constant offset; NaN stays NaN)."""
    nearest = torch.round(u.detach())
    offset = nearest - u.detach()
    offset = torch.where(offset.abs() <= tol, offset, torch.zeros_like(offset))
    return u.add_(offset) if inplace else u + offset


def pad_cubic(heights: torch.Tensor) -> torch.Tensor:
    """Pads one node on every side with the quadratic-exact boundary rule.

    ``f[-1] = 3 f[0] - 3 f[1] + f[2]`` and symmetrically at the far end (Keys 1981, the
    boundary condition that keeps cubic convolution exact on quadratics); with only two
    nodes along an axis the linear rule ``f[-1] = 2 f[0] - f[1]`` is used.

    Args:
        heights: ``(ny, nx)`` heights without voids.

    Returns:
        ``(ny + 2, nx + 2)`` padded heights; rows are extended first, then columns, so the
        corners are the tensor-product extrapolation.
    """

    def pad_axis(a: torch.Tensor, dim: int) -> torch.Tensor:
        a = a.movedim(dim, 0)
        if a.shape[0] >= 3:
            lo = 3.0 * a[0] - 3.0 * a[1] + a[2]
            hi = 3.0 * a[-1] - 3.0 * a[-2] + a[-3]
        else:
            lo = 2.0 * a[0] - a[1]
            hi = 2.0 * a[-1] - a[-2]
        return torch.cat([lo[None], a, hi[None]], dim=0).movedim(0, dim)

    return pad_axis(pad_axis(heights, 0), 1).contiguous()


# Keys cubic convolution (a = -1/2): weights of nodes k-1, k, k+1, k+2 for a point at
# fraction t in [0, 1] between nodes k and k+1, as rows over the powers [t^3, t^2, t, 1];
# rows 4-7 are their derivatives d/dt.
_KEYS = (
    (-0.5, 1.0, -0.5, 0.0),
    (1.5, -2.5, 0.0, 1.0),
    (-1.5, 2.0, 0.5, 0.0),
    (0.5, -0.5, 0.0, 0.0),
    (0.0, -1.5, 2.0, -0.5),
    (0.0, 4.5, -5.0, 0.0),
    (0.0, -4.5, 4.0, 0.5),
    (0.0, 1.5, -1.0, 0.0),
)


def _refresh_padding(module: nn.Module, incompatible_keys: object) -> None:
    """After ``load_state_dict``: rebuild the (non-persistent) bicubic padding from heights."""
    if module.method == "bicubic":
        module.padded = pad_cubic(module.heights.detach())


class GridTerrain(TerrainModel):
    """Bilinear or bicubic interpolation of a `DemTile` as a `TerrainModel`.

    Bicubic is Keys cubic convolution with ``a = -1/2`` and the boundary extrapolation
    ``f[-1] = 3 f[0] - 3 f[1] + f[2]`` (symmetric at the far end): it reproduces every
    quadratic exactly, including in the border cells. Bilinear reproduces planes.
    Void (NaN) nodes are filled with the nearest valid node (metric distance) before
    interpolation; ``n_filled`` says how many.

    Points outside `extent` are clamped to the border: the height is that of the
    nearest border point and the slope component across the border is zero (what autograd
    of the clamp gives). A point within coordinate rounding of a node is taken at the node
    (a node in float32 lands a hair off it), so nodes, border nodes included, get the same
    cell and slope in float32 as in float64. Callers flag off-map points with
    `contains`.
    NaN coordinates give NaN heights (never an indexing error; the slope is NaN or 0).

    ``heights`` (the void-filled grid) is the persistent buffer; the bicubic padding is
    derived from it (rebuilt by ``load_state_dict``).

    Outputs have the floating dtype of ``xy`` (integer ``xy`` uses the grid dtype); the
    gathered node heights are cast, never the whole grid.

    Args:
        tile: The DEM tile.
        method: ``"bilinear"`` or ``"bicubic"``.
        dtype: Floating dtype of the height buffer.

    Raises:
        NeuralMapError: Unknown ``method``, non-floating ``dtype``, or a tile that is not a
            `DemTile`.
    """

    heights: torch.Tensor
    padded: torch.Tensor

    def __init__(
        self, tile: DemTile, *, method: str = "bilinear", dtype: torch.dtype = torch.float64
    ) -> None:
        super().__init__()
        if not isinstance(tile, DemTile):
            raise NeuralMapError(
                f"GridTerrain: 'tile' must be a neuralmap.dem.tile.DemTile, got "
                f"{type(tile).__name__}. Load one with neuralmap.dem.load_tile(name_or_path)."
            )
        if method not in INTERPOLATIONS:
            raise NeuralMapError(
                f"GridTerrain: unknown interpolation method {method!r}; choose one of "
                f"{', '.join(INTERPOLATIONS)}."
            )
        if not (isinstance(dtype, torch.dtype) and dtype.is_floating_point):
            raise NeuralMapError(
                f"GridTerrain: dtype must be a floating torch dtype (e.g. torch.float64), "
                f"got {dtype!r}."
            )
        self.method = method
        self.shape = tile.shape
        self.spacing = tuple(float(s) for s in tile.spacing)
        self.origin = tuple(float(o) for o in tile.origin)
        self.extent = tuple(float(e) for e in tile.extent)  # type: ignore[assignment]
        self.tile_name = tile.name
        self.tile_fingerprint = tile.fingerprint()
        self.n_filled = tile.n_void
        self.register_buffer("void", torch.as_tensor(~np.isfinite(tile.heights)),
                             persistent=False)
        filled = fill_voids_nearest(tile.heights, tile.spacing)
        self.register_buffer("heights", torch.as_tensor(filled, dtype=dtype))
        heights = torch.as_tensor(filled, dtype=torch.float64)
        padded = pad_cubic(heights) if method == "bicubic" else heights.new_zeros(0, 0)
        self.register_buffer("padded", padded.to(dtype), persistent=False)
        ny, nx = self.shape
        pnx = nx + 2
        offsets = torch.arange(4)[:, None] * pnx + torch.arange(4)[None, :]
        self.register_buffer("_cubic_offsets", offsets.reshape(16), persistent=False)
        self._keys_cache: dict[tuple[torch.dtype, torch.device], torch.Tensor] = {}
        self.register_load_state_dict_post_hook(_refresh_padding)

    def extra_repr(self) -> str:
        """Short description for ``print(model)``."""
        return (
            f"tile={self.tile_name!r}, method={self.method!r}, shape={self.shape}, "
            f"spacing={self.spacing}, dtype={self.heights.dtype}"
        )

    def _check_xy(self, xy: torch.Tensor) -> torch.Tensor:
        """Validates ``(..., 2)`` and promotes non-floating input to the grid dtype."""
        if not isinstance(xy, torch.Tensor) or xy.ndim < 1 or xy.shape[-1] != 2:
            shape = tuple(xy.shape) if isinstance(xy, torch.Tensor) else type(xy).__name__
            raise NeuralMapError(
                f"GridTerrain: xy must be a tensor of shape (..., 2) (east, north metres), "
                f"got {shape}."
            )
        if not xy.is_floating_point():
            xy = xy.to(self.heights.dtype)
        return xy

    def _cell(
        self, x: torch.Tensor, y: torch.Tensor, *, inplace: bool, row_stride: int, masks: bool
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor | None, torch.Tensor | None]:
        """Fractional cell position, flat index of the south-west node and not-clamped masks.

        Args:
            x: ``(M,)`` east coordinates.
            y: ``(M,)`` north coordinates.
            inplace: Use in-place ops (only when no autograd graph is being recorded).
            row_stride: Row length of the flat array indexed: ``nx`` for the grid (the
                index is that of node ``(i, j)``), ``nx + 2`` for the padded grid (the
                index is that of padded node ``(i, j)``, i.e. grid node ``(i-1, j-1)``).
            masks: Also return the not-clamped masks (needed for slopes only).

        Returns:
            ``fu, fv`` (differentiable in x, y unless ``inplace``), ``idx`` (long flat
            index), ``in_u, in_v`` (bool, or None without ``masks``).
        """
        ny, nx = self.shape
        (x0, y0), (dx, dy) = self.origin, self.spacing
        if inplace:
            u = (x - x0).mul_(1.0 / dx)
            v = (y - y0).mul_(1.0 / dy)
        else:
            u = (x - x0) * (1.0 / dx)
            v = (y - y0) * (1.0 / dy)
        # A node's own coordinate maps to an integer u only up to rounding (in float32
        # node 15 gives u = 14.999999): snap u, v within that rounding to the node, so a
        # node picks the same cell (the same one-sided bilinear slope) in every dtype and
        # a border node is on the border, not just off it (slope across it kept).
        tol_u, tol_v = self._node_tolerance(u.dtype)
        u, v = _snap(u, tol_u, inplace=inplace), _snap(v, tol_v, inplace=inplace)
        uc = u.clamp(0.0, nx - 1.0)
        vc = v.clamp(0.0, ny - 1.0)
        if masks:
            in_u, in_v = u == uc, v == vc  # False for clamped points (and NaN)
        else:
            in_u = in_v = None
        # NaN coordinates index node 0 here; their fu/fv stay NaN, so outputs are NaN.
        jf = torch.nan_to_num(uc.detach().floor(), nan=0.0).clamp_(max=nx - 2.0)
        i_f = torch.nan_to_num(vc.detach().floor(), nan=0.0).clamp_(max=ny - 2.0)
        if uc.dtype == torch.float64 or (ny + 2) * row_stride < 2**24:  # float index exact
            idx = torch.add(jf, i_f, alpha=row_stride).long()
        else:
            idx = i_f.long() * row_stride + jf.long()
        if inplace:
            return uc.sub_(jf), vc.sub_(i_f), idx, in_u, in_v
        return uc - jf, vc - i_f, idx, in_u, in_v

    def _node_tolerance(self, dtype: torch.dtype) -> tuple[float, float]:
        """How far from a node (in cells, east and north) a point still counts as on it:
        8 roundings of ``u = (x − x0) / dx`` in ``dtype`` (the coordinate's own rounding,
        ``eps·(|x0| + extent) / dx``, plus the division's, ``eps·nx``): ~1e-4 cells in
        float32 on a 400-node tile (a centimetre at 75 m spacing), ~1e-13 in float64."""
        eps = torch.finfo(dtype).eps
        (x0, y0), (dx, dy) = self.origin, self.spacing
        ny, nx = self.shape
        tol_u = 8.0 * eps * ((abs(x0) + nx * dx) / dx + nx)
        tol_v = 8.0 * eps * ((abs(y0) + ny * dy) / dy + ny)
        return tol_u, tol_v

    def bilinear_parts(self, xy: torch.Tensor) -> BilinearParts:
        """Bilinear height, analytic slope and cell twist, without autograd (fast path).

        Uses the bilinear interpolant whatever `method` is.

        Args:
            xy: ``(..., 2)`` east/north metres.

        Returns:
            `BilinearParts`; every field has the leading shape ``(...)``.
        """
        xy = self._check_xy(xy)
        lead = xy.shape[:-1]
        nx = self.shape[1]
        with torch.no_grad():
            flat_xy = xy.reshape(-1, 2)
            fu, fv, idx, in_u, in_v = self._cell(
                flat_xy[:, 0], flat_xy[:, 1], inplace=True, row_stride=nx, masks=True
            )
            flat = self.heights.view(-1)
            dt = xy.dtype
            h00 = flat.index_select(0, idx).to(dt)
            d01 = flat[1:].index_select(0, idx).to(dt).sub_(h00)
            h10 = flat[nx:].index_select(0, idx).to(dt)
            twist = flat[nx + 1 :].index_select(0, idx).to(dt).sub_(h10).sub_(d01)
            d10 = h10.sub_(h00)
            gy = torch.addcmul(d10, fu, twist)
            height = torch.addcmul(h00, fu, d01).addcmul_(fv, gy)
            slope = torch.empty(flat_xy.shape, dtype=dt, device=xy.device)
            gx = torch.addcmul(d01, fv, twist).mul_(1.0 / self.spacing[0])
            torch.mul(gx, in_u, out=slope[:, 0])
            torch.mul(gy.mul_(1.0 / self.spacing[1]), in_v, out=slope[:, 1])
        return BilinearParts(
            height.view(lead),
            slope.view(*lead, 2),
            twist.view(lead),
            fu.view(lead),
            fv.view(lead),
        )

    def _bilinear_height(self, xy: torch.Tensor) -> torch.Tensor:
        """Bilinear heights ``(...)`` without autograd (fast path, no slope)."""
        nx = self.shape[1]
        with torch.no_grad():
            flat_xy = xy.reshape(-1, 2)
            fu, fv, idx, _, _ = self._cell(
                flat_xy[:, 0], flat_xy[:, 1], inplace=True, row_stride=nx, masks=False
            )
            flat = self.heights.view(-1)
            dt = xy.dtype
            h00 = flat.index_select(0, idx).to(dt)
            h01 = flat[1:].index_select(0, idx).to(dt)
            south = torch.lerp(h00, h01, fu)
            h10 = flat[nx:].index_select(0, idx).to(dt)
            h11 = flat[nx + 1 :].index_select(0, idx).to(dt)
            north = torch.lerp(h10, h11, fu)
            return torch.lerp(south, north, fv).view(xy.shape[:-1])

    def _bilinear_autograd(self, xy: torch.Tensor) -> torch.Tensor:
        """Differentiable bilinear heights ``(...)``."""
        nx = self.shape[1]
        fu, fv, idx, _, _ = self._cell(
            xy[..., 0], xy[..., 1], inplace=False, row_stride=nx, masks=False
        )
        flat = self.heights.view(-1)
        dt = xy.dtype
        h00 = flat[idx].to(dt)
        h01 = flat[idx + 1].to(dt)
        h10 = flat[idx + nx].to(dt)
        h11 = flat[idx + (nx + 1)].to(dt)
        a = h00 + fu * (h01 - h00)
        b = h10 + fu * (h11 - h10)
        return a + fv * (b - a)

    def _keys_matrix(self, like: torch.Tensor) -> torch.Tensor:
        """``(8, 4)`` Keys weight/derivative matrix in ``like``'s dtype and device (cached)."""
        key = (like.dtype, like.device)
        mat = self._keys_cache.get(key)
        if mat is None:
            mat = torch.tensor(_KEYS, dtype=like.dtype, device=like.device)
            self._keys_cache[key] = mat
        return mat

    def _cubic(
        self, xy: torch.Tensor, *, with_slope: bool
    ) -> tuple[torch.Tensor, torch.Tensor | None]:
        """Bicubic heights ``(M,)`` and optionally slopes ``(M, 2)`` of ``(M, 2)`` points.

        Differentiable in ``xy`` unless called under ``no_grad``. Works in a
        ``(row, col, M)`` layout so every op runs over contiguous memory.
        """
        inplace = not (torch.is_grad_enabled() and xy.requires_grad)
        nx = self.shape[1]
        pnx = nx + 2
        fu, fv, idx, in_u, in_v = self._cell(
            xy[:, 0], xy[:, 1], inplace=inplace, row_stride=pnx, masks=with_slope
        )
        # idx = padded index of padded node (i, j) = grid node (i - 1, j - 1)
        index = (self._cubic_offsets.unsqueeze(-1) + idx).view(-1)
        vals = self.padded.view(-1).index_select(0, index).to(xy.dtype).view(4, 4, -1)
        keys = self._keys_matrix(fu)
        n_w = 8 if with_slope else 4
        wx = keys[:n_w] @ torch.stack([fu * fu * fu, fu * fu, fu, torch.ones_like(fu)])
        wy = keys[:n_w] @ torch.stack([fv * fv * fv, fv * fv, fv, torch.ones_like(fv)])
        if not with_slope:
            rows = (vals * wx).sum(1)  # (4 rows, M)
            return (rows * wy).sum(0), None
        rows = (vals.unsqueeze(0) * wx.view(2, 1, 4, -1)).sum(2)  # (value|d/dt, 4 rows, M)
        height = (rows[0] * wy[:4]).sum(0)
        gx = (rows[1] * wy[:4]).sum(0) * (1.0 / self.spacing[0]) * in_u
        gy = (rows[0] * wy[4:]).sum(0) * (1.0 / self.spacing[1]) * in_v
        return height, torch.stack([gx, gy], dim=-1)

    def forward(self, xy: torch.Tensor) -> torch.Tensor:
        """Interpolated heights, differentiable in ``xy``.

        Args:
            xy: ``(..., 2)`` east/north metres.

        Returns:
            ``(...)`` heights in metres, dtype of ``xy``.
        """
        xy = self._check_xy(xy)
        if self.method == "bilinear":
            if torch.is_grad_enabled() and xy.requires_grad:
                return self._bilinear_autograd(xy)
            return self._bilinear_height(xy)
        height, _ = self._cubic(xy.reshape(-1, 2), with_slope=False)
        return height.view(xy.shape[:-1])

    def void_at(self, xy: torch.Tensor) -> torch.Tensor:
        """``(...)`` bool: the height at ``xy`` reads a void node of the DEM (one of the
        four nodes around it was a no-data cell, filled from its nearest neighbour: not a
        measured height). All False for a DEM without voids (no work).

        Args:
            xy: ``(..., 2)`` east/north metres (clamped to the map like `forward`).
        """
        xy = self._check_xy(xy)
        if self.n_filled == 0:
            return torch.zeros(xy.shape[:-1], dtype=torch.bool, device=xy.device)
        ny, nx = self.shape
        u = ((xy[..., 0] - self.origin[0]) / self.spacing[0]).clamp(0.0, nx - 1.0)
        v = ((xy[..., 1] - self.origin[1]) / self.spacing[1]).clamp(0.0, ny - 1.0)
        j = u.floor().clamp(max=nx - 2.0).long()
        i = v.floor().clamp(max=ny - 2.0).long()
        void = self.void.to(xy.device)
        return void[i, j] | void[i, j + 1] | void[i + 1, j] | void[i + 1, j + 1]

    def height_and_slope(self, xy: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Heights and analytic slopes ``(dh/dx, dh/dy)`` without autograd.

        Equal to autograd of `forward`, including the zero slope across the border
        for clamped points.

        Args:
            xy: ``(..., 2)`` east/north metres.

        Returns:
            ``(height (...), slope (..., 2))`` in metres and metres per metre.
        """
        if self.method == "bilinear":
            parts = self.bilinear_parts(xy)
            return parts.height, parts.slope
        xy = self._check_xy(xy)
        lead = xy.shape[:-1]
        with torch.no_grad():
            height, slope = self._cubic(xy.reshape(-1, 2), with_slope=True)
        assert slope is not None
        return height.view(lead), slope.view(*lead, 2)
