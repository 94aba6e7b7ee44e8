"""Every raster codec placed between the two rate-distortion bounds of the tile.

Upper: the Gaussian R(D) of the tile's spectrum. Among sources of a given covariance the
Gaussian is the hardest to code, so this is an upper bound on the rate-distortion function of
terrain, not a floor: a codec can sit below it. Lower: an estimate of the Shannon lower bound
``h̄ − ½ log2(2πeD)`` per node, with the entropy rate ``h̄`` estimated from the innovations of
a causal linear predictor (`neuralmap.studies.rate_distortion.shannon_lower_bound_bytes`;
an estimate from above of the true bound). Where the two differ, the difference is the room a
codec that models more than the spectrum could take.

For each tile (jacksboro; matplotlib's ``topobathy.npz``; the synthetic region generator's
terrain) and each codec point, the bytes the codec stores are set beside
`neuralmap.studies.rate_distortion.gaussian_rd_bytes` at the same node RMSE: the
rate of a Gaussian field with the tile's own smoothed (log-frequency x orientation)
spectrum, and the "oracle" rate with every DCT coefficient's power known. A ratio near 1
against the smoothed bound means a linear transform coder has little left to take on that
tile; a target of 0.7x the codec's bytes then needs structure beyond the spectrum
(non-stationarity, shapes), which the oracle column brackets generously.

Codecs (same run): JPEG 2000 over a PSNR sweep on 16-bit heights (the RMSE-optimised use),
and the toolkit's error-bounded codecs (`neuralmap.terrain.codecs.compress_grid`:
JPEG 2000, SZ3, LERC, JPEG-LS) over a sweep of max-error bounds. Node RMSE 0.3-5 m.

Usage:
    python benchmarks/bench_rd_bound.py
    python benchmarks/bench_rd_bound.py --tiles jacksboro
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

REPO_ROOT = Path(__file__).resolve().parents[1]
for path in (REPO_ROOT, REPO_ROOT / "benchmarks"):
    if str(path) not in sys.path:
        sys.path.insert(0, str(path))

from bench_latent_rd import get_tile, jpeg2k_psnr_sweep, node_rmse  # noqa: E402

from neuralmap.docs.bench_run import add_out_option, start_bench  # noqa: E402
from neuralmap.studies.rate_distortion import (  # noqa: E402
    gaussian_rd_bytes,
    innovation_entropy_bits,
    shannon_lower_bound_bytes,
)
from neuralmap.terrain.codecs import compress_grid  # noqa: E402
from neuralmap.terrain.grid import fill_voids_nearest  # noqa: E402

CODECS = ("jpeg2k", "sz3", "lerc", "jpegls")


def _ratio(nbytes: float, bound: float) -> str:
    return f"{nbytes / bound:.2f}" if bound > 0 else "—"


def run_tile(name: str, args: argparse.Namespace) -> list[str]:
    tile = get_tile(name)
    heights = fill_voids_nearest(tile.heights, tile.spacing)
    points = [("JPEG 2000 (PSNR sweep)", r["what"].split(",")[0], r["bytes"], r["rmse_m"])
              for r in jpeg2k_psnr_sweep(tile, args.psnr_levels)]
    for codec in CODECS:
        for bound in args.bounds:
            grid = compress_grid(tile, codec=codec, max_error=bound)
            points.append((f"{codec} (max error)", f"{bound:g} m", grid.nbytes,
                           node_rmse(grid.tile.heights, tile)))
    entropy = innovation_entropy_bits(heights)
    lines = [f"### {tile.name} ({tile.shape[0]} x {tile.shape[1]} nodes, height std "
             f"{np.nanstd(tile.heights):.1f} m, innovation entropy {entropy:.3f} bit/node)", "",
             "| codec | setting | bytes | node RMSE (m) | Shannon lower bound est. (B) | "
             "× SLB | Gaussian R(D), upper (B) | × Gaussian | oracle (B) | × oracle |",
             "|---|---|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for kind, setting, nbytes, rmse in points:
        if not (args.rmse_range[0] <= rmse <= args.rmse_range[1]):
            continue
        smooth = gaussian_rd_bytes(heights, rmse)
        oracle = gaussian_rd_bytes(heights, rmse, oracle=True)
        slb = shannon_lower_bound_bytes(heights, rmse, entropy_bits=entropy)
        lines.append(f"| {kind} | {setting} | {nbytes:,} | {rmse:.3f} | {slb:,.0f} | "
                     f"{_ratio(nbytes, slb)} | {smooth:,.0f} | {_ratio(nbytes, smooth)} | "
                     f"{oracle:,.0f} | {_ratio(nbytes, oracle)} |")
    return lines


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--tiles", nargs="+", default=["jacksboro", "topobathy", "synthetic"])
    parser.add_argument("--psnr_levels", nargs="+", type=float, default=[60, 65, 70, 75, 80])
    parser.add_argument("--bounds", nargs="+", type=float, default=[1, 2, 4, 8])
    parser.add_argument("--rmse_range", nargs=2, type=float, default=[0.3, 5.0])
    add_out_option(parser, "bench_rd_bound")
    args = parser.parse_args(argv)
    bench = start_bench(__file__, args, argv)
    for name in args.tiles:
        print("\n".join(run_tile(name, args)), "\n", flush=True)
    bench.finish()
    return 0


if __name__ == "__main__":
    sys.exit(main())
