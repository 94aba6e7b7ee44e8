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
from typing import Any

import numpy as np
import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.linearize.factory import LINEARIZER_NAMES, TERRAIN_MODEL_METHODS
from neuralmap.nav.metrics import divergence_rule, navigation_metrics
from neuralmap.nav.monte_carlo import run_monte_carlo
from neuralmap.nav.pcrb import pcrb, pcrb_position
from neuralmap.studies.base import StudyConfig
from neuralmap.studies.outputs import StudyOutputs
from neuralmap.studies.setup import prepare_tan, void_exposure
from neuralmap.studies.tan_report import (
    build_results,
    check_claims,
    format_table,
    report_text,
)
from neuralmap.studies.trajectories import write_trajectories
from neuralmap.viz.navigation import (
    plot_error_vs_time,
    plot_final_error_histogram,
    plot_trajectories,
)
from neuralmap.viz.tensorboard_nav import log_navigation

__all__ = ["DEFAULT_METHODS", "TanStudyConfig", "run"]

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
                   truth: Any, runs: dict[str, Any], tile: Any, pcrb_pos: np.ndarray) -> None:
    """Plots through the outputs writer (PNG, report, TensorBoard) and logs the curves."""

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
        outputs.add_figure(name, fig, _FIGURES[name])
    writer = outputs.writer()
    if writer is not None:
        log_navigation(
            writer,
            curves={m: curves[m] for m in runs},
            pcrb_pos=pcrb_pos,
            final_errors=final_errors,
            summary={m: results["methods"][m] for m in runs},
        )


def run(config: TanStudyConfig, outputs: StudyOutputs) -> None:
    """Runs the TAN Monte Carlo study and fills ``outputs``.

    Raises:
        NeuralMapError: Bad input (no map, tile mismatch, bad scenario, device...).
    """

    started = time.perf_counter()
    timing: dict[str, float] = {}
    device, dtype = config.torch_device, config.torch_dtype
    setup = prepare_tan(scenario=config.scenario, methods=config.methods, map_path=config.map,
                        runs_dir=config.runs_dir, seed=config.seed,
                        neural_fit_variance=config.neural_fit_variance,
                        map_error_points=config.map_error_points, device=config.torch_device)
    setup.pin(config)
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
    results["timing_s"]["total"] = time.perf_counter() - started
    outputs.add_text(report_text(results))
    for check in claims:
        paper = "SEEDS 004" if "SEEDS 004" in check.claim else "toolkit target"
        outputs.add_claim(paper, check.claim, check.measured, check.verdict, detail=check.detail)
    _write_figures(outputs, config=config, results=results, truth=truth, runs=runs,
                             tile=tile, pcrb_pos=pcrb_pos)
    tracks = {"truth": truth.pos, "ins": truth.ins_pos,
              **{name: truth.pos + r.err[..., :3] for name, r in runs.items()}}
    write_trajectories(outputs.dir, tile, truth.t.cpu().numpy(),
                       {name: v.detach().cpu().numpy() for name, v in tracks.items()})
    outputs.results.update(results)
