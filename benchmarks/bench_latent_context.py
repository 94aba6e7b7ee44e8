"""Context entropy model + soft rounding + RDOQ against the best raster codec, per tile.

For each tile and rate weight ``lambda``, two latent maps are fitted in the same run
(`neuralmap.terrain.latent.encode.fit_latent_map`, wavelet basis):

* ``factorized``: the factorized Laplace model, noise then straight-through rounding;
* ``context``: the context model (`neuralmap.terrain.latent.context_model`), soft rounding
  annealed then straight-through, symbols chosen by RDOQ (`neuralmap.terrain.latent.rdoq`).
* ``factorized+zones`` / ``context+zones`` (``--variants``): the same with per-zone
  steps and entropy scales on an ``R x R`` grid of zones (``--zones``,
  `neuralmap.terrain.latent.zones`).

Codecs in the same run: JPEG 2000 over a PSNR sweep on 16-bit heights, and the toolkit's
error-bounded JPEG 2000, JPEG-LS, LERC and SZ3 (`neuralmap.terrain.codecs.compress_grid`)
over max-error bounds. The file bytes are counted (codec streams plus
`neuralmap.terrain.codecs.HEADER_BYTES`); distortion is the node RMSE. The BD-rate of each
map against each codec (Bjøntegaard, `bench_latent_rd.bd_rate`, node RMSE 0.5-5 m, the
overlap of the curves) is printed; "vs best" is the largest of them, the codec that is
hardest to beat at equal node RMSE. Target: <= -30 %.

Also measured: the context bitstream's decode time on a 1-million-node tile (synthetic
1000 x 1000, briefly fitted, one thread; target <= 10 s), and the query throughput of a
decoded map against the torch bicubic grid (`GridTerrain`) on the same points.

Usage:
    python benchmarks/bench_latent_context.py
    python benchmarks/bench_latent_context.py --quick
    python benchmarks/bench_latent_context.py --tiles jacksboro rmnp --steps 600
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

REPO_ROOT = Path(__file__).resolve().parents[1]
for path in (REPO_ROOT, REPO_ROOT / "benchmarks"):
    if str(path) not in sys.path:
        sys.path.insert(0, str(path))

from bench_latent_rd import (  # noqa: E402
    bd_rate_span,
    get_tile,
    jpeg2k_psnr_sweep,
    node_rmse,
    refuse_renamed,
)

from neuralmap.dem import load_tile  # noqa: E402
from neuralmap.docs.bench_run import add_out_option, start_bench  # noqa: E402
from neuralmap.terrain.codecs import compress_grid  # noqa: E402
from neuralmap.terrain.grid import GridTerrain  # noqa: E402
from neuralmap.terrain.latent.bitstream import decode_latent_map, encode_latent_map  # noqa: E402
from neuralmap.terrain.latent.encode import fit_latent_map  # noqa: E402

CODECS = ("jpeg2k", "jpegls", "lerc", "sz3")
VARIANTS = {
    "factorized": {},
    "context": {"entropy": "context", "relaxation": "soft", "rdoq": True},
    # ablations (--variants): one ingredient at a time
    "factorized+rdoq": {"rdoq": True},
    "context-noise": {"entropy": "context"},
    "context-soft": {"entropy": "context", "relaxation": "soft"},
    # per-zone steps and entropy scales (neuralmap.terrain.latent.zones), R = --zones
    "factorized+zones": {"zones": -1},
    "context+zones": {"entropy": "context", "relaxation": "soft", "rdoq": True,
                      "zones": -1},
}
#: Options and variants of this script that were renamed: old spelling -> new one.
RENAMED = {"--regions": "--zones", "factorized+regions": "factorized+zones",
           "context+regions": "context+zones"}


def variant_kwargs(variant: str, args: argparse.Namespace) -> dict[str, Any]:
    """`fit_latent_map` keywords of a variant (``zones: -1`` = ``--zones``)."""
    kwargs = dict(VARIANTS[variant])
    if kwargs.get("zones") == -1:
        kwargs["zones"] = args.zones
    return kwargs


def codec_curves(tile: Any, args: argparse.Namespace) -> dict[str, list[tuple[int, float]]]:
    """``{codec: [(bytes, node RMSE)]}`` for every codec of this run."""
    curves = {"jpeg2k (PSNR sweep)": [(r["bytes"], r["rmse_m"])
                                      for r in jpeg2k_psnr_sweep(tile, args.psnr_levels)]}
    for codec in CODECS:
        points = []
        for bound in args.bounds:
            try:
                grid = compress_grid(tile, codec=codec, max_error=bound)
            except Exception as exc:  # noqa: BLE001 - a codec missing on this machine
                print(f"#   {codec}: skipped ({exc})", flush=True)
                break
            points.append((grid.nbytes, node_rmse(grid.tile.heights, tile)))
        if points:
            curves[f"{codec} (max error)"] = points
    return curves


def run_tile(name: str, args: argparse.Namespace) -> list[str]:
    tile = get_tile(name)
    print(f"# tile {tile.name}: {tile.shape[0]} x {tile.shape[1]} nodes", flush=True)
    maps: dict[str, list[tuple[int, float]]] = {v: [] for v in args.variants}
    for variant in args.variants:
        for lam in args.lambdas:
            clock = time.perf_counter()
            latent_map, _ = fit_latent_map(tile, rate_weight=lam, steps=args.steps,
                                           levels=args.levels,
                                           between_weight=args.between_weight,
                                           **variant_kwargs(variant, args))
            nbytes = len(encode_latent_map(latent_map))
            rmse = node_rmse(latent_map.node_heights().numpy(), tile)
            maps[variant].append((nbytes, rmse))
            kept = ("" if "zones" not in variant else
                    "; zones kept" if latent_map.zones is not None else
                    "; zones dropped (they did not pay)")
            print(f"#   {variant} lambda {lam:g}: {nbytes} B, node RMSE {rmse:.3f} m{kept}, "
                  f"{time.perf_counter() - clock:.0f} s", flush=True)
    codecs = codec_curves(tile, args)
    lines = [f"### {tile.name} ({tile.shape[0]} x {tile.shape[1]} nodes)", "",
             "| map / codec | points (bytes @ node RMSE m) |", "|---|---|"]
    for kind, pts in {**maps, **codecs}.items():
        shown = ", ".join(f"{b:,} @ {r:.2f}" for b, r in sorted(pts, key=lambda p: p[1]))
        lines.append(f"| {kind} | {shown} |")
    lines.append("")
    def said(r: Any) -> str:
        span = f"{r.lo_m:.2f}-{r.hi_m:.2f} m" if np.isfinite(r.lo_m) else "no range"
        return f"{r.percent:+.1f} % ({span}{'; ' + r.note if r.note else ''})"

    for variant, pts in maps.items():
        bds = {kind: bd_rate_span(pts, ref) for kind, ref in codecs.items()}
        finite = {k: v for k, v in bds.items() if np.isfinite(v.percent)}
        text = ", ".join(f"{k} {said(v)}" for k, v in bds.items())
        if finite:
            worst = max(finite, key=lambda k: finite[k].percent)
            verdict = "met" if finite[worst].percent <= -30.0 else "missed"
            lines.append(f"BD-rate {variant} vs best codec ({worst}): "
                         f"{finite[worst].percent:+.1f} % (target <= -30 %: {verdict}); per "
                         f"codec: {text}")
        else:
            lines.append(f"BD-rate {variant}: not computed against any codec ({text})")
    first, *others = list(maps)
    for variant in others:
        lines.append(f"BD-rate {variant} vs {first}: "
                     f"{said(bd_rate_span(maps[variant], maps[first]))}")
    return lines


def decode_speed(args: argparse.Namespace) -> list[str]:
    """Decode time of a context bitstream of a 1000 x 1000-node tile, and query speed."""
    tile = load_tile(f"synthetic:{args.big}x{args.big}")
    latent_map, _ = fit_latent_map(tile, rate_weight=1.0, steps=args.big_steps,
                                   levels=args.levels, between_points=1024,
                                   **VARIANTS["context"])
    data = encode_latent_map(latent_map)
    clock = time.perf_counter()
    back = decode_latent_map(data, where="<bench>")
    decode_s = time.perf_counter() - clock
    same = all(np.array_equal(a, b) for a, b in zip(latent_map.symbols, back.symbols,
                                                      strict=True))
    grid = GridTerrain(tile, method="bicubic")
    rng = np.random.default_rng(0)
    lo, hi = np.array(tile.origin), np.array(tile.origin) + (np.array(tile.shape[::-1]) - 1
                                                           ) * np.array(tile.spacing)
    xy = torch.from_numpy(lo + rng.random((200_000, 2)) * (hi - lo)).float()
    rates = {}
    for label, model in (("latent map (context)", back), ("torch bicubic grid", grid)):
        with torch.no_grad():
            model(xy)
            clock = time.perf_counter()
            for _ in range(5):
                model(xy)
        rates[label] = 5 * xy.shape[0] / (time.perf_counter() - clock)
    ratio = rates["latent map (context)"] / rates["torch bicubic grid"]
    return [f"### decode and query, synthetic {args.big} x {args.big} nodes "
            f"({args.big_steps} fit steps)", "",
            f"context bitstream {len(data):,} B decoded in {decode_s:.2f} s on "
            f"{torch.get_num_threads()} thread (target <= 10 s: "
            f"{'met' if decode_s <= 10 else 'missed'}); symbols identical: {same}",
            f"query: latent map {rates['latent map (context)'] / 1e6:.2f} M points/s, torch "
            f"bicubic grid {rates['torch bicubic grid'] / 1e6:.2f} M points/s, ratio "
            f"{ratio:.2f} (target >= 1: {'met' if ratio >= 1 else 'missed'})"]


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--tiles", nargs="+", default=[
        "jacksboro", "topobathy", "synthetic", "rmnp", "volcano", "minnesota"])
    parser.add_argument("--variants", nargs="+", choices=list(VARIANTS),
                        default=["factorized", "context"])
    parser.add_argument("--lambdas", nargs="+", type=float, default=[0.3, 1.0, 3.0, 10.0])
    parser.add_argument("--steps", type=int, default=600)
    parser.add_argument("--levels", type=int, default=6)
    parser.add_argument("--zones", type=int, default=4,
                        help="zone grid side R of the +zones variants")
    parser.add_argument("--between_weight", type=float, default=0.5,
                        help="weight of the between-node term (0: nodes only)")
    parser.add_argument("--psnr_levels", nargs="+", type=float,
                        default=[40, 45, 50, 55, 60, 65, 70, 75, 80, 85, 90])
    parser.add_argument("--bounds", nargs="+", type=float, default=[0.5, 1, 2, 4, 8, 16])
    parser.add_argument("--big", type=int, default=1000, help="decode-speed tile side")
    parser.add_argument("--big_steps", type=int, default=20)
    parser.add_argument("--skip_speed", action="store_true")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--quick", action="store_true")
    add_out_option(parser, "bench_latent_context")
    refuse_renamed(parser, argv, RENAMED)
    args = parser.parse_args(argv)
    if args.quick:
        args.tiles, args.lambdas, args.steps = ["synthetic:64x64"], [1.0, 8.0], 30
        args.psnr_levels, args.bounds, args.big, args.big_steps = [50, 60, 70], [2, 8], 200, 3
    return args


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    bench = start_bench(__file__, args, argv)
    torch.set_num_threads(args.threads)
    print(f"# bench_latent_context: torch {torch.__version__}, {torch.get_num_threads()} "
          f"thread(s); {args.steps} steps, {args.levels} levels, between weight "
          f"{args.between_weight}, lambdas {args.lambdas}",
          flush=True)
    if not args.skip_speed:
        print("\n".join(decode_speed(args)), "\n", flush=True)
    for name in args.tiles:
        print("\n".join(run_tile(name, args)), "\n", flush=True)
    bench.finish()
    return 0


if __name__ == "__main__":
    sys.exit(main())
