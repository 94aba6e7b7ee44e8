"""Adding a correlated DEM-making error to a DEM tile (SEEDS 000, eq. 4: h_d = h_t + m_d)."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from neuralmap.dem.tile import DemTile
from neuralmap.errors.simulation import (
    DEM_ERROR_AR1,
    DEM_ERROR_SIGMA,
    ar1_coefficient,
    ar_error_field,
)


def add_dem_error(
    tile: DemTile,
    *,
    phi: Sequence[float] = DEM_ERROR_AR1,
    phi_north: Sequence[float] | None = None,
    sigma: float = DEM_ERROR_SIGMA,
    correlation_length_m: float | None = None,
    seed: int = 0,
) -> DemTile:
    """Returns a new tile whose heights carry a separable AR DEM-making error field.

    The true terrain ``tile`` is left unchanged; the returned map is what a DEM maker would
    deliver: ``h_d = h_t + m_d`` with ``m_d`` AR(p) along every grid row and column
    (`neuralmap.errors.ar_error_field`). The coefficients are per grid step, so the
    correlation length scales with the tile's spacing (the paper's grid: 100 m). Void nodes
    stay void.

    Args:
        tile: The true terrain.
        phi: AR coefficients between east neighbours (default the paper's AR(1) 0.5315).
        phi_north: AR coefficients between north neighbours (default ``phi``).
        sigma: Standard deviation of the error, m (default 1.0435).
        correlation_length_m: If given, overrides ``phi`` / ``phi_north`` with the AR(1)
            coefficients ``exp(−d / L)`` for the tile's east and north spacing ``d``
            (the paper's φ on its 100 m grid is L ≈ 158 m).
        seed: Seed of the error field.

    Returns:
        A new `DemTile` (same grid, name ``"<name>+dem_error"``); ``meta["dem_error"]``
        records the error model and seed.
    """
    if correlation_length_m is not None:
        phi = (ar1_coefficient(correlation_length_m, tile.spacing[0]),)
        phi_north = (ar1_coefficient(correlation_length_m, tile.spacing[1]),)
    field = ar_error_field(tile.shape, phi=phi, phi_north=phi_north, sigma=sigma, seed=seed)
    meta = dict(tile.meta)
    meta["dem_error"] = {
        "phi_east": [float(v) for v in phi],
        "phi_north": [float(v) for v in (phi if phi_north is None else phi_north)],
        "sigma": float(sigma),
        "correlation_length_m": correlation_length_m,
        "seed": int(seed),
        "true_tile": tile.fingerprint(),
    }
    return DemTile(
        heights=np.asarray(tile.heights) + field,
        spacing=tile.spacing,
        origin=tile.origin,
        name=f"{tile.name}+dem_error",
        geo=tile.geo,
        source=tile.source,
        meta=meta,
    )
