"""Fitting a latent tileset: one latent map per tile of a region, fitted with an overlap.

``train.py latent --data.path 'tiles/*.hgt'`` (a glob or a list of DEM files) plans the
region with `neuralmap.dem.mosaic.plan_mosaic` (same units, spacing, CRS and grid; tiles
that touch) and stitches it into one frame; each file is one tile of the tileset, and the
files must fill a rectangle of tiles. ``--data.tile_nodes N`` instead cuts the region
(or a single DEM, a sample name) into tiles of ``N`` node intervals.

Each tile is fitted by `neuralmap.terrain.latent.encode.fit_latent_map` (the recipe of
`LatentFitModule`, with the run's ``--model.*`` settings and ``max_epochs x
steps_per_epoch`` steps) on its window: its core grown by ``overlap_nodes + 1`` nodes where
it has a neighbour (`TilesetLayout.window`), so the blend zones of
`neuralmap.terrain.latent.tileset` are inside every fit. Every bitstream is written
atomically into ``<run>/tiles/``; the index ``<run>/latent_tileset.json`` is written last,
with the region's node RMSE measured through the blended tileset, so a run that stops
early leaves no index (no half-written tileset that loads).
"""

from __future__ import annotations

import inspect
import math
import threading
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch

from neuralmap.dem.tile import DemTile
from neuralmap.exceptions import NeuralMapError
from neuralmap.io import atomic_write_json, to_jsonable
from neuralmap.progress import progress_bar
from neuralmap.terrain.latent.bitstream import write_latent_map
from neuralmap.terrain.latent.encode import fit_latent_map
from neuralmap.terrain.latent.quality import map_quality
from neuralmap.terrain.latent.tileset import LatentTileset
from neuralmap.terrain.latent.tileset_index import (
    INDEX_FILENAME,
    TileEntry,
    TilesetIndex,
    file_sha256,
    tile_file_name,
    write_tileset_index,
)
from neuralmap.terrain.latent.tileset_layout import TilesetLayout, regular_ranges, window_tile

__all__ = ["TilesetPlan", "fit_options", "fit_tileset", "is_tileset_source", "plan_tileset",
           "region_metrics"]

#: Default overlap margin / blend half-width, node intervals.
DEFAULT_OVERLAP_NODES = 4


def is_tileset_source(path: Any) -> bool:
    """Whether ``--data.path`` names several DEM files: a glob pattern or a list."""
    if isinstance(path, (list, tuple)):
        return True
    return isinstance(path, (str, Path)) and any(c in str(path) for c in "*?[")


@dataclass
class TilesetPlan:
    """The region to fit and its tile grid.

    Attributes:
        region: The whole region as one tile (one metric frame).
        layout: The tile grid.
        sources: The DEM file of each tile, row-major ("" for a regular cut).
    """

    region: DemTile
    layout: TilesetLayout
    sources: list[str]


def _file_grid(plan: Any) -> tuple[list[tuple[int, int]], list[tuple[int, int]], list[str]]:
    """Core column / row ranges of a mosaic plan's files, and each cell's file, checked to
    fill a rectangle of tiles."""
    boxes = [(r, r + t.shape[0] - 1, c, c + t.shape[1] - 1)
             for (r, c), t in zip(plan.offsets, plan.tiles, strict=True)]
    cols = sorted({(b[2], b[3]) for b in boxes})
    rows = sorted({(b[0], b[1]) for b in boxes})
    cells: dict[tuple[int, int], str] = {}
    for box, path in zip(boxes, plan.paths, strict=True):
        cell = (rows.index((box[0], box[1])), cols.index((box[2], box[3])))
        if cell in cells:
            raise NeuralMapError(
                f"--data.path: '{path}' and '{cells[cell]}' cover the same tile cell (rows "
                f"{box[0]}..{box[1]}, columns {box[2]}..{box[3]} of the region); drop one.")
        cells[cell] = str(path)
    missing = [(i, j) for i in range(len(rows)) for j in range(len(cols)) if (i, j) not in cells]
    if missing:
        i, j = missing[0]
        raise NeuralMapError(
            f"--data.path: the {len(boxes)} tiles do not fill a rectangle of "
            f"{len(rows)} x {len(cols)} tiles: none covers tile row {i} (region node rows "
            f"{rows[i][0]}..{rows[i][1]}), column {j} (node columns {cols[j][0]}..{cols[j][1]})"
            f"; a tileset needs every tile of the rectangle (add the missing files).")
    sources = [cells[(i, j)] for i in range(len(rows)) for j in range(len(cols))]
    return cols, rows, sources


