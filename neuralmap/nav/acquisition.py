"""TAN acquisition from large initial errors: point mass or EKF bank, hand-off to the EKF.

An EKF linearises the map at one hypothesis; once the initial horizontal uncertainty spans
several terrain correlation lengths it locks onto the wrong one. This module runs the
grid-based Bayes filter (`PointMassFilter`, the
point-mass filter of Bergman, Ljung and Gustafsson; horizontal error on the grid, altitude
error Rao-Blackwellised per cell) or the EKF bank
(`GaussianSumEKF`) over all Monte Carlo runs at once,
and hands each run to the 5-state TAN EKF (``point_mass_ekf``) or to the whole-flight
point-mass tracker (``point_mass_tracker``, `neuralmap.nav.tracker_handoff`) once its
posterior is unimodal and small. Grid cells whose position lies off the map get zero
likelihood (``map_support``).

Measurement per cell (the TAN altimeter model, SEEDS 004): with the INS error
``δX = [δp, δh, δv]`` (INS − truth), ``y = h_ins − h_radar = t(p_ins − δp) + δh − v``, i.e.
the point-mass model ``y = g(s) + a + e`` with ``s = δp``, ``g(s) = t(p_ins − s)`` evaluated
on the map under test (grid or neural; one batched forward over every cell of every run),
``a = δh`` and ``R = R_m2 + fit_variance_m2`` (altimeter + the map's error variance).

Velocity error: the grid carries the horizontal error only. Its prediction uses the
position marginal of the prior ``[δp, δv]`` model (per axis ``P_pp ← P_pp + 2T P_pv + T² P_pv
+ q_p``, ``P_pv ← P_pv + T P_vv``, ``P_vv ← P_vv + q_v``): the process noise of step k is the
growth of ``P_pp``. At hand-off (and for the point-mass output) the velocity error is the
Gaussian conditional on the position posterior ``N(μ, Σ)``: ``B = P_pv / P_pp`` (per axis),
``δv̂ = v₀ + B (μ − m_p)``, ``cov(δv) = P_vv − B P_pp B + B Σ B``, ``cov(δp, δv) = Σ B`` —
exact for a linear-Gaussian position measurement at the hand-off time, an approximation
otherwise (stated in the study report).

Hand-off test (`handoff_ready`): the grid posterior is **unimodal** — the
Bhattacharyya coefficient between it and its Gaussian fit is ≥ ``handoff_affinity`` — and
**small** — the largest standard deviation ``sqrt(λ_max(Σ))`` ≤ ``handoff_sigma_m`` — for
``handoff_hold`` consecutive steps, and at least ``min_acquire_steps`` have passed.

Fall-back (`lost_lock`): a tracking run whose mean NIS over the last
``fallback_window`` updates exceeds ``χ²_{p}(W) / W`` (``p = fallback_prob``) has lost
lock; its grid is re-initialised around the EKF estimate with the EKF's horizontal
covariance inflated to at least ``reacquire_sigma_m`` per axis.

Spike gate (``spike_gate_prob`` > 0, default off): a clearance whose predictive NIS against
the predicted grid mixture exceeds ``χ²₁(p)`` is not used by the grid
(`neuralmap.nav.spike_gate`); counted per run in ``extra["spikes"]``.

Coupling to the TAN model is kept to `tan_inputs` (truth/scenario → tensors) and the
call of `neuralmap.nav.tan.tan_filter_step`.
"""

from __future__ import annotations

import dataclasses
import functools
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.filters.ekf import BatchedEKF
from neuralmap.filters.ekf_bank import GaussianSumEKF, lattice_prior
from neuralmap.filters.point_mass import PointMassConfig, PointMassFilter
from neuralmap.nav.cell_variance import cell_height_variance
from neuralmap.nav.monte_carlo import FilterRun
from neuralmap.nav.spike_gate import predictive_nis, spiked
from neuralmap.nav.tan import N_STATES, tan_filter_step, transition_matrix
from neuralmap.nav.tracker_handoff import grid_posterior_moments
from neuralmap.terrain.base import inside_extent

__all__ = [
    "ACQUISITION_METHODS",
    "AcquisitionConfig",
    "AcquisitionResult",
    "TanInputs",
    "acquisition_time",
    "cell_height_variance",
    "cells_on_map",
    "handoff_ready",
    "lattice_bilinear",
    "lost_lock",
    "run_acquisition",
    "tan_inputs",
]

#: ``ekf`` (the TAN EKF alone), ``bank`` (EKF bank), ``point_mass`` (grid all the way),
#: ``point_mass_ekf`` (grid, hand-off to the EKF, fall-back on lost lock),
#: ``point_mass_tracker`` (grid, hand-off to the Rao-Blackwellised tracker whose lattice
#: follows the posterior, `neuralmap.nav.tracker_handoff`; fall-back as for the EKF).
ACQUISITION_METHODS = ("ekf", "bank", "point_mass", "point_mass_ekf", "point_mass_tracker")


