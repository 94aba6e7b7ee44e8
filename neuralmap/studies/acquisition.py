"""Acquisition study: TAN from large initial errors, EKF alone vs bank vs point mass (→ EKF).

Flies the scenario (default jacksboro) at several initial horizontal errors σ0 (per axis,
the filter's P0 matched), with the start moved so that ±3σ0 of the prior stays on the
tile, and runs every acquisition method of `neuralmap.nav.acquisition` on the same
truth, on the grid map (bilinear DEM) and, when a trained neural map is available, on the
neural map. Reports divergences, all-run RMSE against the PCRB over the last half, time
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
from neuralmap.nav.acquisition import (
    ACQUISITION_METHODS,
    AcquisitionConfig,
    acquisition_time,
    run_acquisition,
    tan_inputs,
)
from neuralmap.nav.metrics import bound_rms_last_half, divergence_rule, navigation_metrics, nees
from neuralmap.nav.pcrb import map_aware_pcrb, pcrb, pcrb_position
from neuralmap.nav.simulator import simulate
from neuralmap.progress import stage_progress
from neuralmap.studies.cluster_options import ClusterOptions
from neuralmap.studies.outputs import RunCounts, StudyOutputs, verdict
from neuralmap.studies.setup import dem_error_model, prepare_tan
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
        methods: Subset of ``ekf``, ``bank``, ``point_mass``, ``point_mass_ekf``,
            ``point_mass_tracker``.
        maps: ``grid`` (bilinear DEM: point-mass likelihood and ``bilinear`` EKF) and/or
            ``neural`` (the neural map: likelihood by its batched forward, EKF with
            ``neural_region``).
        map: Neural map file; None = newest ``<runs_dir>/*/version_*/neural_map.pt`` of
            the tile. Without one, the neural rows are skipped and the report says so.
        n_runs_tracker: Runs of the ``point_mass_tracker`` rows (the first on-map runs of
            the σ0; grid acquisition, then the tracker's lattice for the rest of the flight:
            the study's most expensive row); None = all.
        neural_likelihood_oversample: The point-mass likelihoods of the neural-map rows read
            the map baked onto a grid this many times finer than the DEM (bilinear; the
            report gives the baked grid's largest deviation from the map at random points);
            0 = the map's own forward at every cell (about 1.5 s per step for 100 runs of
            64² cells on this CPU). The EKF always linearises the map itself.
        n_runs_neural: Runs for the neural-map rows (its forward over every grid cell is
            the expensive part); None = ``n_runs``.
        map_error_points: Seeded random points of the neural map's error against the
            truth (its extra R), as in the TAN study.
        grid_cells: Point-mass cells per axis; None = the fewest covering ±4σ0 at
            ``max_spacing_m`` (at most ``max_cells``).
        max_spacing_m: Largest initial grid spacing when ``grid_cells`` is None, m.
        max_cells: Most cells per axis when ``grid_cells`` is None.
        adaptive_point_mass: Adaptive grid (re-centred, re-sized) for the point-mass-only
            method, which runs the whole flight; point mass → EKF keeps the prior's grid.
        grid_dtype: Point-mass precision.
        min_spacing_m: Finest point-mass spacing, m.
        handoff_sigma_m: Hand-off when the largest posterior σ is below this (m) ...
        handoff_affinity: ... and the Bhattacharyya coefficient grid vs Gaussian fit is
            above this, for ``handoff_hold`` steps.
        handoff_hold: Consecutive steps the hand-off test must pass.
        fallback_window: NIS window of the lost-lock test (0 = no fall-back).
        fallback_prob: χ² probability of its threshold (jacksboro, σ0 = 300 m, 200 runs:
            window 10 / 0.999 gave 16 fall-backs and RMSE/PCRB 1.30; 20 / 0.99999 gave
            4 and 1.21; no fall-back, 2 divergences).
        bank_per_axis: EKF-bank components per axis.
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
    # the whole-flight point-mass row is the tracker (grid acquisition, then the tracker);
    # the adaptive point mass alone (240 s per 50 runs at σ0 = 3 km here) is left out by
    # default. Neural-map rows at 200 runs: each costs about as much as its grid row, and
    # the neural EKF bank (49 EKFs per run linearising the network) 140 s per 1000 runs.
    methods: list[str] = field(
        default_factory=lambda: ["ekf", "bank", "point_mass_ekf", "point_mass_tracker"])
    maps: list[str] = field(default_factory=lambda: ["grid", "neural"])
    map: str | None = None
    n_runs_neural: int | None = 200
    n_runs_tracker: int | None = None
    neural_likelihood_oversample: int = 4
    map_error_points: int = 2000
    grid_cells: int | None = None
    max_spacing_m: float = 50.0
    max_cells: int = 256
    adaptive_point_mass: bool = True
    grid_dtype: str = "float32"
    min_spacing_m: float = 2.0
    handoff_sigma_m: float = 40.0
    handoff_affinity: float = 0.9
    handoff_hold: int = 3
    fallback_window: int = 20
    fallback_prob: float = 0.99999
    bank_per_axis: int = 7
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
        if self.n_runs < 1 or any(k is not None and k < 1 for k in (self.n_runs_neural,
                                                                      self.n_runs_tracker)):
            raise NeuralMapError(
                f"--n_runs, --n_runs_neural and --n_runs_tracker must be >= 1 (the last two may "
                f"be null = --n_runs), got {self.n_runs}, {self.n_runs_neural}, "
                f"{self.n_runs_tracker}.")
        if self.map_error_points < 100:
            raise NeuralMapError(f"--map_error_points must be >= 100, got {self.map_error_points}.")
        if not self.sigmas_m or any(not s > 0 for s in self.sigmas_m):
            raise NeuralMapError(f"--sigmas_m must be a non-empty list of sigmas > 0 m, got "
                                 f"{self.sigmas_m}.")
        bad = [m for m in self.methods if m not in ACQUISITION_METHODS]
        if not self.methods or bad:
            raise NeuralMapError(f"--methods: unknown or empty {bad or self.methods}; pick "
                                 f"from {', '.join(ACQUISITION_METHODS)}.")
        bad = [m for m in self.maps if m not in _MAP_LINEARIZERS]
        if not self.maps or bad:
            raise NeuralMapError(f"--maps: unknown or empty {bad or self.maps}; pick from "
                                 f"{', '.join(_MAP_LINEARIZERS)}.")
        if self.n_runs_flat < 1:
            raise NeuralMapError(f"--n_runs_flat must be >= 1, got {self.n_runs_flat}.")
        if isinstance(self.bank_per_axis, bool) or not isinstance(self.bank_per_axis, int) or (
                self.bank_per_axis < 1):
            raise NeuralMapError(
                f"--bank_per_axis must be an integer >= 1 (EKF-bank components per axis: 1 = "
                f"one EKF at the prior mean, the default 7 = a 7 x 7 lattice), got "
                f"{self.bank_per_axis!r}. Pass e.g. --bank_per_axis 7, or drop `bank` from "
                "--methods.")
        self.acquisition_config().validate()

    def acquisition_config(self) -> AcquisitionConfig:
        """The `AcquisitionConfig` of these options."""
        return AcquisitionConfig(
            cells=self.grid_cells, max_spacing_m=self.max_spacing_m, max_cells=self.max_cells,
            dtype=self.grid_dtype, min_spacing_m=self.min_spacing_m,
            handoff_sigma_m=self.handoff_sigma_m, handoff_affinity=self.handoff_affinity,
            handoff_hold=self.handoff_hold, fallback_window=self.fallback_window,
            fallback_prob=self.fallback_prob,
            bank_per_axis=self.bank_per_axis,
        )


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


def _runs_on_map(inputs: Any, kept: torch.Tensor) -> Any:
    """The `TanInputs` of the runs ``kept (N,)`` only."""
    idx = kept.nonzero().reshape(-1)
    return dataclasses.replace(
        inputs, ins_pos=inputs.ins_pos[idx], radar=inputs.radar[idx],
        ins_error=inputs.ins_error[idx], on_map=inputs.on_map[idx])


def _flat_tile(tile: DemTile) -> DemTile:
    """A plane of the tile's size, spacing and origin at its mean height."""
    heights = np.full(tile.shape, float(np.nanmean(tile.heights)))
    return DemTile(heights=heights, spacing=tile.spacing, origin=tile.origin,
                   name=f"{tile.name}-flat")


