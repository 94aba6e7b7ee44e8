"""The terrain-aided navigation Monte Carlo study (SEEDS 004): methods against the PCRB.

Loads the neural map of the latest ``python train.py`` run (or ``--map PATH``), flies the
scenario's Monte Carlo trajectories once over the scenario's truth terrain, runs the
batched TAN EKF with every linearisation method on the same truth, computes the posterior
Cramér-Rao bound and the metrics, and writes the report, results.json, plots and
TensorBoard events.

Examples:
    python evaluate.py
    python evaluate.py --n_runs 200 --methods [neural,bilinear,lsq_adaptive]
    python evaluate.py --map runs/jacksboro/version_3/neural_map.pt --scenario paper
    python evaluate.py --config configs/tan_tiny.yaml
"""

from __future__ import annotations

import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.linearize.factory import LINEARIZER_NAMES, TERRAIN_MODEL_METHODS
from neuralmap.studies.base import StudyConfig
from neuralmap.studies.maps import check_map_tile, resolve_map_path
from neuralmap.studies.outputs import StudyOutputs
from neuralmap.studies.trajectories import write_trajectories

__all__ = ["DEFAULT_METHODS", "TanStudyConfig", "build_methods", "run"]

#: Methods evaluated when ``--methods`` is not given.
DEFAULT_METHODS: tuple[str, ...] = (
    "neural",
    "neural_region",
    "bilinear",
    "nine_point",
    "mean_point",
    "lsq_adaptive",
    "lsq_min",
)

_FIGURES = {
    "error_vs_time": "Horizontal position RMSE vs time, with the PCRB",
    "trajectories": "Trajectories over the tile (truth and estimates)",
    "final_error_hist": "Final horizontal error",
}


@dataclass
class TanStudyConfig(StudyConfig):
    """Options of the TAN Monte Carlo study (``study: tan``).

    Attributes:
        map: Exported neural map (``neural_map.pt``); ``None`` = the newest
            ``<runs_dir>/*/version_*/neural_map.pt`` of the scenario's tile.
        scenario: Scenario name (``configs/scenarios/<name>.yaml``) or a YAML path.
        n_runs: Monte Carlo trajectories (the same truth for every method).
        methods: Linearisation methods to compare; ``neural`` uses the map with autograd.
        neural_fit_variance: Extra variance (m²) the neural methods add to R for the map
            error. ``None`` = measured: the map's mean squared error against the
            scenario's truth terrain at seeded random points between the nodes, less the
            scenario's ``fit_variance_m2`` that every method gets.
        map_error_points: Random points for that measurement.
        n_plot_trajectories: Trajectories drawn over the hillshade.
        pcrb_factor: Divergence when the final error exceeds this times the final PCRB.
        divergence_sigma: Divergence when the final error exceeds this many times the
            filter's own 1σ horizontal bound ``sqrt(P_xx + P_yy)`` (9 = 3 × the 3σ bound).
    """

    experiment: str = "evaluate"
    map: str | None = None
    scenario: str = "jacksboro"
    n_runs: int = 1000
    methods: list[str] = field(default_factory=lambda: list(DEFAULT_METHODS))
    neural_fit_variance: float | None = None
    map_error_points: int = 20000
    n_plot_trajectories: int = 5
    pcrb_factor: float = 5.0
    divergence_sigma: float = 9.0

    def validate(self) -> None:
        """Checks values; raises :class:`NeuralMapError` naming the option and the fix."""
        super().validate()
        if self.n_runs < 1:
            raise NeuralMapError(f"--n_runs must be >= 1, got {self.n_runs}.")
        if not self.methods:
            raise NeuralMapError(
                f"--methods is empty; pick one or more of {', '.join(LINEARIZER_NAMES)}."
            )
        unknown = [m for m in self.methods if m not in LINEARIZER_NAMES]
        if unknown:
            raise NeuralMapError(
                f"--methods: unknown method(s) {unknown}; known: {', '.join(LINEARIZER_NAMES)}."
            )
        if len(set(self.methods)) != len(self.methods):
            raise NeuralMapError(f"--methods lists a method twice: {self.methods}.")
        if self.neural_fit_variance is not None and not self.neural_fit_variance >= 0:
            raise NeuralMapError(
                f"--neural_fit_variance must be >= 0 m^2 (or null), got {self.neural_fit_variance}."
            )
        if self.map_error_points < 100:
            raise NeuralMapError(f"--map_error_points must be >= 100, got {self.map_error_points}.")
        if self.n_plot_trajectories < 0:
            raise NeuralMapError(
                f"--n_plot_trajectories must be >= 0, got {self.n_plot_trajectories}."
            )
        if not (self.pcrb_factor > 0 and self.divergence_sigma > 0):
            raise NeuralMapError(
                f"--pcrb_factor and --divergence_sigma must be > 0, got {self.pcrb_factor}, "
                f"{self.divergence_sigma}."
            )

    @property
    def needs_map(self) -> bool:
        """Whether any method needs the neural map."""
        return any(m in TERRAIN_MODEL_METHODS for m in self.methods)


