"""The map on a lattice's cells (`neuralmap.tan.cells`): the separable bilinear fast path
against `GridTerrain` read cell by cell, the separable map-support test against
`inside_extent`, the generic reader against the map, and the height spread against NumPy."""

from __future__ import annotations

from typing import Any

import numpy as np
import pytest
import torch

from neuralmap.tan.cells import (
    cell_height_variance,
    cells_on_map,
    heights_on_cells,
    is_bilinear_grid,
    lattice_bilinear,
)
from neuralmap.terrain.base import inside_extent
from neuralmap.terrain.grid import GridTerrain

D = torch.float64


@pytest.fixture(scope="module")
def grid(tiny_tile: Any) -> GridTerrain:  # noqa: ANN401
    return GridTerrain(tiny_tile, method="bilinear")


def _cells(n: int, g: int, seed: int) -> tuple[torch.Tensor, ...]:
    """Random grids ``(centre, spacing, offsets, ins)``, some of their cells off the map."""
    gen = torch.Generator().manual_seed(seed)
    centre = torch.randn(n, 2, generator=gen, dtype=D) * 300.0
    spacing = torch.rand(n, 2, generator=gen, dtype=D) * 40.0 + 1.0
    off = torch.arange(g, dtype=D) - 0.5 * (g - 1)
    ins = torch.rand(n, 2, generator=gen, dtype=D) * 3500.0 - 300.0
    return centre, spacing, off, ins


def _positions(centre: torch.Tensor, spacing: torch.Tensor, off: torch.Tensor,
               ins: torch.Tensor) -> torch.Tensor:
    """``(N, G, G, 2)`` map positions ``p_ins − s`` of every cell (rows along y)."""
    n, g = centre.shape[0], off.shape[0]
    px = (centre[:, 0, None, None] + spacing[:, 0, None, None] * off[None, None, :])
    py = (centre[:, 1, None, None] + spacing[:, 1, None, None] * off[None, :, None])
    s = torch.stack([px.expand(n, g, g), py.expand(n, g, g)], -1)
    return ins[:, None, None, :] - s


def test_lattice_bilinear_equals_grid_terrain(grid: GridTerrain) -> None:
    centre, spacing, off, ins = _cells(4, 12, 0)
    assert is_bilinear_grid(grid)
    fast = lattice_bilinear(grid.heights.to(D), grid.origin, grid.spacing, ins, centre,
                            spacing, off)
    ref = grid(_positions(centre, spacing, off, ins))  # border clamping included
    torch.testing.assert_close(fast, ref, atol=1e-9, rtol=0)


def test_cells_on_map_equals_inside_extent(tiny_tile: Any) -> None:  # noqa: ANN401
    centre, spacing, off, ins = _cells(5, 16, 2)
    spacing = spacing * 1.5 + 4.0
    got = cells_on_map(ins, centre, spacing, off, tiny_tile.extent)
    ref = inside_extent(_positions(centre, spacing, off, ins), tiny_tile.extent)
    assert torch.equal(got, ref) and bool(got.any()) and not bool(got.all())


def test_heights_on_cells_reads_the_map_and_masks_off_map(grid: GridTerrain) -> None:
    centre, spacing, off, ins = _cells(3, 9, 4)
    pos = _positions(centre, spacing, off, ins)
    points = ins[:, None, None, :] - pos  # the cells' state coordinates s
    got = heights_on_cells(grid, ins, grid.extent)(points)
    on = inside_extent(pos, grid.extent)
    assert bool(on.any()) and not bool(on.all())
    torch.testing.assert_close(got[on], grid(pos)[on], atol=1e-9, rtol=0)
    assert bool(got[~on].isnan().all())
    kept = heights_on_cells(grid, ins, grid.extent, mask_off_map=False)(points)
    torch.testing.assert_close(kept, grid(pos), atol=1e-9, rtol=0)


def test_cell_height_variance_equals_a_numpy_computation() -> None:
    gen = torch.Generator().manual_seed(1)
    h = torch.randn(2, 7, 7, generator=gen, dtype=D) * 30.0
    got = cell_height_variance(h).numpy()
    for r in range(2):
        gy, gx = np.gradient(h[r].numpy())  # central differences, one-sided at the border
        np.testing.assert_allclose(got[r], (gx**2 + gy**2) / 12.0, rtol=1e-12, atol=0)