def _row_metrics(res: Any, bound: torch.Tensor, config: AcquisitionStudyConfig,
                 dt: float) -> dict[str, Any]:
    met = navigation_metrics(res.run, bound, pcrb_factor=config.pcrb_factor,
                             divergence_sigma=config.divergence_sigma)
    keep = ~res.run.off_map
    err = res.run.err[keep][..., :2].norm(dim=-1).double()
    t_acq = acquisition_time(err, bound.double(), factor=3.0, dt=dt)
    finite = t_acq[torch.isfinite(t_acq)]
    handed = res.handoff_step[keep]
    handed = handed[handed >= 0].double() * dt
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
        "n_fallbacks": int(res.n_fallbacks.sum()),
        "n_recoveries": int(res.recoveries.sum()),
        "wall_s": float(res.elapsed_s),
        "cell_updates_per_s": (res.cell_updates / res.elapsed_s) if res.elapsed_s > 0 else None,
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
    """One row (one method on one σ0 and map): in this process or as a cluster's task.

    Returns:
        ``{"result": AcquisitionResult}``, or ``{"error": message}`` when the method refused
        its input (the study keeps the other rows and reports this one).
    """
    torch.set_num_threads(int(job["threads"]))  # the caller's: the same rounding
    try:
        return {"result": run_acquisition(job["inputs"], method=job["method"],
                                          terrain=job["terrain"], linearizer=job["linearizer"],
                                          config=job["config"], name=job["name"],
                                          progress=progress)}
    except NeuralMapError as exc:
        return {"error": str(exc)}


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
    acq_cfg = config.acquisition_config()
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
                inputs = _runs_on_map(tan_inputs(truth, scenario), kept)
                inputs = dataclasses.replace(inputs, R=inputs.R + extra_r)
                jobs = []
                for method in config.methods:
                    cfg = acq_cfg
                    if method == "point_mass" and config.adaptive_point_mass:
                        cfg = dataclasses.replace(acq_cfg, adaptive=True)
                    run_inputs, run_bound, run_bound_map = inputs, bound, bound_map
                    if method == "point_mass_tracker" and config.n_runs_tracker is not None:
                        sub = kept & (torch.cumsum(kept.long(), 0) <= config.n_runs_tracker)
                        if int(sub.sum()) < int(kept.sum()):
                            run_inputs = _runs_on_map(inputs, sub[kept])
                            run_bound = pcrb_position(pcrb(truth, scenario, truth_terrain.model,
                                                           runs=sub)).to("cpu")
                            run_bound_map = map_bound(truth, scenario, sub)
                    jobs.append({"inputs": run_inputs, "method": method, "terrain": terrain,
                                 "linearizer": lin, "config": cfg, "name": f"{method}/{kind}",
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
            m = _row_metrics(out["result"], job["bound"], config, stage["scenario"].dt)
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
                flat = _flat_leg(config, base, tile, acq_cfg, device, dtype, seed, progress)
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
    outputs.results.update(results)
    _write_report(outputs, config, rows, headers, results, notes)
    _figure(outputs, results, base.dt)


def _flat_leg(config: AcquisitionStudyConfig, base: Any, tile: DemTile,
              acq_cfg: AcquisitionConfig, device: torch.device, dtype: torch.dtype,
              seed: int, progress: Any = None) -> dict[str, Any]:
    """Point mass over a plane: no terrain information, the posterior must stay wide
    (``progress``: the filter's fraction callback, `neuralmap.progress.stage_progress`)."""
    flat = _flat_tile(tile)
    sigma = float(min(config.sigmas_m))
    scenario = scenario_at_sigma(base, sigma, flat.extent)
    leg = prepare_tan(scenario=scenario, tile=flat, methods=["bilinear"], map_path=None,
                      runs_dir=config.runs_dir, seed=seed, neural_fit_variance=0.0,
                      map_error_points=config.map_error_points, device=device)
    truth = simulate(scenario, flat, n_runs=config.n_runs_flat, seed=seed, dtype=dtype,
                     device=device, truth_terrain=leg.truth_terrain)
    res = run_acquisition(tan_inputs(truth, scenario), method="point_mass_ekf",
                          terrain=GridTerrain(flat, method="bilinear").to(device),
                          config=acq_cfg, linearizer=leg.methods["bilinear"], progress=progress)
    P = res.run.P[:, -1, :2, :2].double()
    post_sigma = torch.linalg.eigvalsh(P)[:, -1].clamp_min(0).sqrt()
    err = res.run.err[:, -1, :2].norm(dim=-1).double()
    return {
        "sigma0_m": sigma,
        "n_runs": config.n_runs_flat,
        "final_posterior_sigma_median_m": float(post_sigma.median()),
        "final_error_rms_m": float(err.square().mean().sqrt()),
        "handed_off_fraction": float((res.handoff_step >= 0).double().mean()),
        "nees_final_mean": float(nees(res.run.err[:, -1, :2], P).mean()),
    }


def _fmt(value: Any) -> str:
    return "n/a" if value is None else f"{value:.3g}"


def _write_report(outputs: StudyOutputs, config: AcquisitionStudyConfig, rows: list[list[Any]],
                  headers: list[str], results: dict[str, Any], notes: list[str]) -> None:
    outputs.add_text(
        "Acquisition from large initial errors. Every method of a σ0 row sees the same "
        "truth. **Hand-off test** (point mass → EKF): the Bhattacharyya coefficient between "
        f"the grid posterior and its Gaussian fit ≥ {config.handoff_affinity:g} and the "
        f"largest posterior σ ≤ {config.handoff_sigma_m:g} m for {config.handoff_hold} "
        "consecutive steps; **fall-back** when the mean NIS over the last "
        f"{config.fallback_window} updates exceeds its χ² point at probability "
        f"{config.fallback_prob:g}. **Time to acquire**: "
        "the first time after which the horizontal error stays below 3× the PCRB. RMSE and "
        "PCRB are RMS over all included runs and the last half of the flight; "
        f"divergence: {results['divergence_rule']} Grid: "
        f"{config.grid_cells or f'up to {config.max_cells}'}² cells over ±4σ0 (at most "
        f"{config.max_spacing_m:g} m apart when the count allows), {config.grid_dtype}; "
        "point mass → EKF and point mass → tracker (the whole-flight point-mass tracker, "
        "started from the grid posterior's moments at hand-off) keep the prior's grid, "
        "point mass alone re-centres and "
        f"re-sizes it (adaptive: {config.adaptive_point_mass}). Wall time and "
        "cell-updates/s on this machine (shared CPUs: compare within the table)."
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
            if key.endswith("point_mass_tracker"):  # the tracker against the map-aware bound
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
