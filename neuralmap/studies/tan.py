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

import dataclasses
import time
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.lab.metrics import bound_rms_last_half, divergence_rule, navigation_metrics
from neuralmap.lab.monte_carlo import fly, run_monte_carlo, study_navigator_config
from neuralmap.lab.noise_calibration import derive_method_noise
from neuralmap.lab.pcrb import map_aware_pcrb, pcrb, pcrb_position
from neuralmap.lab.simulator import simulate
from neuralmap.linearize.measured_noise import (
    MeasuredNoiseLinearizer,
    measure_linearization_noise,
    noise_sigmas,
)
from neuralmap.outputs import RunCounts, StudyOutputs, verdict
from neuralmap.progress import stage_progress
from neuralmap.studies.cluster_options import ClusterOptions
from neuralmap.studies.integrity_report import add_integrity
from neuralmap.studies.setup import (
    DEFAULT_METHODS,
    TanOptions,
    build_methods,
    dem_error_model,
    prepare_tan,
    void_exposure,
)
from neuralmap.studies.tan_report import (
    ClaimCheck,
    build_results,
    check_claims,
    format_table,
    report_text,
)
from neuralmap.studies.trajectories import write_trajectories
from neuralmap.tan.methods import PointMassEkf, PointMassTrackerMethod
from neuralmap.tan.model import TanModel
from neuralmap.tan.registry import method_class
from neuralmap.viz.navigation import (
    plot_error_vs_time,
    plot_final_error_histogram,
    plot_trajectories,
)
from neuralmap.viz.tensorboard_nav import log_navigation

__all__ = ["DEFAULT_METHODS", "STUDY_METHODS", "TanStudyConfig", "run"]

#: The registered methods the study flies by default besides the linearisations: the EKF
#: started by the point-mass grid and the navigator's default method (`navigator.yaml`).
STUDY_METHODS: tuple[str, ...] = (PointMassEkf.name, PointMassTrackerMethod.name)

#: How the EKF methods' R is built (``--noise``).
NOISE_MODES = ("measured", "scenario")

_FIGURES = {
    "error_vs_time": "Horizontal position RMSE vs time, with the PCRB",
    "trajectories": "Trajectories over the tile (truth and estimates)",
    "final_error_hist": "Final horizontal error",
}


