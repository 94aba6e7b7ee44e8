"""Rate-distortion of latent-grid neural maps against JPEG 2000, on three tiles.

For each tile (jacksboro; matplotlib's real ``topobathy.npz`` sample DEM; the synthetic
region generator's terrain) and each rate weight ``lambda``, a latent-grid map is fitted
(`neuralmap.terrain.latent.encode.fit_latent_map`) and its bitstream encoded; the
file size is what is counted. JPEG 2000 in the same run:

* ``jpeg2k (PSNR sweep)``: imagecodecs JPEG 2000 (irreversible wavelet) on heights
  quantised to 16 bits (5 cm step, or coarser when the span needs it), over a sweep of
  target PSNRs: the RMSE-optimised use of the codec, the strongest JPEG 2000 baseline;
* ``jpeg2k (max error)``: `neuralmap.terrain.codecs.compress_grid` (the toolkit's
  error-bounded JPEG 2000, as the map-size study uses it), over a sweep of bounds.

Each stream is charged `neuralmap.terrain.codecs.HEADER_BYTES`. Distortion is the
RMSE at the tile's nodes; the BD-rate (Bjøntegaard) of the latent map against each JPEG
2000 curve is the mean log-rate difference at equal log-RMSE over the overlap of the
curves within 0.5-5 m (cubic fits; fewer points, lower degree). Both are also set against
the Gaussian rate-distortion bound of the tile's smoothed spectrum (reverse water-filling,
`gaussian_rd`): how much room a linear transform coder has left. Between the nodes, every
map is compared with the subgrid truth terrain (`neuralmap.lab.truth_terrain.true_terrain`,
bicubic DEM on a 4x finer grid plus fractal detail continuing the tile's spectrum) at
random points: the latent map itself, bicubic of the DEM, and bicubic of the latent map's
own node values.

Usage:
    python benchmarks/bench_latent_rd.py                 # all three tiles
    python benchmarks/bench_latent_rd.py --quick         # smoke test
    python benchmarks/bench_latent_rd.py --tiles synthetic --steps 400
    python benchmarks/bench_latent_rd.py --starts sweeps exact  # both pyramid starts
    python benchmarks/bench_latent_rd.py --bases wavelet        # the wavelet basis only
    python benchmarks/bench_latent_rd.py --bases wavelet --zones 0 4  # with / without
                                                              # per-zone steps
"""

from __future__ import annotations

import argparse
import sys
import time
import types
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

REPO_ROOT = Path(__file__).resolve().parents[1]
if str(REPO_ROOT) not in sys.path:
    sys.path.insert(0, str(REPO_ROOT))

from neuralmap.dem import load_tile  # noqa: E402
from neuralmap.dem.tile import DemTile  # noqa: E402
from neuralmap.docs.bench_run import add_out_option, start_bench  # noqa: E402
from neuralmap.terrain.codecs import HEADER_BYTES, compress_grid  # noqa: E402
from neuralmap.terrain.grid import GridTerrain  # noqa: E402
from neuralmap.terrain.latent.bitstream import encode_latent_map  # noqa: E402
from neuralmap.terrain.latent.encode import fit_latent_map  # noqa: E402
from neuralmap.terrain.latent.quality import between_points  # noqa: E402

RMSE_RANGE = (0.5, 5.0)


def topobathy_tile() -> DemTile:
    """matplotlib's ``topobathy.npz`` (2-arcminute grid, Pacific Northwest) as a metric tile."""
    import matplotlib.cbook as cbook

    data = cbook.get_sample_data("topobathy.npz")
    lon, lat = np.asarray(data["longitude"], float), np.asarray(data["latitude"], float)
    dx = float(np.mean(np.diff(lon))) * 111_320.0 * np.cos(np.radians(lat.mean()))
    dy = float(np.mean(np.diff(lat))) * 110_574.0
    return DemTile(np.asarray(data["topo"], float), spacing=(dx, dy), name="topobathy",
                   source="matplotlib sample_data/topobathy.npz")


def get_tile(name: str) -> DemTile:
    return topobathy_tile() if name == "topobathy" else load_tile(name)


def node_rmse(decoded: np.ndarray, tile: DemTile) -> float:
    valid = tile.valid_mask
    return float(np.sqrt(np.mean((decoded[valid] - tile.heights[valid]) ** 2)))