def plan_tileset(path: str | Path | Sequence[str | Path], *,
                 overlap_nodes: int = DEFAULT_OVERLAP_NODES, tile_nodes: int | None = None,
                 spacing: Any = None, **load_options: Any) -> TilesetPlan:
    """Loads the region and plans its tiles (module docstring).

    Args:
        path: A glob / list of DEM files (one tile each), or one DEM / sample name with
            ``tile_nodes``.
        overlap_nodes: Overlap margin and blend half-width, node intervals (>= 1).
        tile_nodes: Cut the region into tiles of this many node intervals instead.
        spacing: Grid spacing of a plain ``.npy`` single source (``--data.spacing``).
        **load_options: Reader options of `neuralmap.dem.load_tile`.

    Raises:
        NeuralMapError: An empty glob, files of different spacing / units / CRS, tiles that
            do not touch or do not fill a rectangle, seams too close for the overlap, a
            single DEM without ``tile_nodes``.
    """
    from neuralmap.dem.load import load_tile
    from neuralmap.dem.mosaic import mosaic_tile, plan_mosaic, stitch_into

    if isinstance(overlap_nodes, bool) or not isinstance(overlap_nodes, (int, np.integer)) \
            or overlap_nodes < 1:
        raise NeuralMapError(f"--data.overlap_nodes must be a whole number >= 1, got "
                             f"{overlap_nodes!r}.")
    if tile_nodes is not None and (isinstance(tile_nodes, bool) or int(tile_nodes) < 2):
        raise NeuralMapError(f"--data.tile_nodes must be a whole number >= 2 (or null), got "
                             f"{tile_nodes!r}.")
    if is_tileset_source(path):
        try:
            plan = plan_mosaic(path, **load_options)  # type: ignore[arg-type]
            heights = np.full(plan.shape, np.nan)
            shared = stitch_into(plan, heights, 1.0)
        except NeuralMapError as exc:
            raise NeuralMapError(f"--data.path {path!r}: {exc}") from None
        name = f"tileset_{plan.paths[0].stem}_{len(plan.paths)}"
        region = mosaic_tile(plan, heights, name, shared)
        cols, rows, sources = _file_grid(plan)
    else:
        if tile_nodes is None:
            raise NeuralMapError(
                f"--data.path {path!r} is one DEM: a tileset needs a glob or list of tiles "
                "(--data.path 'tiles/*.hgt') or --data.tile_nodes N to cut it into tiles.")
        region = load_tile(str(path), spacing=spacing, **load_options)
        cols, rows, sources = [], [], []
    if tile_nodes is not None:
        cols = regular_ranges(region.shape[1], int(tile_nodes))
        rows = regular_ranges(region.shape[0], int(tile_nodes))
        sources = [""] * (len(cols) * len(rows))
    layout = TilesetLayout(shape=region.shape, spacing=region.spacing, origin=region.origin,
                           columns=tuple(cols), rows=tuple(rows), overlap_nodes=int(overlap_nodes))
    return TilesetPlan(region=region, layout=layout, sources=sources)


def region_metrics(tileset: LatentTileset, region: DemTile, *, rows_per_chunk: int = 64
                   ) -> dict[str, float]:
    """Node RMSE and max error of the blended tileset over the region (bounded memory)."""
    ny, nx = region.shape
    (x0, y0), (dx, dy) = region.origin, region.spacing
    xs = torch.as_tensor(x0 + np.arange(nx) * dx)
    sq, worst, count = 0.0, 0.0, 0
    for lo in range(0, ny, rows_per_chunk):
        ys = torch.as_tensor(y0 + np.arange(lo, min(ny, lo + rows_per_chunk)) * dy)
        yy, xx = torch.meshgrid(ys, xs, indexing="ij")
        with torch.no_grad():
            got = tileset(torch.stack([xx, yy], -1)).numpy()
        err = (got - region.heights[lo:lo + rows_per_chunk])[region.valid_mask[lo:lo + rows_per_chunk]]
        sq += float((err**2).sum())
        worst = max(worst, float(np.abs(err).max())) if err.size else worst
        count += int(err.size)
    return {"rmse_m": math.sqrt(sq / max(count, 1)), "max_abs_m": worst}


