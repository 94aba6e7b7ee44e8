"""Map size study: stored bytes vs map error vs navigation accuracy, neural maps vs codecs.

Paper 004 (SEEDS 004) argues that a neural map needs less storage than the grid. Nobody
carries a raw float32 grid, so this study measures both families at equal footing on the
scenario's tile:

* **compressed grids**: every codec of :mod:`neuralmap.terrain.codecs` at every maximum
  error and decimation of the config, decoded to a grid (bicubic);
* **neural maps**: every exported map given (or found under ``runs_dir``), stored in float32
  and in each quantised form of :mod:`neuralmap.terrain.quantize`; the stored size is the
  file :func:`~neuralmap.terrain.export.save_map` writes;
* the same neural maps *baked* (evaluated once at the DEM nodes when loaded, then queried
  as a bicubic grid): the neural map's storage with the grid's query speed;
* the raw float32 grid as the reference.

Per map: stored bytes and bits per DEM node, error at the nodes (RMSE, max), error and
slope error against the scenario's truth terrain at random points between the nodes,
height + slope query throughput of the linearizer, and navigation accuracy on the
scenario's Monte Carlo (all-run RMSE, RMSE / PCRB, divergence) with one fixed
linearisation method per map kind: autograd of the bicubic grid for grids, autograd of the
network for neural maps, each with R increased by the map's own error variance against the
truth (beyond the scenario's fit variance), as the TAN study does for the neural map.
The rate-distortion fronts (bytes vs maximum node error, bytes vs navigation RMSE) of both
families are plotted and the targets checked:

* a neural map of at most 25 % of the raw float32 grid with a node RMSE of at most 3 m;
* at equal navigation accuracy (all-run RMSE within 5 % of the full-resolution grid's), a
  neural map no larger than the smallest compressed grid that reaches it.

Examples:
    python evaluate.py --config configs/map_size.yaml
    python evaluate.py --config configs/map_size.yaml --neural_maps [runs/compact_s/version_0/neural_map.pt]
"""

from __future__ import annotations

import math
import os
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import nn

from neuralmap.exceptions import NeuralMapError
from neuralmap.studies.base import StudyConfig
from neuralmap.studies.maps import find_tile_maps
from neuralmap.studies.outputs import RunCounts, StudyOutputs, verdict

__all__ = ["MapEntry", "MapSizeStudyConfig", "pareto_front", "run"]

#: Relative navigation-RMSE tolerance of "equal navigation accuracy".
EQUAL_ACCURACY = 0.05
#: Storage target of a neural map, as a fraction of the raw float32 grid.
TARGET_FRACTION = 0.25
#: Node-RMSE target of that neural map, metres.
TARGET_RMSE_M = 3.0