@dataclass
class AcquisitionConfig:
    """Options of `run_acquisition` (defaults fit the jacksboro scenario).

    Attributes:
        cells: Point-mass grid cells per axis; None = from the prior: the fewest cells
            (≥ 32, ≤ ``max_cells``) that cover ± ``span_sigma`` σ at ``max_spacing_m``.
        max_spacing_m: Largest initial spacing when ``cells`` is None, m.
        max_cells: Most cells per axis when ``cells`` is None.
        span_sigma: Grid half-width in standard deviations.
        min_spacing_m: Finest grid spacing, m.
        dtype: Point-mass dtype, ``"float32"`` or ``"float64"``.
        outlier_prob: Altimeter outlier probability of the likelihood (0 = Gaussian).
        outlier_width_m: Width of the uniform outlier density, m.
        spike_gate_prob: Altimeter spike gate of the grid (`neuralmap.nav.spike_gate`): a
            clearance whose predictive NIS against the predicted grid mixture exceeds
            ``χ²₁(p)`` is not used (that run's grid is predicted only; counted in
            ``extra["spikes"]``), as the navigator's tracker does with
            ``integrity.spike_gate_prob``. 0 (default) = no gate.
        handoff_sigma_m: Largest posterior standard deviation allowed at hand-off, m.
        handoff_affinity: Smallest Bhattacharyya coefficient grid-vs-Gaussian-fit.
        handoff_hold: Consecutive steps the test must pass.
        min_acquire_steps: Steps of acquisition before a hand-off is allowed.
        velocity_from_grid: Condition the velocity error on the grid posterior (module
            docstring); False hands off ``δv̂ = v₀``, ``cov = P_vv`` and no correlation.
        adaptive: Re-centre and re-size the grid (default False: the prior's grid
            throughout; jacksboro, σ0 = 1 km, 100 runs, point mass → EKF: the fixed
            161² grid at 50 m diverged in 0 runs, the adaptive one in 4-5 — a posterior
            that collapses early is cut to its grid; worth it only for long point-mass
            runs, where its speed matters).
        min_half_width_m: The adaptive grid never shrinks below ± this, m (jacksboro,
            σ0 = 1 km, 100 runs: without it a posterior that collapsed early onto a wrong
            mode cut the truth off its grid in 5 runs; a fixed grid diverged in none).
        flatten_likelihood: Add the map's height spread over each cell
            (`cell_height_variance`) to the likelihood's variance, so a coarse grid
            cannot step over a likelihood peak narrower than a cell.
        fallback_window: NIS window W of the lost-lock test (0 disables fall-back).
        fallback_prob: Probability of the χ² threshold of the mean NIS.
        reacquire_sigma_m: Smallest per-axis standard deviation of a re-acquisition grid.
        map_support: Give grid cells whose position ``p_ins − δp`` lies off the map zero
            likelihood (the truth flies over the map; the study excludes runs whose truth
            leaves it). Without it, cells beyond the border read the clamped edge heights
            and can pull an acquiring run's mean off the map (jacksboro, σ0 = 1 km, 999
            runs: 6 estimates left the map for 1–4 steps while acquiring, each counted
            diverged though all converged to < 15 m).
        tracker_cells: Lattice cells per axis of the tracker that ``point_mass_tracker``
            hands off to (`neuralmap.nav.tracker_handoff`).
        bank_per_axis: EKF-bank components per axis (K = per_axis²).
        bank_span_sigma: Half-width of the bank's lattice, prior σ.
        bank_prune: Relative weight under which a bank component is pruned.
        bank_merge: Squared Mahalanobis distance under which components merge.
    """

    cells: int | None = None
    max_spacing_m: float = 50.0
    max_cells: int = 256
    span_sigma: float = 4.0
    min_spacing_m: float = 2.0
    dtype: str = "float32"
    outlier_prob: float = 0.0
    outlier_width_m: float = 1000.0
    spike_gate_prob: float = 0.0
    handoff_sigma_m: float = 40.0
    handoff_affinity: float = 0.9
    handoff_hold: int = 3
    min_acquire_steps: int = 5
    velocity_from_grid: bool = True
    flatten_likelihood: bool = True
    adaptive: bool = False
    min_half_width_m: float = 600.0
    fallback_window: int = 20
    fallback_prob: float = 0.99999
    reacquire_sigma_m: float = 200.0
    map_support: bool = True
    tracker_cells: int = 32
    bank_per_axis: int = 7
    bank_span_sigma: float = 2.5
    bank_prune: float = 1e-4
    bank_merge: float = 1.0

    def validate(self) -> AcquisitionConfig:
        """Checks ranges; raises `NeuralMapError` naming the bad option."""
        if self.dtype not in ("float32", "float64"):
            raise NeuralMapError(
                f"AcquisitionConfig: dtype must be 'float32' or 'float64', got {self.dtype!r}."
            )
        for key in ("handoff_sigma_m", "reacquire_sigma_m", "min_spacing_m", "span_sigma",
                    "bank_span_sigma"):
            if not getattr(self, key) > 0:
                raise NeuralMapError(
                    f"AcquisitionConfig: '{key}' must be > 0, got {getattr(self, key)!r}."
                )
        if not 0.0 < self.handoff_affinity <= 1.0:
            raise NeuralMapError(
                f"AcquisitionConfig: 'handoff_affinity' must be in (0, 1], got "
                f"{self.handoff_affinity!r}."
            )
        if not 0.0 <= self.spike_gate_prob < 1.0:
            raise NeuralMapError(
                f"AcquisitionConfig: 'spike_gate_prob' must be in [0, 1) (0 = no gate), got "
                f"{self.spike_gate_prob!r}."
            )
        if not 0.0 < self.fallback_prob < 1.0:
            raise NeuralMapError(
                f"AcquisitionConfig: 'fallback_prob' must be in (0, 1), got {self.fallback_prob!r}."
            )
        if isinstance(self.tracker_cells, bool) or not isinstance(self.tracker_cells, int) or (
                self.tracker_cells < 8):
            raise NeuralMapError(
                f"AcquisitionConfig: 'tracker_cells' must be an integer >= 8, got "
                f"{self.tracker_cells!r}.")
        for key in ("handoff_hold", "min_acquire_steps", "fallback_window", "bank_per_axis"):
            value = getattr(self, key)
            if isinstance(value, bool) or not isinstance(value, int) or value < 0:
                raise NeuralMapError(
                    f"AcquisitionConfig: '{key}' must be an integer >= 0, got {value!r}."
                )
        self.point_mass_config()
        return self

    def grid_cells(self, sigma: float) -> int:
        """Cells per axis for a prior of largest standard deviation ``sigma``."""
        if self.cells is not None:
            return int(self.cells)
        need = 2.0 * self.span_sigma * sigma / self.max_spacing_m + 1.0
        return int(min(max(math.ceil(need), 32), self.max_cells))

    def point_mass_config(self, sigma: float = 0.0) -> PointMassConfig:
        """The grid options as a `PointMassConfig` (validated) for a prior of
        largest standard deviation ``sigma``."""
        return PointMassConfig(
            cells=self.grid_cells(sigma), span_sigma=self.span_sigma, min_spacing=self.min_spacing_m,
            adaptive=self.adaptive, min_half_width=self.min_half_width_m,
            outlier_prob=self.outlier_prob, outlier_width=self.outlier_width_m,
        ).validate()


