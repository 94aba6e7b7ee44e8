"""Point-mass tracker speed: the lean lattice step against the previous code, the same
algorithm in NumPy and Stone Soup's Lagrangian point-mass filter, in one run.

The tracker is `neuralmap.filters.point_mass_tracker.PointMassTracker` (the ``follow``
lattice of `neuralmap.filters.lattice`) in the Navigator's default configuration: 32 × 32
cells, float32, the 5-state TAN error model (the lattice over the horizontal error, a
Kalman part per cell over altitude and velocity errors), the lattice floor of one step's
transition spread, no internal lost-track test; one altimeter update per step on the
jacksboro tile (bilinear heights at the cells). Rows, measured in the same run:

* **one vehicle** (N = 1, one thread): median and p99 milliseconds of predict + update +
  moments (the lattice step) and of the epoch with the map lookup at the cells, for the
  previous code (the commit ``--before``, loaded from git), the eager step and the step
  under ``torch.compile`` (``TrackerConfig.compile``), and the whole epoch as one compiled
  step (`PointMassTracker.track`: prediction, map lookup at the cells, update and moments
  in one call, as the Navigator runs it with ``compile: true``; its two columns are the
  same call); and the aten operations one step issues (``torch.profiler``: all, and the
  top-level ones);
* **fleet** (N = ``--runs``, one thread): vehicle-epochs per second (lattice step only) and
  cell-updates per second (one predict + update of one cell);
* **same algorithm in NumPy** (`neuralmap.filters.lattice.reference.FollowLatticeReference`,
  one run at a time, float64: the prediction, regrid, Rao-Blackwellised part and update
  of the tracker, tested equal to it): cell-updates per second; the fleet rows' ratio per
  cell-update is against this row. A second, labelled row is the older simplified NumPy
  loop (fixed grid, scalar altitude part, no regrid or moment correction);
* **Stone Soup** (when ``stonesoup`` is installed): its Lagrangian point-mass filter
  (``PointMassPredictor``: re-grid along the predicted covariance's eigenvectors,
  interpolation, FFT convolution; a NumPy Bayes update on its grid) on the same terrain
  with a 2-D state (the horizontal error; altitude and velocity known) at 32² points;
* **grid sizes** (``--sweep``, default 16, 32 and 64 cells per axis): the per-step time
  of Stone Soup's filter (2-D state, G² points, one run) beside the tracker's whole epoch
  as one compiled step for one vehicle (5-state model, G² cells), and their ratio;
* the **roofline**: a NumPy copy gives the memory bandwidth B (read + write); a
  cell-update must at least read and write the cell's mass and linear-part means once,
  ``2 · (1 + nz) · itemsize`` bytes, so the roofline rate is ``B / (2 (1 + nz) itemsize)``.

Targets (reported met or missed, never asserted): one vehicle's lattice step ≤ 0.3 ms
median (the Navigator's epoch ≤ 0.5 ms, must ≤ 1 ms); ≥ 50 000 vehicle-epochs/s for 1000
vehicles on one thread; ≥ 10× the same-algorithm NumPy loop per cell-update.

**Beside the Lagrangian grid-based filter of Matoušek, Duník et al.** (Stone Soup's
``PointMassPredictor``/``PointMassUpdater``). Their idea: the point-mass prediction
``p(x') = Σ p(x' | x) w(x)`` is a convolution when the transition is linear-Gaussian; on a
grid that is regular in the *predicted* coordinates (new grid along the eigenvectors of
``F P Fᵀ + Q``, ±4σ, the prior density interpolated onto it, then moved by ``F``: the
Lagrangian step) the convolution with the transition kernel is one FFT of the whole grid
(``O(G² log G)``, the full 2-D kernel, no separability needed), and the grid is designed
anew each step from the predicted moments. What this tracker does differently: (1) the
lattice follows the posterior through the deterministic part of the motion without
interpolation (the affine part of ``E μ`` moves the cell steps; the lattice is redesigned
only when the posterior no longer fits it, with hysteresis), so most steps resample
nothing; (2) the blur is separable along the lattice axes with the exact per-axis
variance and is applied only to the *residual* noise, which is below a cell in tracking
(a three-tap kernel, ``O(G²)``), the cross-axis part being carried exactly by an affine
moment correction; direct sums keep the far tails exact where an FFT's round-off is
relative to the peak; (3) the conditionally linear states (altitude, velocities) are a
Kalman filter per cell (Rao-Blackwellised) instead of grid dimensions; (4) every step
imposes the exact predicted mean and covariance, so discretisation changes only the shape
beyond the covariance; (5) N runs are one batch of static-shape kernels.

Usage:
    python benchmarks/bench_point_mass.py              # N = 1000, G = 32
    python benchmarks/bench_point_mass.py --quick      # smoke test
    python benchmarks/bench_point_mass.py --device cuda
"""