def build_methods(
    names: list[str],
    *,
    tile: Any,
    terrain_map: Any,
    device: torch.device,
    fit_variance: float = 0.0,
) -> dict[str, Any]:
    """One linearizer per method name (``neural*`` = the map with autograd).

    Args:
        names: Method names (:data:`neuralmap.linearize.factory.LINEARIZER_NAMES`).
        tile: The scenario's DEM tile (grid and plane-fit methods).
        terrain_map: The loaded neural map (None when no neural method is asked for).
        device: Device the filters run on.
        fit_variance: The neural map's error variance (m²), its linearisation variance.

    Returns:
        Method name -> :class:`~neuralmap.linearize.base.Linearizer`, in ``names`` order.
    """
    from neuralmap.linearize.factory import make_linearizer

    methods: dict[str, Any] = {}
    for name in names:
        if name in TERRAIN_MODEL_METHODS:
            linearizer = make_linearizer(
                name, tile=tile, terrain=terrain_map, fit_variance=fit_variance
            )
        else:
            linearizer = make_linearizer(name, tile=tile)
        methods[name] = linearizer.to(device)
    return methods


def _final_horizontal_errors(run: Any) -> np.ndarray:
    """``(M,)`` final horizontal errors (m) of the runs that stayed on the map."""
    err = run.err[:, -1, :2].detach().to("cpu", torch.float64)
    keep = ~run.off_map.detach().cpu()
    return err[keep].norm(dim=-1).numpy()


def _plot_indices(truth: Any, runs: dict[str, Any], count: int) -> list[int]:
    """The first ``count`` runs that stayed on the map for every method."""
    bad = ~truth.on_map.all(dim=1).cpu()
    for run in runs.values():
        bad |= run.off_map.cpu()
    return torch.nonzero(~bad).flatten()[:count].tolist()


def _write_figures(outputs: StudyOutputs, *, config: TanStudyConfig, results: dict[str, Any],
                   truth: Any, runs: dict[str, Any], tile: Any, pcrb_pos: np.ndarray
                   ) -> dict[str, str]:
    """Plots into the run folder and TensorBoard; returns caption -> file name."""
    from neuralmap.io import atomic_write_figure
    from neuralmap.viz.navigation import (
        plot_error_vs_time,
        plot_final_error_histogram,
        plot_trajectories,
    )

    curves = results["curves"]
    t = np.asarray(curves["t"])
    figures = {
        "error_vs_time": plot_error_vs_time(
            t,
            {m: curves[m]["rmse_pos_curve"] for m in runs},
            pcrb_pos,
            converged_curves={m: curves[m]["rmse_pos_converged_curve"] for m in runs},
        ),
    }
    idx = _plot_indices(truth, runs, config.n_plot_trajectories)
    truth_xy = truth.pos[idx, :, :2].detach().cpu().double().numpy()
    figures["trajectories"] = plot_trajectories(
        tile,
        truth_xy,
        {m: run.estimate_xy(truth)[idx].detach().cpu().double().numpy() for m, run in runs.items()},
    )
    final_errors = {m: _final_horizontal_errors(run) for m, run in runs.items()}
    figures["final_error_hist"] = plot_final_error_histogram(
        final_errors, pcrb_final=float(pcrb_pos[-1])
    )
    for name, fig in figures.items():
        atomic_write_figure(outputs.dir / f"{name}.png", fig)
    if config.tensorboard:
        from neuralmap.viz.tensorboard_nav import log_navigation

        log_navigation(
            outputs.dir,
            curves={m: curves[m] for m in runs},
            pcrb_pos=pcrb_pos,
            final_errors=final_errors,
            summary={m: results["methods"][m] for m in runs},
            figures=figures,
        )
    return {_FIGURES[name]: f"{name}.png" for name in figures}