@dataclass
class TanInputs:
    """What acquisition needs from the TAN model (one thin adapter, `tan_inputs`).

    Attributes:
        ins_pos: ``(N, K+1, 3)`` INS positions.
        radar: ``(N, K+1)`` radar-altimeter clearances.
        ins_error: ``(N, K+1, 5)`` true INS errors (for the error outputs only).
        P0: ``(5, 5)`` filter prior covariance.
        Q: ``(5, 5)`` filter process noise per step.
        R: Altimeter + map error variance, m².
        dt: Filter period, s.
        extent: Map extent ``(xmin, xmax, ymin, ymax)``.
        on_map: ``(N, K+1)`` bool, truth on the map.
    """

    ins_pos: torch.Tensor
    radar: torch.Tensor
    ins_error: torch.Tensor
    P0: torch.Tensor
    Q: torch.Tensor
    R: float
    dt: float
    extent: tuple[float, float, float, float]
    on_map: torch.Tensor


def tan_inputs(truth: Any, scenario: Any) -> TanInputs:
    """Adapter from the simulator's truth and the scenario to `TanInputs`."""
    dtype, device = truth.pos.dtype, truth.pos.device
    return TanInputs(
        ins_pos=truth.ins_pos, radar=truth.radar, ins_error=truth.ins_error,
        P0=torch.diag(torch.tensor(scenario.P0_diag, dtype=dtype, device=device)),
        Q=torch.diag(torch.tensor(scenario.Q_diag, dtype=dtype, device=device)),
        R=float(scenario.R_m2 + scenario.fit_variance_m2), dt=float(scenario.dt),
        extent=tuple(truth.extent), on_map=truth.on_map,
    )


@dataclass
class AcquisitionResult:
    """One method's run: the standard `FilterRun` plus acquisition diagnostics.

    Attributes:
        run: Errors, covariances, NIS etc. of the output estimate (acquisition included).
        handoff_step: ``(N,)`` step of the first hand-off to the EKF (−1 = never).
        n_fallbacks: ``(N,)`` number of lost-lock fall-backs.
        recoveries: ``(N,)`` updates whose likelihood vanished in every cell/component.
        acquiring: ``(N, K+1)`` bool, the run was in acquisition at that step.
        elapsed_s: Wall time of the filter loop, s.
        cell_updates: Total grid-cell (or component) measurement updates performed.
    """

    run: FilterRun
    handoff_step: torch.Tensor
    n_fallbacks: torch.Tensor
    recoveries: torch.Tensor
    acquiring: torch.Tensor
    elapsed_s: float
    cell_updates: int
    extra: dict[str, Any] = field(default_factory=dict)


def handoff_ready(
    affinity: torch.Tensor, cov: torch.Tensor, *, max_sigma: float, min_affinity: float
) -> torch.Tensor:
    """The hand-off test of one step: unimodal (affinity) and small (largest σ).

    Args:
        affinity: ``(N,)`` Bhattacharyya coefficient grid posterior vs its Gaussian fit.
        cov: ``(N, 2, 2)`` posterior horizontal covariance.
        max_sigma: Largest allowed ``sqrt(λ_max(cov))``, m.
        min_affinity: Smallest allowed affinity.

    Returns:
        ``(N,)`` bool.
    """
    lam = torch.linalg.eigvalsh(cov.double())[:, -1].clamp_min(0.0)
    return (affinity >= min_affinity) & (lam.sqrt() <= max_sigma)


@functools.lru_cache(maxsize=64)
def _chi2_ppf(prob: float, dof: int) -> float:
    from neuralmap.nav.metrics import chi2_quantile

    return chi2_quantile(prob, dof)


def lost_lock(nis_window: torch.Tensor, count: torch.Tensor, *, prob: float) -> torch.Tensor:
    """The lost-lock test: mean NIS over a full window above ``χ²_prob(W) / W``.

    Args:
        nis_window: ``(N, W)`` last W NIS values.
        count: ``(N,)`` valid entries in the window.
        prob: χ² probability of the threshold.

    Returns:
        ``(N,)`` bool.
    """
    w = nis_window.shape[1]
    threshold = _chi2_ppf(prob, w) / w
    return (count >= w) & (nis_window.mean(1) > threshold)


