"""Between the nodes: maps fitted to some DEM nodes, scored at the real nodes withheld.

For each real tile and each withholding pattern, every map is fitted (or applied) on the
*kept* nodes only and scored at the *withheld* nodes, whose true heights the DEM has:

* ``bicubic``: the torch bicubic grid of the kept nodes (`GridTerrain`, Keys cubic
  convolution) where the kept nodes form a grid (pattern ``x2``); where they do not
  (``random25``, ``squares``) the cubic of scattered data, Clough-Tocher
  (``scipy.interpolate.CloughTocher2DInterpolator``, C1 piecewise cubic on the Delaunay
  triangles of the kept nodes). The column ``clough_tocher`` gives it for ``x2`` too, so the
  two cubics can be compared on one pattern;
* ``blockwise``: the default neural map (``configs/train.yaml``: its model and data
  values, `TerrainFitModule` / `DemDataModule`) trained on the kept nodes; a reduced
  ``--epochs`` budget keeps the default's refit share (150 of 400 epochs);
* ``latent``: the default latent map (``configs/latent_map.yaml``: ``rate_weight`` 3,
  6 wavelet levels, 1500 steps unless ``--latent_steps``) fitted to the kept nodes;
* ``superres``: the residual super-resolution prior (`neuralmap.terrain.superres`,
  factor 2) trained on the *other* tiles of ``--prior_tiles`` (leave one out), applied to
  the kept grid; pattern ``x2`` only (it upsamples a grid).

Patterns: ``x2`` keeps nodes ``[2i, 2j]`` of the tile cropped to odd sizes (the x2
decimation, 3/4 of the nodes withheld; the maps are fitted to the coarse tile);
``random25`` withholds a seeded random 25 % of the interior nodes (the maps are fitted to
the tile with those nodes void); ``squares`` withholds seeded, non-overlapping k x k squares
of interior nodes (``--square`` k, about 25 % of the nodes). RMSE and max |error| in metres
over the withheld nodes, and every RMSE as a ratio to ``bicubic`` of the same tile and
pattern (below 1: better than the cubic). Target: the default map (``blockwise``) no worse
than ``bicubic`` (ratio <= 1) on every tile and pattern.

Usage::

    python benchmarks/bench_between_nodes.py --out runs/bench_between_nodes
    python benchmarks/bench_between_nodes.py --tiny --out /tmp/between   # seconds, for tests
    python benchmarks/bench_between_nodes.py --tiles volcano rmnp --patterns x2 --epochs 100
    # one process per tile on a shared machine, then one table:
    python benchmarks/bench_between_nodes.py --tiles jacksboro --out runs/bn/jacksboro
    python benchmarks/bench_between_nodes.py --merge runs/bn/jacksboro runs/bn/rmnp --out runs/bn

Cost at the default budgets (2 shared cores, load 4-12): a 35 000-160 000-node fit of the
default map 12-13 min, the latent map 2-3 min, each leave-one-out prior 2.5 min.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import torch
import yaml

REPO_ROOT = Path(__file__).resolve().parents[1]
if str(REPO_ROOT) not in sys.path:
    sys.path.insert(0, str(REPO_ROOT))

from neuralmap.dem import load_tile  # noqa: E402
from neuralmap.dem.tile import DemTile  # noqa: E402
from neuralmap.exceptions import NeuralMapError  # noqa: E402
from neuralmap.io import atomic_write_json, atomic_write_text  # noqa: E402
from neuralmap.progress import progress_bar  # noqa: E402
from neuralmap.terrain.grid import GridTerrain  # noqa: E402

PATTERNS = ("x2", "random25", "squares")
METHODS = ("bicubic", "clough_tocher", "blockwise", "latent", "superres")
#: Real sample tiles scored by default (mountainous, ridge-and-valley, a cone, flat LiDAR).
DEFAULT_TILES = ("jacksboro", "rmnp", "volcano", "minnesota")
#: Tiles the leave-one-out prior may learn from (the scored tile is always left out).
DEFAULT_PRIOR_TILES = ("jacksboro", "topobathy", "rmnp", "volcano", "minnesota")
#: Share of the default run spent refitting on every node (configs/train.yaml: 150 of 400).
REFIT_SHARE = 150 / 400


@dataclass
class Split:
    """One tile under one withholding pattern.

    Attributes:
        tile: The (cropped) tile with every node's true height.
        kept: What the maps are fitted to: the coarse tile (``x2``) or the tile with the
            withheld nodes void.
        withheld: ``(ny, nx)`` bool over ``tile``, True at the scored nodes.
        grid: Whether ``kept`` is a complete grid (Keys bicubic and the prior apply).
    """

    tile: DemTile
    kept: DemTile
    withheld: np.ndarray
    grid: bool
    fit_rmse: float | None = None

    @property
    def xy(self) -> np.ndarray:
        """``(M, 2)`` float64 metres of the withheld nodes."""
        return self.tile.node_xy()[self.withheld]

    @property
    def truth(self) -> np.ndarray:
        """``(M,)`` true heights at the withheld nodes."""
        return self.tile.heights[self.withheld]


def split_x2(tile: DemTile) -> Split:
    """Keeps nodes ``[2i, 2j]`` of the tile cropped to odd sizes (the x2 decimation)."""
    ny, nx = tile.shape
    ny, nx = ny - (1 - ny % 2), nx - (1 - nx % 2)
    tile = replace(tile, heights=tile.heights[:ny, :nx], meta=dict(tile.meta))
    coarse = replace(tile, heights=tile.heights[::2, ::2],
                     spacing=(2 * tile.spacing[0], 2 * tile.spacing[1]),
                     name=f"{tile.name}_kept_x2", meta=dict(tile.meta))
    withheld = np.ones(tile.shape, dtype=bool)
    withheld[::2, ::2] = False
    return Split(tile, coarse, withheld & tile.valid_mask, True)


def _interior(shape: tuple[int, int]) -> np.ndarray:
    inner = np.zeros(shape, dtype=bool)
    inner[1:-1, 1:-1] = True
    return inner


def split_random(tile: DemTile, fraction: float, seed: int) -> Split:
    """Withholds a seeded random ``fraction`` of the interior nodes (the border is kept)."""
    rng = np.random.default_rng(seed)
    withheld = _interior(tile.shape) & (rng.random(tile.shape) < fraction) & tile.valid_mask
    return _voided(tile, withheld, "random")


def split_squares(tile: DemTile, k: int, fraction: float, seed: int) -> Split:
    """Withholds seeded non-overlapping ``k x k`` squares of interior nodes.

    The interior is cut into ``(k + 2) x (k + 2)`` cells; each holds, with a probability
    chosen so that about ``fraction`` of the nodes are withheld, one square at a random
    offset of 0 or 1 node, so that two squares never touch (at least one kept node
    between them).
    """
    rng = np.random.default_rng(seed)
    ny, nx = tile.shape
    cell = k + 2
    withheld = np.zeros(tile.shape, dtype=bool)
    p = min(1.0, fraction * cell * cell / (k * k))
    for i0 in range(1, ny - cell, cell):
        for j0 in range(1, nx - cell, cell):
            if rng.random() < p:
                di, dj = rng.integers(0, 2, size=2)
                withheld[i0 + di: i0 + di + k, j0 + dj: j0 + dj + k] = True
    return _voided(tile, withheld & _interior(tile.shape) & tile.valid_mask, f"squares{k}")


def _voided(tile: DemTile, withheld: np.ndarray, label: str) -> Split:
    kept = replace(tile, heights=np.where(withheld, np.nan, tile.heights),
                   name=f"{tile.name}_kept_{label}", meta=dict(tile.meta))
    return Split(tile, kept, withheld, False)


def make_split(tile: DemTile, pattern: str, *, square: int, seed: int) -> Split:
    """The split of ``tile`` under ``pattern`` (one of `PATTERNS`)."""
    if pattern == "x2":
        return split_x2(tile)
    if pattern == "random25":
        return split_random(tile, 0.25, seed)
    if pattern == "squares":
        return split_squares(tile, square, 0.25, seed)
    raise NeuralMapError(f"--patterns: unknown pattern {pattern!r}; choose from {PATTERNS}.")


# ---------------------------------------------------------------------------- the maps
def _query(model: torch.nn.Module, xy: np.ndarray) -> np.ndarray:
    param = next(iter(model.parameters()), None)
    dtype = param.dtype if param is not None else torch.float64
    points = torch.as_tensor(xy)
    with torch.no_grad():
        return torch.cat([model(p.to(dtype)).double() for p in torch.split(points, 65536)]
                         ).numpy()


def _with_kept(model: torch.nn.Module, split: Split) -> np.ndarray:
    """Predictions at the withheld nodes; records the RMSE at the kept nodes (the fit)."""
    kept = split.kept
    valid = kept.valid_mask
    err = _query(model, kept.node_xy()[valid]) - kept.heights[valid]
    split.fit_rmse = float(np.sqrt(np.mean(err**2)))
    return _query(model, split.xy)


def predict_bicubic(split: Split) -> np.ndarray:
    """Keys bicubic of the kept grid (``x2``) or Clough-Tocher of the kept nodes."""
    if split.grid:
        return _query(GridTerrain(split.kept, method="bicubic", dtype=torch.float64), split.xy)
    return predict_clough_tocher(split)


def predict_clough_tocher(split: Split) -> np.ndarray:
    """Clough-Tocher C1 cubic of the kept nodes (scattered, node-index coordinates scaled
    to metres)."""
    from scipy.interpolate import CloughTocher2DInterpolator

    kept = split.kept
    points = kept.node_xy()[kept.valid_mask]
    interp = CloughTocher2DInterpolator(points, kept.heights[kept.valid_mask])
    return np.asarray(interp(split.xy), dtype=np.float64)


def _config(name: str) -> dict[str, Any]:
    return yaml.safe_load((REPO_ROOT / "configs" / name).read_text()) or {}


def predict_blockwise(split: Split, *, epochs: int, overrides: dict[str, dict[str, Any]]
                      | None = None, threads: int = 1) -> np.ndarray:
    """The default map (configs/train.yaml's model and data values) trained on the kept
    nodes for ``epochs`` epochs (refit share as the default's); ``overrides`` =
    ``{"model": {...}, "data": {...}}`` changes values (``--set``)."""
    import lightning.pytorch as pl

    from neuralmap.training.datamodule import DemDataModule
    from neuralmap.training.module import TerrainFitModule
    from neuralmap.training.quiet import quiet_lightning

    config = _config("train.yaml")
    data = {k: v for k, v in (config.get("data") or {}).items()
            if k not in ("path", "spacing", "refit_epochs")}
    model = dict(config.get("model") or {})
    model.update((overrides or {}).get("model", {}))
    data.update((overrides or {}).get("data", {}))
    refit = int(round(REFIT_SHARE * epochs)) if epochs > 1 else 0
    torch.set_num_threads(threads)
    pl.seed_everything(int(config.get("seed_everything", 0)), verbose=False)
    with quiet_lightning():
        dm = DemDataModule.from_tile(split.kept, refit_epochs=refit, **data)
        module = TerrainFitModule(**model)
        trainer = pl.Trainer(max_epochs=epochs, logger=False, enable_checkpointing=False,
                             enable_progress_bar=False, enable_model_summary=False,
                             num_sanity_val_steps=0, accelerator="cpu", devices=1,
                             check_val_every_n_epoch=max(1, epochs // 4))
        trainer.fit(module, datamodule=dm)
    assert module.net is not None
    return _with_kept(module.net.eval(), split)


def predict_latent(split: Split, *, steps: int) -> np.ndarray:
    """The default latent map (configs/latent_map.yaml) fitted to the kept nodes."""
    from neuralmap.terrain.latent.encode import fit_latent_map

    model = dict(_config("latent_map.yaml").get("model") or {})
    levels = int(model.pop("levels", 6))
    ny, nx = split.kept.shape
    levels = max(1, min(levels, int(math.log2(max(2, min(ny, nx) // 4)))))
    latent_map, _ = fit_latent_map(split.kept, steps=steps, levels=levels, **model)
    return _with_kept(latent_map, split)


def train_prior(tiles: dict[str, DemTile], leave_out: str, *, steps: int, patch: int
                ) -> Any:
    """The x2 prior trained on every tile of ``tiles`` but ``leave_out``."""
    from neuralmap.training.superres_prior import fit_superres_prior

    grids = [t.heights for name, t in tiles.items() if name != leave_out]
    if not grids:
        raise NeuralMapError(f"--prior_tiles: no tile other than '{leave_out}' to train the "
                             "leave-one-out prior on; add one.")
    return fit_superres_prior(grids, factor=2, steps=steps, patch=patch, seed=0)


def predict_superres(split: Split, prior: Any) -> np.ndarray:
    """The prior applied to the kept grid, read at the withheld fine nodes."""
    coarse = torch.as_tensor(split.kept.heights, dtype=torch.float32)[None]
    with torch.no_grad():
        fine = prior(coarse)[0].double().numpy()
    return fine[split.withheld]


# ---------------------------------------------------------------------------- the run
def score(pred: np.ndarray, truth: np.ndarray) -> dict[str, float]:
    """RMSE and max |error| (m) over the withheld nodes."""
    err = pred - truth
    if not np.isfinite(err).all():
        raise NeuralMapError(f"{int((~np.isfinite(err)).sum())} non-finite predictions at "
                             "withheld nodes.")
    return {"rmse_m": float(np.sqrt(np.mean(err**2))), "max_m": float(np.abs(err).max())}


def run(args: argparse.Namespace) -> dict[str, Any]:
    """Fits every map on every tile and pattern; returns the results (also printed)."""
    tiles = {name: load_tile(name) for name in args.tiles}
    prior_pool = {name: tiles.get(name) or load_tile(name) for name in args.prior_tiles}
    methods = [m for m in METHODS if m in args.methods]
    results: list[dict[str, Any]] = []
    n_fits = len(tiles) * len(args.patterns)
    bar = progress_bar(total=n_fits, desc="between nodes", unit="fit")
    start = time.perf_counter()
    try:
        for name, tile in tiles.items():
            prior = None
            for pattern in args.patterns:
                split = make_split(tile, pattern, square=args.square, seed=args.seed)
                truth = split.truth
                row: dict[str, Any] = {"tile": name, "pattern": pattern,
                                       "n_withheld": int(truth.size),
                                       "n_kept": int(split.kept.valid_mask.sum())}
                jobs: dict[str, Callable[[], np.ndarray]] = {
                    "bicubic": lambda s=split: predict_bicubic(s),
                    "clough_tocher": lambda s=split: predict_clough_tocher(s),
                    "blockwise": lambda s=split: predict_blockwise(
                        s, epochs=args.epochs, overrides=args.overrides),
                    "latent": lambda s=split: predict_latent(s, steps=args.latent_steps),
                }
                for method in methods:
                    bar.set_description(f"{name} {pattern} {method}")
                    t0 = time.perf_counter()
                    split.fit_rmse = None
                    if method == "superres":
                        if not split.grid:
                            continue
                        if prior is None:
                            prior = train_prior(prior_pool, name, steps=args.prior_steps,
                                                patch=args.prior_patch)
                        pred = predict_superres(split, prior)
                    elif method == "clough_tocher" and not split.grid:
                        continue  # it is the bicubic column there
                    else:
                        pred = jobs[method]()
                    row[method] = {**score(pred, truth), "wall_s": time.perf_counter() - t0}
                    if split.fit_rmse is not None:
                        row[method]["kept_rmse_m"] = split.fit_rmse
                base = row["bicubic"]["rmse_m"]
                for method in methods:
                    if method in row:
                        row[method]["ratio"] = row[method]["rmse_m"] / base if base > 0 else None
                results.append(row)
                print(f"{name} {pattern}: " + ", ".join(
                    f"{m} {row[m]['rmse_m']:.3f} m x{row[m]['ratio']:.3f}"
                    for m in methods if m in row), flush=True)
                bar.set_description(f"{name} {pattern}")
                bar.update(1)
    finally:
        bar.close()
    out = {
        "tiles": list(tiles), "patterns": list(args.patterns), "methods": methods,
        "epochs": args.epochs, "latent_steps": args.latent_steps,
        "prior_steps": args.prior_steps, "prior_tiles": list(args.prior_tiles),
        "square": args.square, "blockwise_overrides": args.overrides, "seed": args.seed, "tiny": bool(args.tiny),
        "wall_s": time.perf_counter() - start, "results": results,
        "target_met": all(r["blockwise"]["ratio"] <= 1.0 for r in results
                          if "blockwise" in r),
    }
    text = markdown(out)
    print(text)
    if args.out:
        folder = Path(args.out)
        folder.mkdir(parents=True, exist_ok=True)
        atomic_write_json(folder / "results.json", out)
        atomic_write_text(folder / "results.md", text + "\n")
    return out


def merge(folders: list[str], out_dir: str | None) -> dict[str, Any]:
    """One table from the ``results.json`` of several runs (e.g. one process per tile)."""
    runs = []
    for folder in folders:
        path = Path(folder) / "results.json"
        if not path.is_file():
            raise NeuralMapError(f"--merge: {path} does not exist; run the benchmark with "
                                 f"--out {folder} first.")
        runs.append(json.loads(path.read_text()))
    out = dict(runs[0])
    out["methods"] = [m for m in METHODS if any(m in r["methods"] for r in runs)]
    out["results"] = [row for r in runs for row in r["results"]]
    out["tiles"] = [t for r in runs for t in r["tiles"]]
    out["patterns"] = sorted({p for r in runs for p in r["patterns"]}, key=PATTERNS.index)
    out["wall_s"] = max(r["wall_s"] for r in runs)
    out["merged_from"] = [str(f) for f in folders]
    out["target_met"] = all(row["blockwise"]["ratio"] <= 1.0 for row in out["results"]
                            if "blockwise" in row)
    text = markdown(out)
    print(text)
    if out_dir:
        folder = Path(out_dir)
        folder.mkdir(parents=True, exist_ok=True)
        atomic_write_json(folder / "results.json", out)
        atomic_write_text(folder / "results.md", text + "\n")
    return out


def markdown(out: dict[str, Any]) -> str:
    """The results as a markdown table: RMSE (max) per map, ratio to bicubic."""
    methods = out["methods"]
    lines = [
        f"# Between the nodes: RMSE at withheld real DEM nodes (m), ratio to bicubic "
        f"(blockwise {out['epochs']} epochs, latent {out['latent_steps']} steps, prior "
        f"{out['prior_steps']} steps, leave-one-out)", "",
        "| tile | pattern | withheld | " + " | ".join(methods) + " |",
        "|---|---|---:|" + "---:|" * len(methods),
    ]
    for r in out["results"]:
        cells = []
        for method in methods:
            m = r.get(method)
            cells.append("n/a" if m is None else
                         f"{m['rmse_m']:.3f} ({m['max_m']:.2f}) ×{m['ratio']:.3f}")
        lines.append(f"| {r['tile']} | {r['pattern']} | {r['n_withheld']} | "
                     + " | ".join(cells) + " |")
    lines += ["", "Cells: RMSE (max |error|) in metres ×ratio of RMSE to bicubic. bicubic = "
              "Keys of the kept grid (x2) or Clough-Tocher of the kept nodes (other patterns). "
              f"Default map no worse than bicubic everywhere: "
              f"{'yes' if out['target_met'] else 'no'}."]
    return "\n".join(lines)


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """Command-line options; ``--tiny`` shrinks every budget (the test's run)."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--tiles", nargs="+", default=list(DEFAULT_TILES))
    parser.add_argument("--patterns", nargs="+", default=["x2", "random25"], choices=PATTERNS)
    parser.add_argument("--methods", nargs="+", default=list(METHODS), choices=METHODS)
    parser.add_argument("--epochs", type=int, default=400,
                        help="blockwise epochs (configs/train.yaml: 400)")
    parser.add_argument("--latent_steps", type=int, default=1500)
    parser.add_argument("--prior_steps", type=int, default=1500)
    parser.add_argument("--prior_patch", type=int, default=24)
    parser.add_argument("--prior_tiles", nargs="+", default=list(DEFAULT_PRIOR_TILES))
    parser.add_argument("--square", type=int, default=3, help="side k of the squares pattern")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--set", nargs="*", default=[], metavar="model.KEY=VALUE",
                        help="override a blockwise model/data value (YAML value)")
    parser.add_argument("--out", default=None, help="folder for results.json / results.md")
    parser.add_argument("--merge", nargs="+", default=None, metavar="FOLDER",
                        help="only merge the results.json of these --out folders into --out")
    parser.add_argument("--stamp", default=None, metavar="DIR",
                        help="also publish a stamped run (summary.md + results.json) into "
                             "DIR/version_N for `python -m neuralmap.docs update`")
    parser.add_argument("--tiny", action="store_true",
                        help="one synthetic tile, tiny budgets (seconds; the test's run)")
    args = parser.parse_args(argv)
    if args.tiny:
        # synthetic tiles only: the test extra alone runs it (no sample packages)
        args.tiles, args.prior_tiles = ["synthetic:61x87"], ["synthetic:61x87", "synthetic:40x40"]
        args.epochs, args.latent_steps, args.prior_steps, args.prior_patch = 2, 3, 3, 8
    args.overrides = {"model": {}, "data": {}}
    for item in args.set:
        key, sep, value = item.partition("=")
        section, _, name = key.partition(".")
        if not sep or section not in args.overrides or not name:
            parser.error(f"--set {item!r}: write model.KEY=VALUE or data.KEY=VALUE")
        args.overrides[section][name] = yaml.safe_load(value)
    for key in ("epochs", "latent_steps", "prior_steps"):
        if getattr(args, key) < 1:
            parser.error(f"--{key} must be >= 1")
    return args


def main(argv: list[str] | None = None) -> dict[str, Any]:
    """Entry point: one line ``error: ...`` and exit 2 on bad input."""
    torch.set_num_threads(1)
    try:
        args = parse_args(argv)
        stamped = None
        if args.stamp:
            from neuralmap.docs.bench_run import start_bench

            stamped = start_bench(__file__, argparse.Namespace(**{**vars(args),
                                                                  "out": args.stamp}), argv)
        out = merge(args.merge, args.out) if args.merge else run(args)
        if stamped is not None:
            stamped.finish(out)
        return out
    except NeuralMapError as exc:
        print(f"error: {exc}", file=sys.stderr)
        raise SystemExit(2) from exc


if __name__ == "__main__":
    main()