def jpeg2k_psnr_sweep(tile: DemTile, levels: list[float]) -> list[dict[str, Any]]:
    """JPEG 2000 at target PSNRs on 16-bit quantised heights: ``[{bytes, rmse_m, ...}]``."""
    import imagecodecs

    from neuralmap.terrain.grid import fill_voids_nearest

    heights = fill_voids_nearest(tile.heights, tile.spacing)
    offset = float(heights.min())
    step = max(0.05, (float(heights.max()) - offset) / 60000.0)
    q = np.round((heights - offset) / step).astype(np.uint16)
    out = []
    for level in levels:
        stream = bytes(imagecodecs.jpeg2k_encode(q, level=level))
        back = np.asarray(imagecodecs.jpeg2k_decode(stream), float) * step + offset
        out.append({"bytes": len(stream) + HEADER_BYTES, "rmse_m": node_rmse(back, tile),
                    "decoded": back, "what": f"PSNR {level:g} dB, step {step:.3g} m"})
    return out


def jpeg2k_bounded_sweep(tile: DemTile, bounds: list[float]) -> list[dict[str, Any]]:
    """`compress_grid` JPEG 2000 at max-error bounds."""
    out = []
    for bound in bounds:
        grid = compress_grid(tile, codec="jpeg2k", max_error=bound)
        decoded = grid.tile.heights
        out.append({"bytes": grid.nbytes, "rmse_m": node_rmse(decoded, tile), "decoded": decoded,
                    "what": f"max error {bound:g} m"})
    return out


@dataclass(frozen=True)
class BDRate:
    """A Bjøntegaard delta rate and the node-RMSE range it was computed over.

    Attributes:
        percent: BD-rate in % (NaN only when it cannot be computed; ``note`` says why).
        lo_m, hi_m: Node-RMSE range of the average (m; NaN when none).
        note: Empty when the range is the overlap of the curves inside the requested
            window; otherwise what was done instead, or why there is no value.
    """

    percent: float
    lo_m: float
    hi_m: float
    note: str = ""


def _log_curve(points: list[tuple[float, float]]) -> tuple[np.ndarray, np.ndarray, int]:
    """``(log rmse, log bytes)`` sorted by RMSE, one point per RMSE (the fewest bytes), only
    finite points with bytes > 0 and RMSE > 0; and how many points were dropped."""
    best: dict[float, float] = {}
    for b, r in points:
        if np.isfinite(b) and np.isfinite(r) and b > 0 and r > 0:
            best[float(r)] = min(float(b), best.get(float(r), np.inf))
    keys = sorted(best)
    return (np.log(np.array(keys)), np.log(np.array([best[k] for k in keys])),
            len(points) - len(keys))


def bd_rate_span(test: list[tuple[float, float]], ref: list[tuple[float, float]],
                 lo: float = RMSE_RANGE[0], hi: float = RMSE_RANGE[1]) -> BDRate:
    """Bjøntegaard delta rate of ``test`` vs ``ref`` (lists of ``(bytes, rmse)``), in %.

    Fits ``log(bytes)`` as a polynomial of ``log(rmse)`` per curve (degree <= 3, < its
    distinct points) and averages the difference of the fits over the overlap of both
    RMSE ranges within ``[lo, hi]``:

    ``BD = exp( 1/(b - a) int_a^b (p_test(x) - p_ref(x)) dx ) - 1``.

    Points with RMSE 0 (lossless) or non-finite values cannot lie on the log axis and are
    dropped (said in ``note``). When the curves overlap only outside ``[lo, hi]`` (a flat
    tile whose every point is under 0.5 m) the average is taken over their whole overlap
    and ``note`` says so. When they do not overlap at all, or a curve has fewer than two
    usable points, ``percent`` is NaN and ``note`` says why.
    """
    xt, yt, dt = _log_curve(test)
    xr, yr, dr = _log_curve(ref)
    dropped = (f"; {dt + dr} point(s) with RMSE 0 or non-finite left out"
               if dt + dr else "")
    if xt.size < 2 or xr.size < 2:
        return BDRate(float("nan"), float("nan"), float("nan"),
                      f"needs >= 2 points of distinct RMSE > 0 per curve (test {xt.size}, "
                      f"reference {xr.size}){dropped}")
    a, b = max(xt[0], xr[0]), min(xt[-1], xr[-1])
    if not b > a:
        return BDRate(float("nan"), float("nan"), float("nan"),
                      f"the curves do not overlap in node RMSE (test "
                      f"{np.exp(xt[0]):.3g}-{np.exp(xt[-1]):.3g} m, reference "
                      f"{np.exp(xr[0]):.3g}-{np.exp(xr[-1]):.3g} m){dropped}")
    wa, wb = max(a, np.log(lo)), min(b, np.log(hi))
    note = dropped.lstrip("; ")
    if wb > wa:
        a, b = wa, wb
    else:
        note = (f"no overlap inside {lo:g}-{hi:g} m: over the curves' whole overlap "
                f"{np.exp(a):.3g}-{np.exp(b):.3g} m" + dropped)
    pt = np.polyfit(xt, yt, min(3, xt.size - 1))
    pr = np.polyfit(xr, yr, min(3, xr.size - 1))
    it, ir = np.polyint(pt), np.polyint(pr)
    diff = (np.polyval(it, b) - np.polyval(it, a) - np.polyval(ir, b) + np.polyval(ir, a)) / (b - a)
    return BDRate(float((np.exp(diff) - 1.0) * 100.0), float(np.exp(a)), float(np.exp(b)),
                  note)