def lattice_bilinear(
    terrain: Any, ins_xy: torch.Tensor, centre: torch.Tensor, spacing: torch.Tensor,
    offsets: torch.Tensor,
) -> torch.Tensor:
    """Bilinear map heights at ``p_ins − s`` for every cell of axis-aligned grids (fast path).

    Equals ``GridTerrain(tile, method="bilinear")(ins_xy − points)`` (border clamping
    included), but the cell arithmetic runs per grid row and column ``(N, G)`` and only the
    four corner gathers and the blend run per cell.

    Args:
        terrain: A bilinear `GridTerrain`.
        ins_xy: ``(N, 2)`` INS horizontal positions.
        centre: ``(N, 2)`` grid centres (state space: INS − truth).
        spacing: ``(N, 2)`` grid spacings.
        offsets: ``(G,)`` cell offsets ``j − (G − 1)/2``.

    Returns:
        ``(N, G, G)`` heights in the dtype of ``centre``.
    """
    ny, nx = terrain.shape
    (x0, y0), (dx, dy) = terrain.origin, terrain.spacing
    dt = centre.dtype
    xs = ins_xy[:, 0:1].to(dt) - (centre[:, 0:1] + spacing[:, 0:1] * offsets)  # (N, G)
    ys = ins_xy[:, 1:2].to(dt) - (centre[:, 1:2] + spacing[:, 1:2] * offsets)
    u = ((xs - x0) / dx).clamp(0.0, nx - 1.0)
    v = ((ys - y0) / dy).clamp(0.0, ny - 1.0)
    jf = u.floor().clamp(max=nx - 2.0)
    i_f = v.floor().clamp(max=ny - 2.0)
    fu, fv = (u - jf)[:, None, :], (v - i_f)[:, :, None]
    idx = (i_f.long() * nx)[:, :, None] + jf.long()[:, None, :]
    flat = terrain.heights.view(-1)
    if flat.dtype != dt:
        flat = flat.to(dt)
    shape = idx.shape
    idx = idx.reshape(-1)
    h00 = flat.index_select(0, idx).view(shape)
    h01 = flat[1:].index_select(0, idx).view(shape)
    south = torch.lerp(h00, h01, fu)
    h10 = flat[nx:].index_select(0, idx).view(shape)
    h11 = flat[nx + 1 :].index_select(0, idx).view(shape)
    return torch.lerp(south, torch.lerp(h10, h11, fu), fv)


def cells_on_map(ins_xy: torch.Tensor, centre: torch.Tensor, spacing: torch.Tensor,
                 offsets: torch.Tensor, extent: tuple[float, ...]) -> torch.Tensor:
    """``(N, G, G)`` bool: the cell's position ``p_ins − s`` lies on the map.

    Separable (rows ``i`` along y, columns ``j`` along x, as `lattice_bilinear`):
    the test runs per grid row and column ``(N, G)`` and one outer product per cell.

    Args:
        ins_xy: ``(N, 2)`` INS horizontal positions.
        centre: ``(N, 2)`` grid centres (state space: INS − truth).
        spacing: ``(N, 2)`` grid spacings.
        offsets: ``(G,)`` cell offsets.
        extent: Map extent ``(xmin, xmax, ymin, ymax)``.
    """
    xmin, xmax, ymin, ymax = extent
    dt = centre.dtype
    xs = ins_xy[:, 0:1].to(dt) - (centre[:, 0:1] + spacing[:, 0:1] * offsets)  # (N, G)
    ys = ins_xy[:, 1:2].to(dt) - (centre[:, 1:2] + spacing[:, 1:2] * offsets)
    inx = (xs >= xmin) & (xs <= xmax)
    iny = (ys >= ymin) & (ys <= ymax)
    return iny[:, :, None] & inx[:, None, :]


def _is_bilinear_grid(terrain: Any) -> bool:
    return getattr(terrain, "method", None) == "bilinear" and hasattr(terrain, "heights")


def _terrain_fn(terrain: torch.nn.Module, ins_xy: torch.Tensor) -> Any:
    """Callable cell coordinates ``(N, G, G, 2)`` → map height at ``p_ins − δp``."""
    try:
        tdtype = next(iter(terrain.parameters())).dtype
    except StopIteration:
        tdtype = None

    def heights(points: torch.Tensor) -> torch.Tensor:
        xy = ins_xy[:, None, None, :].to(points.dtype) - points
        if tdtype is not None and tdtype != xy.dtype:
            xy = xy.to(tdtype)
        with torch.no_grad():
            return terrain(xy).to(points.dtype)

    return heights


def _check_start(inputs: TanInputs) -> None:
    start = inputs.ins_pos[:, 0, :2]
    inside = inside_extent(start, inputs.extent)
    if not bool(inside.all()):
        first = int((~inside).nonzero()[0])
        raise NeuralMapError(
            f"run_acquisition: run {first} starts off the map (INS position "
            f"{start[first].tolist()} outside the extent {list(inputs.extent)}). Move the "
            "scenario's start_xy inside the tile, leaving the initial uncertainty on it."
        )


def run_acquisition(
    inputs: TanInputs,
    *,
    method: str,
    terrain: torch.nn.Module | None = None,
    linearizer: Any = None,
    config: AcquisitionConfig | None = None,
    name: str = "",
    progress: Callable[[float], None] | None = None,
) -> AcquisitionResult:
    """Runs one acquisition method over all runs (see the module docstring).

    Args:
        inputs: From `tan_inputs`.
        method: One of `ACQUISITION_METHODS`.
        terrain: Map evaluated for the grid likelihood (``point_mass*``).
        linearizer: Linearisation for the EKF and the bank (``ekf``, ``bank``,
            ``point_mass_ekf``).
        config: Options (`AcquisitionConfig`).
        name: Method name stored in the run.
        progress: Called with ``1/K`` as each of the K filter steps starts (the fraction of
            the run done, e.g. a progress bar's ``update``); None = silent.

    Returns:
        `AcquisitionResult`.

    Raises:
        NeuralMapError: Unknown method, missing terrain/linearizer, runs starting off the
            map, or bad options.
    """
    cfg = (config or AcquisitionConfig()).validate()
    if method not in ACQUISITION_METHODS:
        raise NeuralMapError(
            f"run_acquisition: unknown method {method!r}; choose one of "
            f"{', '.join(ACQUISITION_METHODS)}."
        )
    if method.startswith("point_mass") and terrain is None:
        raise NeuralMapError(f"run_acquisition: method {method!r} needs a terrain model.")
    if method not in ("point_mass", "point_mass_tracker") and linearizer is None:
        raise NeuralMapError(f"run_acquisition: method {method!r} needs a linearizer.")
    _check_start(inputs)
    if method == "bank":
        return _run_bank(inputs, linearizer, cfg, name or method, progress)
    return _run_grid(inputs, method, terrain, linearizer, cfg, name or method, progress)


