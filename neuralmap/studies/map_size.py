"""Map size study: stored bytes vs map error vs navigation accuracy, neural maps vs codecs.

Paper 004 (SEEDS 004) argues that a neural map needs less storage than the grid. Nobody
carries a raw float32 grid, so this study measures both families at equal footing on the
scenario's tile (jacksboro by default; ``configs/map_size_topobathy.yaml`` and
``configs/map_size_synthetic.yaml`` run it on the other sample tiles):

* **compressed grids**: every codec of `neuralmap.terrain.codecs` (LERC, JPEG-LS,
  JPEG 2000, int16 + zstd, SZ3) at every maximum error and decimation of the config,
  decoded to a grid (bicubic);
* **neural maps**: every map file given (any file `load_map`
  reads) or found under ``runs_dir``. Blockwise maps are stored in float32 and in each
  quantised form of `neuralmap.terrain.quantize`; the stored size is the file
  `save_map` writes. Other maps (e.g. entropy-coded
  latent-grid maps) are measured as the file they are;
* the blockwise maps *baked* (evaluated once at the DEM nodes when loaded, then queried
  as a bicubic grid): the neural map's storage with the grid's query speed;
* the raw float32 grid as the reference.

Per map: stored bytes and bits per DEM node, error at the nodes (RMSE, max), error and
slope error against the scenario's truth terrain at random points between the nodes (and,
for neural maps, against the bicubic DEM there and the bicubic interpolation of the map's
own node values), height + slope query throughput, and navigation accuracy on the
scenario's Monte Carlo. **Every map is linearised by the same robust method**: autograd of
its own surface with the region variance (the tangent plane's mean squared miss over the
position uncertainty, `neuralmap.linearize.region_variance`) and R increased by the
map's own error variance against the truth beyond the scenario's fit variance; so a map is
judged by its surface, and rare divergences of a point linearisation do not decide.
Navigation RMSE is given over all runs and over the converged runs, each with a paired
bootstrap interval (`neuralmap.lab.bootstrap`), and as a ratio to the full-resolution
grid's with its interval.

Fronts (plotted as PNG): bytes vs node RMSE, bytes vs maximum node error, bytes vs
navigation RMSE. Figures of merit: the BD-rate of every neural family against JPEG 2000 on
the node-RMSE front (`bd_rate`), every neural
map's bytes over LERC's and JPEG-LS's at equal maximum error, and the targets:

* a neural map of at most 25 % of the raw float32 grid with a node RMSE of at most 3 m;
* at equal node RMSE a neural map of at most 0.7 x the best codec's bytes
  (BD-rate <= -30 % against JPEG 2000);
* between the nodes every neural map no worse against the truth than the bicubic DEM;
* at equal navigation accuracy (converged-run RMSE whose paired interval reaches within
  5 % of the full-resolution grid's), the smallest neural map at most 0.7 x the smallest
  compressed grid.

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
from matplotlib.figure import Figure
from torch import nn

from neuralmap.exceptions import NeuralMapError
from neuralmap.lab.bootstrap import bootstrap_rmse, paired_ratio, resample_index
from neuralmap.lab.metrics import navigation_metrics
from neuralmap.lab.monte_carlo import run_monte_carlo
from neuralmap.lab.pcrb import pcrb, pcrb_position
from neuralmap.linearize.autograd import AutogradLinearizer
from neuralmap.outputs import RunCounts, StudyOutputs, verdict
from neuralmap.studies.base import StudyConfig
from neuralmap.studies.maps import check_map_tile, find_tile_maps
from neuralmap.studies.rate_distortion import bd_rate, bytes_at_error, pareto_front
from neuralmap.studies.setup import prepare_tan
from neuralmap.terrain.bake import bake_to_grid
from neuralmap.terrain.blockwise import BlockwiseTerrainNet
from neuralmap.terrain.codecs import CODEC_LABELS, GRID_CODECS, compress_grid
from neuralmap.terrain.export import load_map, save_map
from neuralmap.terrain.grid import GridTerrain
from neuralmap.terrain.quantize import QUANT_SCHEMES

__all__ = ["MapEntry", "MapSizeStudyConfig", "pareto_front", "run"]

#: Relative navigation-RMSE tolerance of "equal navigation accuracy".
EQUAL_ACCURACY = 0.05
#: Storage target of a neural map, as a fraction of the raw float32 grid.
TARGET_FRACTION = 0.25
#: Node-RMSE target of that neural map, metres.
TARGET_RMSE_M = 3.0
#: Bytes target of a neural map against the best codec at equal error (and at equal
#: navigation accuracy against the smallest compressed grid).
TARGET_BYTES_RATIO = 0.7
#: The anchor codec of the BD-rate.
BD_ANCHOR = "jpeg2k"
#: Codecs a neural map is compared with at equal maximum error.
MAX_ERROR_CODECS = ("lerc", "jpegls")


@dataclass
class MapSizeStudyConfig(StudyConfig):
    """Options of the map size study (``study: map_size``).

    Attributes:
        scenario: Scenario name (``configs/scenarios/<name>.yaml``) or a YAML path.
        n_runs: Monte Carlo trajectories (the same truth for every map).
        codecs: Grid codecs (`neuralmap.terrain.codecs.GRID_CODECS`).
        max_errors: Maximum node errors (m, each > 0) of every codec.
        decimations: Decimation factors (1 = full resolution; 2, 4: coarser grids
            interpolated back, bicubic).
        decimated_max_errors: Maximum errors used for decimated grids (``None`` = the
            same as ``max_errors``).
        neural_maps: Map files (anything `load_map` reads:
            blockwise ``neural_map.pt``, latent-grid bitstreams, ...); ``None`` = the newest
            map of the scenario's tile in every experiment folder of ``runs_dir``; ``[]`` =
            no neural maps (codecs only). Every map must record the tile it was fitted to.
        quantizations: Stored forms of each blockwise map: ``none`` (float32) and schemes
            of `neuralmap.terrain.quantize.QUANT_SCHEMES` (other maps are measured
            as stored).
        baked: Stored forms (of ``quantizations``) also evaluated *baked*: the loaded map
            evaluated once at the DEM nodes at load time and queried as a bicubic grid
            (`neuralmap.terrain.bake.bake_to_grid`): the neural map's storage with
            the grid's query speed.
        map_error_points: Random points between the nodes for the errors against truth.
        query_points: Points of the throughput measurement.
        pcrb_factor: Divergence when the final error exceeds this times the final PCRB.
        divergence_sigma: Divergence when the final error exceeds this many times the
            filter's own 1σ horizontal bound.
        bootstrap: Resamples of the paired bootstrap of the navigation RMSE.
        confidence: Two-sided coverage of the bootstrap intervals.
    """

    study: str = "map_size"
    experiment: str = "map_size"
    threads: int | None = 1
    progress: bool = False
    scenario: str = "jacksboro"
    n_runs: int = 500
    codecs: list[str] = field(
        default_factory=lambda: ["lerc", "jpegls", "jpeg2k", "zstd", "sz3"])
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
    bootstrap: int = 2000
    confidence: float = 0.95

    def validate(self) -> None:
        """Checks values; raises `NeuralMapError` naming the option and the fix."""
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
        if self.bootstrap < 100 or not (0.5 <= self.confidence < 1.0):
            raise NeuralMapError(
                f"--bootstrap must be >= 100 and --confidence in [0.5, 1), got "
                f"{self.bootstrap}, {self.confidence}. Try 2000 and 0.95."
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


def build_grid_maps(tile: Any, config: MapSizeStudyConfig) -> list[MapEntry]:
    """The raw float32 grid and every codec × max error × decimation of the config."""
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


def map_family(net: nn.Module) -> str:
    """Family label of a neural map: its ``map_family`` attribute, else from its class
    (``BlockwiseTerrainNet`` -> ``"neural blockwise"``)."""
    family = getattr(net, "map_family", None)
    if family:
        return f"neural {family}"
    name = type(net).__name__
    for suffix in ("TerrainNet", "TerrainMap", "Map", "Net"):
        if name.endswith(suffix) and len(name) > len(suffix):
            name = name[: -len(suffix)]
            break
    return f"neural {name.lower()}"


def build_neural_maps(
    paths: list[Path], quantizations: list[str], folder: Path, *, tile: Any,
    baked: list[str] | None = None, scenario_name: str = "",
) -> list[MapEntry]:
    """Every map in every stored form, written to ``folder`` and read back with load_map.

    Blockwise maps are re-saved in each form of ``quantizations``; any other map is
    measured as the file it is (its size on disk). Forms listed in ``baked`` are added
    once more, baked onto the tile's nodes (bicubic).

    Raises:
        NeuralMapError: A map of another tile, or one that records no tile (as the TAN
            study refuses it).
    """
    folder.mkdir(parents=True, exist_ok=True)
    entries = []
    for path in paths:
        net = load_map(path)
        check_map_tile(net, tile, map_path=path, scenario_name=scenario_name)
        label = path.parent.parent.name if path.parent.name.startswith("version_") else path.stem
        family = map_family(net)
        n_params = int(getattr(net, "num_parameters", 0)
                       or sum(p.numel() for p in net.parameters()))
        forms = quantizations if isinstance(net, BlockwiseTerrainNet) else ["stored"]
        for scheme in forms:
            if scheme == "stored":
                out, loaded = path, net
            else:
                out = save_map(net, folder / f"{label}_{scheme}.pt",
                               metrics=getattr(net, "metrics", {}),
                               quantization=None if scheme == "none" else scheme)
                loaded = load_map(out)
            info = {"source": str(path), "file": out.name, "quantization": scheme,
                    "num_parameters": n_params, "config": dict(getattr(net, "config", {}))}
            size = os.path.getsize(out)
            entries.append(MapEntry(f"{label} {scheme}", family, "neural", size, loaded, info))
            if scheme in (baked or []):
                grid = bake_to_grid(loaded, tile)
                grid.tile_fingerprint = loaded.tile_fingerprint  # a map of the same tile
                entries.append(MapEntry(f"{label} {scheme} baked", f"{family} baked", "neural",
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
    entry: MapEntry, tile: Any, truth_model: nn.Module, *, n_points: int, seed: int,
    dem_bicubic: nn.Module | None = None,
) -> dict[str, Any]:
    """Node errors, errors and slope errors against the truth between the nodes.

    Between-node points are uniform over the tile (seeded; the same for every map).

    Returns:
        ``node_rmse_m``, ``node_max_m`` (against the DEM nodes), ``truth_rmse_m``,
        ``truth_max_m``, ``truth_mse_m2`` (height minus truth at random points),
        ``slope_rmse`` (norm of the slope error vector, m/m, same points); with
        ``dem_bicubic`` also ``offnode_rmse_m`` / ``offnode_max_m`` (against the bicubic
        DEM at the same points) and, for neural maps that are not grids,
        ``own_nodes_truth_rmse_m``: the bicubic interpolation of the map's own node
        values against the truth (what the map's nodes would give as a grid).
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
    height = torch.cat(heights)
    truth = torch.cat(true_h)
    err = height - truth
    slope_err = torch.cat(slopes) - torch.cat(true_s)
    out: dict[str, Any] = {
        "node_rmse_m": float(np.sqrt(np.mean(node_err**2))),
        "node_max_m": float(np.abs(node_err).max()),
        "truth_rmse_m": float(err.square().mean().sqrt()),
        "truth_max_m": float(err.abs().max()),
        "truth_mse_m2": float(err.square().mean()),
        "slope_rmse": float(slope_err.square().sum(-1).mean().sqrt()),
    }
    if dem_bicubic is not None:
        with torch.no_grad():
            ref = torch.cat([dem_bicubic(p).double() for p in torch.split(xy, 65536)])
        out["offnode_rmse_m"] = float((height - ref).square().mean().sqrt())
        out["offnode_max_m"] = float((height - ref).abs().max())
    if entry.kind == "neural" and not isinstance(entry.terrain, GridTerrain):
        own = bake_to_grid(entry.terrain, tile)
        with torch.no_grad():
            own_h = torch.cat([own(p).double() for p in torch.split(xy, 65536)])
        out["own_nodes_truth_rmse_m"] = float((own_h - truth).square().mean().sqrt())
    return out


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
    floor = 0.01  # lossless maps (error 0) are drawn at 1 cm on the log axis
    fig = Figure(figsize=(7.5, 5.0))
    ax = fig.add_subplot()
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


def _run_masks(run: Any, metrics: dict[str, Any]) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Per-run mean squared position error over the scored (second-half) samples and the
    included / converged masks, as `navigation_metrics`
    defines them."""
    err = run.err.detach().to("cpu", torch.float64)
    P = run.P.detach().to("cpu", torch.float64)
    half = err.shape[1] // 2
    finite = torch.isfinite(err).all(dim=2).all(dim=1) & torch.isfinite(P).flatten(1).all(1)
    included = ~run.off_map.detach().cpu().bool() & finite
    healthy = run.healthy.detach().cpu().bool()
    diverged = torch.as_tensor(metrics["diverged"], dtype=torch.bool)
    converged = included & healthy & ~diverged
    e2 = err[..., 0] ** 2 + err[..., 1] ** 2
    msq = torch.where(included, e2[:, half:].mean(dim=1), torch.zeros(err.shape[0],
                                                                        dtype=torch.float64))
    return msq, included, converged


def run(config: MapSizeStudyConfig, outputs: StudyOutputs) -> None:
    """Runs the map size study and fills ``outputs``.

    Raises:
        NeuralMapError: Bad input (scenario, maps of another tile, codecs missing...).
    """
    started = time.perf_counter()
    device, dtype = config.torch_device, config.torch_dtype
    # the shared setup: scenario, tile, seed and truth terrain (the maps under test are
    # this study's subject, built below; no linearisation method of the setup's own)
    setup = prepare_tan(scenario=config.scenario, methods=[], map_path=None,
                        runs_dir=config.runs_dir, seed=config.seed, neural_fit_variance=0.0,
                        map_error_points=config.map_error_points, device=device)
    setup.pin(config)
    scenario, tile, seed, truth_terrain = (setup.scenario, setup.tile, setup.seed,
                                           setup.truth_terrain)
    if config.neural_maps is None:
        paths = find_tile_maps(config.runs_dir, tile.fingerprint())
    else:
        paths = [Path(p) for p in config.neural_maps]
    config.neural_maps = [str(p) for p in paths]
    # neural maps first: a map of another tile is refused before the codecs' work
    neural_entries = build_neural_maps(paths, config.quantizations, outputs.dir / "maps",
                                       tile=tile, baked=config.baked,
                                       scenario_name=scenario.name)
    raw_bytes = int(tile.heights.size * 4)
    dem_bicubic = GridTerrain(tile, method="bicubic")

    entries = build_grid_maps(tile, config) + neural_entries
    print(f"map_size: {len(entries)} maps ({len(paths)} neural map file(s)) on tile "
          f"{tile.name} {tile.shape}, scenario {scenario.name}, {config.n_runs} runs", flush=True)

    gen = torch.Generator().manual_seed(seed)
    xmin, xmax, ymin, ymax = tile.extent
    u = torch.rand(config.query_points, 2, generator=gen, dtype=torch.float64)
    query_xy = torch.stack([xmin + u[:, 0] * (xmax - xmin), ymin + u[:, 1] * (ymax - ymin)], -1)
    rows: list[dict[str, Any]] = []
    methods: dict[str, Any] = {}
    queries: dict[str, Any] = {}
    for entry in entries:
        quality = map_quality(entry, tile, truth_terrain.model,
                              n_points=config.map_error_points, seed=seed,
                              dem_bicubic=dem_bicubic)
        extra_variance = max(quality["truth_mse_m2"] - scenario.fit_variance_m2, 0.0)
        # the same robust linearisation for every map: autograd of its own surface with
        # the region variance over the position uncertainty
        methods[entry.name] = AutogradLinearizer(entry.terrain, fit_variance=extra_variance,
                                                 region_variance=True)
        queries[entry.name] = AutogradLinearizer(entry.terrain, fit_variance=extra_variance)
        xy_q = query_xy.to(_model_dtype(entry.terrain))
        rate = query_rate(queries[entry.name], xy_q)
        fast_rate = query_rate(lambda p, t=entry.terrain: _height_and_slope(t, p), xy_q)
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
                                   query_rate(queries[entries[0].name], ref_xy))
    rows[0]["fast_queries_per_s"] = max(
        rows[0]["fast_queries_per_s"],
        query_rate(lambda p, t=entries[0].terrain: _height_and_slope(t, p), ref_xy))
    ref_rate = rows[0]["queries_per_s"]
    ref_fast = rows[0]["fast_queries_per_s"]
    dem_truth = rows[0]["truth_rmse_m"]
    for row in rows:
        row["query_vs_bicubic"] = row["queries_per_s"] / ref_rate
        row["fast_query_vs_bicubic"] = row["fast_queries_per_s"] / ref_fast
        row["truth_vs_bicubic_dem"] = row["truth_rmse_m"] / dem_truth if dem_truth else None

    tick = time.perf_counter()
    truth, runs = run_monte_carlo(
        scenario, methods, n_runs=config.n_runs, seed=seed, progress=config.progress,
        device=device, dtype=dtype, tile=tile, truth_terrain=truth_terrain,
    )
    kept = truth.on_map.all(dim=1)
    bound = pcrb(truth, scenario, truth_terrain.model, runs=kept if bool(kept.any()) else None)
    pcrb_pos = pcrb_position(bound).detach().to("cpu", torch.float64)
    index = resample_index(config.n_runs, config.bootstrap, seed)
    per_run: dict[str, tuple[torch.Tensor, torch.Tensor, torch.Tensor]] = {}
    for row in rows:
        metrics = navigation_metrics(runs[row["name"]], pcrb_pos,
                                     pcrb_factor=config.pcrb_factor,
                                     divergence_sigma=config.divergence_sigma)
        per_run[row["name"]] = _run_masks(runs[row["name"]], metrics)
        row["nav_pcrb_ratio"] = metrics.get("pcrb_ratio_all")
        row["divergence_rate"] = metrics.get("divergence_rate")
        row["n_diverged"] = metrics.get("n_diverged")
        row["n_included"] = metrics.get("n_included")
        row["n_converged"] = metrics.get("n_converged")
        row["n_unhealthy"] = metrics.get("n_unhealthy")
    ref_msq, ref_inc, ref_conv = per_run[rows[0]["name"]]
    for row in rows:
        msq, inc, conv = per_run[row["name"]]
        for key, mask, ref_mask in (("nav_rmse", inc, ref_inc),
                                    ("nav_rmse_converged", conv, ref_conv)):
            figure = bootstrap_rmse(msq, mask, index, confidence=config.confidence)
            row[f"{key}_m"] = figure.value
            row[f"{key}_ci_m"] = [figure.low, figure.high]
            ratio, low, high = paired_ratio(msq, mask, ref_msq, ref_mask, index,
                                            confidence=config.confidence)
            row[f"{key}_vs_grid"] = ratio
            row[f"{key}_vs_grid_ci"] = [low, high]
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
            "every map": "autograd of the map's own surface (grids: the bicubic decoded "
                         "grid; neural maps: the network) with the region variance",
            "variance": "R + max(map MSE against truth - scenario fit variance, 0) + the "
                        "tangent plane's mean squared miss over the position covariance",
        },
        "bootstrap": {"resamples": config.bootstrap, "confidence": config.confidence,
                      "paired": True},
        "timing_s": {"navigation": nav_s, "total": time.perf_counter() - started},
        "config": asdict(config),
    })
    for row in rows:
        if row.get("nav_rmse_converged_m") is not None:
            outputs.log_scalar(f"map_size/nav_rmse_converged/{row['family']}",
                               row["nav_rmse_converged_m"], row["bytes"])
        outputs.log_scalar(f"map_size/node_rmse/{row['family']}", row["node_rmse_m"],
                           row["bytes"])


def _runs(row: dict[str, Any]) -> RunCounts:
    """The runs a verdict on this map rests on (numerical failures count against it)."""
    return RunCounts.from_metrics(row)


def _enough(row: dict[str, Any]) -> bool:
    """Enough converged runs for a verdict on this map (the rule of every study)."""
    return _runs(row).enough()


def _smallest(rows: list[dict[str, Any]], kind: str, ok: Any) -> dict[str, Any] | None:
    """The smallest map of ``kind`` whose row satisfies ``ok``."""
    hits = [r for r in rows if r["kind"] == kind and r["family"] != "raw grid" and ok(r)]
    return min(hits, key=lambda r: r["bytes"]) if hits else None


def _equal_accuracy(rows: list[dict[str, Any]], key: str) -> dict[str, Any]:
    """Smallest grid and neural map as accurate as the full grid on ``key``.

    "As accurate": the lower end of the paired bootstrap interval of the map's RMSE over
    the full grid's is at most ``1 + EQUAL_ACCURACY`` (the runs do not show the map more
    than 5 % worse), and the map has enough converged runs for a verdict.
    """
    ref = rows[0]

    def ok(r: dict[str, Any]) -> bool:
        low = (r.get(f"{key}_vs_grid_ci") or [None])[0]
        return _enough(r) and low is not None and low <= 1.0 + EQUAL_ACCURACY

    grid, neural = _smallest(rows, "grid", ok), _smallest(rows, "neural", ok)
    has_neural = any(r["kind"] == "neural" for r in rows)
    pick = ("name", "bytes", f"{key}_m", f"{key}_ci_m", f"{key}_vs_grid",
            f"{key}_vs_grid_ci", "n_diverged", "n_converged")
    ratio = (neural["bytes"] / grid["bytes"]) if neural and grid else None
    if not _enough(ref):
        outcome = verdict(None, runs=_runs(ref))
    elif not has_neural:
        outcome = verdict(None, detail="no neural map")
    else:
        outcome = verdict(neural is not None and (grid is None or ratio <= TARGET_BYTES_RATIO))
    return {
        "metric": key,
        "reference": ref.get(f"{key}_m"),
        "reference_ci": ref.get(f"{key}_ci_m"),
        "reference_diverged": ref.get("n_diverged"),
        "smallest_grid": grid and {k: grid.get(k) for k in pick},
        "smallest_neural": neural and {k: neural.get(k) for k in pick},
        "bytes_ratio": ratio,
        "verdict": outcome,
    }


def _families(rows: list[dict[str, Any]]) -> list[str]:
    return sorted({r["family"] for r in rows if r["kind"] == "neural"})


def _codec_points(rows: list[dict[str, Any]], codec: str | None) -> list[dict[str, Any]]:
    """Compressed-grid rows of ``codec`` (every decimation); ``None`` = every codec."""
    return [r for r in rows if r["kind"] == "grid" and r["family"] != "raw grid"
            and (codec is None or r.get("codec") == codec)]


def _summarise(rows: list[dict[str, Any]], raw_bytes: int) -> dict[str, Any]:
    """Fronts, figures of merit and targets from the per-map rows."""

    def compact_ok(r: dict[str, Any]) -> bool:
        return r["bytes"] <= TARGET_FRACTION * raw_bytes and r["node_rmse_m"] <= TARGET_RMSE_M

    groups = {"grid": [r for r in rows if r["kind"] == "grid"]}
    groups.update({f: [r for r in rows if r["family"] == f] for f in _families(rows)})
    fronts: dict[str, Any] = {}
    for group, pts in groups.items():
        for key in ("node_rmse_m", "node_max_m", "nav_rmse_converged_m", "nav_rmse_m"):
            idx = pareto_front([r["bytes"] for r in pts], [r.get(key) for r in pts])
            fronts[f"{group}:{key}"] = [
                {"name": pts[i]["name"], "bytes": pts[i]["bytes"], key: pts[i][key]} for i in idx
            ]
    anchor = _codec_points(rows, BD_ANCHOR)
    codecs = _codec_points(rows, None)
    bd: dict[str, Any] = {}
    for family in _families(rows):
        pts = groups[family]
        args = ([r["bytes"] for r in pts], [r["node_rmse_m"] for r in pts])
        bd[family] = {
            f"vs_{BD_ANCHOR}": bd_rate([r["bytes"] for r in anchor],
                                       [r["node_rmse_m"] for r in anchor], *args),
            "vs_best_codec": bd_rate([r["bytes"] for r in codecs],
                                     [r["node_rmse_m"] for r in codecs], *args),
        }
    at_max: list[dict[str, Any]] = []
    for r in rows:
        if r["kind"] != "neural":
            continue
        item: dict[str, Any] = {"name": r["name"], "bytes": r["bytes"],
                                "node_max_m": r["node_max_m"]}
        for codec in MAX_ERROR_CODECS:
            pts = _codec_points(rows, codec)
            need = bytes_at_error([p["bytes"] for p in pts], [p["node_max_m"] for p in pts],
                                  r["node_max_m"])
            item[f"{codec}_bytes"] = need
            item[f"vs_{codec}"] = r["bytes"] / need if need else None
        need = bytes_at_error([p["bytes"] for p in codecs], [p["node_rmse_m"] for p in codecs],
                              r["node_rmse_m"])
        item["best_codec_bytes_at_rmse"] = need
        item["vs_best_codec_at_rmse"] = r["bytes"] / need if need else None
        at_max.append(item)
    dem_truth = rows[0]["truth_rmse_m"]
    between = [
        {"name": r["name"], "truth_rmse_m": r["truth_rmse_m"], "bicubic_dem_m": dem_truth,
         "ratio": r["truth_vs_bicubic_dem"], "own_nodes_bicubic_m": r.get("own_nodes_truth_rmse_m"),
         "offnode_rmse_m": r.get("offnode_rmse_m"), "node_rmse_m": r["node_rmse_m"],
         "met": r["truth_rmse_m"] <= dem_truth}
        for r in rows if r["kind"] == "neural"]
    compact = _smallest(rows, "neural", compact_ok)
    neural_rows = [r for r in rows if r["kind"] == "neural"]
    return {
        "equal_accuracy_converged": _equal_accuracy(rows, "nav_rmse_converged"),
        "equal_accuracy_all_runs": _equal_accuracy(rows, "nav_rmse"),
        "bd_rate_node_rmse": bd,
        "at_equal_error": at_max,
        "between_nodes": between,
        "compact_target_map": compact and {
            k: compact[k] for k in ("name", "bytes", "fraction_of_raw", "node_rmse_m")},
        "target_compact_met": compact is not None if neural_rows else None,
        "target_between_nodes_met": all(b["met"] for b in between) if between else None,
        "fronts": fronts,
    }


def _fmt(value: float | None, spec: str = ".2f") -> str:
    return "n/a" if value is None else format(value, spec)


def _fmt_ci(ci: list[float | None] | None, spec: str = ".1f") -> str:
    if not ci or ci[0] is None:
        return "n/a"
    return f"[{ci[0]:{spec}}, {ci[1]:{spec}}]"


def _write_report(
    outputs: StudyOutputs, config: MapSizeStudyConfig, rows: list[dict[str, Any]],
    summary: dict[str, Any], *, raw_bytes: int, tile: Any, scenario: Any,
    truth_description: str,
) -> None:
    """Tables, fronts, targets and the paper's storage claim."""
    outputs.add_text(
        f"Tile **{tile.name}** ({tile.shape[0]} x {tile.shape[1]} nodes; raw float32 grid "
        f"{_fmt_bytes(raw_bytes)}), scenario **{scenario.name}**, {config.n_runs} Monte Carlo "
        f"runs, truth: {truth_description}. Codecs: "
        + "; ".join(CODEC_LABELS[c] for c in config.codecs)
        + ". Grids are decoded and interpolated bicubic. Every map is linearised by the same "
        "method: autograd of its own surface (grids: the bicubic interpolant; neural maps: "
        "the network) with the region variance (the tangent plane's mean squared miss over "
        "the position uncertainty) and R increased by the map's mean squared error against "
        "the truth beyond the scenario's fit variance. Navigation RMSE over the second half "
        f"of the flight, with {config.confidence:.0%} paired bootstrap intervals "
        f"({config.bootstrap} resamples of the runs). Stored bytes: codec payload + header; "
        "neural maps: the file. Query rates (fastest of 5 calls, one batch): 'M q/s' = the "
        "navigation linearizer's height + slope (autograd), 'fast' = analytic height + "
        "slope; ratios against the raw bicubic grid in the same run."
    )
    headers = ["map", "bytes", "bits/node", "% raw", "node RMSE m", "node max m",
               "truth RMSE m", "off-node vs bicubic m", "slope RMSE", "M q/s", "x bicubic",
               "fast x bicubic", "nav RMSE conv. m", "interval", "nav RMSE all m",
               "interval", "conv. x grid [interval]", "diverged"]
    table = [
        [r["name"], r["bytes"], r["bits_per_node"], 100 * r["fraction_of_raw"],
         r["node_rmse_m"], r["node_max_m"], r["truth_rmse_m"], r.get("offnode_rmse_m"),
         r["slope_rmse"], r["queries_per_s"] / 1e6, r["query_vs_bicubic"],
         r["fast_query_vs_bicubic"], r.get("nav_rmse_converged_m"),
         _fmt_ci(r.get("nav_rmse_converged_ci_m")), r.get("nav_rmse_m"),
         _fmt_ci(r.get("nav_rmse_ci_m")),
         f"{_fmt(r.get('nav_rmse_converged_vs_grid'))} "
         f"{_fmt_ci(r.get('nav_rmse_converged_vs_grid_ci'), '.2f')}",
         f"{r.get('n_diverged')}/{r.get('n_included')}"]
        for r in sorted(rows, key=lambda r: (r["kind"], r["family"], r["bytes"]))
    ]
    outputs.add_table("Every map", headers, table)
    neural = [r for r in rows if r["kind"] == "neural"]
    if neural:
        outputs.add_table(
            "Neural maps between the nodes (against the truth, same random points)",
            ["map", "node RMSE m", "off-node vs bicubic DEM m", "truth RMSE m",
             "bicubic DEM vs truth m", "x bicubic DEM", "own nodes bicubic vs truth m",
             "<= bicubic DEM"],
            [[b["name"], b["node_rmse_m"], b["offnode_rmse_m"], b["truth_rmse_m"],
              b["bicubic_dem_m"], b["ratio"], b["own_nodes_bicubic_m"],
              "yes" if b["met"] else "no"] for b in summary["between_nodes"]])
        outputs.add_table(
            "Neural maps at equal error (bytes over the codec's front, interpolated)",
            ["map", "bytes", "node max m", "x LERC", "x JPEG-LS", "x best codec at node RMSE"],
            [[a["name"], a["bytes"], a["node_max_m"], _fmt(a["vs_lerc"]), _fmt(a["vs_jpegls"]),
              _fmt(a["vs_best_codec_at_rmse"])] for a in summary["at_equal_error"]])
        outputs.add_table(
            "BD-rate on the node-RMSE front (negative = fewer bytes than the anchor)",
            ["family", "vs JPEG 2000", "vs best codec (all codecs' front)"],
            [[f, _fmt_pct(v[f"vs_{BD_ANCHOR}"]), _fmt_pct(v["vs_best_codec"])]
             for f, v in summary["bd_rate_node_rmse"].items()])
    front_rows = []
    for key, front in summary["fronts"].items():
        group, metric = key.split(":")
        front_rows += [[group, metric, p["name"], p["bytes"], p[metric]] for p in front]
    outputs.add_table("Rate-distortion fronts", ["family", "error", "map", "bytes", "error"],
                      front_rows)
    converged = summary["equal_accuracy_converged"]
    all_runs = summary["equal_accuracy_all_runs"]
    _plot_front(outputs, rows, key="node_rmse_m", ylabel="RMSE at the DEM nodes (m)",
                name="bytes_vs_node_rmse", raw_bytes=raw_bytes,
                caption="Stored bytes vs node RMSE: grid codecs and neural maps "
                        "(lossless maps drawn at 0.01 m)")
    _plot_front(outputs, rows, key="node_max_m", ylabel="max |error| at the DEM nodes (m)",
                name="bytes_vs_max_error", raw_bytes=raw_bytes,
                caption="Stored bytes vs maximum node error: grid codecs and neural maps "
                        "(lossless maps drawn at 0.01 m)")
    ref_conv = converged["reference"]
    _plot_front(outputs, rows, key="nav_rmse_converged_m",
                ylabel="converged-run position RMSE (m)", name="bytes_vs_nav_rmse_converged",
                raw_bytes=raw_bytes,
                reference=None if ref_conv is None else (1 + EQUAL_ACCURACY) * ref_conv,
                caption="Stored bytes vs navigation RMSE of the converged runs (every map "
                        "linearised with the region variance)")
    _plot_front(outputs, rows, key="nav_rmse_m", ylabel="all-run position RMSE (m)",
                name="bytes_vs_nav_rmse", raw_bytes=raw_bytes,
                caption="Stored bytes vs navigation RMSE over all runs (second half of the "
                        "flight)")

    if not neural:
        compact_text = "no neural map was given (codecs only)"
        compact_verdict = verdict(None, detail="no neural map")
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
    outputs.add_claim(
        "toolkit target",
        f"a neural map <= {TARGET_FRACTION:.0%} of the raw float32 grid with node RMSE "
        f"<= {TARGET_RMSE_M:g} m", compact_text, compact_verdict)
    bd_text, bd_verdict = _bd_claim(summary)
    outputs.add_claim(
        "toolkit target",
        f"at equal node RMSE a neural map <= {TARGET_BYTES_RATIO:g} x the best codec's bytes "
        f"(BD-rate <= {TARGET_BYTES_RATIO - 1:.0%} against JPEG 2000)", bd_text, bd_verdict)
    between_text, between_verdict = _between_claim(summary)
    outputs.add_claim(
        "toolkit target",
        "between the nodes every neural map is no worse against the truth than the bicubic "
        "DEM", between_text, between_verdict)
    outputs.add_claim(
        "toolkit target",
        f"at equal navigation accuracy (converged-run RMSE, paired interval within "
        f"{EQUAL_ACCURACY:.0%} of the full grid's) the smallest neural map <= "
        f"{TARGET_BYTES_RATIO:g} x the smallest compressed grid",
        _equal_accuracy_text(converged, "converged-run RMSE") + "; over all runs: "
        + _equal_accuracy_text(all_runs, "all-run RMSE"), converged["verdict"],
        runs=RunCounts.weakest(*(_runs(r) for r in rows if r.get("n_included") is not None)))
    storage_text, storage_verdict = _storage_claim(rows, raw_bytes)
    outputs.add_claim("SEEDS 004", "the neural map needs less storage than the grid",
                      storage_text, storage_verdict)