@dataclass
class TanStudyConfig(TanOptions, ClusterOptions):
    """Options of the TAN Monte Carlo study (``study: tan``): the shared TAN options
    (`TanOptions`) plus the plots.

    Attributes:
        n_plot_trajectories: Trajectories drawn over the hillshade.
        methods: EKF linearisation methods (each the cold-started TAN EKF with that
            linearisation, flown through the Navigator with the lost-lock test off, as in the
            paper) and registered navigation methods (`neuralmap.tan.registry`: the
            point-mass tracker, the EKF started by the point-mass grid, ..., or a method of
            your own), flown through the Navigator by name with the product's integrity
            settings on the bilinear DEM, R = altimeter + the DEM's error measured against
            the truth; a method that takes a linearisation gets the bilinear DEM's with its
            measured noise table (`measure_linearization_noise`).
        navigator: Navigator options the registered methods fly with, over the shipped
            ``navigator.yaml`` (sections as there, e.g. ``{point_mass_tracker: {cells:
            48}}`` or ``{integrity: {lost_window: 0}}``).
        stated_r: Fly the navigator's default method (``navigator.yaml``'s ``method``) a
            second time with the R a user has (the altimeter variance + the DEM's stated
            accuracy ``dem_error_sigma_m``², as the `Navigator` builds it, no truth terrain)
            and report what is lost against the truth-tuned R.
        alert_limit_m: Horizontal alert limit of the integrity section (misleading
            fixes, hazards, availability, Stanford diagrams; `neuralmap.lab.integrity`), m.
        noise: R of the EKF methods: ``"measured"`` = the altimeter variance + each method's
            miss against the truth terrain as a function of the position σ, measured over the
            map and on pilot flights (`neuralmap.lab.noise_calibration`); ``"scenario"``
            = the scenario's ``R_m2 + fit_variance_m2`` + each method's own variance.
        noise_pilot_runs: Pilot runs of the in-flight measurement (0 = the map table only).
        noise_iterations: Pilot flights (fixed-point iterations).
        cluster: Where the EKF methods' filters run (one task per method on a Dask cluster,
            `neuralmap.lab.monte_carlo.run_filters`; bit-identical); default this
            process. The registered methods and the pilot flights run here.
    """

    navigation_methods = True
    experiment: str = "evaluate"
    n_plot_trajectories: int = 5
    methods: list[str] = field(default_factory=lambda: [*DEFAULT_METHODS, *STUDY_METHODS])
    navigator: dict[str, Any] = field(default_factory=dict)
    stated_r: bool = True
    alert_limit_m: float = 100.0
    noise: str = "measured"
    noise_pilot_runs: int = 400
    noise_iterations: int = 3

    def validate(self) -> None:
        """Checks values; raises `NeuralMapError` naming the option and the fix."""
        super().validate()
        if not isinstance(self.navigator, dict):
            raise NeuralMapError(f"--navigator must be a mapping of navigator sections, got "
                                 f"{self.navigator!r}.")
        if not self.alert_limit_m > 0:
            raise NeuralMapError(f"--alert_limit_m must be > 0 m, got {self.alert_limit_m!r}.")
        from neuralmap.nav.config import load_navigator_config

        try:
            load_navigator_config(self.navigator)
        except NeuralMapError as exc:
            raise NeuralMapError(f"--navigator: {exc}") from exc
        if self.noise not in NOISE_MODES:
            raise NeuralMapError(f"--noise must be one of {', '.join(NOISE_MODES)}, got "
                                 f"{self.noise!r}.")
        if self.noise_pilot_runs < 0 or self.noise_iterations < 1:
            raise NeuralMapError(f"--noise_pilot_runs must be >= 0 and --noise_iterations >= 1, "
                                 f"got {self.noise_pilot_runs} and {self.noise_iterations}.")
        if self.n_plot_trajectories < 0:
            raise NeuralMapError(
                f"--n_plot_trajectories must be >= 0, got {self.n_plot_trajectories}."
            )


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
    linearized = config.linearized_methods
    setup = prepare_tan(scenario=config.scenario, methods=linearized, map_path=config.map,
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
    # The truth first: a scenario none of whose flights stay on the tile is refused before
    # anything is derived from them (the measured-R pilot flies the same scenario).
    _check_scored(simulate(scenario, tile, n_runs=config.n_runs, seed=seed, dtype=dtype,
                           device=device, truth_terrain=truth_terrain), config, tile)
    noise_info: dict[str, Any] = {"rule": "scenario R_m2 + fit_variance_m2 + the method's own "
                                          "variance"}
    filter_scenario = scenario
    if methods and config.noise == "measured":
        tick = time.perf_counter()
        with stage_progress(f"R derivation ({len(methods)} methods: map table, pilot flights)",
                            len(methods), "method", enabled=config.progress) as progress:
            methods, filter_scenario, noise_info = derive_method_noise(
                methods, scenario=scenario, tile=tile, truth_terrain=truth_terrain, seed=seed,
                sigmas=noise_sigmas(scenario.init_pos_sigma_m),
                n_pilot=config.noise_pilot_runs, iterations=config.noise_iterations,
                progress=progress)
        timing["noise"] = time.perf_counter() - tick
        print(f"R: measured per method ({config.noise_pilot_runs} pilot runs, "
              f"{timing['noise']:.1f} s): " + "; ".join(
                  f"{m} {v['R_m2'][_node(v, 20.0)]:.0f} m² at 20 m, "
                  f"{v['R_m2'][_node(v, 100.0)]:.0f} at 100 m"
                  for m, v in noise_info["methods"].items()), flush=True)

    if methods:
        truth, runs = run_monte_carlo(
            filter_scenario, methods, n_runs=config.n_runs, seed=seed, progress=config.progress,
            device=device, dtype=dtype, tile=tile, truth_terrain=truth_terrain,
            cluster=config.cluster,
        )
    else:
        truth, runs = simulate(scenario, tile, n_runs=config.n_runs, seed=seed, dtype=dtype,
                               device=device, truth_terrain=truth_terrain), {}
    dem_bound = dem_error_model(scenario, tile, truth_terrain,
                                n_points=config.map_error_points, seed=config.seed)
    navigator_info = _fly_registered(config, scenario, truth, tile, truth_terrain, dem_bound,
                                     runs)
    _order_runs(config, runs)
    for name, filter_run in runs.items():
        timing[f"filter_{name}"] = float(filter_run.elapsed_s)
    voids = void_exposure(tile, truth)
    if voids["samples"]:
        print(f"warning: {voids['samples']} truth samples ({voids['runs']} runs) fly over DEM "
              "voids: the truth there is a nearest-node fill of the DEM, not terrain. They stay "
              "in the metrics and are counted in the report.", flush=True)
    kept = truth.on_map.all(dim=1)  # the metrics drop runs whose truth left the map
    _check_scored(truth, config, tile)

    tick = time.perf_counter()
    with stage_progress("PCRB (true terrain, map-aware)", 2, "bound",
                        enabled=config.progress) as progress:
        half = None if progress is None else (lambda f: progress(0.5 * f))
        bound = pcrb(truth, scenario, truth_terrain.model, runs=kept, progress=half)
        pcrb_pos = pcrb_position(bound).detach().to("cpu", torch.float64).numpy()
        pcrb_map_pos = pcrb_position(map_aware_pcrb(
            truth, scenario, dem_bound["terrain"], map_error_var=dem_bound["mse_m2"],
            map_error_corr=dem_bound["corr"], runs=kept, progress=half)
        ).detach().to("cpu", torch.float64).numpy()
    timing["pcrb"] = time.perf_counter() - tick

    method_metrics = {
        name: navigation_metrics(filter_run, torch.as_tensor(pcrb_pos),
                                 pcrb_factor=config.pcrb_factor,
                                 divergence_sigma=config.divergence_sigma,
                                 map_aware_pos=torch.as_tensor(pcrb_map_pos))
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
    _add_map_aware_bound(results, pcrb_map_pos, dem_bound)
    _add_diverged_runs(results, method_metrics, runs, scenario)
    if navigator_info:
        results["navigator"] = navigator_info
    results["noise"] = {"mode": config.noise, **noise_info}
    claims = (check_claims(results) + _default_method_claims(results)
              + _consistency_claims(results))
    print()
    print(format_table(results))
    print(f"bounds: {results['pcrb_map_aware']['label']} {results['pcrb_map_aware']['pos_m']:.1f} m, "
          f"true-terrain PCRB {results.get('pcrb_pos_m', float('nan')):.1f} m (RMS, last half)")
    print()
    print(
        f"off-map runs (excluded from the metrics): truth left the tile in {n_truth_off} of "
        f"{config.n_runs}; per method: "
        + ", ".join(f"{k} {v}" for k, v in off_map["per_method"].items())
    )
    outputs.add_text(report_text(results))
    results["integrity"] = add_integrity(
        outputs, runs, alert_limit_m=config.alert_limit_m,
        targets=tuple(m for m in (_default_method(), PointMassEkf.name) if m in runs),
        diverged={name: m["diverged"] for name, m in method_metrics.items()
                  if m.get("diverged") is not None})
    results["timing_s"]["total"] = time.perf_counter() - started
    default = _default_method()
    info = (navigator_info or {}).get(default, {})
    stated = info.get("stated_R")
    if stated:
        outputs.add_table(
            f"{default}: the R a user has against the truth-tuned R",
            ["R", "R [m²]", "RMSE pos, all runs, last half [m]", "lost runs"],
            [["truth-tuned (altimeter + DEM error measured against the truth)",
              f"{info['R_m2']:.1f}", f"{stated['truth_tuned_rmse_last_half_m']:.2f}",
              info["runs_lost"]],
             ["stated (altimeter + the DEM's stated accuracy, as the Navigator)",
              f"{stated['R_m2']:.1f}", f"{stated['rmse_last_half_m']:.2f}",
              stated["runs_lost"]]])
    for check in claims:
        outputs.add_claim(check.paper, check.claim, check.measured, check.verdict,
                          detail=check.detail)
    _write_figures(outputs, config=config, results=results, truth=truth, runs=runs,
                             tile=tile, pcrb_pos=pcrb_pos)
    tracks = {"truth": truth.pos, "ins": truth.ins_pos,
              **{name: truth.pos + r.err[..., :3] for name, r in runs.items()}}
    write_trajectories(outputs.dir, tile, truth.t.cpu().numpy(),
                       {name: v.detach().cpu().numpy() for name, v in tracks.items()})
    outputs.results.update(results)


def _check_scored(truth: Any, config: Any, tile: Any) -> None:
    """Refuses a scenario none of whose truth trajectories stays on the tile.

    Raises:
        NeuralMapError: Every run's truth left the tile or started off it.
    """
    if not bool(truth.on_map.all(dim=1).any()):
        raise NeuralMapError(
            f"no run could be scored: all {config.n_runs} truth trajectories left the tile "
            f"{tile.name!r} (extent {tuple(round(e) for e in tile.extent)} m) or started off "
            f"it (--scenario {config.scenario}). Move the scenario's start_xy/waypoints "
            "inside the tile, shorten duration_s, or lower start_spread_m."
        )


def _node(table: dict[str, Any], sigma: float) -> int:
    """Index of the table node nearest ``sigma``."""
    return int(np.argmin(np.abs(np.asarray(table["sigmas_m"]) - sigma)))


def _default_method() -> str:
    """The navigator's default method (the shipped ``navigator.yaml``'s ``method``)."""
    from neuralmap.nav.config import load_navigator_config

    return load_navigator_config().method


def _last_half_rmse(run: Any) -> float:
    """Horizontal RMSE over every run and the last half of the flight, m."""
    err = run.err[:, run.err.shape[1] // 2:, :2].double()
    return float(err.square().sum(-1).mean().sqrt())


def _takes_linearizer(name: str) -> bool:
    """The registered method's options name a linearisation (an EKF family method)."""
    return "linearizer" in {f.name for f in dataclasses.fields(method_class(name).Options)}


def _fly_registered(config: Any, scenario: Any, truth: Any, tile: Any, truth_terrain: Any,
                    dem: dict[str, Any], runs: dict[str, Any]) -> dict[str, Any]:
    """Flies every registered navigation method of ``config.methods`` through the
    Navigator over the bilinear DEM (``dem["terrain"]``) and adds its run to ``runs``.

    R = the altimeter variance + the DEM's error variance measured against the truth
    terrain. A method that takes a linearisation (the EKF family) gets the bilinear DEM's,
    its R split into the part every filter shares — the map table at σ = 0 — and the
    linearisation excess over it, ``v(σ) − v(0)``, read from the bilinear method's map table
    at the filter's position σ (`measure_linearization_noise`: the miss ``t(p) − h(p̂) −
    slope(p̂)·(p − p̂)`` against the truth terrain with ``p − p̂ ~ N(0, σ² I)``); no pilot
    flights, since an EKF the grid has started does not lock onto a wrong terrain match,
    which is what the pilot flights of a cold-started EKF add to its R. With ``stated_r``
    the navigator's default method flies again with the R a user has (the altimeter + the
    DEM's stated accuracy², no truth terrain).
    """
    registered = [m for m in config.methods if m not in config.linearized_methods]
    if not registered:
        return {}
    model = TanModel.from_scenario(scenario)
    infos: dict[str, Any] = {}
    table = None
    for name in registered:
        tick = time.perf_counter()
        options: dict[str, Any] = {}
        R_map = float(dem["mse_m2"])
        with stage_progress(name, 2, "part", enabled=config.progress) as progress:
            half = None if progress is None else (lambda f: progress(0.5 * f))
            if _takes_linearizer(name):
                if table is None:
                    bilinear = build_methods(["bilinear"], tile=tile, terrain_map=None,
                                             device=truth.pos.device)["bilinear"]
                    table = measure_linearization_noise(
                        bilinear, truth_terrain.model,
                        extent=tuple(float(e) for e in tile.extent), seed=config.seed,
                        sigmas=noise_sigmas(scenario.init_pos_sigma_m), progress=half)
                    shared = float(table.variance_m2[0])
                    excess = dataclasses.replace(table, variance_m2=tuple(
                        max(v - shared, 0.0) for v in table.variance_m2))
                    linearizer = MeasuredNoiseLinearizer(bilinear, excess)
                options["linearizer"], R_map = linearizer, shared
            nav_cfg = study_navigator_config(scenario, {"method": name, name: options},
                                             overrides=config.navigator, integrity="product")
            run = fly(truth, dem["terrain"], nav_cfg, model=model, map_error_variance=R_map,
                      tile=tile, name=name, progress=half)
        runs[name] = run
        infos[name] = _navigator_info(run, R=model.R_altimeter + R_map, dt=scenario.dt,
                                      seconds=time.perf_counter() - tick)
        if table is not None and "linearizer" in options:
            infos[name]["table"] = table.to_dict()
        handoff = infos[name]["handoff_median_s"]
        handoff = ("no hand-off (started without the acquisition grid)" if handoff is None
                   else f"hand-off median {handoff} s")
        print(f"{name}: R {infos[name]['R_m2']:.1f} m² (altimeter + DEM error) | "
              f"{infos[name]['cell_updates_per_s']:.3g} cell-updates/s | {handoff}, "
              f"lost {infos[name]['runs_lost']} runs | {infos[name]['elapsed_s']:.1f} s",
              flush=True)
    default = _default_method()
    if config.stated_r and default in runs:
        R_user = float(scenario.dem_error_sigma_m) ** 2
        nav_cfg = study_navigator_config(scenario, default, overrides=config.navigator,
                                         integrity="product")
        with stage_progress(f"{default} (stated R)", 1, "flight",
                            enabled=config.progress) as progress:
            user = fly(truth, dem["terrain"], nav_cfg, model=model, map_error_variance=R_user,
                       tile=tile, name=default, progress=progress)
        tuned, stated = _last_half_rmse(runs[default]), _last_half_rmse(user)
        infos[default]["stated_R"] = {
            "R_m2": model.R_altimeter + R_user, "rmse_last_half_m": stated,
            "truth_tuned_rmse_last_half_m": tuned,
            "loss_ratio": stated / tuned if tuned > 0 else None,
            "runs_lost": int(user.lost.sum()) if user.lost is not None else 0}
        print(f"{default} with the R a user has ({model.R_altimeter + R_user:.1f} m²: altimeter "
              f"+ stated DEM accuracy {scenario.dem_error_sigma_m:g} m): last-half RMSE "
              f"{stated:.2f} m against {tuned:.2f} m with the truth-tuned R "
              f"({stated / max(tuned, 1e-12):.3f}x)", flush=True)
    return infos


def _navigator_info(run: Any, *, R: float, dt: float, seconds: float) -> dict[str, Any]:
    """What a registered method's flight reports beside its metrics."""
    counts, per = run.counts, run.vehicle_counts
    first = per.get("first_handoff")
    handed = (first[first >= 0].double() * dt) if first is not None else torch.zeros(0)
    elapsed = max(run.elapsed_s, 1e-9)
    return {"R_m2": R, "elapsed_s": run.elapsed_s, "seconds": seconds,
            "cell_updates_per_s": counts.get("cell_updates", 0) / elapsed,
            "handoff_median_s": float(handed.median()) if handed.numel() else None,
            "never_handed_off": int((first < 0).sum()) if first is not None else 0,
            "lost_lock_events": counts.get("lost", 0), "spikes": counts.get("spikes", 0),
            "runs_lost": int(run.lost.sum()) if run.lost is not None else 0}


def _order_runs(config: Any, runs: dict[str, Any]) -> None:
    """Puts ``runs`` in ``config.methods`` order (in place)."""
    ordered = {name: runs[name] for name in config.methods if name in runs}
    runs.clear()
    runs.update(ordered)


#: Diverged runs listed per method in results.json and the report (the first ones).
_MAX_LISTED_DIVERGED = 10


def _add_diverged_runs(results: dict[str, Any], method_metrics: dict[str, Any],
                       runs: dict[str, Any], scenario: Any) -> None:
    """Each method's diverged runs with their initial horizontal error, in metres and in
    the prior's σ (``sqrt(P0_xx)``; the radial error's ``r/σ``, whose tail beyond ``c`` has
    probability ``exp(−c²/2)`` for a 2-D Gaussian): a cold-started EKF that loses the
    terrain match does so from the far tail of the prior."""
    sigma0 = float(np.sqrt(TanModel.from_scenario(scenario).filter_prior()[0, 0]))
    for name, metrics in method_metrics.items():
        flags = np.asarray(metrics.get("diverged") or [], dtype=bool)
        index = np.flatnonzero(flags)
        if not index.size or name not in runs:
            continue
        start = runs[name].err[:, 0, :2].detach().to("cpu", torch.float64).norm(dim=-1).numpy()
        results["methods"][name]["diverged_runs"] = [
            {"run": int(i), "initial_error_m": float(start[i]),
             "initial_error_sigma": float(start[i] / sigma0)}
            for i in index[:_MAX_LISTED_DIVERGED]]


def _add_map_aware_bound(results: dict[str, Any], bound: np.ndarray, dem: dict[str, Any]) -> None:
    """The map-aware PCRB beside the true-terrain one, and each method's ratio to it."""
    rms = bound_rms_last_half(bound)
    results["pcrb_map_aware"] = {
        "label": "map-aware PCRB (DEM slopes, DEM error as noise)",
        "pos_m": rms, "pos_final_m": float(bound[-1]), "curve": bound.tolist(),
        "map_error_m2": dem["mse_m2"], "map_error_corr": dem["corr"],
        "map_error_corr_lag_m": dem["lag_m"],
    }
    results["pcrb_label"] = "true-terrain PCRB (truth slopes, altimeter noise only)"
    for entry in results["methods"].values():
        rmse = entry.get("rmse_pos_m")
        entry["pcrb_map_ratio_all"] = rmse / rms if rmse is not None and rms > 0 else None


def _default_method_claims(results: dict[str, Any]) -> list[Any]:
    """The navigator's default method's targets against both bounds (toolkit targets),
    each judged by the one verdict rule (`neuralmap.outputs.verdict`): RMSE and
    divergence rest on every on-map run, NEES on the converged runs."""
    name = _default_method()
    entry = results["methods"].get(name)
    if not entry:
        return []
    runs = RunCounts.from_metrics(entry)
    map_ratio, true_ratio = entry.get("pcrb_map_ratio_all"), entry.get("pcrb_ratio_all")
    rate, nees_band = runs.bad_rate, entry.get("nees_in_band")
    rule = "all-run RMSE (last half) / bound (RMS, last half)"

    def judged(ok: bool | None, counts: RunCounts) -> str:
        return verdict(ok, runs=counts)

    return [
        ClaimCheck(f"{name}: RMSE ≤ 1.05× the map-aware PCRB", _ratio_text(map_ratio),
                   judged(None if map_ratio is None else map_ratio <= 1.05, runs.all_runs()),
                   rule),
        ClaimCheck(f"{name}: RMSE ≤ 1.10× the true-terrain PCRB", _ratio_text(true_ratio),
                   judged(None if true_ratio is None else true_ratio <= 1.10, runs.all_runs()),
                   rule),
        ClaimCheck(f"{name}: diverges in 0 runs",
                   f"{entry.get('n_diverged', 0)} diverged + {runs.failed} numerical failures "
                   f"of {runs.total}",
                   judged(None if rate is None else rate == 0.0, runs.all_runs()),
                   "the study's divergence rule"),
        ClaimCheck(f"{name}: NEES in its 95 % band in ≥ 90 % of steps",
                   f"{nees_band:.1%}" if nees_band is not None else "n/a",
                   judged(None if nees_band is None else nees_band >= 0.9, runs),
                   "run-averaged NEES of the 5 states (converged runs) vs the two-sided χ² "
                   "band"),
    ]


def _ratio_text(ratio: float | None) -> str:
    return f"{ratio:.3f}×" if ratio is not None else "n/a"


#: The EKF methods whose consistency the toolkit targets, first the recommended one (the
#: EKF started by the point-mass grid), then the neural method of a cold-started EKF.
RECOMMENDED_EKF = (PointMassEkf.name, "neural_region")


def _consistency_claims(results: dict[str, Any]) -> list[Any]:
    """NEES band coverage of the recommended EKF method (toolkit target: >= 90 % of steps),
    the first of `RECOMMENDED_EKF` in the results; the other methods' coverage is in
    the table."""
    name = next((m for m in RECOMMENDED_EKF
                 if results["methods"].get(m, {}).get("nees_in_band") is not None), None)
    if name is None:
        return []
    band = results["methods"][name]["nees_in_band"]
    noise = results.get("noise", {}).get("mode", "?")
    linearized = set(results.get("config", {}).get("methods", [])) - set(
        results.get("navigator", {}))
    cold = {m: e["nees_in_band"] for m, e in results["methods"].items()
            if m in linearized and e.get("nees_in_band") is not None}
    detail = f"R: {noise}; run-averaged NEES of the 5 states vs the two-sided chi2 band"
    if cold:
        best = max(cold.items(), key=lambda item: item[1])
        detail += (f"; cold-started EKF methods: best {best[0]} {best[1]:.1%}"
                   + (f", neural_region {cold['neural_region']:.1%}"
                      if "neural_region" in cold and best[0] != "neural_region" else ""))
    return [ClaimCheck(
        f"{name} (recommended EKF method): NEES in its 95 % band in ≥ 90 % of steps",
        f"{band:.1%}", verdict(band >= 0.9, runs=RunCounts.from_metrics(results["methods"][name])),
        detail)]
