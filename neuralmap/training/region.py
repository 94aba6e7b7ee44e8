"""Region-scale fitting: memory-mapped heights, block shards, Lightning's DDP launcher.

A region (a mosaic written by `neuralmap.dem.write_mosaic`, the synthetic region of
`neuralmap.dem.region.synthetic_region`, any 2-D ``.npy``) is read through a memory
map (`RegionData`); nothing of the size of the area is ever held in memory.

**Blocks as shards.** The global block layout (the one `BlockwiseTerrainNet` uses)
is cut into rectangles of ``shard_blocks`` blocks. Every block's network is fitted to the
DEM over its own extended domain (core plus blending zone), with its own samples and its
own seeded initial weights; the loss is the sum over blocks of each block's mean squared
normalised error. The fit of a block is therefore the same whichever shard, process or
machine trains it: shards are independent, and blending the independently fitted blocks
with the global C2 partition of unity keeps the map seamless across shard borders
(`ShardedTerrainMap`). Peak memory per process is one
shard's height window, its networks and Adam state, and one batch.

**Processes.** `fit_region` starts the processes with Lightning Fabric's launcher
(``strategy="ddp_spawn"`` from Python, ``"ddp"`` from a script or under ``torchrun`` /
SLURM for several nodes: ``num_nodes``). Rank ``r`` of ``W`` trains shards
``r, r + W, …``; no gradients are exchanged (shards share no parameters), only the end
barrier and the timing gather. Each shard is written as an ordinary map file and rank 0
writes the index that `neuralmap.terrain.load_map` opens lazily.

**Sampling.** The points of block ``g`` at step ``s`` are drawn by a counter-based hash
(splitmix64 of ``seed``, ``g``, ``s`` and the point number): uniform nodes of the block's
extended window, void nodes dropped. The draws do not depend on the array type (memory map
or in-memory), the shard layout or the process count.
"""

from __future__ import annotations

import json
import math
import resource
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch.utils.data import Dataset

from neuralmap.dem.tile import DemTile
from neuralmap.exceptions import NeuralMapError
from neuralmap.terrain.block_layout import BlockLayout, layout_for_tile
from neuralmap.terrain.blockwise import NET_DEFAULTS, BlockwiseTerrainNet, block_height_statistics
from neuralmap.terrain.sharded import shard_block_ranges, write_shard_index

__all__ = ["RegionBatches", "RegionData", "fit_region", "splitmix64", "train_shard"]

_GOLDEN = np.uint64(0x9E3779B97F4A7C15)
#: Lightning Fabric strategies the region fit runs under (None = chosen from the world size).
STRATEGIES = (None, "auto", "ddp", "ddp_spawn")


