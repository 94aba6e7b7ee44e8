"""Uniform cubic B-splines: the smooth (C², hence C¹) upsampling kernel of latent-grid maps.

A latent level ``l`` holds coefficients ``c[i, j]`` on a lattice ``2^l`` node intervals
apart; its continuous feature is the tensor-product cubic B-spline

``f_l(u, v) = sum_ij c[i, j] B(v / 2^l - i) B(u / 2^l - j)``

with ``(u, v)`` the position in node intervals and ``B`` the centred cubic B-spline
(support ``[-2, 2]``). On one cell, at fraction ``t`` in ``[0, 1]``, the four non-zero
weights are ``((1-t)^3, 3t^3 - 6t^2 + 4, -3t^3 + 3t^2 + 3t + 1, t^3) / 6``.

Two-scale relation (exact): ``B(x / 2) = sum_m h[m] B(x - m)`` with
``h = [1, 4, 6, 4, 1] / 8``, so a coarse level is *exactly* a finer-level spline whose
coefficients are the coarse ones upsampled by two and filtered with ``h``
(`refine`). Refining every level to the node lattice gives one coefficient grid per
feature channel; querying it is a single 4 x 4 gather per point, whatever the number of
levels (the multi-level sum is reproduced to float rounding; no map is sampled on a grid).

Coefficient indexing along an axis with ``n`` nodes at level scale ``s = 2^l``: knots
``j = -1 .. ceil((n - 1) / s) + 1`` (stored at array index ``j + 1``), so
`coefficient_count` ``= ceil((n - 1) / s) + 3``; a point at ``u`` lies in cell
``min(floor(u / s), ceil((n - 1) / s) - 1)`` and reads array indices ``cell .. cell + 3``.
"""

from __future__ import annotations

import math

import torch

#: Two-scale (refinement) filter of the cubic B-spline, taps ``m = -2 .. 2``.
REFINE_TAPS = (1.0 / 8.0, 4.0 / 8.0, 6.0 / 8.0, 4.0 / 8.0, 1.0 / 8.0)
#: Node-value filter: the spline at its own knots, ``B(-1), B(0), B(1)``.
NODE_TAPS = (1.0 / 6.0, 4.0 / 6.0, 1.0 / 6.0)

# Cubic B-spline weights of array indices cell .. cell + 3 as rows over [t^3, t^2, t, 1]
# (rows 0-3), and their derivatives d/dt (rows 4-7).
_BSPLINE = (
    (-1.0 / 6.0, 0.5, -0.5, 1.0 / 6.0),
    (0.5, -1.0, 0.0, 4.0 / 6.0),
    (-0.5, 0.5, 0.5, 1.0 / 6.0),
    (1.0 / 6.0, 0.0, 0.0, 0.0),
    (0.0, -0.5, 1.0, -0.5),
    (0.0, 1.5, -2.0, 0.0),
    (0.0, -1.5, 1.0, 0.5),
    (0.0, 0.5, 0.0, 0.0),
)


def coefficient_count(nodes: int, scale: int) -> int:
    """Coefficients along an axis of ``nodes`` nodes at level scale ``scale = 2^l``."""
    return int(math.ceil((nodes - 1) / scale)) + 3


def bspline_matrix(like: torch.Tensor) -> torch.Tensor:
    """``(8, 4)`` weight / derivative matrix over ``[t^3, t^2, t, 1]`` in ``like``'s dtype."""
    return torch.tensor(_BSPLINE, dtype=like.dtype, device=like.device)


def bspline_weights(t: torch.Tensor, *, derivative: bool) -> torch.Tensor:
    """Cubic B-spline weights (and optionally their ``d/dt``) at cell fractions ``t``.

    Args:
        t: ``(M,)`` fractions in ``[0, 1]``.
        derivative: Also return the derivative rows.

    Returns:
        ``(4, M)`` weights, or ``(8, M)`` with rows 4-7 the derivatives ``d/dt``;
        differentiable in ``t``.
    """
    powers = torch.stack([t * t * t, t * t, t, torch.ones_like(t)])
    mat = bspline_matrix(t)
    return (mat if derivative else mat[:4]) @ powers