class _Ticker:
    """Calls ``bar.update(0)`` every few seconds from a thread, so a long tile fit still
    prints its heartbeat line when stdout is a log (a tqdm bar just refreshes)."""

    def __init__(self, bar: Any, every_s: float = 5.0) -> None:
        self._bar, self._every = bar, every_s
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)

    def _run(self) -> None:
        while not self._stop.wait(self._every):
            self._bar.update(0)

    def __enter__(self) -> _Ticker:
        self._thread.start()
        return self

    def __exit__(self, *exc: Any) -> None:
        self._stop.set()
        self._thread.join()


def fit_options(hparams: dict[str, Any]) -> dict[str, Any]:
    """The ``--model.*`` settings `fit_latent_map` takes (the others are Lightning's)."""
    accepted = set(inspect.signature(fit_latent_map).parameters) - {"tile", "steps"}
    return {k: v for k, v in dict(hparams).items() if k in accepted}


def fit_tileset(plan: TilesetPlan, out_dir: str | Path, *, steps: int,
                options: dict[str, Any], progress: bool = True) -> Path:
    """Fits every tile and writes the tileset (module docstring).

    Args:
        plan: The region and its tiles (`plan_tileset`).
        out_dir: The run folder (``tiles/`` and the index go there).
        steps: Adam steps per tile.
        options: `fit_latent_map` settings (``rate_weight`` required).
        progress: Show a progress bar / heartbeat lines.

    Returns:
        The index file.
    """
    if int(steps) < 1:
        raise NeuralMapError(f"latent tileset: steps per tile must be >= 1, got {steps}.")
    out_dir = Path(out_dir)
    layout, region = plan.layout, plan.region
    rows, cols = layout.grid
    entries: list[TileEntry] = []
    bar = progress_bar(total=layout.count * int(steps), desc="latent tileset",
                       unit="step") if progress else None
    start = time.perf_counter()
    try:
        for k, (row, col) in enumerate((i, j) for i in range(rows) for j in range(cols)):
            box = layout.window(row, col)
            tile = window_tile(region, box, f"{region.name}_r{row}c{col}", plan.sources[k])
            if bar is not None:
                bar.set_description(f"latent tileset: tile r{row} c{col} ({k + 1}/{layout.count})")
                with _Ticker(bar):
                    latent_map, _ = fit_latent_map(tile, steps=int(steps), **options)
                bar.update(int(steps))
            else:
                latent_map, _ = fit_latent_map(tile, steps=int(steps), **options)
            quality = map_quality(latent_map, tile, n_between=4096)
            latent_map.metrics = {key: quality[key] for key in
                                  ("rmse_m", "max_abs_m", "between_rmse_m")}
            latent_map.metrics["rate_weight"] = float(options.get("rate_weight", 0.0))
            path = write_latent_map(latent_map, out_dir / tile_file_name(row, col))
            (r0, r1), (c0, c1) = layout.rows[row], layout.columns[col]
            entries.append(TileEntry(
                row=row, col=col, file=tile_file_name(row, col), sha256=file_sha256(path),
                bytes=path.stat().st_size, core=(r0, r1, c0, c1), window=box,
                extent=tile.extent, fingerprint=tile.fingerprint(), source=plan.sources[k],
                metrics=to_jsonable(quality)))
    finally:
        if bar is not None:
            bar.close()
    total_bytes = sum(e.bytes for e in entries)
    info = {"training": to_jsonable({"steps_per_tile": int(steps), **options}),
            "metrics": {"file_bytes": total_bytes,
                        "bits_per_node": 8.0 * total_bytes / max(1, int(region.valid_mask.sum())),
                        "raw_grid_bytes": int(region.shape[0] * region.shape[1] * 4),
                        "fit_seconds": time.perf_counter() - start}}
    index = TilesetIndex(region=region.describe(), layout=layout, tiles=entries, info=info)
    partial = out_dir / f".{INDEX_FILENAME}.partial"
    write_tileset_index(partial, index)
    try:
        info["metrics"].update(region_metrics(LatentTileset(partial), region))
        path = write_tileset_index(out_dir / INDEX_FILENAME, index)
    finally:
        partial.unlink(missing_ok=True)
    atomic_write_json(out_dir / "metrics.json", to_jsonable(
        {"region": region.name, "tiles": layout.count, "grid": list(layout.grid), **info["metrics"]}))
    return path
