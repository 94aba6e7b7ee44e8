"""How far each raster codec is from the Gaussian rate-distortion bound of the tile.

For each tile (jacksboro; matplotlib's ``topobathy.npz``; the synthetic region generator's
terrain) and each codec point, the bytes the codec stores are set beside
:func:`neuralmap.studies.rate_distortion.gaussian_rd_bytes` at the same node RMSE: the
rate of a Gaussian field with the tile's own smoothed (log-frequency x orientation)
spectrum, and the "oracle" rate with every DCT coefficient's power known. A ratio near 1
against the smoothed bound means a linear transform coder has little left to take on that
tile; a target of 0.7x the codec's bytes then needs structure beyond the spectrum
(non-stationarity, shapes), which the oracle column brackets generously.

Codecs (same run): JPEG 2000 over a PSNR sweep on 16-bit heights (the RMSE-optimised use),
and the toolkit's error-bounded codecs (:func:`neuralmap.terrain.codecs.compress_grid`:
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

from neuralmap.studies.rate_distortion import gaussian_rd_bytes  # noqa: E402
from neuralmap.terrain.codecs import compress_grid  # noqa: E402
from neuralmap.terrain.grid import fill_voids_nearest  # noqa: E402

CODECS = ("jpeg2k", "sz3", "lerc", "jpegls")


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
    lines = [f"### {tile.name} ({tile.shape[0]} x {tile.shape[1]} nodes, height std "
             f"{np.nanstd(tile.heights):.1f} m)", "",
             "| codec | setting | bytes | node RMSE (m) | Gaussian bound (B) | × bound | "
             "oracle bound (B) | × oracle |", "|---|---|---:|---:|---:|---:|---:|---:|"]
    for kind, setting, nbytes, rmse in points:
        if not (args.rmse_range[0] <= rmse <= args.rmse_range[1]):
            continue
        smooth = gaussian_rd_bytes(heights, rmse)
        oracle = gaussian_rd_bytes(heights, rmse, oracle=True)
        lines.append(f"| {kind} | {setting} | {nbytes:,} | {rmse:.3f} | {smooth:,.0f} | "
                     f"{nbytes / smooth:.2f} | {oracle:,.0f} | {nbytes / oracle:.2f} |")
    return lines


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--tiles", nargs="+", default=["jacksboro", "topobathy", "synthetic"])
    parser.add_argument("--psnr_levels", nargs="+", type=float, default=[60, 65, 70, 75, 80])
    parser.add_argument("--bounds", nargs="+", type=float, default=[1, 2, 4, 8])
    parser.add_argument("--rmse_range", nargs=2, type=float, default=[0.3, 5.0])
    args = parser.parse_args(argv)
    for name in args.tiles:
        print("\n".join(run_tile(name, args)), "\n", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
