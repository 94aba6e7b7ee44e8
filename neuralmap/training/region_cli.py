"""``python train.py region``: fit a region-scale neural map, shard by shard.

The same command-line style as the map fit (jsonargparse, the parser LightningCLI is built
on): ``--config FILE`` (YAML), ``--data.*``, ``--model.*``, ``--trainer.*``, ``--threads``,
``--print_config``. ``--data.path`` is a 2-D ``.npy`` region (memory-mapped; spacing from
its ``.json`` sidecar or ``--data.spacing``), one or more DEM files / globs (stitched with
`neuralmap.dem.write_mosaic` into ``OUT/region.npy``), or ``synthetic-region``
(`neuralmap.dem.region.synthetic_region`, the paper's 3610 × 1270 nodes at 100 m).
The map goes to ``OUT/map_index.json`` + ``OUT/shards/``; ``neuralmap.terrain.load_map(OUT)``
opens it lazily.

Examples:
    python train.py region --data.path "srtm/N36W08[45].hgt" --out runs/two_tiles --trainer.devices 2
    python train.py region --config configs/train_region.yaml --out runs/paper_region

Outputs are published whole: the run builds ``OUT`` under a hidden name beside it and puts
it in place at the end (`neuralmap.io.replacing_dir`), so a refused mosaic, a failed
or interrupted run, or ``kill -9`` leaves the previous output (or nothing) untouched, and a
second run into the same ``OUT`` while one runs is refused.

With ``--trainer.strategy ddp`` (Lightning's script launcher, or ``torchrun`` over several
nodes) every rank re-runs this command; only rank 0 writes the mosaic / synthetic region
and publishes. Over several machines, write the ``.npy`` once on a shared disk first.
Under ``torchrun`` every rank starts at once: rank 0 takes the output's lock and builds
the hidden folder beside ``--out``, and sends its path to the other ranks (a gloo
broadcast), which write their shards there, so ``--out`` must be on a disk every node
sees at the same path; the ranks start training once rank 0's region file is written.

Exit codes: 0 with the summary (JSON) on stdout; 2 for bad input (one ``error:`` line on
stderr); 1 when interrupted (Ctrl-C: nothing is published).
"""

from __future__ import annotations

import json
import os
import sys
from contextlib import ExitStack
from pathlib import Path
from typing import Any

from jsonargparse import ActionConfigFile, ArgumentParser

from neuralmap.exceptions import NeuralMapError
from neuralmap.io import atomic_write_json, replacing_dir
from neuralmap.training.cli_base import EXIT_BAD_INPUT, EXIT_NO_MAP
from neuralmap.training.region import RegionData, check_fit_options, check_spacing, fit_region

__all__ = ["main_region", "region_parser"]

#: Environment variable through which DDP script-launched ranks learn rank 0's build folder.
STAGING_ENV = "NEURALMAP_REGION_STAGING"
#: The name of the source that generates the paper-size synthetic region.
SYNTHETIC = "synthetic-region"


def region_parser() -> ArgumentParser:
    """The parser of ``train.py region`` (``--data.*``, ``--model.*``, ``--trainer.*``)."""
    from neuralmap.terrain.blockwise import NET_DEFAULTS

    p = ArgumentParser(prog="train.py region", description=__doc__.split("\n")[0],
                       exit_on_error=True)
    p.add_argument("--config", action=ActionConfigFile, help="YAML file of these options.")
    p.add_argument("--out", type=str, required=True,
                   help="Output folder (map_index.json, shards/, region.npy).")
    p.add_argument("--threads", type=int, default=1, help="torch threads per process.")
    p.add_argument("--data.path", type=str | list[str], required=True,
                   help=f".npy region, DEM files/globs (a list or one pattern), or {SYNTHETIC}.")
    p.add_argument("--data.spacing", type=float | None, default=None,
                   help="Grid spacing in metres, for a .npy without a sidecar.")
    p.add_argument("--data.region_shape", type=list[int] | None, default=None,
                   help=f"[ny, nx] of {SYNTHETIC} (default the paper's [1270, 3610]).")
    p.add_argument("--model.block_nodes", type=int | None, default=24)
    p.add_argument("--model.overlap_nodes", type=float, default=float(NET_DEFAULTS.overlap_nodes))
    p.add_argument("--model.shard_blocks", type=list[int], default=[8, 8],
                   help="[sbx, sby] blocks per shard.")
    p.add_argument("--model.steps", type=int, default=500, help="Adam steps per shard.")
    p.add_argument("--model.points_per_block", type=int, default=256)
    p.add_argument("--model.lr", type=float, default=1e-2)
    p.add_argument("--model.seed", type=int, default=0)
    p.add_argument("--trainer.devices", type=int, default=1, help="Processes per node.")
    p.add_argument("--trainer.num_nodes", type=int, default=1)
    p.add_argument("--trainer.strategy", type=str | None, default=None,
                   help="ddp_spawn (default for several devices) | ddp (script / torchrun).")
    return p


