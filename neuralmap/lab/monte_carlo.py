"""Monte Carlo TAN runs: simulated vehicles flown through the Navigator, one method at a time.

`fly` flies every run of a simulated `Truth` through one `neuralmap.nav.navigator.Navigator`
(batched: the N runs are its N vehicles) and scores the fixes against the truth
(`FilterRun`); a study measures exactly what a user runs. `run_filter` flies the 5-state TAN
EKF with one linearisation that way; `run_monte_carlo` simulates the truth once and runs every method on it;
`run_filters` runs several filters on one truth, in this process or one filter per
task on a Dask cluster (`neuralmap.cluster`; bit-identical to this process).

Timing convention: sample 0 is the prior (``δX̂_0 = 0``, ``P_0 = diag(P0_diag)``, no
altimeter update at t = 0, matching the PCRB's ``J_0 = P_0⁻¹``); steps ``k = 1 … K`` each
predict and update with the altimeter sample ``k``.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any, NamedTuple

import torch

from neuralmap.dem.tile import DemTile
from neuralmap.exceptions import NeuralMapError
from neuralmap.filters.policies.compose import quality_members
from neuralmap.lab.scenario import Scenario, load_scenario, scenario_tile
from neuralmap.lab.simulator import Truth, simulate
from neuralmap.linearize.base import Linearizer
from neuralmap.tan.model import TanModel


@dataclass
class FilterRun:
    """One method's filter outputs over all runs and steps.

    Attributes:
        method: Method name (key of the ``methods`` dict).
        t: ``(K+1,)`` sample times, s.
        err: ``(N, K+1, 5)`` corrected estimate minus truth, ``δX − δX̂`` (m, m, m, m/s,
            m/s); ``err[:, 0]`` is the prior error.
        P: ``(N, K+1, 5, 5)`` filter covariance after each step (``P[:, 0] = P0``).
        nis: ``(N, K+1)`` normalised innovation squared; NaN where no update happened
            (sample 0, estimate off the map, unhealthy filter) — use ``updated``.
        residual: ``(N, K+1)`` innovation (m); 0 where no update happened.
        updated: ``(N, K+1)`` bool, an altimeter update was applied at that step.
        est_on_map: ``(N, K+1)`` bool, the horizontal estimate was on the map.
        off_map: ``(N,)`` bool, the truth left the map at some step (run excluded).
        healthy: ``(N,)`` bool, the filter stayed healthy (finite, positive definite).
        elapsed_s: Wall-clock time of the filter loop, s.
        lost: ``(N,)`` bool, runs the navigator declared lost (a lost lock not
            re-acquired by the last epoch); they count as diverged
            (`neuralmap.lab.metrics.diverged_runs`). None: the filter declares none.
        status: ``(N, K+1)`` the navigator's status codes (`neuralmap.nav.fix.STATUS`), or
            None.
        vehicle_counts: The navigator's per-vehicle counters (`FixTrack.vehicle_counts`).
        counts: Its counters summed over vehicles (`FixTrack.counts`).
        protection: Integrity risk → ``(N, K+1)`` horizontal protection levels, m
            (`neuralmap.lab.integrity`).
    """

    method: str
    t: torch.Tensor
    err: torch.Tensor
    P: torch.Tensor
    nis: torch.Tensor
    residual: torch.Tensor
    updated: torch.Tensor
    est_on_map: torch.Tensor
    off_map: torch.Tensor
    healthy: torch.Tensor
    elapsed_s: float = 0.0
    lost: torch.Tensor | None = None
    status: torch.Tensor | None = None
    vehicle_counts: dict[str, torch.Tensor] = field(default_factory=dict)
    counts: dict[str, int] = field(default_factory=dict)
    protection: dict[float, torch.Tensor] = field(default_factory=dict)

    @property
    def n_runs(self) -> int:
        """Number of runs N."""
        return int(self.err.shape[0])

    def estimate_xy(self, truth: Truth) -> torch.Tensor:
        """Corrected horizontal estimate ``truth + err`` of every run, ``(N, K+1, 2)``."""
        return truth.pos[..., :2] + self.err[..., :2]


class MonteCarloResult(NamedTuple):
    """What `run_monte_carlo` returns (unpacks as ``truth, runs``).

    Attributes:
        truth: The simulated truth shared by every method.
        runs: Method name to its `FilterRun`, in the order of ``methods``.
    """

    truth: Truth
    runs: dict[str, FilterRun]


def _map_fingerprint(linearizer: Any) -> str:
    """The tile fingerprint of the map behind a linearizer ("" when unknown)."""
    for owner in (linearizer, getattr(linearizer, "terrain", None),
                  getattr(linearizer, "grid", None), getattr(linearizer, "model", None)):
        fingerprint = getattr(owner, "tile_fingerprint", "") if owner is not None else ""
        if fingerprint:
            return str(fingerprint)
    return ""


def check_map_matches(linearizer: Any, truth: Truth, *, method: str = "") -> None:
    """Raises when the linearizer's map was made from another tile than the scenario's.

    Args:
        linearizer: The method (its ``tile_fingerprint``, or that of its ``terrain``, ``grid``
            or ``model`` attribute, is compared when present).
        truth: The simulated truth (its ``tile_fingerprint``).
        method: Method name for the message.

    Raises:
        NeuralMapError: Both fingerprints are known and differ.
    """
    fingerprint = _map_fingerprint(linearizer)
    if fingerprint and truth.tile_fingerprint and fingerprint != truth.tile_fingerprint:
        raise NeuralMapError(
            f"method {method or type(linearizer).__name__!r}: its map was made from a tile with "
            f"fingerprint {fingerprint}, but the scenario flies over tile "
            f"{truth.tile_name!r} (fingerprint {truth.tile_fingerprint}). Train the map on the "
            "scenario's tile (python train.py) or pick the scenario of the map's tile."
        )


#: Integrity settings of a study flight unless the study says otherwise: the lost-lock test
#: and the spike gate off, so a study measures the method itself (a cold-started EKF that
#: locks onto a wrong match stays there, as in the papers).
STUDY_INTEGRITY = {"lost_window": 0, "spike_gate_prob": 0.0}

#: The integrity risks every study flight reports protection levels at: the navigator's
#: (``integrity.integrity_risk``, 1e-4 by default) and these.
STUDY_REPORT_RISKS = [1.0e-2]


def study_navigator_config(scenario: Any, method: str | dict[str, Any] = "ekf", *,
                           overrides: dict[str, Any] | None = None,
                           integrity: str = "study") -> Any:
    """The navigator config a study flies its simulated vehicles with.

    Over the shipped ``navigator.yaml``: the scenario's period (``sensor.dt_s``), no
    clearance range and no gap limit (the simulator's clearances are all usable), protection
    levels at `STUDY_REPORT_RISKS` too, the integrity settings (``"study"``: `STUDY_INTEGRITY`; ``"product"``: the shipped ones),
    then the method and ``overrides`` (a study's ``navigator`` section: any navigator
    option). The filter's ``P0``, ``Q`` and altimeter variance are the scenario's
    (`TanModel.from_scenario`, given to the Navigator as its model).

    Args:
        scenario: The `Scenario` (its ``dt``).
        method: A method name, or a mapping ``{"method": name, <name>: {options}}``.
        overrides: Navigator options over these (a mapping of sections).
        integrity: ``"study"`` or ``"product"`` (above).

    Raises:
        NeuralMapError: Unknown method or options (names the key).
    """
    from neuralmap.nav.config import load_navigator_config

    if integrity not in ("study", "product"):
        raise NeuralMapError(f"study_navigator_config: integrity must be 'study' or "
                             f"'product', got {integrity!r}.")
    base: dict[str, Any] = {"sensor": {"dt_s": float(scenario.dt), "max_gap_s": math.inf,
                                       "clearance_min_m": -math.inf,
                                       "clearance_max_m": math.inf},
                            "integrity": {"report_risks": list(STUDY_REPORT_RISKS)}}
    if integrity == "study":
        base["integrity"].update(STUDY_INTEGRITY)
    cfg = load_navigator_config(base)
    data = dict(method) if isinstance(method, dict) else {"method": method}
    for part, where in ((data, "study method"), (overrides, "study navigator options")):
        if part:
            cfg = type(cfg).from_dict(part, where=where, base=cfg)
    return cfg


def fly(truth: Truth, terrain: Any, config: Any, *, model: Any,
        map_error_variance: float | None = None, tile: Any = None, name: str = "",
        quality: bool = False, progress: Any = None) -> FilterRun:
    """Flies every simulated vehicle of ``truth`` through one `Navigator` (batched) and
    scores its fixes against the truth.

    Args:
        truth: Simulated truth (`neuralmap.lab.simulator.simulate`).
        terrain: The map the navigator flies (``extent`` and ``forward``).
        config: A `NavigatorConfig` (`study_navigator_config`).
        model: The filter's model (`TanModel.from_scenario`, or an augmented one).
        map_error_variance: The map term of ``R`` (m²); None = the config's.
        tile: The DEM tile (DEM-reading EKF linearisations).
        name: Method name stored in the run.
        quality: Give the navigator the altimeter's quality record (``truth.quality``).
        progress: Called with the fraction of the flight each epoch is; None = silent.

    Returns:
        `FilterRun` (`filter_run`).
    """
    from neuralmap.nav.navigator import Navigator

    nav = Navigator(terrain, config, n_vehicles=truth.n_runs, model=model,
                    map_error_variance=map_error_variance, tile=tile, dtype=truth.pos.dtype,
                    device=truth.pos.device)
    if quality and getattr(truth, "quality", None) is None:
        raise NeuralMapError(
            f"method {name!r}: the policy needs the altimeter quality record, but the truth "
            "has none; simulate it with neuralmap.lab.simulator.simulate.")
    start = time.perf_counter()
    track = nav.replay(truth.t, truth.ins_pos[..., :2], truth.ins_pos[..., 2], truth.radar,
                       quality=truth.quality if quality else None, progress=progress)
    i = nav.config.integrity
    return filter_run(track, truth, name=name, elapsed_s=time.perf_counter() - start,
                      risks=(i.integrity_risk, *i.report_risks))


def filter_run(track: Any, truth: Truth, *, name: str = "", elapsed_s: float = 0.0,
               risks: tuple[float, ...] = ()) -> FilterRun:
    """The `FilterRun` of a navigator's `FixTrack` over a simulated truth.

    ``err = δX − δX̂`` (the truth's INS error minus the fix's correction); a run the
    navigator lost (a lost lock not re-acquired by the last epoch: status ``lost`` or
    ``acquiring`` after a lost-lock detection) is declared lost (it counts as diverged).
    ``risks``: the integrity risks of ``track.hpl`` then of ``track.hpl_extra``'s columns
    (`FilterRun.protection`).
    """
    from neuralmap.nav.fix import STATUS_CODE

    dtype = truth.pos.dtype
    dev = truth.pos.device
    err = truth.ins_error - track.correction.to(dev, dtype)
    P = track.cov.to(dev, dtype)
    updated = track.updated.to(dev)
    residual = torch.where(updated, track.innovation.to(dev, dtype), 0.0)
    status = track.status.to(dev)
    finite = torch.isfinite(err).flatten(1).all(1) & torch.isfinite(P).flatten(1).all(1)
    final = status[:, -1]
    relost = track.vehicle_counts.get("lost")
    lost = None
    if relost is not None:
        lost = (relost.to(dev) > 0) & ((final == STATUS_CODE["lost"])
                                       | (final == STATUS_CODE["acquiring"]))
    levels = [track.hpl] + ([] if track.hpl_extra is None else list(track.hpl_extra.unbind(-1)))
    protection = {float(r): h.to(dev, dtype) for r, h in zip(risks, levels, strict=False)}
    return FilterRun(
        method=name, t=truth.t, err=err, P=P, nis=track.nis.to(dev, dtype), residual=residual,
        updated=updated, est_on_map=status != STATUS_CODE["off_map"],
        off_map=~truth.on_map.all(dim=1), healthy=track.healthy.to(dev).all(1) & finite,
        elapsed_s=elapsed_s, lost=lost, status=status,
        vehicle_counts={k: v.to(dev) for k, v in track.vehicle_counts.items()},
        counts=dict(track.counts), protection=protection)


def run_filter(
    truth: Truth,
    linearizer: Linearizer,
    scenario: Scenario,
    *,
    progress: bool | Any = False,
    method: str = "",
    policy: Any = None,
    model: Any = None,
) -> FilterRun:
    """Flies the 5-state TAN EKF with one linearisation over all N runs, through the
    `Navigator` (method ``ekf``, the study integrity settings `STUDY_INTEGRITY`).

    The filter starts from ``δX̂ = 0``, ``P = diag(P0_diag)`` and uses ``Q = diag(Q_diag)``
    and ``R = R_m2 + fit_variance_m2 + lin.variance`` (SEEDS 004). It runs in the dtype
    and on the device of ``truth``; the linearizer's outputs are cast to them.

    Args:
        truth: Simulated truth (`neuralmap.lab.simulator.simulate`).
        linearizer: The map linearisation method.
        scenario: Supplies the filter tuning (``P0_diag``, ``Q_diag``, ``R_m2``,
            ``fit_variance_m2``, ``dt``).
        progress: True shows a progress bar over the steps (plain lines when stdout is
            not a terminal, `neuralmap.progress`); a tqdm bar object is advanced by
            one per step instead (used by `run_monte_carlo`).
        method: Method name stored in the result.
        policy: Optional robust/adaptive update policy (`neuralmap.filters.policies`),
            reset first; every `QualityR` inside it gets the altimeter's quality record
            (``truth.quality``) before each update. Epochs with a loss of lock (NaN
            clearance) are not updated.
        model: The filter's model; None = ``TanModel.from_scenario(scenario)``. An
            augmented model (`neuralmap.tan.augmented.AugmentedTanModel`, with
            ``n_states > 5`` and a ``jacobian``) runs the augmented filter; the result
            keeps the 5 navigation states (``err``, ``P``).

    Returns:
        `FilterRun`.

    Raises:
        NeuralMapError: The map was made from another tile than the truth's.
    """
    from neuralmap.tan.ekf_step import linearizer_map

    scenario.validate()
    check_map_matches(linearizer, truth, method=method)
    if model is None:
        model = TanModel.from_scenario(scenario)
    options = {"linearizer": linearizer, "policy": "ekf" if policy is None else policy,
               "dtype": "float32" if truth.pos.dtype == torch.float32 else "float64"}
    config = study_navigator_config(scenario, {"method": "ekf", "ekf": options})
    # the Navigator needs the map's extent: the linearizer's map, or (a linearizer that does
    # not expose one) the simulated tile's (its truth terrain; the EKF reads only its own)
    terrain = linearizer_map(linearizer)
    if terrain is None:
        terrain = getattr(truth.terrain, "model", None)
    if terrain is None:
        raise NeuralMapError(f"method {method!r}: the linearizer reads no map with an extent "
                             "(its .terrain, .grid or .model) and the truth has no terrain; "
                             "it cannot fly.")
    bar, own_bar = None, False
    if progress is True:
        from neuralmap.progress import progress_bar

        bar, own_bar = progress_bar(total=truth.n_steps, desc=method or "filter", unit="step"), True
    elif progress is not False and progress is not None:
        bar = progress
    tick = None if bar is None else (lambda f: bar.update(f * truth.n_steps))
    try:
        return fly(truth, terrain, config, model=model,
                   map_error_variance=float(model.base_R) - float(model.R_altimeter),
                   name=method, quality=bool(quality_members(policy)), progress=tick)
    finally:
        if own_bar:
            bar.close()


@dataclass(frozen=True)
class FilterJob:
    """One filter of `run_filters`: what `run_filter` takes besides the truth.

    Attributes:
        linearizer: The map linearisation method.
        scenario: The filter tuning (``P0_diag``, ``Q_diag``, ``R_m2``...).
        policy: Optional update policy (reset before the run).
        model: Optional filter model (None = the scenario's 5-state model).
    """

    linearizer: Any
    scenario: Scenario
    policy: Any = None
    model: Any = None


def _filter_task(truth: Truth, job: tuple[str, FilterJob, int]) -> FilterRun:
    """One filter on a cluster's worker, on the caller's torch thread count."""
    name, filter_job, threads = job
    torch.set_num_threads(threads)
    return run_filter(truth, filter_job.linearizer, filter_job.scenario, method=name,
                      policy=filter_job.policy, model=filter_job.model)


def run_filters(
    truth: Truth,
    jobs: dict[str, FilterJob],
    *,
    cluster: Any = None,
    progress: bool = False,
) -> dict[str, FilterRun]:
    """Runs several filters on the same truth, in this process or on a Dask cluster.

    On a cluster the truth is scattered to the workers once and every filter is one task,
    run with this process's torch thread count, so each `FilterRun` is bit-identical
    to `run_filter` here; the progress bar advances as filters finish (with
    heartbeat lines while waiting).

    Args:
        truth: The simulated truth every filter flies.
        jobs: Filter name to its `FilterJob` (picklable on a cluster: linearizers,
            policies and models travel to the workers).
        cluster: `neuralmap.cluster.open_cluster`'s value: None/``"none"`` = this
            process, ``"local:N"``, a scheduler address, or an open ``distributed.Client``.
        progress: A progress bar over the filters' steps (this process) or over the
            filters (a cluster).

    Returns:
        Filter name to its `FilterRun`, in the order of ``jobs``.

    Raises:
        NeuralMapError: A map of another tile, a bad ``cluster``, Dask not installed.
    """
    from neuralmap.cluster import open_cluster
    from neuralmap.progress import progress_bar

    for name, job in jobs.items():
        check_map_matches(job.linearizer, truth, method=name)
    with open_cluster(cluster) as dispatcher:
        if dispatcher.client is None:
            bar = progress_bar(total=len(jobs) * truth.n_steps, desc="Monte Carlo",
                               unit="step") if progress else None
            runs: dict[str, FilterRun] = {}
            try:
                for name, job in jobs.items():
                    if bar is not None:
                        bar.set_description(f"Monte Carlo [{name}]")
                    runs[name] = run_filter(truth, job.linearizer, job.scenario,
                                            progress=bar if bar is not None else False,
                                            method=name, policy=job.policy, model=job.model)
            finally:
                if bar is not None:
                    bar.close()
            return runs
        bar = progress_bar(total=len(jobs), unit="filter", desc=(
            f"Monte Carlo ({len(jobs)} filters, {dispatcher.description})")) if progress else None
        threads = torch.get_num_threads()
        if threads > 1:
            print(f"note: each filter task runs on {threads} torch threads (this process's "
                  "count, for results bit-identical to it); with one worker per core pass "
                  "--threads 1", flush=True)
        try:
            done = dispatcher.map(
                _filter_task, [(name, job, threads) for name, job in jobs.items()],
                shared=truth, name="tan-filter",
                on_done=None if bar is None else lambda _, __: bar.update(1),
                on_idle=None if bar is None else lambda: bar.update(0))
        finally:
            if bar is not None:
                bar.close()
        return dict(zip(jobs, done, strict=True))


def run_monte_carlo(
    scenario: Scenario | str,
    methods: dict[str, Linearizer],
    *,
    n_runs: int,
    seed: int | None = None,
    progress: bool = True,
    device: str | torch.device = "cpu",
    dtype: torch.dtype = torch.float64,
    tile: DemTile | None = None,
    truth_terrain: Any = None,
    cluster: Any = None,
) -> MonteCarloResult:
    """Simulates the truth once and runs the TAN EKF with every linearisation method.

    Every method sees the same truth (same trajectories, INS errors and altimeter noise),
    so differences between methods are the methods'. The linearizers are moved to
    ``device`` (their parameter dtype is kept; outputs are cast to ``dtype``).

    Args:
        scenario: A `Scenario` or a shipped name / YAML path.
        methods: Method name to linearizer, e.g. ``{"neural": ..., "bilinear": ...}``.
        n_runs: Number of Monte Carlo runs N.
        seed: Simulation seed; None = ``scenario.seed``.
        progress: Show one progress bar over methods × steps (one line per method
            when stdout is not a terminal).
        device: Device of the truth and the filters.
        dtype: Filter dtype (float64 default).
        tile: The scenario's tile, when already loaded (else `scenario_tile`).
        truth_terrain: The truth terrain, when already built
            (`neuralmap.lab.truth_terrain.true_terrain`; else built from the seed).
        cluster: Where the methods' filters run (`run_filters`): None = this
            process, else one task per method on a Dask cluster (bit-identical).

    Returns:
        `MonteCarloResult` ``(truth, runs)``.

    Raises:
        NeuralMapError: Bad scenario, empty ``methods``, a map of another tile, a bad
            ``cluster``.
    """
    scenario = load_scenario(scenario)
    if not isinstance(methods, dict) or not methods:
        raise NeuralMapError(
            "run_monte_carlo: methods must be a non-empty dict of name -> Linearizer, got "
            f"{methods!r}."
        )
    if tile is None:
        tile = scenario_tile(scenario)
    truth = simulate(scenario, tile, n_runs=n_runs, seed=seed, dtype=dtype, device=device,
                     truth_terrain=truth_terrain)
    for name, linearizer in methods.items():
        check_map_matches(linearizer, truth, method=name)
        if isinstance(linearizer, torch.nn.Module):
            linearizer.to(device)
    runs = run_filters(truth, {name: FilterJob(lin, scenario) for name, lin in methods.items()},
                       cluster=cluster, progress=progress)
    return MonteCarloResult(truth, runs)