def _fmt_pct(value: float | None) -> str:
    return "n/a (fronts do not overlap)" if value is None else f"{100 * value:+.1f} %"


def _bd_claim(summary: dict[str, Any]) -> tuple[str, str]:
    """Measured text and verdict of the BD-rate target."""
    bd = summary["bd_rate_node_rmse"]
    if not bd:
        return "no neural map measured", verdict(None, detail="no neural map")
    parts = [f"{f}: {_fmt_pct(v[f'vs_{BD_ANCHOR}'])} vs JPEG 2000, "
             f"{_fmt_pct(v['vs_best_codec'])} vs the best codec" for f, v in bd.items()]
    values = [v[f"vs_{BD_ANCHOR}"] for v in bd.values() if v[f"vs_{BD_ANCHOR}"] is not None]
    if not values:
        return "; ".join(parts), verdict(None, detail="no overlap with the JPEG 2000 front")
    return "; ".join(parts), verdict(min(values) <= TARGET_BYTES_RATIO - 1.0)


def _between_claim(summary: dict[str, Any]) -> tuple[str, str]:
    between = summary["between_nodes"]
    if not between:
        return "no neural map measured", verdict(None, detail="no neural map")
    worst = max(between, key=lambda b: b["ratio"] or 0.0)
    n_met = sum(b["met"] for b in between)
    text = (f"{n_met} of {len(between)} neural maps within the bicubic DEM's "
            f"{worst['bicubic_dem_m']:.2f} m; worst {worst['name']} {worst['truth_rmse_m']:.2f} m "
            f"({_fmt(worst['ratio'])} x; its node RMSE {worst['node_rmse_m']:.2f} m, the "
            f"bicubic of its own node values {_fmt(worst['own_nodes_bicubic_m'])} m)")
    return text, verdict(n_met == len(between), partly=n_met > 0)


