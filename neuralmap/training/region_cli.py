"""Command line of region training: ``python train_region.py SOURCE... --out DIR [options]``.

``SOURCE`` is a 2-D ``.npy`` region (memory-mapped; spacing from its ``.json`` sidecar or
``--spacing``), one or more DEM files / globs (stitched with
:func:`neuralmap.dem.write_mosaic` into ``DIR/region.npy`` first), or ``synthetic-region``
(:func:`neuralmap.dem.region.synthetic_region`, the paper's 3610 × 1270 nodes at 100 m,
written to ``DIR/region.npy``). The map goes to ``DIR/map_index.json`` + ``DIR/shards/``;
``neuralmap.terrain.load_map(DIR)`` opens it lazily.

Examples:
    python train_region.py "srtm/N36W08[45].hgt" --out runs/two_tiles --devices 2
    python train_region.py synthetic-region --out runs/paper_region --devices 2

With ``--strategy ddp`` (Lightning's script launcher, or ``torchrun`` over several nodes)
every rank re-runs this command; only rank 0 writes the mosaic / synthetic region. Over
several machines, write the ``.npy`` once on a shared disk first and pass it.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from pathlib import Path

from neuralmap.exceptions import NeuralMapError

__all__ = ["main"]


def _parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="train_region.py", description=__doc__.split("\n")[0])
    p.add_argument("sources", nargs="+", help=".npy region, DEM files/globs, or synthetic-region")
    p.add_argument("--out", required=True, help="output folder (map_index.json, shards/)")
    p.add_argument("--spacing", type=float, default=None, help="metres, for a bare .npy")
    p.add_argument("--block_nodes", type=int, default=24)
    p.add_argument("--overlap_nodes", type=float, default=4.0)
    p.add_argument("--shard_blocks", type=int, nargs=2, default=[8, 8], metavar=("SBX", "SBY"))
    p.add_argument("--steps", type=int, default=500, help="Adam steps per shard")
    p.add_argument("--points_per_block", type=int, default=256)
    p.add_argument("--lr", type=float, default=1e-2)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--devices", type=int, default=1, help="processes per node")
    p.add_argument("--num_nodes", type=int, default=1)
    p.add_argument("--strategy", default=None, help="ddp_spawn (default) | ddp (torchrun)")
    p.add_argument("--threads", type=int, default=1, help="torch threads per process")
    p.add_argument("--region_shape", type=int, nargs=2, default=None, metavar=("NY", "NX"),
                   help="shape of synthetic-region (default the paper's 1270 3610)")
    return p


def main(argv: list[str] | None = None) -> int:
    """Runs the region trainer; prints the summary as JSON. Returns the exit code."""
    from neuralmap.dem.mosaic import write_mosaic
    from neuralmap.dem.region import PAPER_REGION_SHAPE, synthetic_region
    from neuralmap.training.region import RegionData, fit_region

    args = _parser().parse_args(argv)
    out = Path(args.out)
    try:
        out.mkdir(parents=True, exist_ok=True)
        sources = args.sources
        launched = os.environ.get("LOCAL_RANK", "0") != "0" or os.environ.get("RANK", "0") != "0"
        if launched and sources != [] and not (len(sources) == 1 and sources[0].endswith(".npy")):
            # a rank started by Lightning's script launcher (strategy ddp): rank 0 has
            # written the region already; do not write it again
            path = out / "region.npy"
        elif sources == ["synthetic-region"]:
            shape = tuple(args.region_shape) if args.region_shape else PAPER_REGION_SHAPE
            synthetic_region(out / "region.npy", shape=shape, seed=args.seed)  # type: ignore[arg-type]
            path = out / "region.npy"
        elif len(sources) == 1 and sources[0].lower().endswith(".npy"):
            path = Path(sources[0])
        else:
            write_mosaic(sources, out / "region.npy")
            path = out / "region.npy"
        data = RegionData.open(path, spacing=args.spacing)
        summary = fit_region(
            data, out, block_nodes=args.block_nodes, overlap_nodes=args.overlap_nodes,
            shard_blocks=tuple(args.shard_blocks), steps=args.steps,  # type: ignore[arg-type]
            points_per_block=args.points_per_block, lr=args.lr, seed=args.seed,
            devices=args.devices, num_nodes=args.num_nodes, strategy=args.strategy,
            threads=args.threads)
    except NeuralMapError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(json.dumps(summary, indent=1, default=str))
    return 0
