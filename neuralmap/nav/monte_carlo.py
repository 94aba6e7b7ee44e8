"""Monte Carlo TAN runs: the batched EKF over simulated truth, one method at a time.

`run_filter` runs the 5-state TAN EKF (`neuralmap.nav.tan.tan_filter_step`) for
all N runs of a `Truth` at once with one linearisation
method; `run_monte_carlo` simulates the truth once and runs every method on it;
`run_filters` runs several filters on one truth, in this process or one filter per
task on a Dask cluster (`neuralmap.cluster`; bit-identical to this process).

Timing convention: sample 0 is the prior (``δX̂_0 = 0``, ``P_0 = diag(P0_diag)``, no
altimeter update at t = 0, matching the PCRB's ``J_0 = P_0⁻¹``); steps ``k = 1 … K`` each
predict and update with the altimeter sample ``k``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any, NamedTuple

import torch

from neuralmap.dem.tile import DemTile
from neuralmap.exceptions import NeuralMapError
from neuralmap.filters.policies.compose import quality_members
from neuralmap.linearize.base import Linearizer
from neuralmap.nav.model import N_STATES, TanModel
from neuralmap.nav.scenario import Scenario, load_scenario, scenario_tile
from neuralmap.nav.simulator import Truth, simulate
from neuralmap.nav.tan import tan_filter_step
from neuralmap.terrain.base import inside_extent


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
        lost: ``(N,)`` bool, runs the filter itself declared lost (the point-mass tracker's
            ``lost`` flag: widened beyond recovery); they count as diverged
            (`neuralmap.nav.metrics.diverged_runs`). None: the filter declares none.
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
    """Runs the 5-state TAN EKF over all N runs with one linearisation method.

    The filter starts from ``δX̂ = 0``, ``P = diag(P0_diag)`` and uses ``Q = diag(Q_diag)``
    and ``R = R_m2 + fit_variance_m2 + lin.variance`` (SEEDS 004). It runs in the dtype
    and on the device of ``truth``; the linearizer's outputs are cast to them.

    Args:
        truth: Simulated truth (`neuralmap.nav.simulator.simulate`).
        linearizer: The map linearisation method.
        scenario: Supplies the filter tuning (``P0_diag``, ``Q_diag``, ``R_m2``,
            ``fit_variance_m2``, ``dt``).
        progress: True shows a progress bar over the steps (plain lines when stdout is
            not a terminal, `neuralmap.progress`); a tqdm bar object is advanced by
            one per step instead (used by `run_monte_carlo`).
        method: Method name stored in the result.
        policy: Optional robust/adaptive update policy (`neuralmap.filters.policies`),
            reset first; every `QualityR` inside it gets
            the altimeter's quality record (``truth.quality``) before each update. Epochs
            with a loss of lock (NaN clearance) are not updated.
        model: The filter's model; None = ``TanModel.from_scenario(scenario)``. An
            augmented model (`neuralmap.nav.augmented.AugmentedTanModel`, with
            ``n_states > 5`` and a ``jacobian``) runs the augmented filter; the result
            keeps the 5 navigation states (``err``, ``P``).

    Returns:
        `FilterRun`.

    Raises:
        NeuralMapError: The map was made from another tile than the truth's.
    """
    from neuralmap.filters.ekf import BatchedEKF

    scenario.validate()
    check_map_matches(linearizer, truth, method=method)
    dtype, device = truth.pos.dtype, truth.pos.device
    n, k_steps = truth.n_runs, truth.n_steps
    if model is None:
        model = TanModel.from_scenario(scenario)
    n_states = int(getattr(model, "n_states", N_STATES))
    jacobian = model.jacobian if n_states > N_STATES else None
    ekf = BatchedEKF(torch.zeros(n, n_states, dtype=dtype, device=device),
                     model.filter_prior(dtype=dtype, device=device))
    F = model.transition(dtype=dtype, device=device)
    Q = model.filter_process_noise(dtype=dtype, device=device)
    R = model.base_R

    err = torch.empty(n, k_steps + 1, N_STATES, dtype=dtype, device=device)
    P_hist = torch.empty(n, k_steps + 1, N_STATES, N_STATES, dtype=dtype, device=device)
    nis = torch.full((n, k_steps + 1), float("nan"), dtype=dtype, device=device)
    residual = torch.zeros(n, k_steps + 1, dtype=dtype, device=device)
    updated = torch.zeros(n, k_steps + 1, dtype=torch.bool, device=device)
    est_on_map = torch.ones(n, k_steps + 1, dtype=torch.bool, device=device)
    err[:, 0] = truth.ins_error[:, 0] - ekf.x[:, :N_STATES]
    P_hist[:, 0] = ekf.P[:, :N_STATES, :N_STATES]
    est_on_map[:, 0] = inside_extent(truth.ins_pos[:, 0, :2], truth.extent)

    bar, own_bar = None, False
    if progress is True:
        from neuralmap.progress import progress_bar

        bar, own_bar = progress_bar(total=k_steps, desc=method or "filter", unit="step"), True
    elif progress is not False and progress is not None:
        bar = progress
    quality_policies = quality_members(policy)
    if policy is not None:
        policy.reset()
    if quality_policies and getattr(truth, "quality", None) is None:
        raise NeuralMapError(
            f"method {method!r}: the policy needs the altimeter quality record, but the truth "
            "has none; simulate it with neuralmap.nav.simulator.simulate."
        )
    lock_lost = not bool(torch.isfinite(truth.radar[:, 1:]).all())
    start = time.perf_counter()
    try:
        for k in range(1, k_steps + 1):
            radar = truth.radar[:, k]
            for quality_policy in quality_policies:
                quality_policy.set_quality(truth.quality[:, k])
            diag = tan_filter_step(
                ekf, truth.ins_pos[:, k], radar, linearizer, F=F, Q=Q, R=R,
                extent=truth.extent, mask=torch.isfinite(radar) if lock_lost else None,
                policy=policy, jacobian=jacobian,
            )
            if ekf.x.requires_grad or ekf.P.requires_grad:  # a graph-keeping linearizer
                ekf.x, ekf.P = ekf.x.detach(), ekf.P.detach()
            err[:, k] = truth.ins_error[:, k] - ekf.x[:, :N_STATES]
            P_hist[:, k] = ekf.P[:, :N_STATES, :N_STATES]
            upd = diag.updated.detach()
            nis[:, k] = torch.where(upd, diag.nis.detach(), nis[:, k])
            residual[:, k] = torch.where(upd, diag.residual.detach(), residual[:, k])
            updated[:, k] = upd
            est_on_map[:, k] = diag.on_map
            if bar is not None:
                bar.update(1)
    finally:
        if own_bar:
            bar.close()
    elapsed = time.perf_counter() - start
    # Only the truth leaving the map excludes a run; an estimate that leaves the map is a
    # filter failure and counts as diverged in the metrics (est_on_map).
    off_map = ~truth.on_map.all(dim=1)
    return FilterRun(
        method=method, t=truth.t, err=err, P=P_hist, nis=nis, residual=residual,
        updated=updated, est_on_map=est_on_map, off_map=off_map,
        healthy=ekf.healthy.clone(), elapsed_s=elapsed,
    )




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
            (`neuralmap.nav.truth_terrain.true_terrain`; else built from the seed).
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
