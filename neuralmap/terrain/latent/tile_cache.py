"""A bounded least-recently-used cache of decoded latent tiles.

A decoded `LatentTerrainMap` holds its per-cell
polynomial table, ``16 K`` float32 per cell (``K = 1 + hidden``; 16 times the raw float32
grid for the default linear synthesis), plus its coefficient grid and symbols. A region of
many tiles cannot hold them all, so `DecodedTileCache` keeps at most ``max_tiles`` decoded
tiles and at most ``max_bytes`` of their buffers, dropping the least recently used. The tile
being used is always kept, so a tile larger than ``max_bytes`` still decodes (the bound is
then ``max(max_bytes, the largest tile)``).

Default: `DEFAULT_CACHE_BYTES` = 1 GiB and no count limit; that holds one SRTM 1″ tile
(3601² nodes, 0.83 GB of table with ``hidden = 0``) or eleven 3″ tiles (1201², 92 MB each).
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Callable

import torch

from neuralmap.exceptions import NeuralMapError

__all__ = ["DEFAULT_CACHE_BYTES", "DecodedTileCache", "decoded_bytes"]

#: Default byte budget of the decoded tiles (1 GiB).
DEFAULT_CACHE_BYTES = 2**30


def decoded_bytes(module: torch.nn.Module) -> int:
    """Bytes held by a decoded tile: its buffers (polynomial table, coefficients) and the
    integer symbols it keeps."""
    total = sum(b.numel() * b.element_size() for b in module.buffers())
    total += sum(int(getattr(s, "nbytes", 0)) for s in getattr(module, "symbols", []))
    return int(total)


class DecodedTileCache:
    """LRU cache of decoded tiles, bounded in count and in bytes.

    Args:
        decode: Decodes tile ``key`` (called on a miss).
        max_bytes: Byte budget (None = no byte limit); `DEFAULT_CACHE_BYTES` by default.
        max_tiles: Most decoded tiles kept (None = no count limit).

    Attributes:
        decodes: Number of decodes so far (misses).
        hits: Number of hits.
        peak_tiles: Most tiles resident at once.
        peak_bytes: Most bytes resident at once.

    Raises:
        NeuralMapError: ``max_tiles`` < 1 or ``max_bytes`` < 1.
    """

    def __init__(self, decode: Callable[[int], torch.nn.Module], *,
                 max_bytes: int | None = DEFAULT_CACHE_BYTES, max_tiles: int | None = None
                 ) -> None:
        if max_tiles is not None and (not isinstance(max_tiles, int) or max_tiles < 1):
            raise NeuralMapError(f"latent tileset: cache_tiles must be a whole number >= 1 "
                                 f"(or None for no count limit), got {max_tiles!r}.")
        if max_bytes is not None and (not isinstance(max_bytes, int) or max_bytes < 1):
            raise NeuralMapError(f"latent tileset: cache_bytes must be a whole number of bytes "
                                 f">= 1 (or None for no byte limit), got {max_bytes!r}.")
        self._decode = decode
        self.max_bytes = max_bytes
        self.max_tiles = max_tiles
        self._tiles: OrderedDict[int, tuple[torch.nn.Module, int]] = OrderedDict()
        self.resident_bytes = 0
        self.decodes = 0
        self.hits = 0
        self.peak_tiles = 0
        self.peak_bytes = 0

    def __len__(self) -> int:
        return len(self._tiles)

    @property
    def keys(self) -> list[int]:
        """Resident tile keys, least recently used first."""
        return list(self._tiles)

    def get(self, key: int) -> torch.nn.Module:
        """The decoded tile ``key`` (decoded on a miss, then the LRU bound applied)."""
        if key in self._tiles:
            self._tiles.move_to_end(key)
            self.hits += 1
            return self._tiles[key][0]
        while self._tiles and self.max_tiles is not None and len(self._tiles) >= self.max_tiles:
            self._drop_oldest()  # room for the new tile within the count
        tile = self._decode(key)
        size = decoded_bytes(tile)
        self.decodes += 1
        self._tiles[key] = (tile, size)
        self.resident_bytes += size
        while len(self._tiles) > 1 and self.max_bytes is not None and (
                self.resident_bytes > self.max_bytes):
            self._drop_oldest()  # the newest tile stays, even when larger than the budget
        self.peak_tiles = max(self.peak_tiles, len(self._tiles))
        self.peak_bytes = max(self.peak_bytes, self.resident_bytes)
        return tile

    def _drop_oldest(self) -> None:
        _, (_, size) = self._tiles.popitem(last=False)
        self.resident_bytes -= size

    def clear(self) -> None:
        """Drops every decoded tile."""
        self._tiles.clear()
        self.resident_bytes = 0