def _tracker_pool(inputs: TanInputs, cfg: AcquisitionConfig) -> Any:
    """The whole-flight tracker that runs take over at hand-off
    (`TrackerPool`): ``cfg.tracker_cells`` per axis,
    the lattice no finer than one step's transition blur (as in the TAN study), no
    widening of its own (a lost run goes back to the acquisition grid)."""
    from neuralmap.nav.tracker_handoff import TrackerPool
    from neuralmap.nav.tracking import TrackerOptions, transition_blur

    pm_dtype = torch.float32 if cfg.dtype == "float32" else torch.float64
    options = TrackerOptions(cells=cfg.tracker_cells, dtype=cfg.dtype, lost_window=0)
    blur = transition_blur(inputs.P0, inputs.Q, inputs.dt)
    return TrackerPool(inputs.radar.shape[0], inputs.P0, inputs.Q, inputs.dt,
                       options.tracker_config(blur_m=blur), dtype=pm_dtype,
                       dormant_sigma_m=cfg.handoff_sigma_m, out_dtype=inputs.ins_pos.dtype,
                       device=inputs.ins_pos.device)


def _tracker_heights(terrain: Any, ins_xy: torch.Tensor, *, extent: tuple[float, ...]) -> Any:
    """``g(points) = t(p_ins − s)`` on the tracker's lattice (NaN off the map)."""
    from neuralmap.nav.tracking import heights_on_cells

    return heights_on_cells(terrain, ins_xy, extent)


def _outputs(n: int, k_steps: int, dtype: torch.dtype, device: torch.device) -> dict[str, Any]:
    return {
        "err": torch.empty(n, k_steps + 1, N_STATES, dtype=dtype, device=device),
        "P": torch.empty(n, k_steps + 1, N_STATES, N_STATES, dtype=dtype, device=device),
        "nis": torch.full((n, k_steps + 1), float("nan"), dtype=dtype, device=device),
        "residual": torch.zeros(n, k_steps + 1, dtype=dtype, device=device),
        "updated": torch.zeros(n, k_steps + 1, dtype=torch.bool, device=device),
        "est_on_map": torch.ones(n, k_steps + 1, dtype=torch.bool, device=device),
    }


def _finish(inputs: TanInputs, out: dict[str, Any], name: str, healthy: torch.Tensor,
            elapsed: float, lost: torch.Tensor | None = None) -> FilterRun:
    t = torch.arange(inputs.radar.shape[1], dtype=inputs.radar.dtype) * inputs.dt
    return FilterRun(
        method=name, t=t, err=out["err"], P=out["P"], nis=out["nis"],
        residual=out["residual"], updated=out["updated"], est_on_map=out["est_on_map"],
        off_map=~inputs.on_map.all(dim=1), healthy=healthy, elapsed_s=elapsed, lost=lost,
    )


def _run_bank(inputs: TanInputs, linearizer: Any, cfg: AcquisitionConfig,
              name: str, progress: Callable[[float], None] | None = None) -> AcquisitionResult:
    ins, radar = inputs.ins_pos, inputs.radar
    n, k_steps = radar.shape[0], radar.shape[1] - 1
    dtype, device = ins.dtype, ins.device
    x0 = torch.zeros(n, N_STATES, dtype=dtype, device=device)
    means, covs, logw = lattice_prior(x0, inputs.P0, per_axis=cfg.bank_per_axis,
                                      span_sigma=cfg.bank_span_sigma)
    bank = GaussianSumEKF(means, covs, log_weights=logw, prune_threshold=cfg.bank_prune,
                          merge_distance=cfg.bank_merge, dtype=dtype)
    kc = bank.n_components
    F = transition_matrix(inputs.dt, dtype=dtype, device=device)
    out = _outputs(n, k_steps, dtype, device)
    mean, cov = bank.mixture()
    out["err"][:, 0] = inputs.ins_error[:, 0] - mean
    out["P"][:, 0] = cov
    updates = 0
    start = time.perf_counter()
    for k in range(1, k_steps + 1):
        if progress is not None:
            progress(1.0 / k_steps)
        alive = bank.alive
        diag = tan_filter_step(
            bank.ekf, ins[:, k].repeat_interleave(kc, 0), radar[:, k].repeat_interleave(kc, 0),
            linearizer, F=F, Q=inputs.Q, R=inputs.R, extent=inputs.extent, mask=alive,
        )
        updates += int(alive.sum())
        bank.reweight(diag.residual, diag.S, diag.updated)
        mean, cov = bank.mixture()
        out["err"][:, k] = inputs.ins_error[:, k] - mean
        out["P"][:, k] = cov
        best = bank.log_weights.argmax(1) + torch.arange(n, device=device) * kc
        upd = diag.updated[best]
        out["nis"][:, k] = torch.where(upd, diag.nis[best], out["nis"][:, k])
        out["residual"][:, k] = torch.where(upd, diag.residual[best], 0.0)
        out["updated"][:, k] = upd
        out["est_on_map"][:, k] = inside_extent(ins[:, k, :2] - mean[:, :2], inputs.extent)
    elapsed = time.perf_counter() - start
    healthy = bank.alive.reshape(n, kc).any(1)
    run = _finish(inputs, out, name, healthy, elapsed)
    return AcquisitionResult(
        run=run, handoff_step=torch.full((n,), -1), n_fallbacks=torch.zeros(n, dtype=torch.long),
        recoveries=bank.recoveries.clone(), acquiring=torch.ones(n, k_steps + 1, dtype=torch.bool),
        elapsed_s=elapsed, cell_updates=updates,
    )