def _equal_accuracy_text(check: dict[str, Any], what: str) -> str:
    """One sentence on an equal-accuracy check."""
    key, ref = check["metric"], check["reference"]
    if ref is None:
        return f"{what}: the full grid scored no run"
    grid, neural = check["smallest_grid"], check["smallest_neural"]
    text = (f"{what} of the full grid {ref:.1f} m {_fmt_ci(check['reference_ci'])}, "
            f"{check['reference_diverged']} diverged: ")

    def one(r: dict[str, Any]) -> str:
        return (f"{r['name']} {_fmt_bytes(r['bytes'])} ({r[f'{key}_m']:.1f} m, "
                f"{r[f'{key}_vs_grid']:.2f} x grid {_fmt_ci(r[f'{key}_vs_grid_ci'], '.2f')})")

    text += f"smallest grid {one(grid)}" if grid else "no compressed grid as accurate"
    if neural:
        text += f", smallest neural map {one(neural)}"
        if grid:
            text += f" = {check['bytes_ratio']:.2f} x the grid's bytes"
    else:
        text += ", no neural map as accurate"
    return text


def _storage_claim(rows: list[dict[str, Any]], raw_bytes: int) -> tuple[str, str]:
    """Paper 004's storage claim against the measured fronts, at equal max node error.

    Every neural map is compared with the smallest grid (the raw float32 grid included:
    lossless, it is as accurate as any map) whose maximum node error is no larger.
    """
    neural = [r for r in rows if r["kind"] == "neural"]
    if not neural:
        return "no neural map measured", verdict(None, detail="no neural map")
    parts, beaten = [], 0
    for r in sorted(neural, key=lambda r: r["bytes"]):
        grids = [g for g in rows if g["kind"] == "grid" and g["node_max_m"] <= r["node_max_m"]]
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
               f"float32 grid; {beaten} of {len(neural)} are larger than a grid (raw or "
               "compressed) of equal or smaller maximum node error: ")
    return summary + "; ".join(parts), storage_verdict