def bd_rate(test: list[tuple[float, float]], ref: list[tuple[float, float]],
            lo: float = RMSE_RANGE[0], hi: float = RMSE_RANGE[1]) -> float:
    """`bd_rate_span`'s percentage. NaN only when it cannot be computed, and then with a
    `RuntimeWarning` saying why (never silently)."""
    result = bd_rate_span(test, ref, lo, hi)
    if not np.isfinite(result.percent):
        warnings.warn(f"BD-rate not computed: {result.note}", RuntimeWarning, stacklevel=2)
    return result.percent


def gaussian_rd(tile: DemTile, rmses: list[float]) -> list[dict[str, Any]]:
    """Gaussian rate-distortion bound of the tile at node RMSEs
    (`neuralmap.studies.rate_distortion.gaussian_rd_bytes`: reverse water-filling on
    the tile's smoothed log-frequency x orientation DCT spectrum).

    It is the least rate of a coder that knows only this spectrum (a stationary Gaussian
    model: the limit of a linear transform coder with one fixed distribution per frequency
    band). It is not a bound for the tile itself: the Gaussian is the hardest source of a
    given spectrum, so a coder that exploits non-stationarity or sparsity (a flat sea, local
    roughness) can go below it.
    """
    from neuralmap.studies.rate_distortion import gaussian_rd_bytes
    from neuralmap.terrain.grid import fill_voids_nearest

    heights = fill_voids_nearest(tile.heights, tile.spacing)
    n_nodes = int(tile.valid_mask.sum())
    out = []
    for rmse in rmses:
        nbytes = gaussian_rd_bytes(heights, float(rmse))
        out.append({"bytes": nbytes, "rmse_m": float(rmse),
                    "what": f"RMSE {rmse:g} m, {8 * nbytes / n_nodes:.3f} bit/node"})
    return out


def between_truth(tile: DemTile, n_points: int) -> tuple[Any, np.ndarray, np.ndarray]:
    """Subgrid truth heights at random between-node points: ``(truth model, xy, heights)``."""
    from neuralmap.lab.truth_terrain import true_terrain

    scenario = types.SimpleNamespace(truth_model="subgrid", subgrid_factor=4,
                                     dem_error_sigma_m=0.0, dem_error_corr_m=0.0)
    truth = true_terrain(scenario, tile, seed=0)
    xy = between_points(tile, n_points, seed=7)
    with torch.no_grad():
        heights = truth.model(torch.from_numpy(xy)).numpy()
    return truth, xy, heights


def bicubic_of(tile: DemTile, heights: np.ndarray, xy: np.ndarray) -> np.ndarray:
    grid = GridTerrain(DemTile(heights, spacing=tile.spacing, origin=tile.origin, name=tile.name),
                       method="bicubic")
    with torch.no_grad():
        return grid(torch.from_numpy(xy)).numpy()