class _Float32Grid:
    """A bilinear grid's geometry with its heights cast once to float32."""

    def __init__(self, grid: Any) -> None:
        self.shape, self.origin, self.spacing = grid.shape, grid.origin, grid.spacing
        self.heights = grid.heights.to(torch.float32)


class _VelocityPrior:
    """Per-axis ``[δp, δv]`` prior of the grid runs (see the module docstring)."""

    def __init__(self, n: int, P0: torch.Tensor, dtype: torch.dtype, device: torch.device):
        self.ppp = P0[[0, 1], [0, 1]].to(dtype).expand(n, 2).clone()
        self.ppv = torch.zeros(n, 2, dtype=dtype, device=device)
        self.pvv = P0[[3, 4], [3, 4]].to(dtype).expand(n, 2).clone()
        self.v0 = torch.zeros(n, 2, dtype=dtype, device=device)
        self.mp = torch.zeros(n, 2, dtype=dtype, device=device)

    def step(self, dt: float, qp: torch.Tensor, qv: torch.Tensor) -> torch.Tensor:
        """Propagates; returns the position-variance growth ``(N, 2)`` of this step."""
        grow = 2.0 * dt * self.ppv + dt * dt * self.pvv + qp
        self.ppp = self.ppp + grow
        self.ppv = self.ppv + dt * self.pvv
        self.pvv = self.pvv + qv
        self.mp = self.mp + dt * self.v0
        return grow

    def reset(self, mask: torch.Tensor, ppp: torch.Tensor, ppv: torch.Tensor, pvv: torch.Tensor,
              v0: torch.Tensor, mp: torch.Tensor) -> None:
        m = mask[:, None]
        self.ppp = torch.where(m, ppp, self.ppp)
        self.ppv = torch.where(m, ppv, self.ppv)
        self.pvv = torch.where(m, pvv, self.pvv)
        self.v0 = torch.where(m, v0, self.v0)
        self.mp = torch.where(m, mp, self.mp)

    def state(self, rows: torch.Tensor, mu: torch.Tensor, sigma: torch.Tensor,
              alt_m: torch.Tensor, alt_v: torch.Tensor,
              condition: bool) -> tuple[torch.Tensor, torch.Tensor]:
        """5-state mean ``(M, 5)`` and covariance ``(M, 5, 5)`` of runs ``rows`` from their
        grid posterior ``mu (M, 2)``, ``sigma (M, 2, 2)``."""
        n = mu.shape[0]
        ppp, ppv, pvv0 = self.ppp[rows], self.ppv[rows], self.pvv[rows]
        b = ppv / ppp if condition else torch.zeros_like(ppv)
        bm = torch.diag_embed(b)
        v = self.v0[rows] + b * (mu - self.mp[rows])
        pvv = torch.diag_embed(pvv0 - b * b * ppp) + bm @ sigma @ bm
        ppv = sigma @ bm
        x = torch.cat([mu, alt_m[:, None], v], 1)
        P = torch.zeros(n, N_STATES, N_STATES, dtype=mu.dtype, device=mu.device)
        P[:, :2, :2] = sigma
        P[:, 2, 2] = alt_v
        P[:, :2, 3:] = ppv
        P[:, 3:, :2] = ppv.transpose(1, 2)
        P[:, 3:, 3:] = 0.5 * (pvv + pvv.transpose(1, 2))
        return x, P


