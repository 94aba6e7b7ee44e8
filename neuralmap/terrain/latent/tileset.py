"""LatentTileset: a region of latent-map tiles queried as one `TerrainModel`.

The index (`neuralmap.terrain.latent.tileset_index`) is read at once; a tile's bitstream is
read, checked against its SHA-256 and decoded the first time a point needs it, into a
bounded LRU cache (`neuralmap.terrain.latent.tile_cache`). Tiles are blended across their
seams by the C² partition of unity of `neuralmap.terrain.latent.tileset_layout`:

``h(x) = sum_i phi_i(x) h_i(x)``,
``grad h(x) = sum_i phi_i(x) grad h_i(x) + sum_i h_i(x) grad phi_i(x)``

(product rule; ``phi_i = psi_j(x) chi_k(y)``, so ``grad phi_i = (psi_j' chi_k, psi_j chi_k')``),
over the at most four tiles with ``phi_i > 0`` (one away from the seams). Each ``h_i`` is a
`LatentTerrainMap`, C² inside its window, so the blended
map is C² across seams: height and slope are continuous, and the analytic slope equals the
derivative of the height everywhere, blend zones included.

A query is batch-first: per point the candidate tiles and weights come from vectorised
index arithmetic, the (point, tile) pairs are sorted by tile, and each tile touched is
evaluated once on all its points (a loop over the handful of tiles touched, none over points).
Points outside the region are clamped to its border like a single latent map; non-finite
points give NaN.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path
from typing import Any

import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.terrain.latent.bitstream import decode_latent_map
from neuralmap.terrain.latent.evaluated import EvaluatedTerrain
from neuralmap.terrain.latent.map import LatentTerrainMap
from neuralmap.terrain.latent.tile_cache import DEFAULT_CACHE_BYTES, DecodedTileCache
from neuralmap.terrain.latent.tileset_index import TileEntry, file_sha256, read_tileset_index

__all__ = ["LatentTileset"]


class LatentTileset(EvaluatedTerrain):
    """A latent tileset (index + one bitstream per tile), decoded lazily.

    Args:
        index_path: ``latent_tileset.json`` or its folder.
        cache_bytes: Byte budget of the decoded tiles (default `DEFAULT_CACHE_BYTES`,
            1 GiB; None = unbounded). The tile in use is always kept.
        cache_tiles: Most decoded tiles kept at once (default None: bounded by bytes only).

    Attributes:
        index_path: The index file.
        layout: The tile grid (`TilesetLayout`).
        tiles: The index entries, row-major (tile id = ``row * columns + col``).
        cache: The `DecodedTileCache` (``decodes``, ``peak_tiles``, ``peak_bytes``).
        tile_info: The region's description (``DemTile.describe`` of the whole region).
        metrics: Region metrics stored at training (``rmse_m``, ``max_abs_m``, ...).

    Raises:
        NeuralMapError: Unreadable or malformed index; missing tile files (named).
    """

    def __init__(self, index_path: str | os.PathLike[str], *,
                 cache_bytes: int | None = DEFAULT_CACHE_BYTES,
                 cache_tiles: int | None = None) -> None:
        super().__init__()
        self.index_path, index = read_tileset_index(index_path)
        self.layout = index.layout
        self.tiles: list[TileEntry] = index.tiles
        self.tile_info: dict[str, Any] = dict(index.region)
        self.info = index.info
        self.metrics: dict[str, Any] = dict(index.info.get("metrics", {}))
        self.tile_name = str(self.tile_info.get("name", ""))
        self.tile_fingerprint = str(self.tile_info.get("fingerprint", ""))
        self.extent = self.layout.extent
        missing = [t.file for t in self.tiles if not (self.folder / t.file).is_file()]
        if missing:
            raise NeuralMapError(
                f"latent tileset '{self.index_path}': tile file(s) {missing[:3]} are missing "
                f"({len(missing)} of {len(self.tiles)}); copy the whole tileset folder "
                "(the index and its tiles/ folder).")
        self.cache = DecodedTileCache(self._decode, max_bytes=cache_bytes, max_tiles=cache_tiles)
        # float32 like the tiles' buffers: callers that take a model's dtype from its
        # buffers (map previews) query in float32, as for a single latent map.
        self.register_buffer("frame", torch.tensor(self.extent, dtype=torch.float32),
                             persistent=False)

    @property
    def folder(self) -> Path:
        """The folder the tile file names are relative to."""
        return self.index_path.parent

    def extra_repr(self) -> str:
        """Short description for ``print(model)``."""
        rows, cols = self.layout.grid
        return (f"region={self.tile_name!r}, tiles={rows}x{cols}, "
                f"overlap_nodes={self.layout.overlap_nodes}, resident={len(self.cache)}")

    def _decode(self, tile_id: int) -> LatentTerrainMap:
        """Reads, checks (SHA-256) and decodes one tile's bitstream."""
        entry = self.tiles[tile_id]
        path = self.folder / entry.file
        where = f"latent tileset '{self.index_path}', tile row {entry.row} col {entry.col}"
        try:
            data = path.read_bytes()
        except OSError as exc:
            raise NeuralMapError(f"{where}: tile file '{path}' cannot be read "
                                 f"({exc.strerror or exc}); copy the whole tileset folder."
                                 ) from None
        digest = hashlib.sha256(data).hexdigest()
        if digest != entry.sha256:
            raise NeuralMapError(
                f"{where}: tile file '{path}' is damaged (sha256 {digest[:16]}... differs "
                f"from the index's {entry.sha256[:16]}...); copy it again from the tileset "
                "or train the tileset again.")
        tile = decode_latent_map(data, where=str(path))
        tile.eval()
        return tile

    def tile(self, tile_id: int) -> LatentTerrainMap:
        """The decoded tile (through the cache), on the tileset's device (``.to(device)``
        moves the tileset; tiles decode on the CPU and follow it when used)."""
        model = self.cache.get(int(tile_id))
        if model.coeffs.device != self.frame.device:
            model.to(self.frame.device)
        return model  # type: ignore[return-value]

    def verify(self) -> None:
        """Checks every tile file against the index's SHA-256 (reads, does not decode).

        Raises:
            NeuralMapError: Naming the first damaged or missing file.
        """
        for entry in self.tiles:
            path = self.folder / entry.file
            if not path.is_file() or file_sha256(path) != entry.sha256:
                raise NeuralMapError(
                    f"latent tileset '{self.index_path}': tile file '{path}' (row {entry.row}, "
                    f"col {entry.col}) is missing or damaged (sha256 differs from the index); "
                    "copy the whole tileset folder again.")

    def _pairs(self, flat: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """(point, tile, weight, d weight/dx, d weight/dy) of every pair with weight > 0,
        sorted by tile.

        A point outside every blend zone has one pair, its own tile with weight 1 and no
        weight gradient (``S' = 0`` there); only points in a blend zone get the four
        candidates (lower / upper tile of the nearest seam on each axis), zero weights
        dropped. On an axis of one tile its weight is 0 (``t`` is ``-inf``), so the lower
        tile (the only one) keeps all of it.
        """
        ax = self.layout.axis_weights(flat[:, 0], 0)
        ay = self.layout.axis_weights(flat[:, 1], 1)
        cols = len(self.layout.columns)
        own = ay.own * cols + ax.own
        blend = ax.blending | ay.blending
        alone = torch.nonzero(~blend).squeeze(1)
        mixed = torch.nonzero(blend).squeeze(1)
        ones = torch.ones_like(flat[:, 0]).index_select(0, alone)
        point, tile, weight, dwx, dwy = alone, own.index_select(0, alone), ones, ones * 0, ones * 0
        if mixed.numel():
            (wx, dx), (wy, dy) = ax.weight(mixed), ay.weight(mixed)
            x0, y0 = ax.lower.index_select(0, mixed), ay.lower.index_select(0, mixed)
            x1, y1 = x0 + int(len(self.layout.columns) > 1), y0 + int(len(self.layout.rows) > 1)
            vx, vy = 1.0 - wx, 1.0 - wy  # weights of the lower tiles
            tiles = torch.stack([y0 * cols + x0, y0 * cols + x1, y1 * cols + x0,
                                 y1 * cols + x1], 1).reshape(-1)
            weights = torch.stack([vy * vx, vy * wx, wy * vx, wy * wx], 1).reshape(-1)
            keep = torch.nonzero(weights > 0).squeeze(1)
            point = torch.cat([alone, mixed.repeat_interleave(4).index_select(0, keep)])
            tile = torch.cat([tile, tiles.index_select(0, keep)])
            weight = torch.cat([weight, weights.index_select(0, keep)])
            dwx = torch.cat([dwx, torch.stack([-vy * dx, vy * dx, -wy * dx, wy * dx], 1
                                              ).reshape(-1).index_select(0, keep)])
            dwy = torch.cat([dwy, torch.stack([-dy * vx, -dy * wx, dy * vx, dy * wx], 1
                                              ).reshape(-1).index_select(0, keep)])
        order = torch.argsort(tile, stable=True)
        return (point[order], tile[order], weight[order], dwx[order], dwy[order])

    def _evaluate(self, xy: torch.Tensor, *, with_slope: bool
                  ) -> tuple[torch.Tensor, torch.Tensor | None]:
        """Blended heights ``(M,)`` and optional slopes ``(M, 2)`` of ``(M, 2)`` points
        (module docstring; differentiable in ``xy`` without the slope)."""
        if xy.shape[0] == 0:
            return xy[:, 0] * 0, (xy * 0 if with_slope else None)
        finite = torch.isfinite(xy).all(-1)
        all_finite = bool(finite.all())
        xmin, xmax, ymin, ymax = self.extent
        centre = xy.new_tensor([0.5 * (xmin + xmax), 0.5 * (ymin + ymax)])
        flat = xy if all_finite else torch.where(finite.unsqueeze(-1), xy, centre)
        point, tile, weight, dwx, dwy = self._pairs(flat)
        ids, counts = torch.unique_consecutive(tile, return_counts=True)
        heights, slopes = [], []
        start = 0
        for tile_id, count in zip(ids.tolist(), counts.tolist(), strict=True):
            pts = flat.index_select(0, point[start:start + count])
            start += count
            model = self.tile(tile_id)
            if with_slope:
                h, g = model.height_and_slope(pts)
                slopes.append(g)
            else:
                h = model(pts)
            heights.append(h)
        h_pair = torch.cat(heights).to(xy.dtype)
        height = torch.zeros_like(xy[:, 0]).index_add(0, point, weight * h_pair)
        nan = float("nan")
        height = height if all_finite else torch.where(finite, height, nan)
        if not with_slope:
            return height, None
        g_pair = torch.cat(slopes).to(xy.dtype)
        # grad h = sum phi_i grad h_i + sum h_i grad phi_i
        term = weight.unsqueeze(-1) * g_pair + h_pair.unsqueeze(-1) * torch.stack([dwx, dwy], -1)
        slope = torch.zeros_like(xy).index_add(0, point, term)
        if not all_finite:
            slope = torch.where(finite.unsqueeze(-1), slope, nan)
        return height, slope

