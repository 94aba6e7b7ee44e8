"""The latent pyramid: level shapes, refinement to the node lattice, Laplacian-pyramid start.

Level ``l = 0 .. L-1`` is a cubic B-spline coefficient grid with knots ``2^l`` node
intervals apart (`neuralmap.terrain.latent.bspline`). `node_lattice` refines
every level to the node lattice (one channel per level, exact); `laplacian_init`
starts the latents from a Laplacian pyramid of the DEM (Burt & Adelson 1983): the coarsest
level carries a smoothed DEM, each finer level the residual the coarser ones leave.
"""

from __future__ import annotations

import torch

from neuralmap.terrain.latent.bspline import coefficient_count, node_values, refine


def level_shapes(shape: tuple[int, int], levels: int) -> list[tuple[int, int]]:
    """Coefficient-grid shapes ``(n_y, n_x)`` of levels ``0 .. levels-1`` for ``(ny, nx)`` nodes."""
    ny, nx = shape
    return [(coefficient_count(ny, 2**k), coefficient_count(nx, 2**k)) for k in range(levels)]


def node_lattice(latents: list[torch.Tensor], shape: tuple[int, int]) -> torch.Tensor:
    """Every level refined to the node lattice, one channel per level.

    Args:
        latents: Level coefficient grids, finest first, shapes `level_shapes`.
        shape: ``(ny, nx)`` nodes.

    Returns:
        ``(L, ny + 2, nx + 2)`` coefficients whose splines equal the levels' on the
        node extent (differentiable).
    """
    shapes = level_shapes(shape, len(latents))
    x = latents[-1].unsqueeze(0)
    for level in range(len(latents) - 2, -1, -1):
        x = refine(x, shapes[level])
        x = torch.cat([latents[level].unsqueeze(0), x], dim=0)
    return x


def _reduce_axis(a: torch.Tensor, dim: int) -> torch.Tensor:
    """Burt-Adelson REDUCE along one axis: ``[1, 4, 6, 4, 1] / 16`` blur, every second node.

    ``n`` nodes become ``ceil((n - 1) / 2) + 1`` (replicated borders).
    """
    a = a.movedim(dim, -1)
    n = a.shape[-1]
    count = n // 2 + 1  # = ceil((n - 1) / 2) + 1
    pad = torch.cat([a[..., :1], a[..., :1], a, a[..., -1:], a[..., -1:], a[..., -1:]], dim=-1)
    blur = (pad[..., :-4] + 4.0 * pad[..., 1:-3] + 6.0 * pad[..., 2:-2] + 4.0 * pad[..., 3:-1]
            + pad[..., 4:]) * (1.0 / 16.0)
    return blur[..., ::2][..., :count].movedim(-1, dim)


def _level_samples(residual: torch.Tensor, level: int) -> torch.Tensor:
    """A node grid reduced ``level`` times, with one replicated knot on every side.

    Returns the ``level_shapes`` grid of that level (knots ``-1 .. ceil((n-1)/2^l) + 1``).
    """
    x = residual
    for _ in range(level):
        x = _reduce_axis(_reduce_axis(x, 0), 1)
    x = torch.cat([x[:1], x, x[-1:]], dim=0)
    return torch.cat([x[:, :1], x, x[:, -1:]], dim=1)


def laplacian_init(heights: torch.Tensor, levels: int, *, sweeps: int = 2) -> list[torch.Tensor]:
    """Latents of a Laplacian pyramid of ``heights`` (mean removed by the caller).

    Coarsest first: each level takes the residual left by the coarser levels, reduced to
    its knots (Burt & Adelson 1983's REDUCE), repeated ``sweeps`` times (a Jacobi-like
    correction, since a B-spline does not interpolate its coefficients); what is left
    goes to the finer levels.

    Args:
        heights: ``(ny, nx)`` float64 node heights without voids.
        levels: Number of levels.
        sweeps: Correction sweeps per level.

    Returns:
        Level coefficient grids, finest first (float64).
    """
    shape = tuple(heights.shape)
    shapes = level_shapes(shape, levels)  # type: ignore[arg-type]
    latents = [torch.zeros(s, dtype=heights.dtype) for s in shapes]
    for level in range(levels - 1, -1, -1):
        for _ in range(sweeps):
            decoded = node_values(node_lattice(latents, shape)).sum(0)  # type: ignore[arg-type]
            samples = _level_samples(heights - decoded, level)
            assert samples.shape == shapes[level], (samples.shape, shapes[level])
            latents[level] = latents[level] + samples
    return latents