@dataclass
class MapSizeStudyConfig(StudyConfig):
    """Options of the map size study (``study: map_size``).

    Attributes:
        scenario: Scenario name (``configs/scenarios/<name>.yaml``) or a YAML path.
        n_runs: Monte Carlo trajectories (the same truth for every map).
        codecs: Grid codecs (:data:`neuralmap.terrain.codecs.GRID_CODECS`).
        max_errors: Maximum node errors (m, each > 0) of every codec.
        decimations: Decimation factors (1 = full resolution; 2, 4: coarser grids
            interpolated back, bicubic).
        decimated_max_errors: Maximum errors used for decimated grids (``None`` = the
            same as ``max_errors``).
        neural_maps: Exported neural maps (``neural_map.pt``); ``None`` = the newest map
            of the scenario's tile in every experiment folder of ``runs_dir``; ``[]`` = no
            neural maps (codecs only).
        quantizations: Stored forms of each neural map: ``none`` (float32) and schemes
            of :data:`neuralmap.terrain.quantize.QUANT_SCHEMES`.
        baked: Stored forms (of ``quantizations``) also evaluated *baked*: the loaded map
            evaluated once at the DEM nodes at load time and queried as a bicubic grid
            (:func:`neuralmap.terrain.bake.bake_to_grid`): the neural map's storage with
            the grid's query speed.
        map_error_points: Random points between the nodes for the errors against truth.
        query_points: Points of the throughput measurement.
        pcrb_factor: Divergence when the final error exceeds this times the final PCRB.
        divergence_sigma: Divergence when the final error exceeds this many times the
            filter's own 1σ horizontal bound.
    """

    study: str = "map_size"
    experiment: str = "map_size"
    threads: int | None = 1
    progress: bool = False
    scenario: str = "jacksboro"
    n_runs: int = 500
    codecs: list[str] = field(default_factory=lambda: ["lerc", "jpegls", "jpeg2k", "zstd"])
    max_errors: list[float] = field(default_factory=lambda: [0.5, 1.0, 2.0, 5.0, 10.0])
    decimations: list[int] = field(default_factory=lambda: [1, 2, 4])
    decimated_max_errors: list[float] | None = field(default_factory=lambda: [0.5, 2.0])
    neural_maps: list[str] | None = None
    quantizations: list[str] = field(
        default_factory=lambda: ["none", "fp16", "int8_channel", "int8_block", "int8_tensor"]
    )
    baked: list[str] = field(default_factory=lambda: ["int8_channel"])
    map_error_points: int = 20000
    query_points: int = 50000
    pcrb_factor: float = 5.0
    divergence_sigma: float = 9.0

    def validate(self) -> None:
        """Checks values; raises :class:`NeuralMapError` naming the option and the fix."""
        from neuralmap.terrain.codecs import GRID_CODECS
        from neuralmap.terrain.quantize import QUANT_SCHEMES

        super().validate()
        if self.n_runs < 1:
            raise NeuralMapError(f"--n_runs must be >= 1, got {self.n_runs}.")
        unknown = [c for c in self.codecs if c not in GRID_CODECS]
        if unknown:
            raise NeuralMapError(
                f"--codecs: unknown codec(s) {unknown}; known: {', '.join(GRID_CODECS)}."
            )
        for name, values in (("max_errors", self.max_errors),
                             ("decimated_max_errors", self.decimated_max_errors or [])):
            bad = [v for v in values if not (isinstance(v, int | float) and math.isfinite(v)
                                             and v > 0)]
            if bad:
                raise NeuralMapError(
                    f"--{name}: every maximum error must be a number of metres > 0, got {bad}."
                )
        if self.codecs and not self.max_errors:
            raise NeuralMapError("--max_errors is empty; give e.g. [0.5, 1, 2, 5].")
        bad_dec = [d for d in self.decimations if not (isinstance(d, int) and d >= 1)]
        if bad_dec or not self.decimations:
            raise NeuralMapError(
                f"--decimations must list integers >= 1 (1 = full resolution), got "
                f"{self.decimations}."
            )
        schemes = ("none", *QUANT_SCHEMES)
        bad_q = [q for q in self.quantizations if q not in schemes]
        if bad_q or not self.quantizations:
            raise NeuralMapError(
                f"--quantizations: unknown or empty {bad_q or self.quantizations}; choose "
                f"from {', '.join(schemes)}."
            )
        bad_b = [q for q in self.baked if q not in self.quantizations]
        if bad_b:
            raise NeuralMapError(
                f"--baked: {bad_b} not among --quantizations {self.quantizations}; bake only "
                "stored forms that are measured."
            )
        if self.map_error_points < 100 or self.query_points < 100:
            raise NeuralMapError(
                "--map_error_points and --query_points must be >= 100, got "
                f"{self.map_error_points}, {self.query_points}."
            )
        if not (self.pcrb_factor > 0 and self.divergence_sigma > 0):
            raise NeuralMapError(
                f"--pcrb_factor and --divergence_sigma must be > 0, got {self.pcrb_factor}, "
                f"{self.divergence_sigma}."
            )


@dataclass
class MapEntry:
    """One stored map under test.

    Attributes:
        name: Label in tables and plots.
        family: ``"raw grid"``, a codec name (decimated: ``"<codec> xN"``) or ``"neural"``.
        kind: ``"grid"`` or ``"neural"`` (fixes the linearisation method).
        nbytes: Stored bytes.
        terrain: The decoded map as a terrain model.
        info: Settings (codec, max error, scheme, file, parameters...).
    """

    name: str
    family: str
    kind: str
    nbytes: int
    terrain: nn.Module
    info: dict[str, Any] = field(default_factory=dict)


def pareto_front(sizes: list[float], errors: list[float]) -> list[int]:
    """Indices of the rate-distortion front: no other point is smaller and more accurate.

    Args:
        sizes: Stored bytes per point.
        errors: Error per point (NaN / None points are skipped).

    Returns:
        Indices on the front, by increasing size (and decreasing error).
    """
    points = [
        (s, e, i) for i, (s, e) in enumerate(zip(sizes, errors, strict=True))
        if e is not None and math.isfinite(e)
    ]
    points.sort(key=lambda p: (p[0], p[1]))
    front: list[int] = []
    best = math.inf
    for _, err, index in points:
        if err < best:
            front.append(index)
            best = err
    return front