def _refine_axis(a: torch.Tensor, count: int, dim: int) -> torch.Tensor:
    """Two-scale refinement along one axis: ``count`` fine coefficients from coarse ``a``.

    With knot indices ``j`` (array index ``j + 1``), the fine coefficients are
    ``E[p] = (c[p-1] + 6 c[p] + c[p+1]) / 8`` at fine knot ``2p`` and
    ``O[p] = (c[p] + c[p+1]) / 2`` at ``2p + 1`` (the taps ``h`` split by parity);
    the fine sequence from knot ``-1`` is ``O[-1], E[0], O[0], E[1], ...``.
    """
    a = a.movedim(dim, -1)
    odd = 0.5 * (a[..., :-1] + a[..., 1:])
    even = 0.125 * (a[..., :-2] + 6.0 * a[..., 1:-1] + a[..., 2:])
    even = torch.cat([even, torch.zeros_like(even[..., :1])], dim=-1)
    fine = torch.stack([odd, even], dim=-1).flatten(-2)[..., :count]
    return fine.movedim(-1, dim)


def refine(coeffs: torch.Tensor, target: tuple[int, int]) -> torch.Tensor:
    """One dyadic refinement step (two-scale relation), both axes, exact.

    Args:
        coeffs: ``(..., n_y, n_x)`` coefficients at scale ``2s``.
        target: ``(m_y, m_x)`` coefficient counts at scale ``s``
            (`coefficient_count`).

    Returns:
        ``(..., m_y, m_x)`` coefficients at scale ``s`` whose spline equals the input's on
        the node extent.
    """
    return _refine_axis(_refine_axis(coeffs, target[0], -2), target[1], -1)


def node_values(coeffs: torch.Tensor) -> torch.Tensor:
    """Spline values at the nodes of a node-lattice coefficient grid.

    Args:
        coeffs: ``(C, ny + 2, nx + 2)`` coefficients at scale 1.

    Returns:
        ``(C, ny, nx)`` values at the nodes (separable ``[1, 4, 1] / 6`` filter).
    """
    x = (coeffs[..., :-2, :] + 4.0 * coeffs[..., 1:-1, :] + coeffs[..., 2:, :]) * (1.0 / 6.0)
    return (x[..., :-2] + 4.0 * x[..., 1:-1] + x[..., 2:]) * (1.0 / 6.0)


def cell_position(
    u: torch.Tensor, cells: int
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Cell index and fraction of positions along one node-lattice axis.

    Args:
        u: ``(M,)`` positions in node intervals (any real; clamped to ``[0, cells]``).
        cells: Number of cells ``n - 1``.

    Returns:
        ``(index (M,) long, fraction t (M,), inside (M,) bool)``; ``inside`` is False where
        ``u`` was clamped (the slope across the border is then zero) or is NaN.
    """
    uc = u.clamp(0.0, float(cells))
    inside = uc == u
    cell = torch.nan_to_num(uc.detach().floor(), nan=0.0).clamp_(max=cells - 1.0)
    return cell.long(), uc - cell, inside


def interpolation_operator(nodes: int) -> torch.Tensor:
    """``(nodes + 2, nodes)`` float64 matrix from node values to interpolating coefficients.

    The cubic B-spline coefficients ``c_{-1} .. c_n`` whose spline passes through the node
    values, ``(c_{k-1} + 4 c_k + c_{k+1}) / 6 = h_k``, closed by the natural end conditions
    ``c_{-1} - 2 c_0 + c_1 = 0`` and ``c_{n-2} - 2 c_{n-1} + c_n = 0`` (zero second
    derivative at the border nodes, so the grid continues smoothly past the extent).
    A dense solve, ``O(n^3)`` once per axis.
    """
    n = int(nodes)
    system = torch.zeros(n + 2, n + 2, dtype=torch.float64)
    rows = torch.arange(n)
    for offset, tap in enumerate(NODE_TAPS):
        system[rows, rows + offset] = tap
    system[n, :3] = torch.tensor([1.0, -2.0, 1.0], dtype=torch.float64)
    system[n + 1, n - 1 :] = torch.tensor([1.0, -2.0, 1.0], dtype=torch.float64)
    rhs = torch.zeros(n + 2, n, dtype=torch.float64)
    rhs[rows, rows] = 1.0
    return torch.linalg.solve(system, rhs)


def interpolating_coefficients(heights: torch.Tensor) -> torch.Tensor:
    """``(ny + 2, nx + 2)`` node-lattice coefficients whose spline interpolates ``heights``.

    Args:
        heights: ``(ny, nx)`` node values (float64, no voids).

    Returns:
        Coefficients with `node_values` equal to ``heights`` (float64).
    """
    ny, nx = heights.shape
    return interpolation_operator(ny) @ heights.double() @ interpolation_operator(nx).T