def _run_grid(inputs: TanInputs, method: str, terrain: Any, linearizer: Any,
              cfg: AcquisitionConfig, name: str,
              progress: Callable[[float], None] | None = None) -> AcquisitionResult:
    """Point mass (optionally handing off to the EKF) or the EKF alone.

    The grid filter holds only the runs in acquisition (``rows``): runs handed off are
    dropped from it and runs that lose lock are appended, so its cost follows the number
    of runs still acquiring.
    """
    ins, radar = inputs.ins_pos, inputs.radar
    n, k_steps = radar.shape[0], radar.shape[1] - 1
    dtype, device = ins.dtype, ins.device
    pm_dtype = torch.float32 if cfg.dtype == "float32" else torch.float64
    P0, Q = inputs.P0, inputs.Q
    F = transition_matrix(inputs.dt, dtype=dtype, device=device)
    use_pm = method.startswith("point_mass")
    use_ekf = method in ("ekf", "point_mass_ekf")
    handing = method in ("point_mass_ekf", "point_mass_tracker")
    ekf = BatchedEKF(torch.zeros(n, N_STATES, dtype=dtype, device=device), P0) if use_ekf else None
    pool = _tracker_pool(inputs, cfg) if method == "point_mass_tracker" else None
    track = ekf if ekf is not None else pool  # the tracking filter (x, P of its runs)
    map_terrain = terrain
    pm: PointMassFilter | None = None
    vel = _VelocityPrior(n, P0, dtype, device)
    rows = torch.arange(n, device=device) if use_pm else torch.zeros(0, dtype=torch.long)
    if use_pm:
        pm = PointMassFilter(torch.zeros(n, 2, dtype=pm_dtype, device=device),
                             P0[:2, :2].to(pm_dtype), scalar_mean=0.0,
                             scalar_var=float(P0[2, 2]),
                             config=cfg.point_mass_config(float(P0[:2, :2].diagonal().max()) ** 0.5),
                             dtype=pm_dtype)
    fast_grid = use_pm and _is_bilinear_grid(terrain)
    if fast_grid and pm_dtype == torch.float32:
        terrain = _Float32Grid(terrain)
    qp = Q[[0, 1], [0, 1]].expand(n, 2)
    qv = Q[[3, 4], [3, 4]].expand(n, 2)
    out = _outputs(n, k_steps, dtype, device)
    out["err"][:, 0] = inputs.ins_error[:, 0]
    out["P"][:, 0] = P0
    acq_hist = torch.zeros(n, k_steps + 1, dtype=torch.bool, device=device)
    acq_hist[rows, 0] = True
    handoff_step = torch.full((n,), -1, dtype=torch.long, device=device)
    n_fallbacks = torch.zeros(n, dtype=torch.long, device=device)
    recoveries = torch.zeros(n, dtype=torch.long, device=device)
    spikes = torch.zeros(n, dtype=torch.long, device=device)
    hold = torch.zeros(n, dtype=torch.long, device=device)
    since = torch.zeros(n, dtype=torch.long, device=device)
    win = max(cfg.fallback_window, 1)
    nis_win = torch.zeros(n, win, dtype=dtype, device=device)
    nis_count = torch.zeros(n, dtype=torch.long, device=device)
    updates = 0
    start = time.perf_counter()
    for k in range(1, k_steps + 1):
        if progress is not None:
            progress(1.0 / k_steps)
        x_out = torch.zeros(n, N_STATES, dtype=dtype, device=device)
        P_out = torch.zeros(n, N_STATES, N_STATES, dtype=dtype, device=device)
        acquiring = torch.zeros(n, dtype=torch.bool, device=device)
        acquiring[rows] = True
        grow = vel.step(inputs.dt, qp, qv)
        if pm is not None and rows.numel() > 0:
            pm.predict(Q=grow[rows].to(pm_dtype), shift=(inputs.dt * vel.v0[rows]).to(pm_dtype),
                       scalar_q=float(Q[2, 2]))
            y = (ins[rows, k, 2] - radar[rows, k]).to(pm_dtype)
            ins_xy = ins[rows, k, :2]
            if fast_grid:
                pred = lattice_bilinear(terrain, ins_xy, pm.centre, pm.spacing, pm.offsets)
            else:
                pred = _terrain_fn(terrain, ins_xy)(pm.points())
            cell_var = cell_height_variance(pred) if cfg.flatten_likelihood else None
            if cfg.map_support:  # the truth flies over the map: off-map cells get 0
                on = cells_on_map(ins_xy, pm.centre, pm.spacing, pm.offsets, inputs.extent)
                pred = pred.masked_fill(~on, math.nan)
            keep = None
            if cfg.spike_gate_prob > 0:  # a clearance past χ²₁(p) of its predictive NIS
                gated = spiked(predictive_nis(y, pm.weights, pred, pm.scalar_mean,
                                              pm.scalar_var, inputs.R), cfg.spike_gate_prob)
                spikes.index_add_(0, rows, gated.long())
                keep = ~gated
            upd_pm = pm.update(y, pred, R=inputs.R, cell_variance=cell_var, mask=keep)
            recoveries.index_add_(0, rows, upd_pm.recovered.long())
            updates += rows.numel() * pm.cells**2
            since[rows] += 1
            mu, sigma = pm.mean().to(dtype), pm.cov().to(dtype)
            alt_m, alt_v = (t.to(dtype) for t in pm.scalar_moments())
            x_pm, P_pm = vel.state(rows, mu, sigma, alt_m, alt_v, cfg.velocity_from_grid)
            x_out[rows] = x_pm
            P_out[rows] = P_pm
        if track is not None:
            tracking = ~acquiring
            if ekf is not None:
                diag = tan_filter_step(ekf, ins[:, k], radar[:, k], linearizer, F=F, Q=Q,
                                       R=inputs.R, extent=inputs.extent,
                                       mask=None if not use_pm else tracking)
            else:
                diag = pool.step(ins[:, k, :2], ins[:, k, 2] - radar[:, k],
                                 functools.partial(_tracker_heights, map_terrain,
                                                   extent=inputs.extent), inputs.R)
            upd = diag.updated & tracking
            x_out = torch.where(tracking[:, None], track.x, x_out)
            P_out = torch.where(tracking[:, None, None], track.P, P_out)
            out["nis"][:, k] = torch.where(upd, diag.nis, out["nis"][:, k])
            out["residual"][:, k] = torch.where(upd, diag.residual, 0.0)
            out["updated"][:, k] = upd
            if use_pm and cfg.fallback_window > 0:
                slot = (k - 1) % win
                nis_win[:, slot] = torch.where(upd, diag.nis, nis_win[:, slot])
                nis_count = nis_count + upd.long()
                lost = tracking & lost_lock(nis_win, nis_count, prob=cfg.fallback_prob)
                if bool(lost.any()):
                    lost_rows = lost.nonzero().reshape(-1)
                    same = cfg if pm is None or rows.numel() == 0 else dataclasses.replace(
                        cfg, cells=pm.cells)  # appended grids must match the filter's G
                    fresh = _reacquisition_grid(track, vel, lost, lost_rows, same, pm_dtype)
                    if pool is not None:
                        pool.drop(lost)
                    pm = fresh if pm is None or rows.numel() == 0 else pm.extend(fresh)
                    rows = torch.cat([rows, lost_rows])
                    n_fallbacks += lost.long()
                    hold = torch.where(lost, 0, hold)
                    since = torch.where(lost, 0, since)
        if pm is not None and handing and rows.numel() > 0:
            cov_pm = pm.cov().to(dtype)
            # the affinity (a pass over every cell) only where the size test passes
            small = torch.linalg.eigvalsh(cov_pm.double())[:, -1].clamp_min(0.0).sqrt() <= (
                cfg.handoff_sigma_m)
            affinity = torch.zeros(cov_pm.shape[0], dtype=dtype, device=device)
            cand = small.nonzero().reshape(-1)
            if cand.numel() > 0:
                affinity[cand] = pm.gaussian_affinity(cand).to(dtype)
            ready = handoff_ready(affinity, cov_pm, max_sigma=cfg.handoff_sigma_m,
                                  min_affinity=cfg.handoff_affinity)
            ready = ready[: rows.numel()]  # runs appended by a fall-back this step: not yet
            if ready.numel() < rows.numel():
                ready = torch.cat([ready, torch.zeros(rows.numel() - ready.numel(),
                                                      dtype=torch.bool, device=device)])
            hold[rows] = torch.where(ready, hold[rows] + 1, 0)
            go_rows = (hold[rows] >= max(cfg.handoff_hold, 1)) & (
                since[rows] >= cfg.min_acquire_steps)
            if bool(go_rows.any()):
                go = torch.zeros(n, dtype=torch.bool, device=device)
                go[rows[go_rows]] = True
                if ekf is not None:
                    ekf.x = torch.where(go[:, None], x_out, ekf.x)
                    ekf.P = torch.where(go[:, None, None], P_out, ekf.P)
                else:  # the tracker starts from the grid posterior's full moments
                    sel = go_rows.nonzero().reshape(-1)
                    go_idx = rows[sel]
                    xg, Pg = grid_posterior_moments(
                        pm, sel, ppp=vel.ppp[go_idx], ppv=vel.ppv[go_idx],
                        pvv=vel.pvv[go_idx], v0=vel.v0[go_idx], mp=vel.mp[go_idx],
                        condition=cfg.velocity_from_grid)
                    x_full = x_out.clone()
                    P_full = P_out.clone()
                    x_full[go_idx] = xg.to(dtype)
                    P_full[go_idx] = Pg.to(dtype)
                    pool.add(go, x_full, P_full)
                    x_out, P_out = x_full, P_full
                handoff_step = torch.where(go & (handoff_step < 0), k, handoff_step)
                nis_count = torch.where(go, 0, nis_count)
                nis_win = torch.where(go[:, None], 0.0, nis_win)
                keep = (~go_rows).nonzero().reshape(-1)
                rows = rows[keep]
                pm = pm.take(keep) if keep.numel() > 0 else pm
        out["err"][:, k] = inputs.ins_error[:, k] - x_out
        out["P"][:, k] = P_out
        out["est_on_map"][:, k] = inside_extent(ins[:, k, :2] - x_out[:, :2], inputs.extent)
        acq_hist[rows, k] = True
    elapsed = time.perf_counter() - start
    healthy = track.healthy.clone() if track is not None else torch.ones(n, dtype=torch.bool)
    lost = None
    if pool is not None:
        updates += pool.cell_updates
        # the tracker's lost flag of a run it took over counts as a divergence (metrics)
        lost = pool.tracker.lost & (handoff_step >= 0)
    if pm is not None and rows.numel() > 0:
        finite = torch.isfinite(pm.weights).flatten(1).all(1)
        healthy[rows] = healthy[rows] & finite
    run = _finish(inputs, out, name, healthy, elapsed, lost)
    return AcquisitionResult(
        run=run, handoff_step=handoff_step, n_fallbacks=n_fallbacks, recoveries=recoveries,
        acquiring=acq_hist, elapsed_s=elapsed, cell_updates=updates,
        extra={"spikes": spikes} if cfg.spike_gate_prob > 0 else {},
    )


