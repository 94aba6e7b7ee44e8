"""Grouped matrix products: many small per-block MLPs in one batched tensor operation.

Point-block pairs are sorted by block and packed into fixed-size tiles that each belong to
one block; a layer is then one ``bmm`` of the tiles with their block's weights gathered per
tile. Padding is bounded by one tile per block, so the cost stays proportional to the
number of pairs however the points are spread over the blocks (a filter with 100 000
trajectories all in one block costs the same as one spread over the map).
"""

from __future__ import annotations

import torch


class TileGroups:
    """Packing of ``Q`` pairs, each tagged with a block id, into per-block tiles.

    Args:
        block: ``(Q,)`` int64 block id of each pair.
        num_blocks: Number of blocks ``B``.
        tile_size: Rows per tile; ``None`` picks a power of two near ``Q / B`` in [8, 256].
    """

    def __init__(self, block: torch.Tensor, num_blocks: int, tile_size: int | None = None) -> None:
        q = block.shape[0]
        if tile_size is None:
            mean = max(q / max(num_blocks, 1), 1.0)
            tile_size = int(min(256, max(8, 2 ** int(torch.tensor(mean).log2().floor()))))
        self.tile_size = tile_size
        order = torch.argsort(block, stable=True)
        sorted_block = block[order]
        counts = torch.bincount(block, minlength=num_blocks)
        tiles_per_block = (counts + tile_size - 1) // tile_size
        first_pair = torch.cumsum(counts, 0) - counts  # start of each block in sorted order
        first_tile = torch.cumsum(tiles_per_block, 0) - tiles_per_block
        rank = torch.arange(q, device=block.device) - first_pair[sorted_block]
        tile = first_tile[sorted_block] + torch.div(rank, tile_size, rounding_mode="floor")
        slot = rank % tile_size
        self.num_tiles = int(tiles_per_block.sum())
        # Flat row of each pair (in original order) inside the (num_tiles * tile_size) slab.
        flat = torch.empty_like(block)
        flat[order] = tile * tile_size + slot
        self.flat_index = flat
        self.tile_block = torch.repeat_interleave(
            torch.arange(num_blocks, device=block.device), tiles_per_block
        )

    def pack(self, values: torch.Tensor) -> torch.Tensor:
        """``(Q, d)`` pair values -> ``(num_tiles, tile_size, d)`` tiles (padding is zero)."""
        d = values.shape[-1]
        slab = values.new_zeros(self.num_tiles * self.tile_size, d)
        slab = slab.index_copy(0, self.flat_index, values)
        return slab.view(self.num_tiles, self.tile_size, d)

    def unpack(self, tiles: torch.Tensor) -> torch.Tensor:
        """``(num_tiles, tile_size, d)`` tiles -> ``(Q, d)`` pair values in original order
        (``(0, d)`` when there are no pairs: the width is named, not inferred)."""
        slab = tiles.reshape(self.num_tiles * self.tile_size, tiles.shape[-1])
        return slab.index_select(0, self.flat_index)

    def linear(
        self, tiles: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor
    ) -> torch.Tensor:
        """Per-block affine map of packed tiles.

        Args:
            tiles: ``(num_tiles, tile_size, d_in)``.
            weight: ``(B, d_in, d_out)`` per-block weights.
            bias: ``(B, d_out)`` per-block biases.

        Returns:
            ``(num_tiles, tile_size, d_out)``.
        """
        return torch.baddbmm(
            bias.index_select(0, self.tile_block).unsqueeze(1),
            tiles,
            weight.index_select(0, self.tile_block),
        )
