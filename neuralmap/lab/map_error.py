"""A map's error against the scenario's truth terrain, measured between the nodes.

The filter's R must cover the map's error where the aircraft flies, which is mostly
*between* DEM nodes. A fit RMSE at the training nodes (after refitting on every node it is
in-sample) understates it; the honest number compares the map with the truth terrain at
random points. Points are uniform over the tile's extent, seeded.
"""

from __future__ import annotations

import math
from typing import Any

import torch

from neuralmap.dem.tile import DemTile

__all__ = ["map_error_correlation", "measure_map_error"]


def measure_map_error(
    terrain_map: Any,
    truth_model: Any,
    tile: DemTile,
    *,
    n_points: int = 20000,
    seed: int = 0,
    chunk: int = 65536,
) -> dict[str, Any]:
    """Error statistics of ``terrain_map − truth`` at seeded random points of the tile.

    Args:
        terrain_map: Any terrain model (``forward(xy) -> height``).
        truth_model: The truth terrain (`neuralmap.lab.truth_terrain.true_terrain`).
        tile: The tile whose extent the points cover.
        n_points: Number of points.
        seed: Seed of the points.
        chunk: Points per forward pass.

    Returns:
        ``{"rmse_m", "mse_m2", "mean_m", "max_abs_m", "p99_abs_m", "n_points", "seed"}``
        (the neural method adds ``mse_m2`` to R).
    """
    xmin, xmax, ymin, ymax = tile.extent
    gen = torch.Generator().manual_seed(int(seed) + 0x3E7)
    u = torch.rand(n_points, 2, generator=gen, dtype=torch.float64)
    xy = torch.stack([xmin + u[:, 0] * (xmax - xmin), ymin + u[:, 1] * (ymax - ymin)], dim=-1)
    errors = []
    param = next(iter(terrain_map.parameters()), None) if hasattr(terrain_map, "parameters") else None
    dtype = param.dtype if param is not None else torch.float64
    device = param.device if param is not None else torch.device("cpu")
    with torch.no_grad():
        for start in range(0, n_points, chunk):
            part = xy[start:start + chunk]
            predicted = terrain_map(part.to(device=device, dtype=dtype)).double().cpu()
            errors.append(predicted - truth_model(part))
    err = torch.cat(errors)
    err = err[torch.isfinite(err)]
    if err.numel() == 0:
        return {"n_points": 0, "seed": seed}
    mse = float((err * err).mean())
    abs_err = err.abs()
    return {
        "rmse_m": math.sqrt(mse),
        "mse_m2": mse,
        "mean_m": float(err.mean()),
        "max_abs_m": float(abs_err.max()),
        "p99_abs_m": float(torch.quantile(abs_err, 0.99)) if err.numel() > 1 else float(abs_err[0]),
        "n_points": int(err.numel()),
        "seed": int(seed),
    }


def map_error_correlation(
    terrain_map: Any,
    truth_model: Any,
    tile: DemTile,
    *,
    lag_m: float,
    n_points: int = 20000,
    seed: int = 0,
) -> float:
    """Correlation of the map error between points ``lag_m`` apart (random directions).

    ``ρ = corr(e(p), e(p + lag · u))`` with ``e = map − truth``, ``p`` uniform over the
    tile shrunk by ``lag_m``, ``u`` a uniform random unit vector (seeded): the correlation
    of the map error between successive altimeter samples when ``lag_m`` is the distance
    flown per step (the map-aware PCRB's Gauss-Markov map error).

    Returns:
        ρ clipped to ``[0, 0.99]`` (0 when the error has no spread).
    """
    xmin, xmax, ymin, ymax = tile.extent
    gen = torch.Generator().manual_seed(int(seed) + 0x5EED)
    u = torch.rand(n_points, 2, generator=gen, dtype=torch.float64)
    p = torch.stack([xmin + lag_m + u[:, 0] * (xmax - xmin - 2 * lag_m),
                     ymin + lag_m + u[:, 1] * (ymax - ymin - 2 * lag_m)], -1)
    ang = 2.0 * math.pi * torch.rand(n_points, generator=gen, dtype=torch.float64)
    q = p + lag_m * torch.stack([ang.cos(), ang.sin()], -1)
    param = next(iter(terrain_map.parameters()), None) if hasattr(terrain_map, "parameters") else None
    dtype = param.dtype if param is not None else torch.float64
    with torch.no_grad():
        e1 = terrain_map(p.to(dtype)).double() - truth_model(p)
        e2 = terrain_map(q.to(dtype)).double() - truth_model(q)
    ok = torch.isfinite(e1) & torch.isfinite(e2)
    e1, e2 = e1[ok] - e1[ok].mean(), e2[ok] - e2[ok].mean()
    denom = float((e1.square().mean() * e2.square().mean()).sqrt())
    if not denom > 0:
        return 0.0
    return min(max(float((e1 * e2).mean()) / denom, 0.0), 0.99)