def run_tile(name: str, args: argparse.Namespace) -> dict[str, Any]:
    tile = get_tile(name)
    print(f"# tile {tile.name}: {tile.shape[0]} x {tile.shape[1]} nodes, spacing "
          f"{tile.spacing[0]:.1f} x {tile.spacing[1]:.1f} m, height std "
          f"{np.nanstd(tile.heights):.1f} m", flush=True)
    _, xy, truth = between_truth(tile, args.n_between)
    rms = lambda a: float(np.sqrt(np.mean((a - truth) ** 2)))  # noqa: E731
    bicubic_dem = rms(bicubic_of(tile, tile.heights, xy))
    rows: list[dict[str, Any]] = []
    variants = [(basis, start, zones) for basis in args.bases
                for start in (args.starts if basis == "pyramid" else ["exact"])
                for zones in args.zones]
    latent_kinds = [f"latent {basis} ({start} start{f', {r} x {r} zones' if r else ''})"
                    for basis, start, r in variants]
    for (basis, start, zones), kind in zip(variants, latent_kinds, strict=True):
        for lam in args.lambdas:
            clock = time.perf_counter()
            latent_map, _ = fit_latent_map(
                tile, rate_weight=lam, steps=args.steps, hidden=args.hidden,
                levels=args.wavelet_levels if basis == "wavelet" else args.levels,
                init_sweeps=args.init_sweeps, exact_start=start == "exact",
                between_weight=args.between_weight, basis=basis, wavelet=args.wavelet,
                init_step=args.init_step, zones=zones)
            nodes = latent_map.node_heights().numpy()
            with torch.no_grad():
                own = latent_map(torch.from_numpy(xy).float()).double().numpy()
            rows.append({"kind": kind, "what": f"lambda {lam:g}",
                         "bytes": len(encode_latent_map(latent_map)),
                         "rmse_m": node_rmse(nodes, tile), "between_truth_m": rms(own),
                         "bicubic_nodes_truth_m": rms(bicubic_of(tile, nodes, xy)),
                         "fit_s": time.perf_counter() - clock})
            print(f"#   {kind} lambda {lam:g}: {rows[-1]['bytes']} B, RMSE "
                  f"{rows[-1]['rmse_m']:.3f} m, {rows[-1]['fit_s']:.0f} s", flush=True)
    for kind, sweep in (("jpeg2k (PSNR sweep)", jpeg2k_psnr_sweep(tile, args.psnr_levels)),
                        ("jpeg2k (max error)", jpeg2k_bounded_sweep(tile, args.bounds))):
        for r in sweep:
            rows.append({"kind": kind, "what": r["what"], "bytes": r["bytes"], "rmse_m": r["rmse_m"],
                         "between_truth_m": rms(bicubic_of(tile, r["decoded"], xy)),
                         "bicubic_nodes_truth_m": float("nan"), "fit_s": float("nan")})
    bound_kind = "Gaussian R(D) bound (smoothed spectrum)"
    for r in gaussian_rd(tile, [0.3, 0.5, 0.7, 1.0, 1.5, 2.0, 3.0, 4.0, 5.0, 7.0]):
        rows.append({"kind": bound_kind, "what": r["what"], "bytes": round(r["bytes"]),
                     "rmse_m": r["rmse_m"], "between_truth_m": float("nan"),
                     "bicubic_nodes_truth_m": float("nan"), "fit_s": float("nan")})
    bd = {}
    curve = lambda kind: [(r["bytes"], r["rmse_m"]) for r in rows if r["kind"] == kind]  # noqa: E731
    for latent_kind in latent_kinds:
        for kind in ("jpeg2k (PSNR sweep)", "jpeg2k (max error)"):
            bd[f"{latent_kind} vs {kind}"] = bd_rate(curve(latent_kind), curve(kind))
    for latent_kind in latent_kinds:  # both codecs over the latent curve's RMSE range
        span = [r for _, r in curve(latent_kind)]
        lo, hi = max(RMSE_RANGE[0], min(span)), min(RMSE_RANGE[1], max(span))
        for kind in (latent_kind, "jpeg2k (PSNR sweep)"):
            bd[f"{kind} vs the {bound_kind}, node RMSE {lo:.2f}-{hi:.2f} m"] = bd_rate(
                curve(kind), curve(bound_kind), lo, hi)
    return {"tile": tile, "rows": rows, "bd": bd, "bicubic_dem_truth_m": bicubic_dem}


