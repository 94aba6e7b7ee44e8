"""Sharded neural maps: one index file plus one map file per shard, loaded lazily.

A region map is a `BlockLayout` over the whole area
whose block grid is cut into rectangular shards of ``shard_blocks = (sbx, sby)`` blocks.
Each shard is an ordinary `BlockwiseTerrainNet` file (``save_map``) holding the
networks of its blocks; the index (``map_index.json``) holds the global layout and which
file holds which blocks. `ShardedTerrainMap` reads the index only and loads a shard
the first time a point needs one of its blocks (keeping at most ``max_loaded`` shards),
so a filter flying over a corner of a 361 km map never reads the rest.

Blending is global: the weights of the (up to four) blocks that see a point come from the
global layout (the C2 partition of unity of `neuralmap.terrain.block_layout`), so
height and slope stay continuous across shard borders exactly as across block borders.

A shard whose area holds no finite height (a void of the source DEM: sea, a data gap) is
stored as void — ``"file": null, "void": true`` in the index, no network — and queries
there return NaN, as a grid does over void nodes; so does the blend band along its border,
where a void block carries weight (NaN is never blended into a height).
"""

from __future__ import annotations

import json
import os
from collections import OrderedDict
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.io import atomic_write_json
from neuralmap.terrain.base import TerrainModel
from neuralmap.terrain.block_layout import BlockLayout
from neuralmap.terrain.blockwise import BlockwiseTerrainNet

__all__ = ["INDEX_FORMAT", "ShardedTerrainMap", "shard_block_ranges", "write_shard_index"]

INDEX_FORMAT = "neuralmap-sharded-map"
INDEX_VERSION = 1


def shard_block_ranges(
    num_blocks: tuple[int, int], shard_blocks: tuple[int, int]
) -> list[tuple[int, int, int, int]]:
    """Block ranges ``(bx0, bx1, by0, by1)`` (end exclusive) of every shard, row-major.

    Args:
        num_blocks: ``(nbx, nby)`` of the global layout.
        shard_blocks: ``(sbx, sby)`` blocks per shard (the last row/column may be smaller).
    """
    nbx, nby = num_blocks
    sbx, sby = max(1, int(shard_blocks[0])), max(1, int(shard_blocks[1]))
    return [(bx, min(bx + sbx, nbx), by, min(by + sby, nby))
            for by in range(0, nby, sby) for bx in range(0, nbx, sbx)]


def write_shard_index(
    path: str | os.PathLike[str],
    *,
    layout: BlockLayout,
    shard_blocks: tuple[int, int],
    files: list[str | None],
    info: dict[str, Any] | None = None,
) -> Path:
    """Writes the index of a sharded map (JSON, atomically).

    Args:
        path: Destination (conventionally ``map_index.json`` next to the shard files).
        layout: The global block layout.
        shard_blocks: ``(sbx, sby)`` blocks per shard.
        files: Shard file names relative to the index, in `shard_block_ranges` order;
            None for a void shard (no finite height: stored as void, queries give NaN).
        info: Region description, training settings, metrics.
    """
    ranges = shard_block_ranges(layout.num_blocks, shard_blocks)
    if len(files) != len(ranges):
        raise NeuralMapError(
            f"write_shard_index: {len(ranges)} shards but {len(files)} files given."
        )
    payload = {
        "format": INDEX_FORMAT,
        "format_version": INDEX_VERSION,
        "layout": {"extent": list(layout.extent), "num_blocks": list(layout.num_blocks),
                   "blend_width": list(layout.blend_width)},
        "shard_blocks": [int(shard_blocks[0]), int(shard_blocks[1])],
        "shards": [{"file": f, "blocks": list(r)} if f is not None
                   else {"file": None, "blocks": list(r), "void": True}
                   for f, r in zip(files, ranges, strict=True)],
        "info": dict(info or {}),
    }
    path = Path(path)
    atomic_write_json(path, payload)
    return path


