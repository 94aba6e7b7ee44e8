"""Stored size and height + slope query speed of compact maps, against the bicubic grid.

Measures in one run, on the jacksboro sample, one torch thread unless ``--threads``:

* the torch bicubic and bilinear grids (``GridTerrain.height_and_slope``, analytic);
* neural maps of a few sizes (the default ``configs/train.yaml`` net and the compact
  ``configs/compact_*.yaml`` nets; trained maps given with ``--map`` or untrained nets of
  the same architecture, which cost the same), each with the slope by reverse-mode
  autograd (``AutogradLinearizer``) and by forward mode (``height_and_slope``);
* each neural map baked once onto the DEM nodes and queried as a bicubic grid
  (``neuralmap.terrain.bake``: stored compact, decoded at load time like a codec).

Stored bytes: float32 grid; neural maps as int8 (per-channel scales) ``save_map`` files.
Every rate is a median over repeats after warm-up; ratios are against the bicubic grid
measured in the same run.

Usage:
    python benchmarks/bench_map_size.py            # about a minute
    python benchmarks/bench_map_size.py --quick    # smoke test
    python benchmarks/bench_map_size.py --map runs/compact_s/version_0/neural_map.pt
"""

from __future__ import annotations

import argparse
import os
import platform
import sys
import tempfile
from pathlib import Path

import torch

REPO_ROOT = Path(__file__).resolve().parents[1]
for extra_path in (REPO_ROOT, REPO_ROOT / "benchmarks"):
    if str(extra_path) not in sys.path:  # run as a script from anywhere
        sys.path.insert(0, str(extra_path))

from bench_filter import Row, _rates, timed  # noqa: E402

from neuralmap.dem.load import load_tile  # noqa: E402
from neuralmap.docs.bench_run import add_out_option, start_bench  # noqa: E402
from neuralmap.linearize.autograd import AutogradLinearizer  # noqa: E402
from neuralmap.terrain.bake import bake_to_grid  # noqa: E402
from neuralmap.terrain.blockwise import BlockwiseTerrainNet  # noqa: E402
from neuralmap.terrain.export import load_map, save_map  # noqa: E402
from neuralmap.terrain.grid import GridTerrain  # noqa: E402

#: Architectures measured when no trained map is given: (label, from_tile keywords).
ARCHITECTURES = (
    ("default (configs/train.yaml)", {"block_nodes": 24, "n_frequencies": 16, "hidden": 32}),
    ("compact_m", {"block_nodes": 32, "n_frequencies": 8, "hidden": 20}),
    ("compact_s", {"block_nodes": 32, "n_frequencies": 8, "hidden": 16}),
)


def stored_int8_bytes(net: BlockwiseTerrainNet) -> int:
    """File size of the map exported with int8 per-channel weights."""
    with tempfile.TemporaryDirectory() as tmp:
        path = save_map(net, Path(tmp) / "map.pt", quantization="int8_channel")
        return os.path.getsize(path)


def run(args: argparse.Namespace) -> list[Row]:
    """Runs the measurements; returns rows (rate = queries/s; detail holds bytes, ratio)."""
    torch.set_num_threads(args.threads)
    tile = load_tile("jacksboro")
    raw = tile.heights.size * 4
    print(
        f"# bench_map_size: torch {torch.__version__}, {torch.get_num_threads()} threads, "
        f"{platform.processor() or platform.machine()}; tile {tile.name} "
        f"{tile.shape[0]}x{tile.shape[1]}, {args.n} points, float32"
    )
    gen = torch.Generator().manual_seed(0)
    xmin, xmax, ymin, ymax = tile.extent
    lo = torch.tensor([xmin, ymin])
    span = torch.tensor([xmax - xmin, ymax - ymin])
    xy = lo + span * torch.rand(args.n, 2, generator=gen)
    repeats = args.repeats

    def measure(fn: object) -> tuple[float, float]:
        return _rates(args.n, timed(fn, repeats=repeats))  # type: ignore[arg-type]

    rows: list[Row] = []
    bicubic = GridTerrain(tile, method="bicubic", dtype=torch.float32)
    ref_rate, ref_best = measure(lambda: bicubic.height_and_slope(xy))
    rows.append(Row("grid", "torch bicubic grid, analytic", ref_rate, ref_best, "q/s", f"{raw}"))
    bilinear = GridTerrain(tile, method="bilinear", dtype=torch.float32)
    rate, best = measure(lambda: bilinear.height_and_slope(xy))
    rows.append(Row("grid", "torch bilinear grid, analytic", rate, best, "q/s", f"{raw}"))

    maps: list[tuple[str, BlockwiseTerrainNet]] = [
        (f"trained {Path(p).parent.parent.name}", load_map(p)) for p in args.map
    ]
    if not maps:
        archs = ARCHITECTURES[-1:] if args.quick else ARCHITECTURES
        maps = [
            (f"{label}, untrained", BlockwiseTerrainNet.from_tile(tile, **kw).eval())
            for label, kw in archs
        ]
    for label, net in maps:
        size = stored_int8_bytes(net)
        lin = AutogradLinearizer(net)
        rate, best = measure(lambda lin=lin: lin(xy))
        rows.append(Row(label, "neural, autograd slope", rate, best, "q/s", f"{size}"))
        rate, best = measure(lambda net=net: net.height_and_slope(xy))
        rows.append(Row(label, "neural, forward-mode slope", rate, best, "q/s", f"{size}"))
        baked = bake_to_grid(net, tile).float()
        rate, best = measure(lambda baked=baked: baked.height_and_slope(xy))
        rows.append(Row(label, "neural baked to bicubic grid", rate, best, "q/s", f"{size}"))

    print(f"{'map':44s} {'query':32s} {'bytes':>9s} {'% raw':>6s} {'M q/s':>7s} {'best':>6s} "
          f"{'x bicubic':>9s}")
    for row in rows:
        nbytes = int(row.detail)
        print(
            f"{row.group[:44]:44s} {row.name:32s} {nbytes:9d} {100 * nbytes / raw:6.1f} "
            f"{row.rate / 1e6:7.3f} {row.best / 1e6:6.3f} {row.rate / ref_rate:9.3f}"
        )
    return rows


def main(argv: list[str] | None = None) -> int:
    """Command-line entry point; returns the exit status."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--n", type=int, default=200_000, help="query points")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--map", action="append", default=[], help="trained neural_map.pt")
    parser.add_argument("--quick", action="store_true", help="small smoke run")
    add_out_option(parser, "bench_map_size")
    args = parser.parse_args(argv)
    bench = start_bench(__file__, args, argv)
    if args.quick:
        args.n, args.repeats = min(args.n, 20_000), 2
    run(args)
    bench.finish()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