@dataclass
class TanSetup:
    """What a TAN study flies: scenario, tile, truth terrain, map and methods.

    Attributes:
        scenario: The validated scenario.
        tile: Its DEM tile.
        seed: The seed used.
        truth_terrain: The truth terrain (one world per seed).
        terrain_map: The neural map (None when no method needs it).
        map_path: Its file.
        map_error: Its error against the truth between nodes (empty without a map).
        fit_variance: The extra R of the neural methods, m².
        methods: Method name -> linearizer.
    """

    scenario: Any
    tile: Any
    seed: int
    truth_terrain: Any
    terrain_map: Any
    map_path: Path | None
    map_error: dict[str, Any]
    fit_variance: float
    methods: dict[str, Any]

    def map_info(self) -> dict[str, Any]:
        """The map's description for results.json."""
        terrain_map = self.terrain_map
        return {
            "path": str(self.map_path) if self.map_path else None,
            "tile_name": getattr(terrain_map, "tile_name", ""),
            "tile_fingerprint": getattr(terrain_map, "tile_fingerprint", ""),
            "model": type(terrain_map).__name__ if terrain_map is not None else None,
            "num_parameters": int(sum(p.numel() for p in terrain_map.parameters()))
            if terrain_map is not None else None,
            "fit_metrics": dict(getattr(terrain_map, "metrics", None) or {}),
            "error_vs_truth": self.map_error,
            "neural_extra_variance_m2": self.fit_variance,
        }


def prepare(config: Any, *, scenario: Any = None) -> TanSetup:
    """Loads the scenario, map and truth terrain and builds the methods of a TAN study.

    ``config`` needs ``scenario``, ``map``, ``runs_dir``, ``methods``, ``seed``,
    ``neural_fit_variance``, ``map_error_points`` and the device; its ``map`` and ``seed``
    are set to the values actually used (so the saved config.yaml reruns exactly this).

    Raises:
        NeuralMapError: Bad scenario, no map, a map of another tile.
    """
    from neuralmap.nav.map_error import measure_map_error
    from neuralmap.nav.scenario import load_scenario, scenario_tile
    from neuralmap.nav.truth_terrain import true_terrain
    from neuralmap.terrain.export import load_map

    scenario = load_scenario(config.scenario) if scenario is None else scenario
    tile = scenario_tile(scenario)
    map_path: Path | None = None
    terrain_map = None
    if any(m in TERRAIN_MODEL_METHODS for m in config.methods):
        map_path = resolve_map_path(config.map, config.runs_dir,
                                    tile_fingerprint=tile.fingerprint())
        terrain_map = load_map(map_path)
        check_map_tile(terrain_map, tile, map_path=map_path, scenario_name=scenario.name)
    seed = scenario.seed if config.seed is None else int(config.seed)
    config.map = str(map_path) if map_path is not None else config.map
    config.seed = seed
    truth_terrain = true_terrain(scenario, tile, seed=seed)
    map_error: dict[str, Any] = {}
    if terrain_map is not None:
        map_error = measure_map_error(terrain_map, truth_terrain.model, tile,
                                      n_points=config.map_error_points, seed=seed)
    if config.neural_fit_variance is None:
        mse = map_error.get("mse_m2", 0.0) or 0.0
        fit_variance = max(float(mse) - scenario.fit_variance_m2, 0.0)
    else:
        fit_variance = float(config.neural_fit_variance)
    methods = build_methods(config.methods, tile=tile, terrain_map=terrain_map,
                            device=config.torch_device, fit_variance=fit_variance)
    return TanSetup(scenario, tile, seed, truth_terrain, terrain_map, map_path, map_error,
                    fit_variance, methods)


def void_exposure(tile: Any, truth: Any) -> dict[str, int]:
    """Truth samples (and runs) whose terrain height is read from a DEM void.

    Under a void the truth terrain is the grid's nearest-node fill, not real terrain; the
    count goes into the report so that a study over voids is never silently wrong.
    """
    if tile.n_void == 0:
        return {"samples": 0, "runs": 0}
    under = tile.void_under(truth.pos[..., :2].detach().cpu().double().numpy(), halo=1)
    return {"samples": int(under.sum()), "runs": int(under.any(axis=1).sum())}


