"""How good a latent-grid map is: size on disk, error at and between the nodes."""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from neuralmap.dem.tile import DemTile
from neuralmap.terrain.grid import GridTerrain
from neuralmap.terrain.latent.bitstream import encode_latent_map
from neuralmap.terrain.latent.map import LatentTerrainMap


def between_points(tile: DemTile, count: int, seed: int = 0) -> np.ndarray:
    """``(count, 2)`` seeded uniform random points (metres) inside the tile's extent."""
    xmin, xmax, ymin, ymax = tile.extent
    rng = np.random.default_rng([int(seed), 0xB37])
    return rng.uniform([xmin, ymin], [xmax, ymax], size=(int(count), 2))


def map_quality(latent_map: LatentTerrainMap, tile: DemTile, *, n_between: int = 20000,
                seed: int = 0) -> dict[str, Any]:
    """File size and errors of a latent map against its tile.

    Returns:
        ``file_bytes`` (the encoded file), ``bits_per_node``, ``rmse_m`` / ``max_abs_m``
        (valid nodes), ``between_rmse_m`` (RMS difference to bicubic interpolation of the
        DEM at ``n_between`` random points between the nodes).
    """
    nbytes = len(encode_latent_map(latent_map))
    valid = tile.valid_mask
    err = (latent_map.node_heights().numpy() - tile.heights)[valid]
    xy = torch.from_numpy(between_points(tile, n_between, seed))
    bicubic = GridTerrain(tile, method="bicubic")(xy).numpy()
    with torch.no_grad():
        got = latent_map(xy.float()).double().numpy()
    return {
        "file_bytes": nbytes,
        "bits_per_node": 8.0 * nbytes / int(valid.sum()),
        "rmse_m": float(np.sqrt(np.mean(err**2))),
        "max_abs_m": float(np.abs(err).max()),
        "between_rmse_m": float(np.sqrt(np.mean((got - bicubic) ** 2))),
    }