from __future__ import annotations

import argparse
import math
import platform
import statistics
import subprocess
import sys
import tempfile
import time
import warnings
from collections.abc import Callable
from pathlib import Path
from types import ModuleType
from typing import Any

import numpy as np
import torch

REPO_ROOT = Path(__file__).resolve().parents[1]
if str(REPO_ROOT) not in sys.path:  # run as a script from anywhere
    sys.path.insert(0, str(REPO_ROOT))

from neuralmap.docs.bench_run import add_out_option, start_bench  # noqa: E402
from neuralmap.filters.lattice.reference import FollowLatticeReference  # noqa: E402
from neuralmap.filters.point_mass_tracker import PointMassTracker, TrackerConfig  # noqa: E402

#: The commit whose lattice filter is the "previous code" row (before the lean step).
BEFORE = "1ee01c0"
T = 1.0
SPEED = np.array([42.0, 28.0])  # m/s: a long diagonal track stays on the tile
SIGMA0 = 60.0  # m, horizontal prior σ (tracking after acquisition)
P0_DIAG = [SIGMA0**2, SIGMA0**2, 20.0**2, 0.5**2, 0.5**2]
Q_DIAG = [1.0, 1.0, 1.0, 0.0025, 0.0025]
R_M2 = 9.0 + 4.0  # altimeter 3 m + map error 2 m
CPU = torch.device("cpu")


# ---------------------------------------------------------------------------- set-up
def check_device(name: str) -> torch.device:
    """The torch device ``name``; exits with one error line when it is absent."""
    try:
        dev = torch.device(name)
    except (RuntimeError, TypeError):
        print(f"error: --device {name!r} is not a torch device; use cpu, cuda or cuda:<i>.",
              file=sys.stderr)
        raise SystemExit(2) from None
    if dev.type == "cuda" and not torch.cuda.is_available():
        print(f"error: --device {name}: CUDA is not available on this machine; use "
              "--device cpu.", file=sys.stderr)
        raise SystemExit(2)
    return dev