def format_tile(result: dict[str, Any]) -> str:
    tile = result["tile"]
    lines = [f"### {tile.name} ({tile.shape[0]} x {tile.shape[1]} nodes; bicubic of the DEM vs "
             f"truth between nodes: {result['bicubic_dem_truth_m']:.3f} m RMSE)", "",
             "| map | setting | bytes | bits/node | node RMSE (m) | between-node RMSE vs truth (m) "
             "| bicubic of its nodes vs truth (m) |", "|---|---|---:|---:|---:|---:|---:|"]
    n = tile.shape[0] * tile.shape[1]
    for r in result["rows"]:
        if not (0.2 <= r["rmse_m"] <= 8.0) and not r["kind"].startswith("latent"):
            continue
        own = "" if np.isnan(r["bicubic_nodes_truth_m"]) else f"{r['bicubic_nodes_truth_m']:.3f}"
        between = "" if np.isnan(r["between_truth_m"]) else f"{r['between_truth_m']:.3f}"
        lines.append(f"| {r['kind']} | {r['what']} | {r['bytes']:,} | {8 * r['bytes'] / n:.3f} | "
                     f"{r['rmse_m']:.3f} | {between} | {own} |")
    for kind, value in result["bd"].items():
        span = "" if "node RMSE" in kind else f" (node RMSE {RMSE_RANGE[0]}-{RMSE_RANGE[1]} m)"
        lines.append(f"\nBD-rate {kind}{span}: {value:+.1f} %")
    return "\n".join(lines)


#: Options of this script that were renamed: old spelling -> new one.
RENAMED = {"--regions": "--zones"}


def refuse_renamed(parser: argparse.ArgumentParser, argv: list[str] | None,
                   renamed: dict[str, str]) -> None:
    """Exits with a usage error naming the new spelling when ``argv`` (default
    ``sys.argv[1:]``) uses a renamed option or value (``renamed``: old -> new)."""
    words = sys.argv[1:] if argv is None else argv
    for old, new in renamed.items():
        if any(w == old or w.startswith(old + "=") for w in words):
            parser.error(f"{old} is renamed {new}")


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--tiles", nargs="+", default=["jacksboro", "topobathy", "synthetic"])
    parser.add_argument("--lambdas", nargs="+", type=float, default=[0.1, 0.5, 2.0, 8.0, 32.0])
    parser.add_argument("--steps", type=int, default=1500)
    parser.add_argument("--levels", type=int, default=6, help="pyramid levels")
    parser.add_argument("--bases", nargs="+", choices=["wavelet", "pyramid"],
                        default=["wavelet", "pyramid"], help="latent bases to compare")
    parser.add_argument("--wavelet", default="cdf97", choices=["cdf97", "cdf53"])
    parser.add_argument("--wavelet_levels", type=int, default=6)
    parser.add_argument("--init_step", type=float, default=1.0)
    parser.add_argument("--hidden", type=int, default=0)
    parser.add_argument("--init_sweeps", type=int, default=12)
    parser.add_argument("--starts", nargs="+", choices=["sweeps", "exact"], default=["exact"],
                        help="latent starts to compare: pyramid sweeps only, or + exact nodes")
    parser.add_argument("--between_weight", type=float, default=0.5)
    parser.add_argument("--zones", nargs="+", type=int, default=[0],
                        help="zone grid sides R to compare (0 = one step per subband; "
                             "neuralmap.terrain.latent.zones)")
    parser.add_argument("--psnr_levels", nargs="+", type=float,
                        default=[40, 45, 50, 55, 60, 65, 70, 75, 80, 85, 90])
    parser.add_argument("--bounds", nargs="+", type=float, default=[1, 2, 4, 8, 16])
    parser.add_argument("--n_between", type=int, default=20000)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--quick", action="store_true")
    add_out_option(parser, "bench_latent_rd")
    refuse_renamed(parser, argv, RENAMED)
    args = parser.parse_args(argv)
    if args.quick:
        args.tiles, args.lambdas, args.steps = ["synthetic"], [1.0, 8.0], 30
        args.psnr_levels, args.bounds, args.n_between = [50, 60, 70], [2, 8], 2000
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    bench = start_bench(__file__, args, argv)
    torch.set_num_threads(args.threads)
    print(f"# bench_latent_rd: torch {torch.__version__}, {torch.get_num_threads()} thread(s); "
          f"{args.steps} steps, bases {args.bases} (wavelet {args.wavelet}, "
          f"{args.wavelet_levels} levels), pyramid levels {args.levels}, hidden {args.hidden}, "
          f"init sweeps {args.init_sweeps}, starts {args.starts}, between weight "
          f"{args.between_weight}, init step {args.init_step}, lambdas {args.lambdas}")
    for name in args.tiles:
        print(format_tile(run_tile(name, args)), flush=True)
        print()
    bench.finish()
    return 0


if __name__ == "__main__":
    sys.exit(main())