def _sources(path: str | list[str]) -> list[str]:
    sources = [path] if isinstance(path, str) else list(path)
    if not sources:
        raise NeuralMapError(f"--data.path is empty; give a .npy region, DEM files or {SYNTHETIC}.")
    return sources


def _check_out(out: Path) -> None:
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


def _torchrun() -> bool:
    """Whether ``torchrun`` started this process as one rank of several (it sets
    ``TORCHELASTIC_RUN_ID`` and ``WORLD_SIZE``)."""
    return "TORCHELASTIC_RUN_ID" in os.environ and int(os.environ.get("WORLD_SIZE", "1")) > 1


def _torchrun_build(build: Path | None) -> Path:
    """Rank 0's build folder, sent to every rank of a ``torchrun`` job (gloo broadcast on
    the process group Fabric then reuses); rank 0 passes it, the others ``None``."""
    import torch.distributed as dist

    if not dist.is_initialized():
        dist.init_process_group("gloo")  # env:// from torchrun's RANK, WORLD_SIZE, MASTER_*
    box = [str(build) if build is not None else ""]
    dist.broadcast_object_list(box, src=0)
    return Path(box[0])


def _train(cfg: Any, build: Path, out: Path, launched: bool) -> dict[str, Any]:
    sources = _sources(cfg.data.path)
    region = _region_file(sources, build, cfg, launched)
    if _torchrun():  # every rank started at once: the others wait for rank 0's region file
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


def main_region(argv: list[str] | None = None) -> Path | None:
    """Runs the region trainer; prints the summary as JSON.

    Returns:
        The published ``OUT/map_index.json`` (``None`` on script-launched DDP ranks).

    Raises:
        SystemExit: 2 on bad input (one ``error:`` line on stderr), 1 when interrupted.
    """
    cfg = region_parser().parse_args(argv)
    out = Path(cfg.out)
    launched = os.environ.get("LOCAL_RANK", "0") != "0" or os.environ.get("RANK", "0") != "0"
    try:
        if cfg.data.spacing is not None:
            check_spacing(cfg.data.spacing, where="--data.spacing")
        check_fit_options(
            block_nodes=cfg.model.block_nodes, overlap_nodes=cfg.model.overlap_nodes,
            shard_blocks=tuple(cfg.model.shard_blocks), steps=cfg.model.steps,
            points_per_block=cfg.model.points_per_block, lr=cfg.model.lr,
            devices=cfg.trainer.devices, num_nodes=cfg.trainer.num_nodes,
            strategy=cfg.trainer.strategy, threads=cfg.threads)
        _sources(cfg.data.path)
        with ExitStack() as building:
            if launched and _torchrun():  # rank 0's folder; torchrun ends us if rank 0 fails
                build = _torchrun_build(None)
            elif launched and os.environ.get(STAGING_ENV):  # Lightning's script launcher
                build = Path(os.environ[STAGING_ENV])
            else:
                _check_out(out)
                build = building.enter_context(replacing_dir(out, option="--out"))
                if _torchrun():
                    _torchrun_build(build)
            os.environ[STAGING_ENV] = str(build)
            summary = _train(cfg, build, out, launched)
    except NeuralMapError as exc:
        sys.stdout.flush()
        print(f"error: {exc}", file=sys.stderr, flush=True)
        raise SystemExit(EXIT_BAD_INPUT) from None
    except KeyboardInterrupt:
        sys.stdout.flush()
        print(f"error: interrupted; nothing was published to --out '{out}' (an earlier "
              "output there is unchanged). Run the command again to train.",
              file=sys.stderr, flush=True)
        raise SystemExit(EXIT_NO_MAP) from None
    finally:
        if not launched:
            os.environ.pop(STAGING_ENV, None)
    if launched:
        return None
    print(json.dumps(summary, indent=1, default=str), flush=True)
    return out / "map_index.json"