def _sync(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


class Flight:
    """Straight diagonal tracks over the tile: INS positions, truth, altimeter measurements.

    Attributes:
        ins: ``(N, K, 2)`` INS horizontal positions; ``y``: ``(N, K)`` ``h_ins − h_radar``
            (the map at the true position plus the altitude error and noise).
    """

    def __init__(self, tile: Any, n: int, steps: int, seed: int = 0) -> None:
        rng = np.random.default_rng(seed)
        xmin, xmax, ymin, ymax = tile.extent
        span = SPEED * T * steps
        start = np.stack([rng.uniform(xmin + 2e3, xmax - 2e3 - span[0], n),
                          rng.uniform(ymin + 2e3, ymax - 2e3 - span[1], n)], 1)
        k = np.arange(steps)[None, :, None]
        self.ins = start[:, None, :] + (k + 1) * SPEED * T
        err = rng.normal(size=(n, 5)) * np.sqrt(P0_DIAG)
        truth = np.empty((n, steps, 5))
        for i in range(steps):
            err[:, 0:2] += T * err[:, 3:5]
            err += rng.normal(size=(n, 5)) * np.sqrt(Q_DIAG)
            truth[:, i] = err
        heights = np.asarray(tile.heights, dtype=np.float64)
        self.heights = np.where(np.isfinite(heights), heights, np.nanmean(heights))
        self.origin, self.spacing = tuple(tile.origin), tuple(tile.spacing)
        self.y = (numpy_bilinear(self.heights, self.origin, self.spacing,
                                 self.ins - truth[..., :2]) + truth[..., 2]
                  + rng.normal(0.0, math.sqrt(R_M2), (n, steps)))


def numpy_bilinear(heights: np.ndarray, origin, spacing, xy: np.ndarray) -> np.ndarray:
    """Bilinear heights at ``xy (..., 2)`` (clamped to the tile)."""
    ny, nx = heights.shape
    u = np.clip((xy[..., 0] - origin[0]) / spacing[0], 0.0, nx - 1.0)
    v = np.clip((xy[..., 1] - origin[1]) / spacing[1], 0.0, ny - 1.0)
    j = np.minimum(np.floor(u), nx - 2).astype(np.int64)
    i = np.minimum(np.floor(v), ny - 2).astype(np.int64)
    fu, fv = u - j, v - i
    h00, h01 = heights[i, j], heights[i, j + 1]
    h10, h11 = heights[i + 1, j], heights[i + 1, j + 1]
    return (h00 * (1 - fu) + h01 * fu) * (1 - fv) + (h10 * (1 - fu) + h11 * fu) * fv


class TorchMap:
    """The tile's bilinear heights in torch (the map lookup at the lattice cells)."""

    def __init__(self, flight: Flight, dtype: torch.dtype, device: torch.device) -> None:
        self.h = torch.as_tensor(flight.heights, dtype=dtype, device=device)
        self.origin, self.spacing = flight.origin, flight.spacing

    def __call__(self, xy: torch.Tensor) -> torch.Tensor:
        return bilinear_at(self.h, self.origin, self.spacing, xy)


def bilinear_at(h: torch.Tensor, origin: tuple[float, float], spacing: tuple[float, float],
                xy: torch.Tensor) -> torch.Tensor:
    """Bilinear heights of the grid ``h`` at ``xy (..., 2)`` (clamped to the grid)."""
    ny, nx = h.shape
    u = ((xy[..., 0] - origin[0]) / spacing[0]).clamp(0.0, nx - 1.0)
    v = ((xy[..., 1] - origin[1]) / spacing[1]).clamp(0.0, ny - 1.0)
    j = u.floor().clamp(max=nx - 2)
    i = v.floor().clamp(max=ny - 2)
    fu, fv = u - j, v - i
    idx = (i * nx + j).long()
    flat = h.reshape(-1)
    h00, h01 = flat[idx], flat[idx + 1]
    h10, h11 = flat[idx + nx], flat[idx + nx + 1]
    return (h00 * (1 - fu) + h01 * fu) * (1 - fv) + (h10 * (1 - fu) + h11 * fu) * fv


def map_at_cells(h: torch.Tensor, origin: tuple[float, float], spacing: tuple[float, float],
                 ins: torch.Tensor, points: torch.Tensor) -> torch.Tensor:
    """`bilinear_at` ``ins − points`` as a module-level function: the map lookup a
    whole-epoch step (`PointMassTracker.track`) fuses with the filter."""
    return bilinear_at(h, origin, spacing, ins[:, None, None, :] - points)


def tracker_config(module: ModuleType, cells: int, **extra: Any) -> Any:
    """The Navigator's tracker options: lattice floor ``1.5 b (G − 1)/2`` with ``b`` one
    step's transition spread, no internal lost-track test."""
    b = math.sqrt(max(Q_DIAG[:2]) + T**2 * max(P0_DIAG[3:]))
    return module.TrackerConfig(cells=cells, lost_window=0,
                                min_half_width=1.5 * b * 0.5 * (cells - 1), **extra)


def make_tracker(module: ModuleType, n: int, cells: int, dtype: torch.dtype,
                 device: torch.device, **extra: Any) -> Any:
    kw = {"dtype": dtype, "device": device}
    E = torch.tensor([[0.0, T, 0.0], [0.0, 0.0, T]], **kw)
    return module.PointMassTracker(
        torch.zeros(n, 5, **kw), torch.diag(torch.tensor(P0_DIAG, **kw)), E=E,
        F=torch.eye(3, **kw), c=torch.tensor([1.0, 0.0, 0.0], **kw),
        config=tracker_config(module, cells, **extra), dtype=dtype)


def load_previous(commit: str) -> ModuleType | None:
    """``point_mass_tracker`` (with its lattice package) as of ``commit``, imported under
    another name; None without git or the commit."""
    files = ["neuralmap/filters/point_mass_tracker.py", "neuralmap/filters/point_mass.py"]
    names = ["__init__", "algebra2", "filter", "follow_policy", "grid_policy", "kernels",
             "policy"]
    files += [f"neuralmap/filters/lattice/{m}.py" for m in names]
    root = Path(tempfile.mkdtemp()) / "_previous_lattice"
    (root / "lattice").mkdir(parents=True)
    (root / "__init__.py").write_text("")
    for path in files:
        try:
            src = subprocess.run(["git", "-C", str(REPO_ROOT), "show", f"{commit}:{path}"],
                                 check=True, capture_output=True, text=True).stdout
        except (OSError, subprocess.CalledProcessError):
            return None
        for old, new in (("neuralmap.filters.lattice", "_previous_lattice.lattice"),
                         ("neuralmap.filters.point_mass_tracker",
                          "_previous_lattice.point_mass_tracker"),
                         ("neuralmap.filters.point_mass", "_previous_lattice.point_mass")):
            src = src.replace(old, new)
        (root / path.removeprefix("neuralmap/filters/")).write_text(src)
    sys.path.insert(0, str(root.parent))
    import importlib

    return importlib.import_module("_previous_lattice.point_mass_tracker")


# ---------------------------------------------------------------------------- timing
def _qs_qz(dtype: torch.dtype, device: torch.device) -> tuple[torch.Tensor, torch.Tensor]:
    q = torch.tensor(Q_DIAG, dtype=dtype, device=device)
    return torch.diag(q[:2]), torch.diag(q[2:])


def fly(trk: Any, flight: Flight, rows: slice, steps: range, tmap: TorchMap,
        device: torch.device) -> tuple[list[float], list[float]]:
    """Steps of one tracker; returns per-step seconds of the lattice step (predict +
    update + moments) and of the epoch (with the map lookup at the cells)."""
    dtype = trk.dtype
    qs, qz = _qs_qz(dtype, device)
    ins = torch.as_tensor(flight.ins[rows], dtype=dtype, device=device)
    y = torch.as_tensor(flight.y[rows], dtype=dtype, device=device)
    lattice, epoch = [], []
    for k in steps:
        _sync(device)
        t0 = time.perf_counter()
        trk.predict(Q_s=qs, Q_z=qz)
        _sync(device)
        t1 = time.perf_counter()
        g = tmap(ins[:, k, None, None, :] - trk.points())
        _sync(device)
        t2 = time.perf_counter()
        trk.update(y[:, k], g, R=R_M2)
        trk.moments()
        _sync(device)
        t3 = time.perf_counter()
        lattice.append((t1 - t0) + (t3 - t2))
        epoch.append(t3 - t0)
    return lattice, epoch


def _track_args(trk: Any, flight: Flight, rows: slice, tmap: TorchMap,
                device: torch.device) -> tuple[Any, ...]:
    dtype = trk.dtype
    ins = torch.as_tensor(flight.ins[rows], dtype=dtype, device=device)
    y = torch.as_tensor(flight.y[rows], dtype=dtype, device=device)
    n = ins.shape[0]
    r = torch.full((n,), R_M2, dtype=dtype, device=device)
    everyone = torch.ones(n, dtype=torch.bool, device=device)
    return ins, y, r, everyone


def track_epoch(trk: Any, k: int, args: tuple[Any, ...], tmap: TorchMap,
                qs: torch.Tensor, qz: torch.Tensor) -> None:
    """One epoch as one step (`PointMassTracker.track`: predict, map lookup, update,
    moments); the separate prediction and update where the step declines."""
    ins, y, r, everyone = args
    out = trk.track(Q_s=qs, Q_z=qz, measurement=y[:, k], heights=map_at_cells,
                    heights_args=(tmap.h, tmap.origin, tmap.spacing, ins[:, k]), R=r,
                    mask=everyone)
    if out is None:
        trk.predict(Q_s=qs, Q_z=qz)
        trk.update(y[:, k], tmap(ins[:, k, None, None, :] - trk.points()), R=R_M2)
    trk.moments()


def fly_track(trk: Any, flight: Flight, rows: slice, steps: range, tmap: TorchMap,
              device: torch.device) -> tuple[list[float], list[float]]:
    """`fly` with each epoch as one step (`track_epoch`): the lattice step and the epoch
    are the same call (the map lookup inside)."""
    qs, qz = _qs_qz(trk.dtype, device)
    args = _track_args(trk, flight, rows, tmap, device)
    epoch = []
    for k in steps:
        _sync(device)
        t0 = time.perf_counter()
        track_epoch(trk, k, args, tmap, qs, qz)
        _sync(device)
        epoch.append(time.perf_counter() - t0)
    return epoch, epoch


def aten_calls(trk: Any, flight: Flight, k: int, tmap: TorchMap,
               device: torch.device, whole_epoch: bool = False) -> tuple[int, int]:
    """aten operations of one lattice step (predict, update, moments; the map lookup not
    counted): all of them and the top-level ones."""
    from torch.profiler import ProfilerActivity, profile

    dtype = trk.dtype
    qs, qz = _qs_qz(dtype, device)
    ins = torch.as_tensor(flight.ins[:1, k], dtype=dtype, device=device)
    y = torch.as_tensor(flight.y[:1, k], dtype=dtype, device=device)
    events = []
    if whole_epoch:  # one call: predict, map lookup, update, moments
        args = _track_args(trk, flight, slice(0, 1), tmap, device)
        with profile(activities=[ProfilerActivity.CPU]) as prof:
            track_epoch(trk, k, args, tmap, qs, qz)
        aten = [e for e in prof.events() if e.name.startswith("aten::")]
        top = [e for e in aten
               if e.cpu_parent is None or not e.cpu_parent.name.startswith("aten::")]
        return len(aten), len(top)
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        trk.predict(Q_s=qs, Q_z=qz)
    events += list(prof.events())
    g = tmap(ins[:, None, None, :] - trk.points())
    with profile(activities=[ProfilerActivity.CPU]) as prof:
        trk.update(y, g, R=R_M2)
        trk.moments()
    events += list(prof.events())
    aten = [e for e in events if e.name.startswith("aten::")]
    top = [e for e in aten if e.cpu_parent is None or not e.cpu_parent.name.startswith("aten::")]
    return len(aten), len(top)


def median_p99(ts: list[float]) -> tuple[float, float]:
    s = sorted(ts)
    return statistics.median(s), s[max(0, math.ceil(0.99 * len(s)) - 1)]


# ---------------------------------------------------------------------------- references
def reference_rate(flight: Flight, runs: int, steps: int, cells: int) -> float:
    """Cell-updates/s of the same algorithm in NumPy, one run at a time (float64)."""
    E = np.array([[0.0, T, 0.0], [0.0, 0.0, T]])
    qs, qz = np.diag(Q_DIAG[:2]), np.diag(Q_DIAG[2:])
    cfg = tracker_config(sys.modules[TrackerConfig.__module__], cells)
    start = time.perf_counter()
    for r in range(runs):
        ref = FollowLatticeReference(np.zeros(5), np.diag(P0_DIAG), E=E, F=np.eye(3),
                                     c=np.array([1.0, 0.0, 0.0]), config=cfg)
        for k in range(steps):
            ref.predict(qs, qz)
            pts = flight.ins[r, k] - ref.points()
            ref.update(float(flight.y[r, k]),
                       numpy_bilinear(flight.heights, flight.origin, flight.spacing, pts),
                       R_M2)
            ref.moments()
    return runs * steps * cells * cells / (time.perf_counter() - start)


def simple_numpy_rate(flight: Flight, runs: int, steps: int, cells: int) -> float:
    """Cell-updates/s of the older simplified loop: a fixed grid over the horizontal error,
    a scalar altitude Kalman part per cell, separable Gaussian blur (scipy), one run at a
    time, float64 (no regrid, no velocity coupling, no moment correction)."""
    from scipy.ndimage import convolve1d

    half = 0.5 * (cells - 1)
    d = 5.0 * SIGMA0 / half
    off = (np.arange(cells) - half) * d
    sx, sy = np.meshgrid(off, off)
    sigma_cells = math.sqrt(Q_DIAG[0]) / d
    hl = max(1, int(math.ceil(4 * sigma_cells)))
    kern = np.exp(-0.5 * (np.arange(-hl, hl + 1) / sigma_cells) ** 2)
    kern /= kern.sum()
    start = time.perf_counter()
    for r in range(runs):
        logw = -0.5 * (sx**2 + sy**2) / SIGMA0**2
        w = np.exp(logw - logw.max())
        w /= w.sum()
        m = np.zeros_like(w)
        v = P0_DIAG[2]
        for k in range(steps):
            w = convolve1d(convolve1d(w, kern, axis=1, mode="constant"), kern, axis=0,
                           mode="constant")
            wm = convolve1d(convolve1d(w * m, kern, axis=1, mode="constant"), kern, axis=0,
                            mode="constant")
            m = wm / np.maximum(w, 1e-300)
            v += Q_DIAG[2]
            xy = np.stack([flight.ins[r, k, 0] - sx, flight.ins[r, k, 1] - sy], -1)
            g = numpy_bilinear(flight.heights, flight.origin, flight.spacing, xy)
            nu = flight.y[r, k] - g - m
            s = v + R_M2
            lw = np.log(np.maximum(w, 1e-300)) - 0.5 * nu * nu / s
            w = np.exp(lw - lw.max())
            w /= w.sum()
            m = m + v / s * nu
            v = v * R_M2 / s
    return runs * steps * cells * cells / (time.perf_counter() - start)


def stonesoup_rate(flight: Flight, runs: int, steps: int, cells: int) -> float | None:
    """Cell-updates/s of Stone Soup's Lagrangian point-mass filter (``PointMassPredictor``)
    with a NumPy Bayes update (log domain), 2-D state, one run at a time; None without
    stonesoup."""
    try:
        from stonesoup.functions import grid_creation
        from stonesoup.models.transition.linear import (
            CombinedLinearGaussianTransitionModel,
            RandomWalk,
        )
        from stonesoup.predictor.pointmass import PointMassPredictor
        from stonesoup.types.array import StateVectors
        from stonesoup.types.state import PointMassState
    except ImportError:
        return None
    from datetime import datetime, timedelta

    npa = np.array([cells, cells])
    q = Q_DIAG[0] + T**2 * P0_DIAG[3]  # the velocity error as part of the random walk
    predictor = PointMassPredictor(
        CombinedLinearGaussianTransitionModel([RandomWalk(q), RandomWalk(q)]))
    t0 = datetime(2026, 1, 1)
    # a prior with distinct eigenvalues: Stone Soup's grid design (numpy.linalg.eig) turns
    # complex on an isotropic covariance and its prediction then overflows
    cov = SIGMA0**2 * np.array([[1.0, 0.1], [0.1, 0.85]])
    start = time.perf_counter()
    for r in range(runs):
        grid, delta, dims, centre, eig = grid_creation(np.zeros((2, 1)), cov, 4.0, 2, npa)
        pdf = np.exp(-0.5 * np.sum(grid * np.linalg.solve(cov, grid), axis=0))
        pdf = pdf / (pdf.sum() * np.prod(delta))
        state = PointMassState(state_vector=StateVectors(grid), weight=pdf.reshape(-1, 1),
                               grid_delta=delta, grid_dim=dims, center=centre, eigVec=eig,
                               Npa=npa, timestamp=t0)
        for k in range(steps):
            state = predictor.predict(state, timestamp=t0 + timedelta(seconds=k + 1))
            pts = np.asarray(state.state_vector, dtype=float)
            xy = np.stack([flight.ins[r, k, 0] - pts[0], flight.ins[r, k, 1] - pts[1]], -1)
            g = numpy_bilinear(flight.heights, flight.origin, flight.spacing, xy)
            w = np.asarray(state.weight, dtype=float).reshape(-1)
            lw = np.log(np.maximum(w, 1e-300)) - 0.5 * (flight.y[r, k] - g) ** 2 / (
                R_M2 + P0_DIAG[2])
            w = np.exp(lw - lw.max())
            w = w / (w.sum() * np.prod(state.grid_delta))
            state = PointMassState(state_vector=state.state_vector, weight=w.reshape(-1, 1),
                                   grid_delta=state.grid_delta, grid_dim=state.grid_dim,
                                   center=state.center, eigVec=state.eigVec, Npa=npa,
                                   timestamp=state.timestamp)
    return runs * steps * cells * cells / (time.perf_counter() - start)


def copy_bandwidth(megabytes: int = 256, repeats: int = 5) -> float:
    """Memory bandwidth (bytes read + written per second) of a NumPy copy, best of repeats."""
    src = np.ones(megabytes * 2**20 // 8)
    dst = np.empty_like(src)
    np.copyto(dst, src)
    best = math.inf
    for _ in range(repeats):
        start = time.perf_counter()
        np.copyto(dst, src)
        best = min(best, time.perf_counter() - start)
    return 2.0 * src.nbytes / best


def device_copy_bandwidth(device: torch.device, megabytes: int = 256) -> float:
    """Memory bandwidth (read + write per second) of a torch copy on ``device``."""
    src = torch.ones(megabytes * 2**20 // 8, dtype=torch.float64, device=device)
    dst = torch.empty_like(src)
    dst.copy_(src)
    best = math.inf
    for _ in range(5):
        _sync(device)
        start = time.perf_counter()
        dst.copy_(src)
        _sync(device)
        best = min(best, time.perf_counter() - start)
    return 2.0 * src.nbytes / best


# ---------------------------------------------------------------------------- main
def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=1000, help="vehicles of the fleet rows")
    parser.add_argument("--steps", type=int, default=8, help="timed fleet steps")
    parser.add_argument("--one_steps", type=int, default=150, help="timed one-vehicle steps")
    parser.add_argument("--cells", type=int, default=32)
    parser.add_argument("--ref_runs", type=int, default=3,
                        help="runs of the NumPy and Stone Soup references (one at a time)")
    parser.add_argument("--repeats", type=int, default=2, help="repeats of the fleet rows")
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--before", default=BEFORE,
                        help="commit of the previous code's row ('' to skip it)")
    parser.add_argument("--no_compile", action="store_true",
                        help="skip the torch.compile rows (they compile for minutes)")
    parser.add_argument("--sweep", default="16,32,64",
                        help="cells per axis of the grid-size rows beside Stone Soup")
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--device", default="cpu",
                        help="torch device of the tracker rows (cpu, cuda, cuda:<i>)")
    add_out_option(parser, "bench_point_mass")
    args = parser.parse_args()
    device = check_device(args.device)
    bench = start_bench(__file__, args)
    if args.quick:
        args.runs, args.steps, args.one_steps, args.ref_runs, args.repeats = 50, 3, 20, 1, 1
        args.sweep = "16,32"
    torch.set_num_threads(args.threads)
    warnings.filterwarnings("ignore", category=FutureWarning)
    from neuralmap.dem import load_tile

    tile = load_tile("jacksboro")
    warm = 6
    one = Flight(tile, max(args.ref_runs, 1), warm + args.one_steps, seed=1)
    fleet = Flight(tile, args.runs, 3 + args.steps, seed=2)
    dtype, g = torch.float32, args.cells
    nz = 3
    print(f"point-mass tracker benchmark: {platform.processor() or platform.machine()}, torch "
          f"{torch.__version__}, {args.threads} thread(s); {g}² cells, float32, 5-state TAN "
          f"model; tracker rows on {device}")
    previous = load_previous(args.before) if args.before else None
    if args.before and previous is None:
        print(f"(previous code row skipped: commit {args.before} not available via git)")
    current = sys.modules[PointMassTracker.__module__]
    variants: list[tuple[str, Callable[[int], Any], Callable[..., Any]]] = []
    if previous is not None:
        variants.append((f"previous code ({args.before}), eager",
                         lambda n: make_tracker(previous, n, g, dtype, device), fly))
    variants.append(("lean step, eager",
                     lambda n: make_tracker(current, n, g, dtype, device), fly))
    if not args.no_compile:
        variants.append(("lean step, torch.compile",
                         lambda n: make_tracker(current, n, g, dtype, device, compile=True),
                         fly))
        variants.append(("one step per epoch (`track`, map lookup inside), torch.compile",
                         lambda n: make_tracker(current, n, g, dtype, device, compile=True),
                         fly_track))
    tmap = TorchMap(one, dtype, device)
    one_rows, fleet_rows = [], []
    for name, make, flies in variants:
        trk = make(1)
        flies(trk, one, slice(0, 1), range(warm), tmap, device)  # warm-up (compiles)
        lat, ep = flies(trk, one, slice(0, 1), range(warm, warm + args.one_steps), tmap,
                        device)
        calls = aten_calls(trk, one, warm + args.one_steps - 1, tmap, device,
                           whole_epoch=flies is fly_track)
        one_rows.append((name, *median_p99(lat), *median_p99(ep), *calls))
    fmap = TorchMap(fleet, dtype, device)
    for name, make, flies in variants:
        rates = []
        for _ in range(args.repeats):
            trk = make(args.runs)
            flies(trk, fleet, slice(None), range(3), fmap, device)  # warm-up (compiles)
            lat, _ = flies(trk, fleet, slice(None), range(3, 3 + args.steps), fmap, device)
            rates.append(args.runs / statistics.median(lat))
        fleet_rows.append((name, statistics.median(rates), max(rates)))
    ref = reference_rate(one, args.ref_runs, args.one_steps // 3 or 1, g)
    simple = simple_numpy_rate(one, args.ref_runs, args.one_steps // 3 or 1, g)
    ss, ss_note = None, "(stonesoup not installed: pip install -e .[test] for its row)"
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            ss = stonesoup_rate(one, args.ref_runs, args.one_steps // 3 or 1, g)
    except (np.linalg.LinAlgError, ValueError) as exc:
        ss_note = f"(Stone Soup row failed on this problem: {type(exc).__name__}: {exc})"
    sweep = []  # (cells, tracker ms per epoch, Stone Soup ms per step or None)
    if not args.no_compile:
        for cells in (int(c) for c in args.sweep.split(",") if c.strip()):
            trk = make_tracker(current, 1, cells, dtype, device, compile=True)
            fly_track(trk, one, slice(0, 1), range(warm), tmap, device)  # compiles
            _, ep = fly_track(trk, one, slice(0, 1), range(warm, warm + args.one_steps),
                              tmap, device)
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                try:
                    rate = stonesoup_rate(one, 1, args.one_steps // 3 or 1, cells)
                except (np.linalg.LinAlgError, ValueError):
                    rate = None
            sweep.append((cells, statistics.median(ep),
                          None if rate is None else cells * cells / rate))
    bandwidth = copy_bandwidth()
    device_bw = bandwidth if device.type == "cpu" else device_copy_bandwidth(device)
    cell_bytes = 2 * (1 + nz) * dtype.itemsize
    print(f"memory bandwidth (copy, read + write): {device_bw / 1e9:.2f} GB/s; roofline = "
          f"bandwidth / {cell_bytes} B per cell-update (mass + {nz} linear-part means, read "
          "and written once)")
    print()
    print("| one vehicle (N = 1) | lattice step median ms | p99 ms | epoch with map lookup "
          "median ms | p99 ms | aten calls per step (all / top-level) |")
    print("|---|---:|---:|---:|---:|---:|")
    for name, lm, lp, em, ep, n_all, n_top in one_rows:
        print(f"| {name} | {1e3 * lm:.3f} | {1e3 * lp:.3f} | {1e3 * em:.3f} | {1e3 * ep:.3f} "
              f"| {n_all} / {n_top} |")
    print()
    print(f"| fleet, N = {args.runs}, {args.threads} thread(s) | vehicle-epochs/s (median) "
          "| best | cell-upd/s | ratio to the same algorithm in NumPy | roofline |")
    print("|---|---:|---:|---:|---:|---:|")
    for name, rate, best in fleet_rows:
        cells_s = rate * g * g
        print(f"| {name} | {rate:,.0f} | {best:,.0f} | {cells_s:.3e} | {cells_s / ref:.1f}x "
              f"| {cells_s * cell_bytes / device_bw:.2%} |")
    print(f"| NumPy, same algorithm (`FollowLatticeReference`), one run at a time, float64 | "
          f"{ref / g / g:,.0f} | | {ref:.3e} | 1.0x | {ref * 2 * (1 + nz) * 8 / bandwidth:.2%} |")
    print(f"| NumPy, older simplified loop (fixed grid, scalar part), one run at a time | "
          f"{simple / g / g:,.0f} | | {simple:.3e} | {simple / ref:.1f}x | |")
    if ss is not None:
        print(f"| Stone Soup Lagrangian PMF (2-D state, {g}² points), one run at a time | "
              f"{ss / g / g:,.0f} | | {ss:.3e} | {ss / ref:.1f}x | |")
    else:
        print(ss_note)
    if sweep:
        print()
        print("| cells per axis | tracker, one step per epoch, compiled, one vehicle, ms | "
              "Stone Soup Lagrangian PMF (2-D state), ms per step | Stone Soup / tracker |")
        print("|---:|---:|---:|---:|")
        for cells, ours, theirs in sweep:
            peer = "n/a" if theirs is None else f"{1e3 * theirs:.3f}"
            ratio = "n/a" if theirs is None else f"{theirs / ours:.1f}x"
            print(f"| {cells} | {1e3 * ours:.3f} | {peer} | {ratio} |")
    print()
    current_rows = [r for r in one_rows if not r[0].startswith("previous")]
    best_one = min(r[1] for r in current_rows if "track" not in r[0])
    best_epoch = min(r[3] for r in current_rows)
    best_fleet = max(r[1] for r in fleet_rows)
    ratio = best_fleet * g * g / ref

    def met(ok: bool) -> str:
        return "met" if ok else "missed"

    print(f"targets: one vehicle's lattice step <= 0.3 ms median: {1e3 * best_one:.3f} ms "
          f"({met(best_one <= 3e-4)}); epoch with the map lookup <= 0.5 ms: "
          f"{1e3 * best_epoch:.3f} ms ({met(best_epoch <= 5e-4)}); >= 50,000 vehicle-epochs/s "
          f"for {args.runs} vehicles: {best_fleet:,.0f} ({met(best_fleet >= 5e4)}); >= 10x the "
          f"same-algorithm NumPy loop per cell-update: {ratio:.1f}x ({met(ratio >= 10)})")
    bench.finish()


if __name__ == "__main__":
    main()