def find_neural_maps(runs_dir: str, tile_fingerprint: str) -> list[Path]:
    """Newest exported map of the tile in every experiment folder of ``runs_dir`` (the
    one map discovery: :func:`neuralmap.studies.maps.find_tile_maps`)."""
    return find_tile_maps(runs_dir, tile_fingerprint)


def build_grid_maps(tile: Any, config: MapSizeStudyConfig) -> list[MapEntry]:
    """The raw float32 grid and every codec × max error × decimation of the config."""
    from neuralmap.terrain.codecs import compress_grid
    from neuralmap.terrain.grid import GridTerrain

    raw = GridTerrain(tile, method="bicubic")
    entries = [MapEntry("raw float32 grid", "raw grid", "grid", tile.heights.size * 4, raw,
                        {"codec": None, "max_error_m": 0.0, "decimation": 1})]
    for codec in config.codecs:
        for decimation in config.decimations:
            errors = config.max_errors
            if decimation > 1 and config.decimated_max_errors is not None:
                errors = config.decimated_max_errors
            for max_error in errors:
                grid = compress_grid(tile, codec=codec, max_error=float(max_error),
                                     decimation=int(decimation))
                family = codec if decimation == 1 else f"{codec} x{decimation}"
                entries.append(MapEntry(
                    grid.name, family, "grid", grid.nbytes, grid.terrain(method="bicubic"),
                    {"codec": codec, "max_error_m": grid.max_error, "decimation": decimation,
                     "error_bound_m": grid.error_bound, "stored_shape": list(grid.stored_shape),
                     "settings": grid.settings,
                     "decode_nodes_per_s": (grid.stored_shape[0] * grid.stored_shape[1]
                                            / max(grid.decode_s, 1e-9))},
                ))
    return entries


def build_neural_maps(
    paths: list[Path], quantizations: list[str], folder: Path, *, tile: Any,
    baked: list[str] | None = None,
) -> list[MapEntry]:
    """Every map in every stored form, written to ``folder`` and read back with load_map.

    Forms listed in ``baked`` are added once more, baked onto the tile's nodes (bicubic).
    """
    from neuralmap.terrain.bake import bake_to_grid
    from neuralmap.terrain.export import load_map, save_map

    folder.mkdir(parents=True, exist_ok=True)
    entries = []
    for path in paths:
        net = load_map(path)
        label = path.parent.parent.name if path.parent.name.startswith("version_") else path.stem
        for scheme in quantizations:
            out = save_map(net, folder / f"{label}_{scheme}.pt",
                           metrics=getattr(net, "metrics", {}),
                           quantization=None if scheme == "none" else scheme)
            loaded = load_map(out)
            info = {"source": str(path), "file": out.name, "quantization": scheme,
                    "num_parameters": int(net.num_parameters), "config": dict(net.config)}
            size = os.path.getsize(out)
            entries.append(MapEntry(f"{label} {scheme}", "neural", "neural", size, loaded, info))
            if scheme in (baked or []):
                grid = bake_to_grid(loaded, tile)
                grid.tile_fingerprint = loaded.tile_fingerprint  # a map of the same tile
                entries.append(MapEntry(f"{label} {scheme} baked", "neural baked", "neural",
                                        size, grid, {**info, "baked": True}))
    return entries


