"""Latent tileset query speed and memory against one latent map and the bicubic grid.

One synthetic region (``--side`` nodes a side, 30 m) is fitted twice with the same latent
settings and ``--steps`` steps (query speed does not depend on the fit's quality): as one
`LatentTerrainMap` of the whole region, and as a tileset of tiles ``--tile_nodes`` node
intervals wide with a ``--overlap`` node blend (`neuralmap.training.latent_tileset`). In the
same run (best of ``--repeats``, the methods interleaved in every repeat), height and slope
(``height_and_slope``, float64 points, one thread) of:

* the tileset, every tile resident (warm cache), at uniform random points of the region,
  and at points inside the blend zones only (two or four tiles per point: the worst case);
* the tileset with a two-tile cache at uniform points (every batch decodes again: the cost
  of a cache far smaller than the area flown over);
* the single latent map and `GridTerrain` (torch bicubic of the DEM) at the same points.

Reported: points per second, the ratios, the decoded bytes per tile (the polynomial table
of 16 float32 per cell, 16x the raw grid) against the raw float32 grid, the bitstream bytes,
and the decode time of one tile.

Usage::

    python benchmarks/bench_tileset.py              # 257 x 257 region, 4 x 4 tiles
    python benchmarks/bench_tileset.py --quick      # 129 x 129, 2 x 2 tiles
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
import torch

REPO_ROOT = Path(__file__).resolve().parents[1]
if str(REPO_ROOT) not in sys.path:
    sys.path.insert(0, str(REPO_ROOT))

from neuralmap.docs.bench_run import add_out_option, start_bench  # noqa: E402
from neuralmap.terrain.grid import GridTerrain  # noqa: E402
from neuralmap.terrain.latent.bitstream import encode_latent_map  # noqa: E402
from neuralmap.terrain.latent.encode import fit_latent_map  # noqa: E402
from neuralmap.terrain.latent.tile_cache import decoded_bytes  # noqa: E402
from neuralmap.terrain.latent.tileset import LatentTileset  # noqa: E402
from neuralmap.training.latent_tileset import fit_tileset, plan_tileset  # noqa: E402


def rates(fns: dict, xy: dict, repeats: int) -> dict[str, float]:  # noqa: ANN001
    """Best-of-``repeats`` points per second of every ``fns[name](xy[name])``, the methods
    interleaved within each repeat (a load change on a shared machine hits them alike)."""
    best = dict.fromkeys(fns, float("inf"))
    for name, fn in fns.items():
        fn(xy[name][:1024])  # warm-up
    for _ in range(repeats):
        for name, fn in fns.items():
            start = time.perf_counter()
            fn(xy[name])
            best[name] = min(best[name], time.perf_counter() - start)
    return {name: xy[name].shape[0] / best[name] for name in fns}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--side", type=int, default=257, help="Region nodes a side.")
    parser.add_argument("--tile_nodes", type=int, default=64, help="Tile core, node intervals.")
    parser.add_argument("--overlap", type=int, default=4, help="Blend half-width, nodes.")
    parser.add_argument("--steps", type=int, default=20, help="Fit steps (speed only).")
    parser.add_argument("--points", type=int, default=200_000, help="Query points.")
    parser.add_argument("--repeats", type=int, default=7)
    parser.add_argument("--quick", action="store_true", help="129 x 129, 2 x 2 tiles.")
    add_out_option(parser, "bench_tileset")
    args = parser.parse_args()
    if args.quick:
        args.side, args.points, args.repeats = 129, 50_000, 3
    torch.set_num_threads(1)
    run = start_bench(__file__, args)
    options = {"rate_weight": 3.0, "levels": 5, "between_points": 2048, "seed": 0}
    plan = plan_tileset(f"synthetic:{args.side}x{args.side}", overlap_nodes=args.overlap,
                        tile_nodes=args.tile_nodes)
    region = plan.region
    rows, cols = plan.layout.grid
    print(f"region {args.side} x {args.side} nodes (30 m), {rows} x {cols} tiles of "
          f"{args.tile_nodes} node intervals, overlap {args.overlap} nodes, {args.steps} steps")
    with tempfile.TemporaryDirectory() as tmp:
        index = fit_tileset(plan, tmp, steps=args.steps, options=options, progress=False)
        single, _ = fit_latent_map(region, steps=args.steps, **options)
        warm = LatentTileset(index, cache_bytes=None)
        small = LatentTileset(index, cache_tiles=2)
        grid = GridTerrain(region, method="bicubic", dtype=torch.float64)
        g = np.random.default_rng(0)
        xmin, xmax, ymin, ymax = region.extent
        uniform = torch.as_tensor(g.uniform([xmin, ymin], [xmax, ymax], (args.points, 2)))
        seams_x = np.array(plan.layout.seams(0))
        wx = plan.layout.blend_width[0]
        pick = g.integers(0, len(seams_x), args.points)
        blend = uniform.clone()
        blend[:, 0] = torch.as_tensor(seams_x[pick] + g.uniform(-wx, wx, args.points))
        t0 = time.perf_counter()
        warm.tile(0)
        decode_s = time.perf_counter() - t0
        for k in range(plan.layout.count):
            warm.tile(k)
        per_tile = decoded_bytes(warm.tile(0))
        window = warm.tiles[0].window
        raw_tile = 4 * (window[1] - window[0] + 1) * (window[3] - window[2] + 1)
        fns = {
            "tileset (warm), uniform": warm.height_and_slope,
            "tileset (warm), blend zones": warm.height_and_slope,
            "tileset (2-tile cache), uniform":
                lambda p: [small.height_and_slope(c) for c in p.split(8192)],
            "single LatentTerrainMap, uniform": single.height_and_slope,
            "GridTerrain bicubic, uniform": grid.height_and_slope,
        }
        points = {name: blend if "blend" in name else uniform for name in fns}
        results = rates(fns, points, args.repeats)
        bitstream = sum(t.bytes for t in warm.tiles)
        single_bytes = len(encode_latent_map(single))
    grid_rate = results["GridTerrain bicubic, uniform"]
    single_rate = results["single LatentTerrainMap, uniform"]
    print("\n| query (height + slope, float64, 1 thread) | points/s | / single map | / bicubic |")
    print("|---|---:|---:|---:|")
    for name, value in results.items():
        print(f"| {name} | {value:,.0f} | {value / single_rate:.2f} | {value / grid_rate:.2f} |")
    print("\n| memory | bytes |")
    print("|---|---:|")
    print(f"| decoded tile (table + coefficients + symbols) | {per_tile:,} |")
    print(f"| raw float32 grid of that tile's window | {raw_tile:,} |")
    print(f"| decoded / raw | {per_tile / raw_tile:.1f}x |")
    print(f"| all {plan.layout.count} tiles decoded | {warm.cache.resident_bytes:,} |")
    print(f"| 2-tile cache peak | {small.cache.peak_bytes:,} ({small.cache.decodes} decodes) |")
    print(f"| tileset bitstreams | {bitstream:,} |")
    print(f"| single map bitstream | {single_bytes:,} |")
    print(f"\ndecode of one tile: {decode_s * 1e3:.1f} ms")
    run.finish({"rates": results, "decoded_tile_bytes": per_tile, "raw_tile_bytes": raw_tile,
                "decode_s": decode_s, "bitstream_bytes": bitstream,
                "single_bitstream_bytes": single_bytes})


if __name__ == "__main__":
    main()