def _reacquisition_grid(ekf: BatchedEKF, vel: _VelocityPrior, lost: torch.Tensor,
                        lost_rows: torch.Tensor, cfg: AcquisitionConfig,
                        pm_dtype: torch.dtype) -> PointMassFilter:
    """A grid for the runs that lost lock, around the EKF estimate (module docstring)."""
    x, P = ekf.x[lost_rows], ekf.P[lost_rows]
    var = torch.diagonal(P[:, :2, :2], dim1=1, dim2=2).clamp_min(cfg.reacquire_sigma_m**2)
    fresh = PointMassFilter(x[:, :2].to(pm_dtype), torch.diag_embed(var).to(pm_dtype),
                            scalar_mean=x[:, 2].to(pm_dtype),
                            scalar_var=P[:, 2, 2].clamp_min(1.0).to(pm_dtype),
                            config=cfg.point_mass_config(float(var.max()) ** 0.5),
                            dtype=pm_dtype)
    full_var = torch.zeros(lost.shape[0], 2, dtype=var.dtype, device=var.device)
    full_var[lost_rows] = var
    pvv = torch.diagonal(ekf.P[:, 3:, 3:], dim1=1, dim2=2)
    vel.reset(lost, full_var, torch.zeros_like(full_var), pvv, ekf.x[:, 3:], ekf.x[:, :2])
    return fresh


def acquisition_time(err_xy: torch.Tensor, bound: torch.Tensor, factor: float = 3.0,
                     dt: float = 1.0) -> torch.Tensor:
    """Time to acquire per run: the first time after which the error stays below
    ``factor`` times the bound.

    Args:
        err_xy: ``(N, K+1)`` horizontal error norms, m.
        bound: ``(K+1,)`` PCRB position bound, m.
        factor: Multiple of the bound.
        dt: Sample period, s.

    Returns:
        ``(N,)`` seconds; ``inf`` for a run still above the threshold at the last sample.
    """
    above = err_xy > factor * bound[None, :]
    k1 = above.shape[1]
    idx = torch.arange(k1, device=err_xy.device).expand_as(above)
    last_above = torch.where(above, idx, -1).amax(1)
    t = (last_above + 1).to(torch.float64) * dt
    return torch.where(last_above >= k1 - 1, math.inf, t)