def _height_and_slope(terrain: nn.Module, xy: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Heights and slopes (analytic / forward mode when the model has it, else autograd)."""
    fast = getattr(terrain, "height_and_slope", None)
    if fast is not None:
        return fast(xy)
    with torch.enable_grad():
        points = xy.detach().requires_grad_(True)
        height = terrain(points)
        (slope,) = torch.autograd.grad(height.sum(), points)
    return height.detach(), slope


def _model_dtype(terrain: nn.Module) -> torch.dtype:
    param = next(iter(terrain.parameters()), None)
    if param is not None:
        return param.dtype
    heights = getattr(terrain, "heights", None)
    return heights.dtype if isinstance(heights, torch.Tensor) else torch.float64


def map_quality(
    entry: MapEntry, tile: Any, truth_model: nn.Module, *, n_points: int, seed: int
) -> dict[str, Any]:
    """Node errors, errors and slope errors against the truth between the nodes.

    Returns:
        ``node_rmse_m``, ``node_max_m`` (against the DEM nodes), ``truth_rmse_m``,
        ``truth_max_m``, ``truth_mse_m2`` (height minus truth at random points),
        ``slope_rmse`` (norm of the slope error vector, m/m, same points).
    """
    dtype = _model_dtype(entry.terrain)
    valid = np.isfinite(tile.heights)
    nodes = torch.from_numpy(tile.node_xy()[valid])
    with torch.no_grad():
        node_h = torch.cat([entry.terrain(p.to(dtype)).double()
                            for p in torch.split(nodes, 65536)])
    node_err = node_h.numpy() - tile.heights[valid]
    xmin, xmax, ymin, ymax = tile.extent
    gen = torch.Generator().manual_seed(int(seed) + 0x51E)
    u = torch.rand(n_points, 2, generator=gen, dtype=torch.float64)
    xy = torch.stack([xmin + u[:, 0] * (xmax - xmin), ymin + u[:, 1] * (ymax - ymin)], -1)
    heights, slopes, true_h, true_s = [], [], [], []
    for part in torch.split(xy, 65536):
        h, s = _height_and_slope(entry.terrain, part.to(dtype))
        th, ts = _height_and_slope(truth_model, part)
        heights.append(h.double())
        slopes.append(s.double())
        true_h.append(th.double())
        true_s.append(ts.double())
    err = torch.cat(heights) - torch.cat(true_h)
    slope_err = torch.cat(slopes) - torch.cat(true_s)
    return {
        "node_rmse_m": float(np.sqrt(np.mean(node_err**2))),
        "node_max_m": float(np.abs(node_err).max()),
        "truth_rmse_m": float(err.square().mean().sqrt()),
        "truth_max_m": float(err.abs().max()),
        "truth_mse_m2": float(err.square().mean()),
        "slope_rmse": float(slope_err.square().sum(-1).mean().sqrt()),
    }


def query_rate(linearizer: Any, xy: torch.Tensor, *, repeats: int = 5) -> float:
    """Height + slope queries per second of a callable: fastest of ``repeats`` calls.

    The fastest call (after one warm-up) is what the code does without interference from
    other processes, which on a shared machine is the comparable number.
    """
    linearizer(xy)
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        linearizer(xy)
        times.append(time.perf_counter() - start)
    return xy.shape[0] / max(min(times), 1e-12)


def _fmt_bytes(n: float) -> str:
    return f"{n / 1024:.1f} KiB" if n < 1024**2 else f"{n / 1024**2:.2f} MiB"


def _plot_front(
    outputs: StudyOutputs, rows: list[dict[str, Any]], *, key: str, ylabel: str, name: str,
    caption: str, raw_bytes: int, reference: float | None = None,
) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    floor = 0.01  # lossless maps (error 0) are drawn at 1 cm on the log axis
    fig, ax = plt.subplots(figsize=(7.5, 5.0))
    families = sorted({r["family"] for r in rows}, key=lambda f: (f.startswith("neural"), f))
    markers = "osD^v<>ph*Xd"
    for i, family in enumerate(families):
        pts = [r for r in rows if r["family"] == family and r.get(key) is not None]
        if not pts:
            continue
        ax.scatter([r["bytes"] for r in pts], [max(r[key], floor) for r in pts],
                   marker=markers[i % len(markers)],
                   s=60 if family.startswith("neural") else 36,
                   label=family, zorder=3)
    for kind, style in (("grid", "k--"), ("neural", "r-")):
        pts = [r for r in rows if r["kind"] == kind and r.get(key) is not None]
        idx = pareto_front([r["bytes"] for r in pts], [r[key] for r in pts])
        if idx:
            ax.plot([pts[i]["bytes"] for i in idx], [max(pts[i][key], floor) for i in idx], style,
                    lw=1.2, label=f"{kind} front", zorder=2)
    ax.axvline(raw_bytes, color="grey", lw=0.8, ls=":", label="raw float32 grid")
    ax.axvline(TARGET_FRACTION * raw_bytes, color="grey", lw=0.8, ls="-.",
               label=f"{TARGET_FRACTION:.0%} of raw")
    if reference is not None:
        ax.axhline(reference, color="tab:green", lw=0.8, ls=":",
                   label=f"full grid + {EQUAL_ACCURACY:.0%}")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("stored bytes")
    ax.set_ylabel(ylabel)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    outputs.add_figure(name, fig, caption)
    plt.close(fig)


def run(config: MapSizeStudyConfig, outputs: StudyOutputs) -> None:
    """Runs the map size study and fills ``outputs``.

    Raises:
        NeuralMapError: Bad input (scenario, maps of another tile, codecs missing...).
    """
    from neuralmap.linearize.autograd import AutogradLinearizer
    from neuralmap.nav.metrics import navigation_metrics
    from neuralmap.nav.monte_carlo import run_monte_carlo
    from neuralmap.nav.pcrb import pcrb, pcrb_position
    from neuralmap.nav.scenario import load_scenario, scenario_tile
    from neuralmap.nav.truth_terrain import true_terrain
    from neuralmap.terrain.export import load_map_payload

    started = time.perf_counter()
    device, dtype = config.torch_device, config.torch_dtype
    scenario = load_scenario(config.scenario)
    tile = scenario_tile(scenario)
    seed = scenario.seed if config.seed is None else int(config.seed)
    config.seed = seed
    if config.neural_maps is None:
        paths = find_neural_maps(config.runs_dir, tile.fingerprint())
    else:
        paths = [Path(p) for p in config.neural_maps]
    for path in paths:
        payload = load_map_payload(path)
        fingerprint = payload.get("config", {}).get("tile_info", {}).get("fingerprint", "")
        if fingerprint and fingerprint != tile.fingerprint():
            raise NeuralMapError(
                f"--neural_maps: {path} was fitted to another tile (fingerprint {fingerprint}) "
                f"than the scenario's {tile.name!r} ({tile.fingerprint()}); train a map on it "
                "(python train.py --config configs/compact_s.yaml) or drop the file."
            )
    config.neural_maps = [str(p) for p in paths]
    truth_terrain = true_terrain(scenario, tile, seed=seed)
    raw_bytes = int(tile.heights.size * 4)

    entries = build_grid_maps(tile, config)
    entries += build_neural_maps(paths, config.quantizations, outputs.dir / "maps", tile=tile,
                                 baked=config.baked)
    print(f"map_size: {len(entries)} maps ({len(paths)} neural map file(s)) on tile "
          f"{tile.name} {tile.shape}, scenario {scenario.name}, {config.n_runs} runs", flush=True)

    gen = torch.Generator().manual_seed(seed)
    xmin, xmax, ymin, ymax = tile.extent
    u = torch.rand(config.query_points, 2, generator=gen, dtype=torch.float64)
    query_xy = torch.stack([xmin + u[:, 0] * (xmax - xmin), ymin + u[:, 1] * (ymax - ymin)], -1)
    rows: list[dict[str, Any]] = []
    methods: dict[str, Any] = {}
    for entry in entries:
        quality = map_quality(entry, tile, truth_terrain.model,
                              n_points=config.map_error_points, seed=seed)
        extra_variance = max(quality["truth_mse_m2"] - scenario.fit_variance_m2, 0.0)
        linearizer = AutogradLinearizer(entry.terrain, fit_variance=extra_variance)
        xy_q = query_xy.to(_model_dtype(entry.terrain))
        rate = query_rate(linearizer, xy_q)
        fast_rate = query_rate(lambda p, t=entry.terrain: _height_and_slope(t, p), xy_q)
        methods[entry.name] = linearizer
        rows.append({
            "name": entry.name, "family": entry.family, "kind": entry.kind,
            "bytes": int(entry.nbytes), "bits_per_node": 8.0 * entry.nbytes / tile.heights.size,
            "fraction_of_raw": entry.nbytes / raw_bytes, **quality,
            "extra_variance_m2": extra_variance, "queries_per_s": rate,
            "fast_queries_per_s": fast_rate, **entry.info,
        })
    if len(set(methods)) != len(entries):
        raise NeuralMapError("map_size: two maps share a name; give the neural map files "
                             "distinct experiment folders.")
    # the raw grid was measured first, while the process was still warming up: measure it
    # again now and keep the faster of the two (the ratios are against this rate)
    ref_xy = query_xy.to(_model_dtype(entries[0].terrain))
    rows[0]["queries_per_s"] = max(rows[0]["queries_per_s"],
                                   query_rate(methods[entries[0].name], ref_xy))
    rows[0]["fast_queries_per_s"] = max(
        rows[0]["fast_queries_per_s"],
        query_rate(lambda p, t=entries[0].terrain: _height_and_slope(t, p), ref_xy))
    ref_rate = rows[0]["queries_per_s"]
    ref_fast = rows[0]["fast_queries_per_s"]
    for row in rows:
        row["query_vs_bicubic"] = row["queries_per_s"] / ref_rate
        row["fast_query_vs_bicubic"] = row["fast_queries_per_s"] / ref_fast

    tick = time.perf_counter()
    truth, runs = run_monte_carlo(
        scenario, methods, n_runs=config.n_runs, seed=seed, progress=config.progress,
        device=device, dtype=dtype, tile=tile, truth_terrain=truth_terrain,
    )
    kept = truth.on_map.all(dim=1)
    bound = pcrb(truth, scenario, truth_terrain.model, runs=kept if bool(kept.any()) else None)
    pcrb_pos = pcrb_position(bound).detach().to("cpu", torch.float64)
    for row in rows:
        metrics = navigation_metrics(runs[row["name"]], pcrb_pos,
                                     pcrb_factor=config.pcrb_factor,
                                     divergence_sigma=config.divergence_sigma)
        row["nav_rmse_m"] = metrics.get("rmse_pos_m")
        row["nav_pcrb_ratio"] = metrics.get("pcrb_ratio_all")
        row["nav_rmse_converged_m"] = metrics.get("rmse_pos_converged_m")
        row["divergence_rate"] = metrics.get("divergence_rate")
        row["n_diverged"] = metrics.get("n_diverged")
        row["n_included"] = metrics.get("n_included")
    nav_s = time.perf_counter() - tick

    summary = _summarise(rows, raw_bytes)
    _write_report(outputs, config, rows, summary, raw_bytes=raw_bytes, tile=tile,
                  scenario=scenario, truth_description=truth_terrain.description)
    outputs.results.update({
        "tile": tile.describe(),
        "scenario": scenario.to_dict(),
        "truth_model": truth_terrain.summary(),
        "raw_grid_bytes": raw_bytes,
        "maps": rows,
        "summary": summary,
        "pcrb_pos_final_m": float(pcrb_pos[-1]),
        "linearisation": {
            "grid": "autograd of the bicubic decoded grid",
            "neural": "autograd of the network",
            "variance": "R + max(map MSE against truth - scenario fit variance, 0)",
        },
        "timing_s": {"navigation": nav_s, "total": time.perf_counter() - started},
        "config": asdict(config),
    })
    for row in rows:
        if row.get("nav_rmse_m") is not None:
            outputs.log_scalar(f"map_size/nav_rmse/{row['family']}", row["nav_rmse_m"],
                               row["bytes"])


def _smallest(rows: list[dict[str, Any]], kind: str, ok: Any) -> dict[str, Any] | None:
    """The smallest map of ``kind`` whose row satisfies ``ok``."""
    hits = [r for r in rows if r["kind"] == kind and r["family"] != "raw grid" and ok(r)]
    return min(hits, key=lambda r: r["bytes"]) if hits else None


def _equal_accuracy(
    rows: list[dict[str, Any]], key: str, *, robust: bool
) -> dict[str, Any]:
    """Smallest grid and neural map within ``EQUAL_ACCURACY`` of the full grid's ``key``.

    With ``robust`` a map must also diverge in no more runs than the full grid.
    """
    ref = rows[0]
    ref_value = ref.get(key)
    threshold = None if ref_value is None else (1.0 + EQUAL_ACCURACY) * ref_value

    def ok(r: dict[str, Any]) -> bool:
        if threshold is None or r.get(key) is None or r[key] > threshold:
            return False
        return not robust or (r.get("n_diverged") or 0) <= (ref.get("n_diverged") or 0)

    grid, neural = _smallest(rows, "grid", ok), _smallest(rows, "neural", ok)
    has_neural = any(r["kind"] == "neural" for r in rows)
    pick = ("name", "bytes", key, "n_diverged")
    return {
        "metric": key,
        "reference": ref_value,
        "reference_diverged": ref.get("n_diverged"),
        "threshold_m": threshold,
        "smallest_grid": grid and {k: grid.get(k) for k in pick},
        "smallest_neural": neural and {k: neural.get(k) for k in pick},
        "met": None if not has_neural else bool(
            neural is not None and (grid is None or neural["bytes"] <= grid["bytes"])),
    }


def _summarise(rows: list[dict[str, Any]], raw_bytes: int) -> dict[str, Any]:
    """Fronts and targets from the per-map rows."""

    def compact_ok(r: dict[str, Any]) -> bool:
        return r["bytes"] <= TARGET_FRACTION * raw_bytes and r["node_rmse_m"] <= TARGET_RMSE_M

    fronts: dict[str, Any] = {}
    for kind in ("grid", "neural"):
        pts = [r for r in rows if r["kind"] == kind]
        for key in ("node_max_m", "nav_rmse_m", "nav_rmse_converged_m"):
            idx = pareto_front([r["bytes"] for r in pts], [r.get(key) for r in pts])
            fronts[f"{kind}:{key}"] = [
                {"name": pts[i]["name"], "bytes": pts[i]["bytes"], key: pts[i][key]} for i in idx
            ]
    compact = _smallest(rows, "neural", compact_ok)
    neural_rows = [r for r in rows if r["kind"] == "neural"]
    best_nav = min((r for r in neural_rows if r.get("nav_rmse_m") is not None),
                   key=lambda r: r["nav_rmse_m"], default=None)
    return {
        "equal_accuracy_all_runs": _equal_accuracy(rows, "nav_rmse_m", robust=False),
        "equal_accuracy_converged": _equal_accuracy(rows, "nav_rmse_converged_m", robust=True),
        "best_neural_nav": best_nav and {k: best_nav[k] for k in ("name", "bytes", "nav_rmse_m")},
        "compact_target_map": compact and {
            k: compact[k] for k in ("name", "bytes", "fraction_of_raw", "node_rmse_m")},
        "target_compact_met": compact is not None if neural_rows else None,
        "target_equal_accuracy_met": _equal_accuracy(rows, "nav_rmse_m", robust=False)["met"],
        "fronts": fronts,
    }


def _write_report(
    outputs: StudyOutputs, config: MapSizeStudyConfig, rows: list[dict[str, Any]],
    summary: dict[str, Any], *, raw_bytes: int, tile: Any, scenario: Any,
    truth_description: str,
) -> None:
    """Tables, fronts, targets and the paper's storage claim."""
    outputs.add_text(
        f"Tile **{tile.name}** ({tile.shape[0]} x {tile.shape[1]} nodes; raw float32 grid "
        f"{_fmt_bytes(raw_bytes)}), scenario **{scenario.name}**, {config.n_runs} Monte Carlo "
        f"runs, truth: {truth_description}. Grids are decoded and interpolated bicubic; "
        "every map is linearised by autograd of its own surface (grids: the bicubic "
        "interpolant; neural maps: the network) with R increased by the map's mean squared "
        "error against the truth beyond the scenario's fit variance. Stored bytes: codec "
        "payload + header; neural maps: the save_map file. Query rates (fastest of 5 calls, "
        "one batch): 'M q/s' = the navigation linearizer (autograd), 'fast' = analytic "
        "height + slope (grids: closed-form bicubic; neural maps: forward mode); ratios "
        "against the raw bicubic grid in the same run."
    )
    headers = ["map", "bytes", "bits/node", "% raw", "node RMSE m", "node max m",
               "truth RMSE m", "truth max m", "slope RMSE", "M q/s", "x bicubic",
               "M q/s fast", "fast x bicubic", "nav RMSE m", "RMSE/PCRB",
               "nav RMSE conv. m", "diverged"]
    table = [
        [r["name"], r["bytes"], r["bits_per_node"], 100 * r["fraction_of_raw"],
         r["node_rmse_m"], r["node_max_m"], r["truth_rmse_m"], r["truth_max_m"],
         r["slope_rmse"], r["queries_per_s"] / 1e6, r["query_vs_bicubic"],
         r["fast_queries_per_s"] / 1e6, r["fast_query_vs_bicubic"], r.get("nav_rmse_m"),
         r.get("nav_pcrb_ratio"), r.get("nav_rmse_converged_m"),
         f"{r.get('n_diverged')}/{r.get('n_included')}"]
        for r in sorted(rows, key=lambda r: (r["kind"], r["family"], r["bytes"]))
    ]
    outputs.add_table("Every map", headers, table)
    front_rows = []
    for key, front in summary["fronts"].items():
        kind, metric = key.split(":")
        front_rows += [[kind, metric, p["name"], p["bytes"], p[metric]] for p in front]
    outputs.add_table("Rate-distortion fronts", ["family", "error", "map", "bytes", "error"],
                      front_rows)
    all_runs = summary["equal_accuracy_all_runs"]
    converged = summary["equal_accuracy_converged"]
    _plot_front(outputs, rows, key="node_max_m", ylabel="max |error| at the DEM nodes (m)",
                name="bytes_vs_max_error", raw_bytes=raw_bytes,
                caption="Stored bytes vs maximum node error: grid codecs and neural maps "
                        "(lossless maps drawn at 0.01 m)")
    _plot_front(outputs, rows, key="nav_rmse_m", ylabel="all-run position RMSE (m)",
                name="bytes_vs_nav_rmse", raw_bytes=raw_bytes, reference=all_runs["threshold_m"],
                caption="Stored bytes vs navigation RMSE (all runs, second half of the flight)")
    _plot_front(outputs, rows, key="nav_rmse_converged_m",
                ylabel="converged-run position RMSE (m)", name="bytes_vs_nav_rmse_converged",
                raw_bytes=raw_bytes, reference=converged["threshold_m"],
                caption="Stored bytes vs navigation RMSE of the converged runs (the all-run "
                        "RMSE is set by the few diverged runs)")

    neural = [r for r in rows if r["kind"] == "neural"]
    navigated = [r for r in rows if r.get("n_included") is not None]
    nav_runs = (RunCounts.weakest(*(RunCounts(r["n_included"], r["n_included"])
                                    for r in navigated)) if navigated else None)
    if not neural:
        compact_text = "no neural map was given (codecs only)"
        compact_verdict = verdict(None, detail="no neural map")
        eq_text, eq_verdict = compact_text, compact_verdict
    else:
        best = min(neural, key=lambda r: (r["fraction_of_raw"] > TARGET_FRACTION,
                                          r["node_rmse_m"]))
        hit = summary["compact_target_map"]
        compact_text = (
            f"{hit['name']}: {100 * hit['fraction_of_raw']:.1f} % of raw, node RMSE "
            f"{hit['node_rmse_m']:.2f} m" if hit else
            f"closest: {best['name']} at {100 * best['fraction_of_raw']:.1f} % of raw with "
            f"node RMSE {best['node_rmse_m']:.2f} m"
        )
        compact_verdict = verdict(bool(hit))
        eq_text = (_equal_accuracy_text(all_runs, "all-run RMSE") + "; robust check: "
                   + _equal_accuracy_text(converged, "converged-run RMSE, no more diverged runs"))
        eq_verdict = verdict(bool(all_runs["met"]))
    outputs.add_claim(
        "toolkit target",
        f"a neural map <= {TARGET_FRACTION:.0%} of the raw float32 grid with node RMSE "
        f"<= {TARGET_RMSE_M:g} m", compact_text, compact_verdict)
    outputs.add_claim(
        "toolkit target",
        f"at equal navigation accuracy (all-run RMSE within {EQUAL_ACCURACY:.0%} of the "
        "full-resolution grid's) a neural map no larger than the smallest compressed grid",
        eq_text, eq_verdict, runs=nav_runs)
    storage_text, storage_verdict = _storage_claim(rows, raw_bytes)
    outputs.add_claim("SEEDS 004", "the neural map needs less storage than the grid",
                      storage_text, storage_verdict)


def _equal_accuracy_text(check: dict[str, Any], what: str) -> str:
    """One sentence on an equal-accuracy check."""
    key, ref = check["metric"], check["reference"]
    if ref is None:
        return f"{what}: the full grid scored no run"
    grid, neural = check["smallest_grid"], check["smallest_neural"]
    text = (f"{what} <= {check['threshold_m']:.1f} m (full grid {ref:.1f} m, "
            f"{check['reference_diverged']} diverged): ")
    text += (f"smallest grid {grid['name']} {_fmt_bytes(grid['bytes'])} ({grid[key]:.1f} m)"
             if grid else "no compressed grid")
    if neural:
        text += (f", smallest neural map {neural['name']} {_fmt_bytes(neural['bytes'])} "
                 f"({neural[key]:.1f} m)")
        if grid:
            text += f" = {neural['bytes'] / grid['bytes']:.2f} x the grid's bytes"
    else:
        text += ", no neural map reaches it"
    return text


def _storage_claim(rows: list[dict[str, Any]], raw_bytes: int) -> tuple[str, str]:
    """Paper 004's storage claim against the measured fronts, at equal max node error."""
    neural = [r for r in rows if r["kind"] == "neural"]
    if not neural:
        return "no neural map measured", verdict(None, detail="no neural map")
    parts, beaten = [], 0
    for r in sorted(neural, key=lambda r: r["bytes"]):
        grids = [g for g in rows if g["kind"] == "grid" and g["family"] != "raw grid"
                 and g["node_max_m"] <= r["node_max_m"]]
        best = min(grids, key=lambda g: g["bytes"]) if grids else None
        if best is not None and best["bytes"] < r["bytes"]:
            beaten += 1
        parts.append(
            f"{r['name']} {_fmt_bytes(r['bytes'])} ({100 * r['bytes'] / raw_bytes:.0f} % of raw, "
            f"max {r['node_max_m']:.1f} m) vs "
            + (f"{best['name']} {_fmt_bytes(best['bytes'])}" if best else "no grid as accurate")
        )
    smaller_than_raw = sum(r["bytes"] < raw_bytes for r in neural)
    storage_verdict = verdict(beaten == 0, partly=beaten < len(neural))
    summary = (f"{smaller_than_raw} of {len(neural)} neural maps are smaller than the raw "
               f"float32 grid; {beaten} of {len(neural)} are larger than a compressed grid of "
               "equal or smaller maximum node error: ")
    return summary + "; ".join(parts), storage_verdict
