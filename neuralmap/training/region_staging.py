"""Staging of a region fit: the region file, the hidden build folder shared by the ranks,
the fit and the summary that names the published paths.

`neuralmap.training.cli.RegionMode` parses ``train.py region`` and publishes the build
folder; this module holds what happens inside it. ``--data.path`` is a 2-D ``.npy`` region
(memory-mapped; spacing from its ``.json`` sidecar or ``--data.spacing``), one or more DEM
files / globs (stitched with `neuralmap.dem.write_mosaic` into ``OUT/region.npy``), or
``synthetic-region`` (`neuralmap.dem.region.synthetic_region`). Under ``torchrun`` every
rank starts at once: rank 0 builds the hidden folder beside ``--out`` and sends its path to
the other ranks (a gloo broadcast), which wait for its region file.
"""

from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Any

from neuralmap.exceptions import NeuralMapError
from neuralmap.io import atomic_write_json
from neuralmap.training.region import RegionData, fit_region

__all__ = ["STAGING_ENV", "SYNTHETIC", "check_region_out", "region_sources", "torchrun_build",
           "train_region", "under_torchrun"]

#: Environment variable through which DDP script-launched ranks learn rank 0's build folder.
STAGING_ENV = "NEURALMAP_REGION_STAGING"
#: The name of the source that generates the paper-size synthetic region.
SYNTHETIC = "synthetic-region"


def region_sources(path: str | list[str]) -> list[str]:
    """``--data.path`` as a list of sources (refuses an empty one)."""
    sources = [path] if isinstance(path, str) else list(path)
    if not sources:
        raise NeuralMapError(f"--data.path is empty; give a .npy region, DEM files or {SYNTHETIC}.")
    return sources


def check_region_out(out: Path) -> None:
    """Refuses an ``--out`` that is a file or a folder of something other than a region map."""
    if out.exists() and not out.is_dir():
        raise NeuralMapError(f"--out '{out}' is a file; give a folder (new or an earlier output).")
    if out.is_dir() and any(out.iterdir()) and not (out / "map_index.json").is_file():
        raise NeuralMapError(
            f"--out '{out}' is a folder holding other files (no map_index.json of an earlier "
            "region map); it would be replaced. Give a new folder.")


def _is_npy(sources: list[str]) -> bool:
    return len(sources) == 1 and sources[0].lower().endswith(".npy")


def _region_file(sources: list[str], build: Path, cfg: Any, launched: bool) -> Path:
    """The ``.npy`` to train on: the given one, or a mosaic / synthetic region in ``build``."""
    from neuralmap.dem.mosaic import write_mosaic
    from neuralmap.dem.region import PAPER_REGION_SHAPE, synthetic_region

    if _is_npy(sources):
        return Path(sources[0])
    path = build / "region.npy"
    if launched:  # a rank started by the script launcher: rank 0 wrote it already
        return path
    if sources == [SYNTHETIC]:
        shape = cfg.data.region_shape or PAPER_REGION_SHAPE
        if len(shape) != 2 or min(shape) < 2:
            raise NeuralMapError(
                f"--data.region_shape must be [ny, nx] with both >= 2, got {shape}.")
        synthetic_region(path, shape=tuple(shape), seed=cfg.model.seed)
    else:
        write_mosaic(sources, path)
    return path


def under_torchrun() -> bool:
    """Whether ``torchrun`` started this process as one rank of several (it sets
    ``TORCHELASTIC_RUN_ID`` and ``WORLD_SIZE``)."""
    return "TORCHELASTIC_RUN_ID" in os.environ and int(os.environ.get("WORLD_SIZE", "1")) > 1


def torchrun_build(build: Path | None) -> Path:
    """Rank 0's build folder, sent to every rank of a ``torchrun`` job (gloo broadcast on
    the process group Fabric then reuses); rank 0 passes it, the others ``None``."""
    import torch.distributed as dist

    if not dist.is_initialized():
        dist.init_process_group("gloo")  # env:// from torchrun's RANK, WORLD_SIZE, MASTER_*
    box = [str(build) if build is not None else ""]
    dist.broadcast_object_list(box, src=0)
    return Path(box[0])


def train_region(cfg: Any, build: Path, out: Path, launched: bool) -> dict[str, Any]:
    """Writes the region file if needed, fits the shards into ``build`` and returns the
    summary, with paths naming where ``build`` is published (``out``)."""
    sources = region_sources(cfg.data.path)
    region = _region_file(sources, build, cfg, launched)
    if under_torchrun():  # every rank started at once: the others wait for rank 0's region file
        import torch.distributed as dist

        dist.barrier()
    data = RegionData.open(region, spacing=cfg.data.spacing)
    published_region = region if _is_npy(sources) else out / "region.npy"
    summary = fit_region(
        data, build, block_nodes=cfg.model.block_nodes, overlap_nodes=cfg.model.overlap_nodes,
        shard_blocks=tuple(cfg.model.shard_blocks),  # type: ignore[arg-type]
        steps=cfg.model.steps, points_per_block=cfg.model.points_per_block, lr=cfg.model.lr,
        seed=cfg.model.seed, devices=cfg.trainer.devices, num_nodes=cfg.trainer.num_nodes,
        strategy=cfg.trainer.strategy, threads=cfg.threads, record_path=str(published_region))
    sidecar = build / "region.npy.json"
    if sidecar.is_file() and not launched:  # the mosaic's description names its final path
        info = json.loads(sidecar.read_text(encoding="utf-8"))
        info["path"] = str(published_region)
        atomic_write_json(sidecar, info)
    if summary.get("index"):
        summary["index"] = str(out / "map_index.json")
    return summary