def check_spacing(spacing: Any, *, where: str) -> tuple[float, float]:
    """``(dx, dy)`` from one number or a pair, each finite and > 0.

    Raises:
        NeuralMapError: Text, a wrong count, or a value that is not finite and positive.
    """
    try:
        values = np.asarray(spacing, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        values = np.array([])
    if values.size not in (1, 2) or isinstance(spacing, (str, bytes)) or not (
            np.isfinite(values).all() and (values > 0).all()):
        raise NeuralMapError(
            f"{where} must be one number or [dx, dy] of metres > 0, got {spacing!r}.")
    dx, dy = np.broadcast_to(values, (2,))
    return float(dx), float(dy)


def check_fit_options(*, block_nodes: int | None, overlap_nodes: float,
                      shard_blocks: tuple[int, int], steps: int, points_per_block: int,
                      lr: float, devices: int, num_nodes: int, strategy: str | None,
                      threads: int) -> None:
    """Refuses region-fit settings that would fit nothing or fail in a worker.

    Raises:
        NeuralMapError: Naming the option (as ``train.py region`` spells it) and the fix.
    """
    counts = {"--model.steps": steps, "--model.points_per_block": points_per_block,
              "--trainer.devices": devices, "--trainer.num_nodes": num_nodes,
              "--threads": threads}
    for option, value in counts.items():
        if not isinstance(value, (int, np.integer)) or isinstance(value, bool) or value < 1:
            raise NeuralMapError(
                f"{option} must be a whole number >= 1, got {value!r} (with 0 nothing is "
                "trained and an untrained map would be published).")
    if block_nodes is not None and (not isinstance(block_nodes, (int, np.integer))
                                    or block_nodes < 2):
        raise NeuralMapError(f"--model.block_nodes must be >= 2 (or null), got {block_nodes!r}.")
    if not (isinstance(overlap_nodes, (int, float)) and math.isfinite(overlap_nodes)
            and overlap_nodes >= 0):
        raise NeuralMapError(f"--model.overlap_nodes must be finite and >= 0, got {overlap_nodes!r}.")
    if len(tuple(shard_blocks)) != 2 or any(int(b) < 1 for b in shard_blocks):
        raise NeuralMapError(
            f"--model.shard_blocks must be two whole numbers >= 1 (blocks per shard in x and "
            f"y), got {list(shard_blocks)!r}.")
    if not (isinstance(lr, (int, float)) and math.isfinite(lr) and lr > 0):
        raise NeuralMapError(f"--model.lr must be a finite number > 0, got {lr!r}; try 0.01.")
    if strategy not in STRATEGIES:
        raise NeuralMapError(
            f"--trainer.strategy must be one of {', '.join(str(s) for s in STRATEGIES)}, "
            f"got {strategy!r} (ddp_spawn from Python, ddp from a script or torchrun).")


def check_has_data(data: RegionData, *, rows_per_chunk: int = 256) -> int:
    """Counts the finite heights of a region, a band of rows at a time (bounded memory).

    Raises:
        NeuralMapError: No finite height at all (an all-void region fits nothing).
    """
    ny = data.shape[0]
    finite = 0
    for i in range(0, ny, rows_per_chunk):
        finite += int(np.isfinite(np.asarray(data.heights[i:i + rows_per_chunk])).sum())
    if finite == 0:
        raise NeuralMapError(
            f"region '{data.path or data.name}' ({data.shape[0]} x {data.shape[1]} nodes) "
            "holds no finite height (every node is void/NaN); there is nothing to fit. "
            "Check the source files and their no-data value.")
    return finite


def void_shards(data: RegionData, layout: BlockLayout,
                ranges: list[tuple[int, int, int, int]], *, rows_per_chunk: int = 256) -> list[int]:
    """Shards whose core area holds no finite height (read a band of rows at a time).

    Such a shard has nothing to fit; the region map stores it as void (queries there return
    NaN, as a grid does over void nodes; `neuralmap.terrain.sharded`).

    Args:
        data: The region.
        layout: The global block layout.
        ranges: Block ranges of the shards (`
            shard_block_ranges`).
        rows_per_chunk: Rows read at once.

    Returns:
        Ids of the void shards, increasing.
    """
    (cx, cy), (xmin, _, ymin, _) = layout.core_size, layout.extent
    out = []
    for shard_id, (bx0, bx1, by0, by1) in enumerate(ranges):
        core = np.array([xmin + bx0 * cx, xmin + bx1 * cx, ymin + by0 * cy, ymin + by1 * cy])
        i0, i1, j0, j1 = data.node_window(core).tolist()
        if not any(np.isfinite(np.asarray(data.heights[i:min(i + rows_per_chunk, i1), j0:j1])).any()
                   for i in range(i0, i1, rows_per_chunk)):
            out.append(shard_id)
    return out


def splitmix64(x: np.ndarray) -> np.ndarray:
    """The splitmix64 finaliser (Steele et al. 2014) on uint64 arrays (wrapping arithmetic)."""
    z = np.asarray(x, dtype=np.uint64) + _GOLDEN
    z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
    z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return z ^ (z >> np.uint64(31))


def peak_rss_mb() -> float:
    """Peak resident set size of this process so far, MiB (Linux ``ru_maxrss``)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


@dataclass
class RegionData:
    """A region's heights as a 2-D array (memory-mapped or in memory), row 0 south.

    Attributes:
        heights: ``(ny, nx)`` heights, metres (float32 memory map or any array); NaN = void.
        spacing: ``(dx, dy)`` metres.
        origin: ``(x0, y0)`` tile-frame metres of node ``[0, 0]``.
        name: Region name (recorded in the map).
        path: The ``.npy`` file when opened from one (re-opened, not copied, in workers).
        info: The sidecar description (georeference, generator...).
    """

    heights: Any
    spacing: tuple[float, float]
    origin: tuple[float, float] = (0.0, 0.0)
    name: str = "region"
    path: str | None = None
    info: dict[str, Any] = field(default_factory=dict)

    @classmethod
    def open(
        cls, path: str | Path, *, spacing: float | tuple[float, float] | None = None,
        in_memory: bool = False, name: str | None = None,
    ) -> RegionData:
        """Opens a 2-D ``.npy`` (memory-mapped unless ``in_memory``) and its ``.json`` sidecar.

        Raises:
            NeuralMapError: Missing file, not 2-D, no spacing (neither given nor in the
                sidecar).
        """
        path = Path(path)
        if not path.is_file():
            raise NeuralMapError(f"region file not found: '{path}'; give a 2-D .npy of heights.")
        sidecar = Path(str(path) + ".json")
        info: dict[str, Any] = {}
        if sidecar.is_file():
            try:
                info = json.loads(sidecar.read_text(encoding="utf-8"))
            except (ValueError, UnicodeDecodeError) as exc:
                raise NeuralMapError(
                    f"region '{path}': its sidecar '{sidecar.name}' is not JSON ({exc}); fix "
                    "or delete it (then give the spacing in metres).") from None
            if not isinstance(info, dict):
                raise NeuralMapError(
                    f"region '{path}': its sidecar '{sidecar.name}' must hold a JSON object "
                    f"(with \"spacing\": [dx, dy]), got {type(info).__name__}.")
        try:
            heights = np.load(path, mmap_mode=None if in_memory else "r", allow_pickle=False)
        except (ValueError, OSError, EOFError) as exc:
            raise NeuralMapError(
                f"region '{path}' is not a NumPy .npy array ({exc}); write the heights with "
                "numpy.save or neuralmap.dem.write_mosaic.") from None
        if heights.ndim != 2:
            raise NeuralMapError(f"region '{path}': heights must be 2-D, got {heights.shape}.")
        if not np.issubdtype(heights.dtype, np.number) or np.iscomplexobj(heights):
            raise NeuralMapError(
                f"region '{path}': heights must be real numbers, got dtype {heights.dtype}.")
        source = "given"
        if spacing is None:
            if "spacing" not in info:
                raise NeuralMapError(
                    f"region '{path}': no spacing in '{sidecar.name}'; give it in metres "
                    "(--data.spacing 100, or spacing=100 from Python)."
                )
            spacing, source = info["spacing"], f"of the sidecar '{sidecar.name}'"
        pair = check_spacing(spacing, where=f"region '{path}': the spacing {source}")
        return cls(heights=heights, spacing=pair, name=name or path.stem,  # type: ignore[arg-type]
                   path=str(path), info=info)

    @classmethod
    def from_tile(cls, tile: DemTile) -> RegionData:
        """An in-memory region from a loaded tile (e.g. a `load_mosaic` result)."""
        return cls(heights=tile.heights, spacing=tile.spacing, origin=tile.origin,
                   name=tile.name, info=tile.describe())

    def __getstate__(self) -> dict[str, Any]:
        state = dict(self.__dict__)
        if self.path is not None and isinstance(self.heights, np.memmap):
            state["heights"] = None  # workers re-open the memory map instead of a copy
        return state

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)
        if self.heights is None:
            self.heights = np.load(self.path, mmap_mode="r")

    @property
    def shape(self) -> tuple[int, int]:
        """``(ny, nx)`` nodes."""
        return tuple(self.heights.shape)  # type: ignore[return-value]

    @property
    def extent(self) -> tuple[float, float, float, float]:
        """``(xmin, xmax, ymin, ymax)`` of the node grid, metres."""
        ny, nx = self.shape
        return (self.origin[0], self.origin[0] + (nx - 1) * self.spacing[0],
                self.origin[1], self.origin[1] + (ny - 1) * self.spacing[1])

    def node_window(self, bounds: np.ndarray) -> np.ndarray:
        """Node ranges ``(i0, i1, j0, j1)`` (end exclusive) inside metric bounds ``(..., 4)``."""
        ny, nx = self.shape
        (x0, y0), (dx, dy) = self.origin, self.spacing
        j0 = np.clip(np.ceil((bounds[..., 0] - x0) / dx - 1e-9), 0, nx)
        j1 = np.clip(np.floor((bounds[..., 1] - x0) / dx + 1e-9) + 1, 0, nx)
        i0 = np.clip(np.ceil((bounds[..., 2] - y0) / dy - 1e-9), 0, ny)
        i1 = np.clip(np.floor((bounds[..., 3] - y0) / dy + 1e-9) + 1, 0, ny)
        return np.stack([i0, i1, j0, j1], axis=-1).astype(np.int64)


class RegionBatches(Dataset):
    """Training batches of a group of blocks; item ``s`` is step ``s``'s batch.

    Args:
        heights: The height window (any array indexable by ``[rows, cols]``; a memory map
            or an in-memory array give identical batches).
        window: ``(i0, j0)`` global node index of ``heights[0, 0]``.
        data: The region (spacing and origin).
        block_windows: ``(nb, 4)`` global node ranges ``(i0, i1, j0, j1)`` of each block's
            extended domain.
        block_ids: ``(nb,)`` global block ids (they key the sampling hash).
        points_per_block: Draws per block and step (void nodes are dropped).
        steps: Number of steps (the dataset length).
        seed: Sampling seed.

    Items: ``(xy (Q, 2) float32, h (Q,) float32, block (Q,) int64 index into block_ids)``.
    """

    def __init__(self, heights: Any, window: tuple[int, int], data: RegionData,
                 block_windows: np.ndarray, block_ids: np.ndarray, *, points_per_block: int,
                 steps: int, seed: int) -> None:
        self.heights = heights
        self.window = window
        self.data = data
        self.block_windows = np.asarray(block_windows, dtype=np.int64)
        self.block_ids = np.asarray(block_ids, dtype=np.uint64)
        self.points = int(points_per_block)
        self.steps = int(steps)
        self.seed = int(seed)

    def __len__(self) -> int:
        return self.steps

    def indices(self, step: int) -> tuple[np.ndarray, np.ndarray]:
        """Global node ``(rows, cols)``, each ``(nb, P)``, drawn for ``step``."""
        key = splitmix64(splitmix64(np.full(1, self.seed, dtype=np.uint64)) ^ self.block_ids)
        key = splitmix64(key ^ np.uint64(step))[:, None]  # (nb, 1)
        j = np.arange(2 * self.points, dtype=np.uint64)[None, :]
        u = splitmix64(key + j * _GOLDEN)
        i0, i1, j0, j1 = (self.block_windows[:, k:k + 1].astype(np.uint64) for k in range(4))
        rows = i0 + u[:, : self.points] % np.maximum(i1 - i0, np.uint64(1))
        cols = j0 + u[:, self.points:] % np.maximum(j1 - j0, np.uint64(1))
        return rows.astype(np.int64), cols.astype(np.int64)

    def __getitem__(self, step: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        if not 0 <= step < self.steps:
            raise IndexError(step)
        rows, cols = self.indices(step)
        h = np.asarray(self.heights[rows - self.window[0], cols - self.window[1]],
                       dtype=np.float32)
        block = np.broadcast_to(np.arange(rows.shape[0])[:, None], rows.shape)
        keep = np.isfinite(h)
        (x0, y0), (dx, dy) = self.data.origin, self.data.spacing
        xy = np.stack([x0 + cols[keep] * dx, y0 + rows[keep] * dy], axis=-1)
        return (torch.as_tensor(xy, dtype=torch.float32), torch.as_tensor(h[keep]),
                torch.as_tensor(block[keep], dtype=torch.int64))


def _shard_geometry(layout: BlockLayout, blocks: tuple[int, int, int, int]) -> dict[str, Any]:
    """Core extent, block ids and extended bounds of a shard's blocks."""
    bx0, bx1, by0, by1 = blocks
    (cx, cy), (xmin, _, ymin, _) = layout.core_size, layout.extent
    nbx = layout.num_blocks[0]
    bxs, bys = np.meshgrid(np.arange(bx0, bx1), np.arange(by0, by1))
    ids = (bys * nbx + bxs).ravel()
    bounds = layout.block_bounds()[ids]
    extent = (xmin + bx0 * cx, xmin + bx1 * cx, ymin + by0 * cy, ymin + by1 * cy)
    return {"ids": ids, "bounds": bounds, "extent": extent, "num_blocks": (bx1 - bx0, by1 - by0)}


def _init_blocks(net: BlockwiseTerrainNet, ids: np.ndarray, seed: int) -> None:
    """Re-draws every block's initial weights from a generator keyed by its global id."""
    keys = splitmix64(splitmix64(np.full(1, seed, dtype=np.uint64)) ^ ids.astype(np.uint64))
    with torch.no_grad():
        for local, key in enumerate(keys.tolist()):
            gen = torch.Generator().manual_seed(int(key) & 0x7FFF_FFFF_FFFF_FFFF)

            def uniform(shape: torch.Size, gen: torch.Generator = gen) -> torch.Tensor:
                """U(-1, 1) on the generator's device (not a caller's default device)."""
                return torch.rand(shape, generator=gen, device=gen.device) * 2 - 1

            for weight, bias in zip(net.weights, net.biases, strict=True):
                bound = 1.0 / math.sqrt(weight.shape[1])
                weight[local] = uniform(weight.shape[1:]) * bound
                bias[local] = uniform(bias.shape[1:]) * bound
            bound = 1.0 / math.sqrt(net.out_weight.shape[1])
            net.out_weight[local] = uniform(net.out_weight.shape[1:]) * bound
            net.out_bias[local] = 0.0


def train_shard(
    data: RegionData,
    layout: BlockLayout,
    blocks: tuple[int, int, int, int],
    *,
    steps: int,
    points_per_block: int = 256,
    lr: float = 1e-2,
    seed: int = 0,
    net_options: dict[str, Any] | None = None,
) -> tuple[BlockwiseTerrainNet, dict[str, float]]:
    """Fits the networks of one shard's blocks (each block on its own extended domain).

    Args:
        data: The region.
        layout: The global block layout.
        blocks: ``(bx0, bx1, by0, by1)`` block range of the shard (end exclusive).
        steps: Adam steps (cosine learning-rate decay to zero).
        points_per_block: Samples per block and step.
        lr: Peak learning rate.
        seed: Seed of the sampling and of the per-block initial weights.
        net_options: ``encoding``, ``n_frequencies``, ``frequency_scale``, ``hidden``,
            ``depth``, ``activation`` of `BlockwiseTerrainNet`.

    Returns:
        ``(net, stats)``: the shard's network (its blocks in shard order) and
        ``points`` (pairs trained), ``seconds``, ``final_loss``.
    """
    geo = _shard_geometry(layout, blocks)
    opts = {k: v for k, v in (net_options or {}).items()}
    blend = layout.blend_width != (0.0, 0.0)
    net = BlockwiseTerrainNet(extent=geo["extent"], num_blocks=geo["num_blocks"],
                              blend_width=layout.blend_width, blend=blend,
                              seed=seed, tile_info={"name": data.name}, **opts)
    windows = data.node_window(geo["bounds"])
    i0, i1 = int(windows[:, 0].min()), int(windows[:, 1].max())
    j0, j1 = int(windows[:, 2].min()), int(windows[:, 3].max())
    heights = np.asarray(data.heights[i0:i1, j0:j1], dtype=np.float32)
    if np.isfinite(heights).any() and min(heights.shape) >= 2:
        window_tile = DemTile(heights=heights.astype(np.float64), spacing=data.spacing,
                              origin=(data.origin[0] + j0 * data.spacing[0],
                                      data.origin[1] + i0 * data.spacing[1]))
        mean, std = block_height_statistics(window_tile, net.layout)
        net.height_mean.copy_(torch.as_tensor(mean, dtype=torch.float32))
        net.height_std.copy_(torch.as_tensor(std, dtype=torch.float32))
    _init_blocks(net, geo["ids"], seed)
    batches = RegionBatches(heights, (i0, j0), data, windows, geo["ids"],
                            points_per_block=points_per_block, steps=steps, seed=seed)
    optimizer = torch.optim.Adam(net.parameters(), lr=lr)
    schedule = torch.optim.lr_scheduler.LambdaLR(
        optimizer, lambda s: 0.5 * (1.0 + math.cos(math.pi * min(s, steps) / max(steps, 1))))
    n_blocks = len(geo["ids"])
    tile_size = max(8, 1 << (max(points_per_block, 1) - 1).bit_length())
    points, loss_value, start = 0, float("nan"), time.perf_counter()
    for step in range(steps):
        xy, h, block = batches[step]
        if block.numel() == 0:
            continue
        pred = net.block_heights(xy, block, tile_size=tile_size)
        err = (pred - h) / net.height_std.index_select(0, block)
        count = torch.bincount(block, minlength=n_blocks).clamp_min(1)
        per_block = torch.zeros(n_blocks).index_add(0, block, err * err) / count
        loss = per_block.sum()
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        optimizer.step()
        schedule.step()
        points += int(block.numel())
        loss_value = float(loss.detach()) / n_blocks
    return net, {"points": float(points), "seconds": time.perf_counter() - start,
                 "final_loss": loss_value}


def plan_layout(data: RegionData, *, block_nodes: int | None = NET_DEFAULTS.block_nodes,
                overlap_nodes: float = NET_DEFAULTS.overlap_nodes,
                num_blocks: tuple[int, int] | None = None) -> BlockLayout:
    """The global block layout of a region (as `BlockwiseTerrainNet.from_tile`)."""
    return layout_for_tile(data.shape, data.spacing, data.extent, block_nodes=block_nodes,
                           overlap_nodes=overlap_nodes, num_blocks=num_blocks)


def _worker(fabric: Any, plan: dict[str, Any]) -> dict[str, Any]:
    """One process: trains its shards, writes them; rank 0 writes the index."""
    torch.set_num_threads(int(plan["threads"]))
    rank, world = int(fabric.global_rank), int(fabric.world_size)
    data = plan["data"]
    layout = BlockLayout(**plan["layout"])  # passed as a dict: Fabric rebuilds dataclasses
    out = Path(plan["out_dir"])
    ranges = shard_block_ranges(layout.num_blocks, plan["shard_blocks"])
    todo = plan["shard_ids"] if plan["shard_ids"] is not None else list(range(len(ranges)))
    void = set(plan["void_shards"])  # nothing to fit: stored as void in the index
    mine = [i for i in todo if i not in void][rank::world]
    points, seconds, losses = 0.0, 0.0, []
    cpu_start = time.process_time()
    from neuralmap.terrain.export import save_map

    for shard_id in mine:
        net, stats = train_shard(data, layout, ranges[shard_id], steps=plan["steps"],
                                 points_per_block=plan["points_per_block"], lr=plan["lr"],
                                 seed=plan["seed"], net_options=plan["net_options"])
        save_map(net, out / "shards" / f"shard_{shard_id:05d}.pt",
                 extra={"shard": shard_id, "blocks": list(ranges[shard_id])})
        points += stats["points"]
        seconds += stats["seconds"]
        losses.append(stats["final_loss"])
    cpu = time.process_time() - cpu_start
    mine_stats = torch.tensor([points, seconds, peak_rss_mb(), float(len(mine)), cpu],
                              dtype=torch.float64)
    gathered = fabric.all_gather(mine_stats) if world > 1 else mine_stats.unsqueeze(0)
    fabric.barrier()
    per_rank = gathered.reshape(world, 5).tolist()
    return {"per_rank": [{"points": r[0], "seconds": r[1], "peak_rss_mb": r[2],
                          "shards": int(r[3]), "cpu_seconds": r[4]} for r in per_rank],
            "mean_loss": float(np.mean(losses)) if losses else float("nan")}


def fit_region(
    data: RegionData,
    out_dir: str | Path,
    *,
    block_nodes: int | None = NET_DEFAULTS.block_nodes,
    overlap_nodes: float = NET_DEFAULTS.overlap_nodes,
    num_blocks: tuple[int, int] | None = None,
    shard_blocks: tuple[int, int] = (8, 8),
    steps: int = 500,
    points_per_block: int = 256,
    lr: float = 1e-2,
    seed: int = 0,
    devices: int = 1,
    num_nodes: int = 1,
    strategy: str | None = None,
    threads: int = 1,
    shard_ids: list[int] | None = None,
    net_options: dict[str, Any] | None = None,
    record_path: str | None = None,
) -> dict[str, Any]:
    """Fits a region shard by shard on ``devices × num_nodes`` CPU processes.

    A shard whose area holds no finite height is not trained: the index stores it as void
    and the map returns NaN there, as a grid does over voids (`void_shards`).

    Writes into ``out_dir`` directly; to publish whole (as ``train.py region`` does), build
    inside ``with neuralmap.io.replacing_dir(out) as build: fit_region(data, build)``.

    Args:
        data: The region (`RegionData.open` for a memory-mapped ``.npy``).
        out_dir: Folder for ``map_index.json`` and ``shards/``.
        block_nodes, overlap_nodes, num_blocks: Global block layout (as the tile trainer).
        shard_blocks: ``(sbx, sby)`` blocks per shard.
        steps: Adam steps per shard.
        points_per_block: Samples per block and step.
        lr: Peak learning rate (cosine decay).
        seed: Sampling and initialisation seed (results do not depend on ``devices``).
        devices: Processes per node.
        num_nodes: Machines (launch with ``torchrun``/SLURM and ``strategy="ddp"``).
        strategy: Lightning Fabric strategy; default ``"ddp_spawn"`` for ``devices > 1``
            on one node, ``"ddp"`` for several nodes.
        threads: Torch threads per process.
        shard_ids: Train only these shards (benchmarks); the index is then not written.
        net_options: Architecture options of `BlockwiseTerrainNet`.
        record_path: Region path recorded in the index (default ``data.path``; the command
            line gives the published path when it builds under a hidden name).

    Returns:
        Summary: ``index`` path (or None), ``layout``, ``shards``, ``void_shards`` (ids of
        the shards without any finite height in their area: not trained, stored as void,
        queries there give NaN), ``per_rank`` points,
        seconds, CPU seconds and peak RSS, ``points_per_s`` (total points / slowest rank's
        seconds), ``points_per_cpu_s`` (total points / summed CPU seconds: the rate each
        process would keep on a free core).

    Raises:
        NeuralMapError: Bad settings (`check_fit_options`), a region without any
            finite height, shard ids outside the layout.
    """
    from lightning.fabric import Fabric

    check_fit_options(block_nodes=block_nodes, overlap_nodes=overlap_nodes,
                      shard_blocks=shard_blocks, steps=steps,
                      points_per_block=points_per_block, lr=lr, devices=devices,
                      num_nodes=num_nodes, strategy=strategy, threads=threads)
    layout = plan_layout(data, block_nodes=block_nodes, overlap_nodes=overlap_nodes,
                         num_blocks=num_blocks)
    ranges = shard_block_ranges(layout.num_blocks, shard_blocks)
    void = void_shards(data, layout, ranges)
    if len(void) == len(ranges):
        check_has_data(data)  # says so when the region holds no finite height at all
    out = Path(out_dir)
    (out / "shards").mkdir(parents=True, exist_ok=True)
    if shard_ids is not None and any(not 0 <= int(i) < len(ranges) for i in shard_ids):
        raise NeuralMapError(
            f"fit_region: shard_ids {shard_ids} name shards outside 0..{len(ranges) - 1} "
            f"(the region has {len(ranges)} shards of {shard_blocks} blocks)."
        )
    world = int(devices) * int(num_nodes)
    if strategy is None:
        strategy = "auto" if world == 1 else ("ddp" if num_nodes > 1 else "ddp_spawn")
    layout_dict = {"extent": layout.extent, "num_blocks": layout.num_blocks,
                   "blend_width": layout.blend_width}
    plan = {"data": data, "layout": layout_dict, "out_dir": str(out), "shard_blocks": shard_blocks,
            "shard_ids": shard_ids, "steps": int(steps), "points_per_block": int(points_per_block),
            "lr": float(lr), "seed": int(seed), "net_options": dict(net_options or {}),
            "threads": int(threads), "void_shards": void}
    fabric = Fabric(accelerator="cpu", devices=int(devices), num_nodes=int(num_nodes),
                    strategy=strategy)
    started = time.perf_counter()
    result = fabric.launch(_worker, plan)
    wall = time.perf_counter() - started
    total_points = sum(r["points"] for r in result["per_rank"])
    slowest = max(r["seconds"] for r in result["per_rank"]) or float("nan")
    summary = {
        "index": None,
        "layout": {"extent": list(layout.extent), "num_blocks": list(layout.num_blocks),
                   "blend_width": list(layout.blend_width)},
        "shards": len(ranges),
        "trained_shards": len(set(shard_ids if shard_ids is not None else range(len(ranges)))
                              - set(void)),
        "void_shards": void,
        "world_size": world,
        "per_rank": result["per_rank"],
        "points": total_points,
        "points_per_s": total_points / slowest,
        "points_per_cpu_s": total_points / max(
            sum(r["cpu_seconds"] for r in result["per_rank"]), 1e-9),
        "wall_s": wall,
        "mean_final_loss": result["mean_loss"],
    }
    if shard_ids is None and fabric.global_rank == 0:
        files = [None if i in set(void) else f"shards/shard_{i:05d}.pt"
                 for i in range(len(ranges))]
        info = {"name": data.name, "region": {"shape": list(data.shape),
                                              "spacing": list(data.spacing),
                                              "origin": list(data.origin),
                                              "path": record_path or data.path},
                "training": {k: v for k, v in plan.items()
                             if k not in ("data", "layout", "out_dir", "void_shards")},
                "metrics": {"points": total_points}, "void_shards": void}
        summary["index"] = str(write_shard_index(out / "map_index.json", layout=layout,
                                                 shard_blocks=shard_blocks, files=files,
                                                 info=info))
    return summary