def run(config: TanStudyConfig, outputs: StudyOutputs) -> None:
    """Runs the TAN Monte Carlo study and fills ``outputs``.

    Raises:
        NeuralMapError: Bad input (no map, tile mismatch, bad scenario, device...).
    """
    from neuralmap.nav.metrics import divergence_rule, navigation_metrics
    from neuralmap.nav.monte_carlo import run_monte_carlo
    from neuralmap.nav.pcrb import pcrb, pcrb_position
    from neuralmap.studies.tan_report import (
        build_results,
        check_claims,
        format_table,
        render_report,
    )

    started = time.perf_counter()
    timing: dict[str, float] = {}
    device, dtype = config.torch_device, config.torch_dtype
    setup = prepare(config)
    scenario, tile, seed = setup.scenario, setup.tile, setup.seed
    truth_terrain, methods, map_path = setup.truth_terrain, setup.methods, setup.map_path
    print(
        f"evaluate: map {map_path or '(none needed)'} | scenario {scenario.name} (tile "
        f"{tile.name}, {scenario.n_steps} steps of {scenario.dt:g} s, truth: "
        f"{truth_terrain.description}) | {config.n_runs} runs | methods "
        f"{', '.join(config.methods)} | {config.dtype} on {device}",
        flush=True,
    )
    timing["setup"] = time.perf_counter() - started

    truth, runs = run_monte_carlo(
        scenario, methods, n_runs=config.n_runs, seed=seed, progress=config.progress,
        device=device, dtype=dtype, tile=tile, truth_terrain=truth_terrain,
    )
    for name, filter_run in runs.items():
        timing[f"filter_{name}"] = float(filter_run.elapsed_s)
    voids = void_exposure(tile, truth)
    if voids["samples"]:
        print(f"warning: {voids['samples']} truth samples ({voids['runs']} runs) fly over DEM "
              "voids: the truth there is a nearest-node fill of the DEM, not terrain. They stay "
              "in the metrics and are counted in the report.", flush=True)
    kept = truth.on_map.all(dim=1)  # the metrics drop runs whose truth left the map
    if not bool(kept.any()):
        raise NeuralMapError(
            f"no run could be scored: all {config.n_runs} truth trajectories left the tile "
            f"{tile.name!r} (extent {tuple(round(e) for e in tile.extent)} m) or started off "
            "it. Move the scenario's start_xy/waypoints inside the tile, shorten duration_s, "
            "or lower start_spread_m."
        )

    tick = time.perf_counter()
    bound = pcrb(truth, scenario, truth_terrain.model, runs=kept)
    pcrb_pos = pcrb_position(bound).detach().to("cpu", torch.float64).numpy()
    timing["pcrb"] = time.perf_counter() - tick

    method_metrics = {
        name: navigation_metrics(filter_run, torch.as_tensor(pcrb_pos),
                                 pcrb_factor=config.pcrb_factor,
                                 divergence_sigma=config.divergence_sigma)
        for name, filter_run in runs.items()
    }
    n_truth_off = int((~truth.on_map.all(dim=1)).sum())
    off_map = {
        "truth": n_truth_off,
        "per_method": {name: int(r.off_map.sum()) for name, r in runs.items()},
    }
    config_dump = asdict(config)
    results = build_results(
        method_metrics=method_metrics,
        t=truth.t.detach().cpu().tolist(),
        pcrb_pos=pcrb_pos.tolist(),
        divergence_rule=divergence_rule(config.pcrb_factor, config.divergence_sigma),
        config=config_dump,
        scenario=scenario.to_dict(),
        map_info=setup.map_info(),
        off_map=off_map,
        timing_s=timing,
        truth_model={**truth_terrain.summary(), "void_exposure": voids},
        pcrb_kind=scenario.pcrb_kind(),
    )
    claims = check_claims(results)
    print()
    print(format_table(results))
    print()
    print(
        f"off-map runs (excluded from the metrics): truth left the tile in {n_truth_off} of "
        f"{config.n_runs}; per method: "
        + ", ".join(f"{k} {v}" for k, v in off_map["per_method"].items())
    )
    for check in claims:
        outputs.claims.append(_as_claim(check))
        print(f"claim: {check.claim}: {check.measured} -> {check.verdict}")
    results["timing_s"]["total"] = time.perf_counter() - started
    figures = _write_figures(outputs, config=config, results=results, truth=truth, runs=runs,
                             tile=tile, pcrb_pos=pcrb_pos)
    tracks = {"truth": truth.pos, "ins": truth.ins_pos,
              **{name: truth.pos + r.err[..., :3] for name, r in runs.items()}}
    write_trajectories(outputs.dir, tile, truth.t.cpu().numpy(),
                       {name: v.detach().cpu().numpy() for name, v in tracks.items()})
    outputs.results.update(results)
    outputs.set_report(render_report(results, claims=claims, figures=figures))


def _as_claim(check: Any) -> Any:
    from neuralmap.studies.outputs import Claim

    paper = "SEEDS 004" if "SEEDS 004" in check.claim else "toolkit target"
    return Claim(paper, check.claim, check.measured, check.verdict)
