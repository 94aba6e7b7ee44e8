"""One table of the `tan` study across relief: the newest run of each tile's config.

Reads the newest ``<runs>/<experiment>/version_*/results.json`` of each tile (the tile's
``configs/tan_<tile>.yaml`` names its experiment; jacksboro's default study writes to
``evaluate``, gironde's ``configs/tan_gentle.yaml`` to ``tan_gentle``) and prints one
Markdown table for the docs: the tile, its relief along the flown paths (heights and rms
slope of the DEM under the truth tracks the run saved in ``trajectories.csv``, the grid
spacing), the map's error against the truth (σ and its correlation over one step of
flight), then for one method (the navigator's default, ``point_mass_tracker``) its RMSE
over the true-terrain and the map-aware PCRB, the diverged share, the NEES band coverage
and the misleading-information rates at the integrity risks 1e-4 and 1e-2 (count over the
tracking epochs), and how many of its diverged runs said so (status or HPL) before their
error left their HPL. Nothing is recomputed from the filters: every number but the relief is
the run's own.

Usage::

    python benchmarks/relief_summary.py                       # runs/, every tile found
    python benchmarks/relief_summary.py --runs_dir runs --method point_mass_ekf
    python benchmarks/relief_summary.py --tiles jacksboro gironde volcano

The stated size of each run is 1000 Monte Carlo runs (the configs' ``n_runs``); a run of
another size is listed with its size in the ``runs`` column.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
from pathlib import Path
from typing import Any

#: Tile -> experiment folders of its tan config, first the preferred one
#: (``configs/tan_<tile>.yaml``'s ``experiment``), then the older names.
TILES: dict[str, tuple[str, ...]] = {
    "jacksboro": ("evaluate",),
    "synthetic": ("tan_synthetic",),
    "gironde": ("tan_gentle",),
    "rmnp": ("tan_rmnp",),
    "volcano": ("tan_volcano",),
    "minnesota": ("tan_minnesota",),
    "topobathy": ("tan_topobathy",),
}

#: The config that writes each tile's runs (printed for a tile without a run).
CONFIGS: dict[str, str] = {
    "jacksboro": "configs/tan.yaml",
    "synthetic": "configs/tan_synthetic.yaml",
    "gironde": "configs/tan_gentle.yaml",
    "rmnp": "configs/tan_rmnp.yaml",
    "volcano": "configs/tan_volcano.yaml",
    "minnesota": "configs/tan_minnesota.yaml",
    "topobathy": "configs/tan_topobathy.yaml",
}


def newest_results(runs_dir: Path, experiments: tuple[str, ...]) -> Path | None:
    """The newest ``results.json`` (by modification time) under any of ``experiments``."""
    found = [p for e in experiments for p in (runs_dir / e).glob("version_*/results.json")]
    return max(found, key=lambda p: p.stat().st_mtime) if found else None


def path_relief(folder: Path, scenario: dict[str, Any]) -> str:
    """Heights and rms slope of the DEM under the run's saved truth tracks, and its grid
    spacing (``"n/a"`` when the tile or the tracks cannot be read)."""
    try:
        import numpy as np
        import torch

        from neuralmap.lab.scenario import Scenario, scenario_tile
        from neuralmap.terrain.grid import GridTerrain

        fields = {f for f in Scenario.__dataclass_fields__}
        tile = scenario_tile(Scenario(**{k: v for k, v in scenario.items() if k in fields}))
        xy = []
        with open(folder / "trajectories.csv", newline="", encoding="utf-8") as fh:
            for row in csv.DictReader(fh):
                if row["track"] == "truth":
                    xy.append((float(row["x_m"]), float(row["y_m"])))
        if not xy:
            return "n/a"
        grid = GridTerrain(tile, method="bilinear", dtype=torch.float64)
        p = torch.tensor(xy, dtype=torch.float64)
        step = 0.25 * min(tile.spacing)
        with torch.no_grad():
            h = grid(p)
            gx = (grid(p + torch.tensor([step, 0.0])) - grid(p - torch.tensor([step, 0.0])))
            gy = (grid(p + torch.tensor([0.0, step])) - grid(p - torch.tensor([0.0, step])))
        slope = float(((gx.square() + gy.square()) / (2 * step) ** 2).mean().sqrt())
        h = h.numpy()
        spacing = float(np.mean(tile.spacing))
        return (f"{np.min(h):.0f}–{np.max(h):.0f} m, rms slope {100 * slope:.1f} %, "
                f"{spacing:.3g} m grid")
    except Exception as exc:  # noqa: BLE001 - a summary line, not a failure
        return f"n/a ({type(exc).__name__})"


def _ratio(value: Any) -> str:
    return f"{value:.3f}" if isinstance(value, (int, float)) and math.isfinite(value) else "n/a"


def _mi(entry: dict[str, Any], risk: str) -> str:
    mi = entry.get("risks", {}).get(risk, {}).get("misleading", {})
    if not mi or mi.get("epochs") is None:
        return "n/a"
    if not mi["epochs"]:
        return "n/a (0 tracking epochs)"
    return f"{mi['rate']:.1e} ({mi['count']}/{mi['epochs']})"


def _flagged(entry: dict[str, Any]) -> str:
    """Diverged runs flagged first at the largest risk (the smallest HPL)."""
    risks = {r: e.get("diverged_flagged") for r, e in entry.get("risks", {}).items()}
    risks = {r: f for r, f in risks.items() if f is not None}
    if not risks:
        return "n/a"
    flagged = risks[max(risks, key=float)]
    return f"{flagged['flagged']} of {flagged['runs']}"


def summary_row(tile: str, path: Path, method: str, relief: bool) -> list[str]:
    """One table row from one run's ``results.json``."""
    results = json.loads(path.read_text(encoding="utf-8"))
    entry = results.get("methods", {}).get(method)
    if entry is None:
        return [tile, "—", f"no {method} in {path.parent}"] + [""] * 9
    bound = results.get("pcrb_map_aware", {})
    mse, corr = bound.get("map_error_m2"), bound.get("map_error_corr")
    map_error = (f"{math.sqrt(mse):.2g} m (ρ {corr:.2f})"
                 if isinstance(mse, (int, float)) and isinstance(corr, (int, float)) else "n/a")
    n_incl = entry.get("n_included") or 0
    diverged = entry.get("n_diverged", 0)
    band = entry.get("nees_in_band")
    integrity = results.get("integrity", {}).get(method, {})
    return [
        tile,
        path_relief(path.parent, results.get("scenario", {})) if relief else "—",
        map_error,
        str(entry.get("n_runs", "?")),
        _ratio(entry.get("pcrb_ratio_all")),
        _ratio(entry.get("pcrb_map_ratio_all")),
        f"{100.0 * diverged / n_incl:.1f} % ({diverged})" if n_incl else "n/a",
        f"{100.0 * band:.1f} %" if isinstance(band, (int, float)) else "n/a",
        _mi(integrity, "0.0001"),
        _mi(integrity, "0.01"),
        _flagged(integrity),
        f"{path.parent.parent.name}/{path.parent.name}",
    ]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs_dir", default="runs", help="where the studies wrote (runs/)")
    parser.add_argument("--method", default="point_mass_tracker",
                        help="the method summarised (a registered or linearisation name)")
    parser.add_argument("--tiles", nargs="*", default=list(TILES), help="tiles, in order")
    parser.add_argument("--no_relief", action="store_true",
                        help="skip the relief column (it loads each tile)")
    args = parser.parse_args(argv)
    runs_dir = Path(args.runs_dir)
    header = ["tile", "relief along the paths", "map error vs truth", "runs",
              f"{args.method} ÷ true-terrain PCRB", "÷ map-aware PCRB", "diverged",
              "NEES in band", "MI rate at 1e-4 (count/tracking epochs)",
              "MI rate at 1e-2", "diverged runs flagged first", "run"]
    rows, missing = [], []
    for tile in args.tiles:
        if tile not in TILES:
            parser.error(f"unknown tile {tile!r}; one of {', '.join(TILES)}")
        path = newest_results(runs_dir, TILES[tile])
        if path is None:
            missing.append(tile)
            continue
        rows.append(summary_row(tile, path, args.method, not args.no_relief))
    print("| " + " | ".join(header) + " |")
    print("|" + "|".join(["---"] * 3 + ["---:"] * 8 + ["---"]) + "|")
    for row in rows:
        print("| " + " | ".join(row) + " |")
    for tile in missing:
        print(f"\nno run of {tile} under {runs_dir}/{{{','.join(TILES[tile])}}}: "
              f"python evaluate.py --config {CONFIGS[tile]}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
