"""Acquisition study: TAN from large initial errors, EKF alone vs bank vs point mass (→ EKF).

Flies the scenario (default jacksboro) at several initial horizontal errors σ0 (per axis,
the filter's P0 matched), with the start moved so that ±3σ0 of the prior stays on the
tile, and flies every navigation method asked for through the `Navigator` (by registered
name, with the product's acquisition grid, hand-off and lost-lock re-acquisition) on the
same truth, on the grid map (bilinear DEM) and, when a trained neural map is available, on
the neural map. Reports divergences, all-run RMSE against the PCRB over the last half, time
to acquire (first time after which the error stays below 3× the PCRB), wall time and
grid-cell updates per second, and a flat-terrain leg (a synthetic plane: no terrain
information) that shows the posterior staying wide.

Examples:
    python evaluate.py --config configs/acquisition.yaml
    python evaluate.py --config configs/acquisition_tiny.yaml
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from neuralmap.cluster import open_cluster
from neuralmap.dem.tile import DemTile
from neuralmap.exceptions import NeuralMapError
from neuralmap.lab.metrics import (
    acquisition_time,
    bound_rms_last_half,
    divergence_rule,
    navigation_metrics,
    nees,
)
from neuralmap.lab.monte_carlo import fly, study_navigator_config
from neuralmap.lab.pcrb import map_aware_pcrb, pcrb, pcrb_position
from neuralmap.lab.simulator import simulate
from neuralmap.outputs import RunCounts, StudyOutputs, verdict
from neuralmap.progress import stage_progress
from neuralmap.studies.cluster_options import ClusterOptions
from neuralmap.studies.integrity_report import (
    add_integrity_table,
    add_stanford,
    integrity_entry,
)
from neuralmap.studies.setup import dem_error_model, prepare_tan
from neuralmap.tan.methods import (
    EkfBank,
    EkfMethod,
    PointMassEkf,
    PointMassGrid,
    PointMassTrackerMethod,
)
from neuralmap.tan.model import TanModel
from neuralmap.tan.registry import method_class, method_names
from neuralmap.terrain.base import inside_extent
from neuralmap.terrain.grid import GridTerrain
from neuralmap.viz.navigation import plot_error_vs_time

__all__ = ["AcquisitionStudyConfig", "run"]

#: Map kind -> the EKF's linearisation method on it (the point mass's likelihood terrain
#: is the bilinear DEM for ``grid``, the neural map itself for ``neural``).
_MAP_LINEARIZERS = {"grid": "bilinear", "neural": "neural_region"}


@dataclass
class AcquisitionStudyConfig(ClusterOptions):
    """Options of the acquisition study (``study: acquisition``).

    Attributes:
        scenario: Scenario name or YAML path (its flight, noise and filter tuning).
        sigmas_m: Initial horizontal errors σ0 per axis, m (P0 matched).
        n_runs: Monte Carlo runs per σ0 (the same truth for every method and map).
        methods: Registered navigation methods (`neuralmap.tan.registry`): by default the
            EKF alone, the EKF bank, the EKF started by the point-mass grid and the
            point-mass tracker (grid acquisition, then the tracker); ``point_mass`` (the grid
            for the whole flight) and methods of your own fly too.
        maps: ``grid`` (bilinear DEM: point-mass likelihood and ``bilinear`` EKF) and/or
            ``neural`` (the neural map: likelihood by its batched forward, EKF with
            ``neural_region``).
        map: Neural map file; None = newest ``<runs_dir>/*/version_*/neural_map.pt`` of
            the tile. Without one, the neural rows are skipped and the report says so.
        n_runs_per_method: Runs of a method's rows (the first on-map runs of the σ0),
            e.g. ``{point_mass: 100}`` for an expensive one; a method not named flies
            every run.
        neural_likelihood_oversample: The point-mass likelihoods of the neural-map rows read
            the map baked onto a grid this many times finer than the DEM (bilinear; the
            report gives the baked grid's largest deviation from the map at random points);
            0 = the map's own forward at every cell (about 1.5 s per step for 100 runs of
            64² cells on this CPU). The EKF always linearises the map itself.
        n_runs_neural: Runs for the neural-map rows (its forward over every grid cell is
            the expensive part); None = ``n_runs``.
        map_error_points: Seeded random points of the neural map's error against the
            truth (its extra R), as in the TAN study.
        adaptive_point_mass: Adaptive grid (re-centred, re-sized) for the ``point_mass``
            rows, which fly the grid for the whole flight; the acquisition grid of the other
            methods keeps the prior's grid.
        alert_limit_m: Horizontal alert limit of the integrity tables (per σ0: misleading
            fixes, hazards, availability per row; a Stanford diagram of the default
            method's rows), m.
        navigator: Navigator options every row flies with, over the shipped
            ``navigator.yaml`` (its sections: ``point_mass`` sizes the grid, ``acquisition``
            the hand-off test, ``integrity`` the lost-lock test, ``ekf_bank`` the bank...).
        flat_leg: Also fly the smallest σ0 over a synthetic plane.
        n_runs_flat: Runs of the flat leg.
        pcrb_factor: Divergence when the final error exceeds this times the final PCRB.
        divergence_sigma: ... or this many times the filter's own 1σ horizontal bound.
        cluster: Where the rows run: default this process (row by row, the progress bar
            step by step); on a Dask cluster (``local:N``, ``tcp://HOST:8786``) every row
            (σ0 × map × method) is one task, dealt once all σ0 are simulated (their inputs
            are held together), with the same results bit for bit. The flat leg runs here.
    """

    study: str = "acquisition"
    experiment: str = "acquisition"
    progress: bool = True
    # one torch thread: on the shared 2-core machine two threads made the small batched
    # ops of the EKF rows many times slower whenever other work ran (neural EKF, 200 runs,
    # σ0 = 100 m: 76.8 s with two threads at load 6, against ~3 s with one)
    threads: int | None = 1
    scenario: str = "jacksboro"
    sigmas_m: list[float] = field(default_factory=lambda: [100.0, 300.0, 1000.0, 3000.0])
    n_runs: int = 1000
    methods: list[str] = field(default_factory=lambda: [
        EkfMethod.name, EkfBank.name, PointMassEkf.name, PointMassTrackerMethod.name])
    maps: list[str] = field(default_factory=lambda: ["grid", "neural"])
    map: str | None = None
    n_runs_neural: int | None = 200
    n_runs_per_method: dict[str, int] = field(default_factory=dict)
    neural_likelihood_oversample: int = 4
    map_error_points: int = 2000
    adaptive_point_mass: bool = True
    navigator: dict[str, Any] = field(default_factory=dict)
    alert_limit_m: float = 100.0
    flat_leg: bool = True
    n_runs_flat: int = 100
    pcrb_factor: float = 5.0
    divergence_sigma: float = 9.0

    def validate(self) -> None:
        """Checks values; raises `NeuralMapError` naming the option and the fix."""
        super().validate()
        if self.neural_likelihood_oversample < 0:
            raise NeuralMapError(f"--neural_likelihood_oversample must be >= 0, got "
                                 f"{self.neural_likelihood_oversample}.")
        if self.n_runs < 1 or (self.n_runs_neural is not None and self.n_runs_neural < 1):
            raise NeuralMapError(
                f"--n_runs and --n_runs_neural must be >= 1 (the last may be null = --n_runs), "
                f"got {self.n_runs}, {self.n_runs_neural}.")
        bad = {k: v for k, v in dict(self.n_runs_per_method).items()
               if k not in self.methods or isinstance(v, bool) or not isinstance(v, int) or v < 1}
        if bad:
            raise NeuralMapError(f"--n_runs_per_method: {bad} must name methods of --methods "
                                 "with run counts >= 1.")
        if self.map_error_points < 100:
            raise NeuralMapError(f"--map_error_points must be >= 100, got {self.map_error_points}.")
        if not self.sigmas_m or any(not s > 0 for s in self.sigmas_m):
            raise NeuralMapError(f"--sigmas_m must be a non-empty list of sigmas > 0 m, got "
                                 f"{self.sigmas_m}.")
        bad = [m for m in self.methods if m not in method_names()]
        if not self.methods or bad:
            raise NeuralMapError(f"--methods: unknown or empty {bad or self.methods}; pick "
                                 f"from {', '.join(method_names())}.")
        bad = [m for m in self.maps if m not in _MAP_LINEARIZERS]
        if not self.maps or bad:
            raise NeuralMapError(f"--maps: unknown or empty {bad or self.maps}; pick from "
                                 f"{', '.join(_MAP_LINEARIZERS)}.")
        if self.n_runs_flat < 1:
            raise NeuralMapError(f"--n_runs_flat must be >= 1, got {self.n_runs_flat}.")
        if not isinstance(self.navigator, dict):
            raise NeuralMapError(f"--navigator must be a mapping of navigator sections, got "
                                 f"{self.navigator!r}.")
        self.navigator_config()

    def navigator_config(self) -> Any:
        """The navigator options every row flies with (validated; `navigator`)."""
        from neuralmap.nav.config import load_navigator_config

        try:
            return load_navigator_config(self.navigator)
        except NeuralMapError as exc:
            raise NeuralMapError(f"--navigator: {exc}") from exc


def scenario_at_sigma(scenario: Any, sigma: float, extent: tuple[float, ...]) -> Any:
    """The scenario with initial horizontal error σ per axis, P0 matched, and the start
    moved so that ±3σ of the prior stays on the tile.

    With waypoints, the start slides along the first leg (toward the first waypoint) until
    it is ``3σ + 500 m`` inside the tile, and the flight is shortened by the distance
    skipped, so that the path (and its end) stays the scenario's; without, it is clamped.
    """
    xmin, xmax, ymin, ymax = extent
    margin = 3.0 * sigma + 500.0
    start = np.array(scenario.start_xy if scenario.start_xy is not None
                     else [0.5 * (xmax - xmin), 0.5 * (ymax - ymin)], dtype=float)
    size = np.array([xmax - xmin, ymax - ymin])

    def inside(p: np.ndarray) -> bool:
        return bool(np.all(p >= margin) and np.all(p <= size - margin))

    duration = scenario.duration_s
    if not inside(start) and scenario.waypoints:
        target = np.array(scenario.waypoints[0], dtype=float)
        for t in np.linspace(0.0, 1.0, 201):
            p = start + t * (target - start)
            if inside(p):
                duration -= float(np.linalg.norm(p - start)) / scenario.speed_mps
                start = p
                break
    start = np.clip(start, margin, np.maximum(size - margin, margin))
    p0 = [sigma**2, sigma**2, *scenario.P0_diag[2:]]
    return dataclasses.replace(scenario, init_pos_sigma_m=sigma, P0_diag=p0,
                               start_xy=[float(start[0]), float(start[1])],
                               duration_s=max(duration, 10.0 * scenario.dt)).validate()


def _flat_tile(tile: DemTile) -> DemTile:
    """A plane of the tile's size, spacing and origin at its mean height."""
    heights = np.full(tile.shape, float(np.nanmean(tile.heights)))
    return DemTile(heights=heights, spacing=tile.spacing, origin=tile.origin,
                   name=f"{tile.name}-flat")


def _row_metrics(run: Any, bound: torch.Tensor, config: AcquisitionStudyConfig,
                 dt: float, bound_map: torch.Tensor | None = None) -> dict[str, Any]:
    met = navigation_metrics(run, bound, pcrb_factor=config.pcrb_factor,
                             divergence_sigma=config.divergence_sigma, map_aware_pos=bound_map)
    keep = ~run.off_map
    err = run.err[keep][..., :2].norm(dim=-1).double()
    t_acq = acquisition_time(err, bound.double(), factor=3.0, dt=dt)
    finite = t_acq[torch.isfinite(t_acq)]
    per = run.vehicle_counts
    handed = per["first_handoff"][keep]
    handed = handed[handed >= 0].double() * dt
    recoveries = sum(int(v.sum()) for k, v in per.items() if k.endswith("recoveries"))
    return {
        "n_included": met["n_included"],
        "n_diverged": met["n_diverged"],
        "divergence_rate": met["divergence_rate"],
        "rmse_pos_m": met["rmse_pos_m"],
        "pcrb_pos_m": met["pcrb_pos_m"],
        "pcrb_ratio_all": met["pcrb_ratio_all"],
        "pcrb_ratio_converged": met["pcrb_ratio_converged"],
        "rmse_pos_curve": met["rmse_pos_curve"],
        "acquired_fraction": float(torch.isfinite(t_acq).double().mean()) if t_acq.numel() else None,
        "time_to_acquire_median_s": float(finite.median()) if finite.numel() else None,
        "time_to_acquire_p90_s": float(finite.quantile(0.9)) if finite.numel() else None,
        "handoff_median_s": float(handed.median()) if handed.numel() else None,
        "n_fallbacks": int(per["lost"].sum()),
        "n_recoveries": recoveries,
        "wall_s": float(run.elapsed_s),
        "cell_updates_per_s": (run.counts.get("cell_updates", 0) / run.elapsed_s
                               if run.elapsed_s > 0 else None),
    }


def _maps(config: AcquisitionStudyConfig, device: torch.device,
          ) -> tuple[Any, dict[str, tuple[Any, Any, float]], list[str]]:
    """The shared setup (`prepare_tan`) and, per map kind of
    ``config.maps``, (likelihood terrain, EKF linearizer, extra R); the notes say which
    neural map flies, or why its rows are skipped (no map given and none found)."""
    setup = prepare_tan(
        scenario=config.scenario, methods=[_MAP_LINEARIZERS[k] for k in config.maps],
        map_path=config.map, runs_dir=config.runs_dir, seed=config.seed,
        neural_fit_variance=None, map_error_points=config.map_error_points, device=device,
        map_optional=True,
    )
    setup.pin(config)
    maps: dict[str, tuple[Any, Any, float]] = {}
    bake_notes: list[str] = []
    for kind in config.maps:
        linearizer = setup.methods.get(_MAP_LINEARIZERS[kind])
        if linearizer is None:
            continue
        if kind == "grid":
            maps[kind] = (GridTerrain(setup.tile, method="bilinear").to(device), linearizer, 0.0)
        else:
            maps[kind] = (_likelihood_map(setup, config, bake_notes).to(device), linearizer,
                          setup.fit_variance)
    notes = []
    if setup.map_note:
        notes.append(f"neural map rows skipped: {setup.map_note}")
    elif setup.map_path is not None:
        notes.append(f"neural map {setup.map_path}")
    return setup, maps, notes + bake_notes


def _likelihood_map(setup: Any, config: AcquisitionStudyConfig, notes: list[str]) -> Any:
    """The neural map for the point-mass likelihoods: baked onto a finer grid
    (``neural_likelihood_oversample``), with its measured deviation in ``notes``."""
    if config.neural_likelihood_oversample <= 0:
        return setup.terrain_map
    from neuralmap.terrain.bake import bake_to_grid

    k = int(config.neural_likelihood_oversample)
    baked = bake_to_grid(setup.terrain_map, setup.tile, oversample=k, method="bilinear")
    gen = torch.Generator().manual_seed(int(config.seed or 0) + 0xBA4E)
    xmin, xmax, ymin, ymax = setup.tile.extent
    u = torch.rand(20000, 2, generator=gen, dtype=torch.float64)
    xy = torch.stack([xmin + u[:, 0] * (xmax - xmin), ymin + u[:, 1] * (ymax - ymin)], -1)
    dtype = next((p.dtype for p in setup.terrain_map.parameters()), torch.float32)
    with torch.no_grad():
        dev = (baked(xy) - setup.terrain_map(xy.to(dtype)).double()).abs()
    notes.append(f"neural-map point-mass likelihoods read the map baked onto a {k}x finer "
                 f"bilinear grid: deviation from the map at 20000 random points RMS "
                 f"{float(dev.square().mean().sqrt()):.3f} m, max {float(dev.max()):.3f} m")
    return baked


def _run_row(_: Any, job: dict[str, Any], *, progress: Any = None) -> dict[str, Any]:
    """One row (one method on one σ0 and map) through the Navigator: in this process or as
    a cluster's task.

    Returns:
        ``{"result": FilterRun}``, or ``{"error": message}`` when the method refused its
        input (the study keeps the other rows and reports this one).
    """
    torch.set_num_threads(int(job["threads"]))  # the caller's: the same rounding
    try:
        return {"result": fly(job["truth"], job["terrain"], job["config"], model=job["model"],
                              map_error_variance=job["map_error_variance"], name=job["name"],
                              progress=progress)}
    except NeuralMapError as exc:
        return {"error": str(exc)}


def _row_config(config: AcquisitionStudyConfig, scenario: Any, method: str,
                linearizer: Any) -> Any:
    """The navigator config of one row: the study's ``navigator`` options, the method and,
    for a method that takes a linearisation, the map's (an EKF's)."""
    options: dict[str, Any] = {}
    fields = {f.name for f in dataclasses.fields(method_class(method).Options)}
    if "linearizer" in fields:
        options["linearizer"] = linearizer
    if issubclass(method_class(method), PointMassGrid):
        options["adaptive"] = config.adaptive_point_mass
    return study_navigator_config(scenario, {"method": method, method: options},
                                  overrides=config.navigator, integrity="product")


def run(config: AcquisitionStudyConfig, outputs: StudyOutputs) -> None:
    """Runs the acquisition study and fills ``outputs``.

    Raises:
        NeuralMapError: Bad input (scenario, map, runs starting off the map...).
    """
    started = time.perf_counter()
    device, dtype = config.torch_device, config.torch_dtype
    setup, maps, notes = _maps(config, device)
    base, tile, seed = setup.scenario, setup.tile, setup.seed
    truth_terrain = setup.truth_terrain  # the same world at every sigma0
    config.navigator_config()  # refuses bad navigator options before any work
    results: dict[str, Any] = {"sigmas": {}, "notes": notes,
                               "divergence_rule": divergence_rule(config.pcrb_factor,
                                                                  config.divergence_sigma)}
    # the map-aware PCRB (the bound of a filter that knows the DEM: its slopes, its measured
    # error as noise) beside the true-terrain one; one DEM error model for every sigma0
    dem = dem_error_model(base, tile, truth_terrain, n_points=config.map_error_points,
                          seed=seed)
    results["pcrb_map_aware"] = {
        "label": "map-aware PCRB (DEM slopes, DEM error as noise)",
        "map_error_m2": dem["mse_m2"], "map_error_corr": dem["corr"],
        "map_error_corr_lag_m": dem["lag_m"]}
    results["pcrb_label"] = "true-terrain PCRB (truth slopes, altimeter noise only)"

    def map_bound(truth: Any, scenario: Any, runs: torch.Tensor) -> torch.Tensor:
        return pcrb_position(map_aware_pcrb(
            truth, scenario, dem["terrain"], map_error_var=dem["mse_m2"],
            map_error_corr=dem["corr"], runs=runs)).to("cpu")

    integrity: dict[str, dict[str, Any]] = {}
    default_method = config.navigator_config().method
    headers = ["sigma0 m", "map", "method", "runs", "off-map", "diverged", "RMSE m", "PCRB m",
               "RMSE/PCRB", "conv. RMSE/PCRB", "map PCRB m", "RMSE/map PCRB", "acquired",
               "t_acq median s", "hand-off s", "fall-backs", "recoveries", "wall s",
               "cell-upd/s"]
    rows: list[list[Any]] = []
    curves: dict[str, Any] = {}
    off_map: dict[str, Any] = {}
    results["off_map"] = off_map
    bar = None
    if config.progress:  # a line per finished row (rows done, rate, time left), heartbeats inside
        from neuralmap.progress import ProgressLines

        bar = ProgressLines(total=len(config.sigmas_m) * len(maps) * len(config.methods),
                            desc="acquisition", unit="row")
    threads = torch.get_num_threads()

    def stages() -> Any:
        """Per (σ0, map): the simulated runs' bounds and one job per method's row."""
        for sigma in config.sigmas_m:
            scenario = scenario_at_sigma(base, float(sigma), tile.extent)
            results["sigmas"][f"{sigma:g}"] = {}
            for kind, (terrain, lin, extra_r) in maps.items():
                n = config.n_runs if kind == "grid" or config.n_runs_neural is None else min(
                    config.n_runs, config.n_runs_neural)
                truth = simulate(scenario, tile, n_runs=n, seed=seed, dtype=dtype,
                                 device=device, truth_terrain=truth_terrain)
                # runs whose truth leaves the map (or whose INS starts off it: draws beyond
                # the ±3σ0 the start keeps on the tile) are counted and excluded, as in `tan`
                kept = truth.on_map.all(dim=1) & inside_extent(truth.ins_pos[:, 0, :2],
                                                               truth.extent)
                n_off = int((~kept).sum())
                off_map[f"{sigma:g}/{kind}"] = {"runs": n, "off_map": n_off}
                if n_off:
                    print(f"acquisition: sigma0 {sigma:g} m, {kind}: {n_off} of {n} runs leave "
                          "the map (or start off it); excluded and counted", flush=True)
                if not bool(kept.any()):
                    notes.append(f"sigma0 {sigma:g} m, {kind}: all {n} runs leave the map; "
                                 "no rows.")
                    continue
                bound = pcrb_position(pcrb(truth, scenario, truth_terrain.model,
                                           runs=kept)).to("cpu")
                bound_map = map_bound(truth, scenario, kept)
                model = TanModel.from_scenario(scenario)
                on_map = truth.take(kept)
                jobs = []
                for method in config.methods:
                    run_truth, run_bound, run_bound_map = on_map, bound, bound_map
                    limit = config.n_runs_per_method.get(method)
                    if limit is not None:
                        sub = kept & (torch.cumsum(kept.long(), 0) <= limit)
                        if int(sub.sum()) < int(kept.sum()):
                            run_truth = truth.take(sub)
                            run_bound = pcrb_position(pcrb(truth, scenario, truth_terrain.model,
                                                           runs=sub)).to("cpu")
                            run_bound_map = map_bound(truth, scenario, sub)
                    jobs.append({"truth": run_truth, "method": method, "terrain": terrain,
                                 "config": _row_config(config, scenario, method, lin),
                                 "model": model, "map_error_variance": model.fit_variance
                                 + extra_r, "name": f"{method}/{kind}",
                                 "threads": threads, "bound": run_bound,
                                 "bound_map": run_bound_map})
                del truth
                yield {"sigma": sigma, "kind": kind, "scenario": scenario, "n_off": n_off,
                       "bound": bound, "bound_map": bound_map, "jobs": jobs}

    def finish(stage: dict[str, Any], outs: list[dict[str, Any]]) -> None:
        """The rows, curves and lines of one (σ0, map) from its finished rows."""
        sigma, kind, n_off = stage["sigma"], stage["kind"], stage["n_off"]
        per_sigma = results["sigmas"][f"{sigma:g}"]
        for job, out in zip(stage["jobs"], outs, strict=True):
            method = job["method"]
            if "error" in out:  # keep every finished stage; report this one
                notes.append(f"sigma0 {sigma:g} m, {kind}, {method} failed: {out['error']}")
                print(f"acquisition: sigma0 {sigma:g} m, {kind}, {method} failed: "
                      f"{out['error']}", flush=True)
                continue
            m = _row_metrics(out["result"], job["bound"], config, stage["scenario"].dt,
                             job["bound_map"])
            entry = integrity_entry(out["result"], alert_limit_m=config.alert_limit_m)
            if entry is not None:
                integrity.setdefault(f"sigma0 {sigma:g} m, ", {})[f"{kind}/{method}"] = entry
                if method == default_method:
                    add_stanford(outputs, f"{kind}/{method}", out["result"],
                                 alert_limit_m=config.alert_limit_m,
                                 prefix=f"sigma0 {sigma:g} m, ")
            m["n_off_map"] = n_off
            m["pcrb_map_pos_m"] = bound_rms_last_half(job["bound_map"])
            m["pcrb_map_ratio_all"] = (
                m["rmse_pos_m"] / m["pcrb_map_pos_m"]
                if m["rmse_pos_m"] is not None and m["pcrb_map_pos_m"] else None)
            per_sigma[f"{kind}/{method}"] = m
            curves[f"{sigma:g}/{kind}/{method}"] = m["rmse_pos_curve"]
            rows.append([sigma, kind, method, m["n_included"], n_off, m["n_diverged"],
                         m["rmse_pos_m"], m["pcrb_pos_m"], m["pcrb_ratio_all"],
                         m["pcrb_ratio_converged"], m["pcrb_map_pos_m"],
                         m["pcrb_map_ratio_all"], m["acquired_fraction"],
                         m["time_to_acquire_median_s"], m["handoff_median_s"],
                         m["n_fallbacks"], m["n_recoveries"], m["wall_s"],
                         m["cell_updates_per_s"]])
            print(f"acquisition: sigma0 {sigma:g} m, {kind}, {method}: diverged "
                  f"{m['n_diverged']}/{m['n_included']}, RMSE/PCRB "
                  f"{_fmt(m['pcrb_ratio_all'])} (map-aware {_fmt(m['pcrb_map_ratio_all'])}), "
                  f"wall {m['wall_s']:.1f} s", flush=True)
        curves[f"{sigma:g}/pcrb"] = stage["bound"].tolist()
        curves[f"{sigma:g}/pcrb_map_aware"] = stage["bound_map"].tolist()

    try:
        with open_cluster(config.cluster) as dispatcher:
            if dispatcher.client is None:  # row by row; the bar advances step by step inside
                for stage in stages():
                    outs = []
                    for job in stage["jobs"]:
                        if bar is not None:
                            bar.set_description(f"acquisition sigma0 {stage['sigma']:g} m, "
                                                f"{stage['kind']}, {job['method']}")
                        outs.append(_run_row(None, job,
                                             progress=None if bar is None else bar.update))
                    finish(stage, outs)
            else:  # every row a task; the cluster reports each finished row
                staged = list(stages())
                if bar is not None:
                    bar.set_description(f"acquisition rows on {dispatcher.description}")
                outs = dispatcher.map(
                    _run_row, [job for stage in staged for job in stage["jobs"]],
                    name="acquisition-row",
                    on_done=None if bar is None else lambda _, __: bar.update(1),
                    on_idle=None if bar is None else lambda: bar.update(0))
                start = 0
                for stage in staged:
                    finish(stage, outs[start:start + len(stage["jobs"])])
                    start += len(stage["jobs"])
    finally:
        if bar is not None:
            bar.close()
    flat = None
    if config.flat_leg:
        try:
            with stage_progress("acquisition flat-terrain leg", 1, "leg",
                                enabled=config.progress) as progress:
                flat = _flat_leg(config, base, tile, device, dtype, seed, progress)
        except NeuralMapError as exc:  # the finished stages stay; the leg is reported
            notes.append(f"flat-terrain leg failed: {exc}")
    results["flat_leg"] = flat
    results["curves"] = curves
    results["timing_s"] = {"total": time.perf_counter() - started}
    for key, curve in curves.items():  # TensorBoard: RMSE curves and the summary per row
        outputs.log_curve(f"rmse_pos/{key}", curve)
    for sigma_key, per_sigma in results["sigmas"].items():
        for name, m in per_sigma.items():
            for metric in ("rmse_pos_m", "pcrb_ratio_all", "acquired_fraction", "n_diverged"):
                outputs.log_scalar(f"summary/{metric}/sigma{sigma_key}/{name}", m[metric])
    results["integrity"] = integrity
    outputs.results.update(results)
    _write_report(outputs, config, rows, headers, results, notes)
    for prefix, table in integrity.items():
        add_integrity_table(outputs, table, alert_limit_m=config.alert_limit_m,
                            targets=tuple(k for k in table if k.endswith(f"/{default_method}")),
                            prefix=prefix)
    _figure(outputs, results, base.dt)


def _flat_leg(config: AcquisitionStudyConfig, base: Any, tile: DemTile,
              device: torch.device, dtype: torch.dtype, seed: int,
              progress: Any = None) -> dict[str, Any]:
    """The EKF started by the point-mass grid over a plane: no terrain information, the
    posterior must stay wide (``progress``: the fraction callback of the flight,
    `neuralmap.progress.stage_progress`)."""
    flat = _flat_tile(tile)
    sigma = float(min(config.sigmas_m))
    scenario = scenario_at_sigma(base, sigma, flat.extent)
    leg = prepare_tan(scenario=scenario, tile=flat, methods=["bilinear"], map_path=None,
                      runs_dir=config.runs_dir, seed=seed, neural_fit_variance=0.0,
                      map_error_points=config.map_error_points, device=device)
    truth = simulate(scenario, flat, n_runs=config.n_runs_flat, seed=seed, dtype=dtype,
                     device=device, truth_terrain=leg.truth_terrain)
    model = TanModel.from_scenario(scenario)
    run = fly(truth, GridTerrain(flat, method="bilinear").to(device),
              _row_config(config, scenario, PointMassEkf.name, leg.methods["bilinear"]),
              model=model, map_error_variance=model.fit_variance, progress=progress)
    P = run.P[:, -1, :2, :2].double()
    post_sigma = torch.linalg.eigvalsh(P)[:, -1].clamp_min(0).sqrt()
    err = run.err[:, -1, :2].norm(dim=-1).double()
    return {
        "sigma0_m": sigma,
        "n_runs": config.n_runs_flat,
        "final_posterior_sigma_median_m": float(post_sigma.median()),
        "final_error_rms_m": float(err.square().mean().sqrt()),
        "handed_off_fraction": float((run.vehicle_counts["first_handoff"] >= 0).double().mean()),
        "nees_final_mean": float(nees(run.err[:, -1, :2], P).mean()),
    }


def _fmt(value: Any) -> str:
    return "n/a" if value is None else f"{value:.3g}"


def _write_report(outputs: StudyOutputs, config: AcquisitionStudyConfig, rows: list[list[Any]],
                  headers: list[str], results: dict[str, Any], notes: list[str]) -> None:
    nav = config.navigator_config()
    a, grid, i = nav.acquisition, nav.methods[PointMassGrid.name], nav.integrity
    outputs.add_text(
        "Acquisition from large initial errors. Every method of a σ0 row sees the same "
        "truth, and every row flies the `Navigator` (the product's pipeline). **Hand-off "
        "test** (acquisition grid → method): the Bhattacharyya coefficient between the grid "
        f"posterior and its Gaussian fit ≥ {a.handoff_affinity:g} and the largest posterior "
        f"σ ≤ {a.handoff_sigma_m:g} m for {a.handoff_hold} consecutive steps; **lost lock** "
        f"when the mean NIS over the last {i.lost_window} updates exceeds its χ² point at "
        f"probability {i.lost_prob:g}: re-acquisition from the open-loop prior (fall-backs "
        "in the table). **Time to acquire**: "
        "the first time after which the horizontal error stays below 3× the PCRB. RMSE and "
        "PCRB are RMS over all included runs and the last half of the flight; "
        f"divergence: {results['divergence_rule']} Grid: "
        f"{grid.cells or f'up to {grid.max_cells}'}² cells over ±{grid.span_sigma:g}σ0 (at "
        f"most {grid.max_spacing:g} m apart when the count allows), {grid.dtype}; the "
        "acquisition grid keeps the prior's grid, the point mass alone (method "
        f"`{PointMassGrid.name}`) re-centres and re-sizes it (adaptive: "
        f"{config.adaptive_point_mass}). Wall time and cell-updates/s on this machine "
        "(shared CPUs: compare within the table)."
    )
    for note in notes:
        outputs.add_text(f"Note: {note}")
    outputs.add_table("Acquisition methods against the PCRB", headers, rows)
    flat = results.get("flat_leg")
    if flat:
        outputs.add_text(
            f"Flat-terrain leg (a plane, σ0 = {flat['sigma0_m']:g} m, point mass → EKF, "
            f"{flat['n_runs']} runs): without terrain information the posterior stays "
            f"wide — median final horizontal σ {flat['final_posterior_sigma_median_m']:.0f} m "
            f"(prior {flat['sigma0_m']:g} m per axis), RMS final error "
            f"{flat['final_error_rms_m']:.0f} m, hand-offs in "
            f"{100 * flat['handed_off_fraction']:.0f} % of runs, mean final NEES (2-D) "
            f"{flat['nees_final_mean']:.2f}."
        )
    for sigma, per in results["sigmas"].items():
        for key, m in per.items():
            div_ok = (m["divergence_rate"] or 0.0) <= (0.002 if float(sigma) >= 3000 else 0.0)
            target = "none" if float(sigma) < 3000 else "<= 0.2 %"
            runs = RunCounts(m["n_included"] - m["n_diverged"], m["n_included"]).all_runs()
            outputs.add_claim(
                "toolkit target",
                f"sigma0 = {sigma} m, {key}: divergences {target}",
                f"{m['n_diverged']} of {m['n_included']}",
                verdict(div_ok), runs=runs,
            )
            ratio = m["pcrb_ratio_all"]
            outputs.add_claim(
                "toolkit target",
                f"sigma0 = {sigma} m, {key}: all-run RMSE over the last half <= 1.10x PCRB",
                _fmt(ratio),
                verdict(None if ratio is None else ratio <= 1.10,
                        detail=(f"by {100 * (ratio - 1.10) / 1.10:.0f} %"
                                if ratio is not None and ratio > 1.10 else None)),
                runs=runs,
            )
            map_ratio = m.get("pcrb_map_ratio_all")
            if key.endswith(f"/{nav.method}"):  # the default method vs the map-aware bound
                outputs.add_claim(
                    "toolkit target",
                    f"sigma0 = {sigma} m, {key}: all-run RMSE over the last half <= 1.05x the "
                    "map-aware PCRB",
                    _fmt(map_ratio),
                    verdict(None if map_ratio is None else map_ratio <= 1.05,
                            detail=(f"by {100 * (map_ratio - 1.05) / 1.05:.0f} %"
                                    if map_ratio is not None and map_ratio > 1.05 else None)),
                    runs=runs,
                )


def _figure(outputs: StudyOutputs, results: dict[str, Any], dt: float) -> None:
    """One error-vs-time figure per σ0 (`plot_error_vs_time`)."""
    curves = results["curves"]
    for sigma in results["sigmas"]:
        rows = {key.split("/", 1)[1]: curve for key, curve in curves.items()
                if key.startswith(f"{sigma}/") and not key.endswith(("/pcrb", "/pcrb_map_aware"))}
        if not rows:
            continue
        if f"{sigma}/pcrb_map_aware" in curves:
            rows["map-aware PCRB"] = curves[f"{sigma}/pcrb_map_aware"]
        n = len(next(iter(rows.values())))
        fig = plot_error_vs_time(np.arange(n) * dt, rows, curves.get(f"{sigma}/pcrb"),
                                 title=f"Horizontal RMSE vs time, σ0 = {sigma} m")
        outputs.add_figure(f"rmse_vs_time_sigma{sigma}", fig,
                           f"Horizontal RMSE vs time against the PCRB, σ0 = {sigma} m")
