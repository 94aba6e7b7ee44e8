"""TAN with the point-mass tracker for the whole flight (Bergman, Ljung and Gustafsson).

The 5-state TAN error model (SEEDS 004, ``δX = [δx, δy, δh, δv_x, δv_y]``, INS − truth)
maps onto `PointMassTracker` as

* ``s = δp`` (on the lattice), ``z = [δh, δv_x, δv_y]`` (a Kalman part per cell);
* ``s_{k+1} = s_k + T [δv_x, δv_y] + w_p``: ``E = T [[0, 1, 0], [0, 0, 1]]``, ``F = I``;
* ``y = h_ins − h_radar = t(p_ins − s) + δh − v`` (the altimeter model of
  `neuralmap.nav.acquisition`): ``g(s) = t(p_ins − s)`` on the map under test (any
  `TerrainModel`: a grid, or a neural map — baked onto a
  grid first when that is faster, `neuralmap.terrain.bake.bake_to_grid`), ``c =
  [1, 0, 0]``, ``R`` = altimeter variance + the map's error variance.

Cells whose ``p_ins − s`` lies off the map get zero likelihood; a run whose every cell is
off the map is predicted only. The result is a `FilterRun`
like every EKF method's, so the metrics, PCRB comparison and reports take it unchanged.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.filters.point_mass_tracker import PointMassTracker, TrackerConfig
from neuralmap.nav.model import N_STATES
from neuralmap.nav.monte_carlo import FilterRun
from neuralmap.terrain.base import inside_extent

__all__ = ["TRACKER_METHOD", "TrackerOptions", "TrackerResult", "heights_on_cells", "run_tracker",
           "transition_blur"]

#: Method name of the point-mass tracker in the studies.
TRACKER_METHOD = "point_mass_tracker"


@dataclass
class TrackerOptions:
    """Options of `run_tracker`.

    Attributes:
        cells: Lattice cells per axis.
        span_sigma: Lattice half-width in posterior σ (cell = ``span_sigma · σ / h``).
        principal_axes: Align the lattice with the posterior's principal axes.
        dtype: ``"float32"`` (default, 2× faster; linear-Gaussian agreement with the Kalman
            filter 2e-3 σ) or ``"float64"``.
        lost_window: NIS window of the lost-track test (0 disables widening).
        widen_min_sigma_m: Smallest σ of a widened grid, m.
        chunk_runs: Runs per tracker batch (bounds memory; 0 = all at once).
        flatten_likelihood: Add the map's height spread over each cell to the likelihood
            variance (`neuralmap.nav.cell_variance.cell_height_variance`): needed while
            the cells are coarser than the terrain's detail (large initial errors).
        min_cell_blur: Smallest cell step in units of one step's horizontal transition
            spread ``b = sqrt(λ_max(Q_s) + T² λ_max(P0_v))`` (the lattice's minimum
            half-width is ``min_cell_blur · b · (G − 1) / 2``); 0 = no floor. A lattice
            finer than the transition blur gains nothing in accuracy, but the blur kernel
            of its prediction grows with it (all runs share the longest kernel, which goes
            to an FFT above 9 taps): with 1.5 the kernel stays below one cell σ (≤ 9 taps).
    """

    cells: int = 32
    span_sigma: float = 5.0
    principal_axes: bool = True
    dtype: str = "float32"
    lost_window: int = 10
    widen_min_sigma_m: float = 50.0
    chunk_runs: int = 0
    flatten_likelihood: bool = False
    min_cell_blur: float = 1.5
    extra: dict[str, Any] = field(default_factory=dict)

    def tracker_config(self, blur_m: float = 0.0) -> TrackerConfig:
        """The `TrackerConfig` (validated); ``blur_m`` = one step's transition
        spread ``b`` (m) for the lattice floor (``min_cell_blur``)."""
        if self.dtype not in ("float32", "float64"):
            raise NeuralMapError(
                f"tracker: dtype must be 'float32' or 'float64', got {self.dtype!r}.")
        if not self.min_cell_blur >= 0.0:
            raise NeuralMapError(
                f"tracker: min_cell_blur must be >= 0, got {self.min_cell_blur!r}.")
        extra = dict(self.extra)
        extra.setdefault("min_half_width", self.min_cell_blur * blur_m * 0.5 * (self.cells - 1))
        return TrackerConfig(cells=self.cells, span_sigma=self.span_sigma,
                             principal_axes=self.principal_axes, lost_window=self.lost_window,
                             widen_min_sigma=self.widen_min_sigma_m, **extra).validate()


@dataclass
class TrackerResult:
    """The tracker's `FilterRun` and its own counters.

    Attributes:
        run: Errors, covariances, NIS of the tracker's posterior mean.
        regrids, widenings, recoveries: ``(N,)`` counters.
        lost: ``(N,)`` bool, lost beyond recovery.
        cell_updates: Grid-cell measurement updates performed.
    """

    run: FilterRun
    regrids: torch.Tensor
    widenings: torch.Tensor
    recoveries: torch.Tensor
    lost: torch.Tensor
    cell_updates: int


def _tan_matrices(dt: float, dtype: torch.dtype) -> tuple[torch.Tensor, ...]:
    E = torch.tensor([[0.0, dt, 0.0], [0.0, 0.0, dt]], dtype=dtype)
    return E, torch.eye(3, dtype=dtype), torch.tensor([1.0, 0.0, 0.0], dtype=dtype)


def transition_blur(P0: torch.Tensor, Q: torch.Tensor, dt: float) -> float:
    """One step's horizontal transition spread ``b = sqrt(λ_max(Q_s) + T² λ_max(P0_v))``, m
    (the lattice floor of `TrackerOptions.min_cell_blur`); ``P0``, ``Q``: ``(5, 5)``."""
    P0 = torch.as_tensor(P0, dtype=torch.float64)
    Q = torch.as_tensor(Q, dtype=torch.float64)
    q = torch.linalg.eigvalsh(0.5 * (Q[:2, :2] + Q[:2, :2].T))[-1].clamp_min(0.0)
    v = torch.linalg.eigvalsh(0.5 * (P0[3:, 3:] + P0[3:, 3:].T))[-1].clamp_min(0.0)
    return float((q + float(dt) ** 2 * v).sqrt())


def heights_on_cells(terrain: Any, ins_xy: torch.Tensor, extent: tuple[float, ...]):
    """``g(s) = t(p_ins − s)`` on the cells, NaN off the map.

    Args:
        terrain: The map (``forward(xy (M, 2)) -> (M,)``).
        ins_xy: ``(N, 2)`` INS horizontal positions.
        extent: Map extent ``(xmin, xmax, ymin, ymax)``.

    Returns:
        Callable on cell coordinates ``(N, G, G, 2)`` returning ``(N, G, G)`` heights.
    """

    def g(points: torch.Tensor) -> torch.Tensor:
        xy = ins_xy[:, None, None, :].to(points.dtype) - points
        flat = xy.reshape(-1, 2)
        param = next(iter(terrain.parameters()), None) if hasattr(terrain, "parameters") else None
        dtype = param.dtype if param is not None and not hasattr(terrain, "heights") else flat.dtype
        with torch.no_grad():
            h = terrain(flat.to(dtype)).to(points.dtype).reshape(points.shape[:-1])
        return torch.where(inside_extent(xy, extent), h, torch.nan)

    return g


_heights = heights_on_cells


def run_tracker(truth: Any, terrain: Any, *, P0: torch.Tensor, Q: torch.Tensor, R: float,
                dt: float, options: TrackerOptions | None = None,
                method: str = TRACKER_METHOD,
                progress: Callable[[float], None] | None = None) -> TrackerResult:
    """Runs the point-mass tracker over every run of a simulated truth.

    Timing as `neuralmap.nav.monte_carlo.run_filter`: sample 0 is the prior
    (``δX̂ = 0``, ``P0``), steps ``k = 1 … K`` predict and update with altimeter sample k.

    Args:
        truth: `Truth` (``ins_pos``, ``radar``,
            ``ins_error``, ``on_map``, ``extent``, ``t``).
        terrain: The map under test (``forward(xy) -> heights``).
        P0: ``(5, 5)`` prior covariance (positive definite).
        Q: ``(5, 5)`` process noise per step (the position/altitude/velocity blocks are used;
            cross terms between ``s`` and ``z`` are not).
        R: Measurement variance, m² (altimeter + map error).
        dt: Period T, s.
        options: `TrackerOptions`.
        method: Name stored in the run.
        progress: Called with the share of the work each step of each chunk of runs does
            (`neuralmap.progress.stage_progress`); None = silent.

    Returns:
        `TrackerResult`.

    Raises:
        NeuralMapError: ``P0`` not positive definite, bad options, ``R`` not > 0.
    """
    opts = options or TrackerOptions()
    if not (R > 0 and R < float("inf")):
        raise NeuralMapError(f"tracker: R must be finite and > 0 m², got {R!r}.")
    pm_dtype = torch.float32 if opts.dtype == "float32" else torch.float64
    out_dtype, device = truth.ins_pos.dtype, truth.ins_pos.device
    n, k1 = truth.radar.shape
    P0 = torch.as_tensor(P0, dtype=torch.float64)
    Q = torch.as_tensor(Q, dtype=torch.float64)
    cfg = opts.tracker_config(blur_m=transition_blur(P0, Q, dt))
    E, F, c = _tan_matrices(float(dt), pm_dtype)
    err = torch.empty(n, k1, N_STATES, dtype=out_dtype, device=device)
    P_hist = torch.empty(n, k1, N_STATES, N_STATES, dtype=out_dtype, device=device)
    nis = torch.full((n, k1), float("nan"), dtype=out_dtype, device=device)
    residual = torch.zeros(n, k1, dtype=out_dtype, device=device)
    updated = torch.zeros(n, k1, dtype=torch.bool, device=device)
    est_on_map = torch.ones(n, k1, dtype=torch.bool, device=device)
    counters = {k: torch.zeros(n, dtype=torch.long) for k in ("regrids", "widenings",
                                                              "recoveries")}
    lost = torch.zeros(n, dtype=torch.bool)
    chunk = n if opts.chunk_runs <= 0 else opts.chunk_runs
    cell_updates = 0
    start = time.perf_counter()
    for lo in range(0, n, chunk):
        rows = slice(lo, min(n, lo + chunk))
        m = rows.stop - rows.start
        tracker = PointMassTracker(torch.zeros(m, N_STATES, dtype=pm_dtype), P0.to(pm_dtype),
                                   E=E, F=F, c=c, config=cfg, dtype=pm_dtype)
        qs, qz = Q[:2, :2].to(pm_dtype), Q[2:, 2:].to(pm_dtype)
        err[rows, 0] = truth.ins_error[rows, 0]
        P_hist[rows, 0] = P0.to(out_dtype)
        est_on_map[rows, 0] = inside_extent(truth.ins_pos[rows, 0, :2], truth.extent)
        for k in range(1, k1):
            tracker.predict(Q_s=qs, Q_z=qz)
            ins_xy = truth.ins_pos[rows, k, :2]
            y = (truth.ins_pos[rows, k, 2] - truth.radar[rows, k]).to(pm_dtype)
            g = _heights(terrain, ins_xy, truth.extent)(tracker.points())
            cell_var = None
            if opts.flatten_likelihood:
                from neuralmap.nav.cell_variance import cell_height_variance

                cell_var = torch.nan_to_num(cell_height_variance(g), nan=0.0)
            upd = tracker.update(y, g, R=R, cell_variance=cell_var)
            cell_updates += m * cfg.cells**2
            mean, cov = tracker.moments()
            err[rows, k] = truth.ins_error[rows, k] - mean.to(out_dtype)
            P_hist[rows, k] = cov.to(out_dtype)
            nis[rows, k] = torch.where(upd.applied, upd.nis, torch.nan).to(out_dtype)
            residual[rows, k] = torch.where(upd.applied, upd.innovation, 0.0).to(out_dtype)
            updated[rows, k] = upd.applied
            est_on_map[rows, k] = inside_extent(ins_xy - mean[:, :2].to(out_dtype), truth.extent)
            if progress is not None:
                progress(m / (n * max(k1 - 1, 1)))
        for key in counters:
            counters[key][rows] = getattr(tracker, key).cpu()
        lost[rows] = tracker.lost.cpu()
    elapsed = time.perf_counter() - start
    finite = torch.isfinite(err).flatten(1).all(1) & torch.isfinite(P_hist).flatten(1).all(1)
    run = FilterRun(method=method, t=truth.t, err=err, P=P_hist, nis=nis, residual=residual,
                    updated=updated, est_on_map=est_on_map, off_map=~truth.on_map.all(dim=1),
                    healthy=finite, elapsed_s=elapsed, lost=lost.to(device))
    return TrackerResult(run=run, lost=lost, cell_updates=cell_updates, **counters)