class ShardedTerrainMap(TerrainModel):
    """A region map stored as an index plus shard files; shards load on first use.

    Args:
        index_path: The ``map_index.json`` written by `write_shard_index`.
        load_shard: Reads one shard file (``neuralmap.terrain.export.load_map_file``;
            `load_map` passes it, which keeps this module
            free of an import of the export module).
        max_loaded: Most shards kept in memory (least recently used ones are dropped).

    Raises:
        NeuralMapError: Missing or malformed index, missing shard file.
    """

    def __init__(
        self,
        index_path: str | os.PathLike[str],
        *,
        load_shard: Callable[[Path], BlockwiseTerrainNet],
        max_loaded: int = 16,
    ) -> None:
        super().__init__()
        self.index_path = Path(index_path)
        self._load_shard = load_shard
        try:
            index = json.loads(self.index_path.read_text())
        except (OSError, ValueError) as exc:
            raise NeuralMapError(
                f"sharded map index '{index_path}' could not be read ({exc}); give the "
                "map_index.json written by the region trainer."
            ) from None
        if not isinstance(index, dict) or index.get("format") != INDEX_FORMAT:
            raise NeuralMapError(
                f"'{index_path}' is not a sharded neuralmap index (no '{INDEX_FORMAT}' header)."
            )
        lay = index["layout"]
        self.layout = BlockLayout(extent=tuple(lay["extent"]),  # type: ignore[arg-type]
                                  num_blocks=tuple(lay["num_blocks"]),  # type: ignore[arg-type]
                                  blend_width=tuple(lay["blend_width"]))  # type: ignore[arg-type]
        self.extent = self.layout.extent
        self.shard_blocks = tuple(index["shard_blocks"])
        self.shards = index["shards"]
        self.info = index.get("info", {})
        self.tile_name = str(self.info.get("name", ""))
        self.tile_fingerprint = str(self.info.get("fingerprint", ""))
        self.metrics = self.info.get("metrics", {})
        self.max_loaded = max(1, int(max_loaded))
        self._loaded: OrderedDict[int, BlockwiseTerrainNet] = OrderedDict()
        self.loads = 0
        missing = [s["file"] for s in self.shards if s.get("file") is not None
                   and not (self.index_path.parent / s["file"]).is_file()]
        if missing:
            raise NeuralMapError(
                f"sharded map '{index_path}': shard file(s) {missing[:3]} are missing "
                f"({len(missing)} of {len(self.shards)}); copy the whole map folder."
            )

    @property
    def num_shards(self) -> int:
        """Number of shard files."""
        return len(self.shards)

    @property
    def void_shards(self) -> list[int]:
        """Ids of the void shards (no network; queries there give NaN)."""
        return [i for i, s in enumerate(self.shards) if s.get("file") is None]

    @property
    def loaded_shards(self) -> list[int]:
        """Ids of the shards now in memory."""
        return list(self._loaded)

    def shard(self, shard_id: int) -> BlockwiseTerrainNet:
        """The network of one shard (loaded on first use, least recently used dropped)."""
        if shard_id in self._loaded:
            self._loaded.move_to_end(shard_id)
            return self._loaded[shard_id]
        net = self._load_shard(self.index_path.parent / self.shards[shard_id]["file"])
        self.loads += 1
        self._loaded[shard_id] = net
        while len(self._loaded) > self.max_loaded:
            self._loaded.popitem(last=False)
        return net

    def _weights(self, xy: torch.Tensor, block: torch.Tensor) -> torch.Tensor:
        """Differentiable global blending weight of each (point, block) pair."""
        nbx = self.layout.num_blocks[0]
        weight = torch.ones_like(xy[:, 0])
        if self.layout.blend_width == (0.0, 0.0):
            return weight
        for axis, index in ((0, block % nbx), (1, torch.div(block, nbx, rounding_mode="floor"))):
            i0, w0, _, w1 = self.layout.axis_candidates(xy[:, axis], axis)
            weight = weight * torch.where(index == i0, w0, w1)
        return weight

    def forward(self, xy: torch.Tensor) -> torch.Tensor:
        """Heights at metric points, blended over blocks and shards.

        Args:
            xy: ``(..., 2)`` metres (computed in float32, returned in ``xy``'s dtype).

        Returns:
            ``(...)`` heights in metres (NaN at non-finite points and where a void shard's
            block has weight).
        """
        if xy.shape[-1] != 2:
            raise NeuralMapError(f"xy must have shape (..., 2), got {tuple(xy.shape)}.")
        lead = xy.shape[:-1]
        flat = xy.reshape(-1, 2).to(torch.float32)
        finite = torch.isfinite(flat).all(-1)
        centre = torch.tensor([self.extent[0], self.extent[2]], dtype=flat.dtype)
        flat = torch.where(finite.unsqueeze(-1), flat, centre)
        with torch.no_grad():
            point, block, _ = self.layout.assign(flat.detach())
        pair_xy = flat.index_select(0, point)
        weight = self._weights(pair_xy, block)
        nbx = self.layout.num_blocks[0]
        sbx, sby = self.shard_blocks
        bx, by = block % nbx, torch.div(block, nbx, rounding_mode="floor")
        nsx = -(-nbx // sbx)
        shard = torch.div(by, sby, rounding_mode="floor") * nsx + torch.div(
            bx, sbx, rounding_mode="floor")
        metres = torch.zeros_like(weight)
        void = torch.zeros(flat.shape[0], dtype=torch.bool)
        for shard_id in torch.unique(shard).tolist():
            sel = torch.nonzero(shard == shard_id).squeeze(1)
            if self.shards[shard_id].get("file") is None:  # void: NaN where it has weight
                hit = sel[weight.index_select(0, sel).detach() > 0]
                void = void.index_fill(0, point.index_select(0, hit), True)
                continue
            bx0, bx1, by0, by1 = self.shards[shard_id]["blocks"]
            local = (by.index_select(0, sel) - by0) * (bx1 - bx0) + (
                bx.index_select(0, sel) - bx0)
            net = self.shard(int(shard_id))
            values = net.block_heights(pair_xy.index_select(0, sel), local)
            metres = metres.index_put((sel,), values)
        height = torch.zeros(flat.shape[0], dtype=flat.dtype).index_add(
            0, point, weight * metres)
        height = torch.where(finite & ~void, height, torch.full_like(height, float("nan")))
        return height.reshape(lead).to(xy.dtype)


def is_sharded_index(path: str | os.PathLike[str]) -> bool:
    """Whether ``path`` is a sharded-map index (a ``.json`` file or a folder holding one)."""
    path = Path(path)
    return path.suffix.lower() == ".json" or (path.is_dir() and (path / "map_index.json").is_file())
