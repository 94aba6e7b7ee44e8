"""Point-mass filter throughput: batched torch filter vs a single-run NumPy loop.

Measures in one run, on the jacksboro tile, grid-point updates per second (one predict +
one altimeter update of one grid cell counts as one), and prints the ratio per
cell-update against (c) (target: >= 10x for the batched filter, N = 1000, 32² lattice,
one thread) and the rate as a fraction of the machine's memory roofline: a NumPy copy
benchmark measured in the same run gives the bandwidth B (bytes read + written per
second); one cell-update must at least read and write the cell's mass and its scalar /
linear-part mean once (``2 · (1 + nz) · itemsize`` bytes), so the roofline rate is
``B / (2 · (1 + nz) · itemsize)``.

(a) `neuralmap.filters.point_mass.PointMassFilter` over N runs at once (default
    N = 1000, G = 32 cells per axis; float32 adaptive, float32 fixed grid, float64
    adaptive), likelihood on the bilinear DEM through
    `neuralmap.nav.acquisition.lattice_bilinear`;
(a') `neuralmap.filters.point_mass_tracker.PointMassTracker` (the whole-flight
    tracker: the lattice follows the posterior, moment-exact prediction and regrid) on the
    same model (a scalar Kalman part per cell: the altitude error), likelihood on
    `GridTerrain` (bilinear) at its rotated cells;
(b) Stone Soup's ``PointMassPredictor`` (eigen-aligned re-grid + FFT convolution) with a
    NumPy Bayes update, one run at a time (when ``stonesoup`` is installed; its row is
    reported, the ratio column stays against (c));
(c) the reference: the same model one run at a time in a Python loop with NumPy / scipy
    (``scipy.ndimage.convolve1d`` with the sampled Gaussian kernel, bilinear interpolation
    with NumPy indexing, log-domain weights, the per-cell altitude Kalman filter), over a
    handful of runs (it is slow and steady), fixed grid.

Both fly the same straight 200 m/s track from a 1 km prior; the process noise is that of
the scenario's INS position error. Rates are medians over repeats after a warm-up; the
fastest repeat is printed too (on a shared machine it shows the code without interference).

``--device cuda`` runs the torch rows (a), (a') on the GPU (timed between
``torch.cuda.synchronize()`` calls; their roofline is then the device's own copy bandwidth,
a torch copy on it); the NumPy and Stone Soup references stay on the CPU.

Usage:
    python benchmarks/bench_point_mass.py              # N = 1000, G = 32, 20 steps
    python benchmarks/bench_point_mass.py --quick      # smoke test
    python benchmarks/bench_point_mass.py --device cuda
"""

from __future__ import annotations

import argparse
import math
import platform
import statistics
import sys
import time
from pathlib import Path

import numpy as np
import torch

REPO_ROOT = Path(__file__).resolve().parents[1]
if str(REPO_ROOT) not in sys.path:  # run as a script from anywhere
    sys.path.insert(0, str(REPO_ROOT))

from neuralmap.docs.bench_run import add_out_option, start_bench  # noqa: E402
from neuralmap.exceptions import NeuralMapError  # noqa: E402
from neuralmap.filters.point_mass import PointMassConfig, PointMassFilter  # noqa: E402
from neuralmap.nav.acquisition import lattice_bilinear  # noqa: E402
from neuralmap.studies.base import check_device  # noqa: E402

SIGMA0 = 1000.0
R_M2 = 106.0
Q_POS = 1.0
Q_ALT = 1.0
CPU = torch.device("cpu")


def track(n_runs: int, steps: int, tile_extent: tuple[float, float, float, float],
          seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """INS positions ``(N, K, 2)`` and true horizontal errors ``(N, 2)`` of straight tracks."""
    rng = np.random.default_rng(seed)
    xmin, xmax, ymin, ymax = tile_extent
    start = np.stack([rng.uniform(xmin + 6e3, xmax - 12e3, n_runs),
                      rng.uniform(ymin + 6e3, ymax - 6e3, n_runs)], 1)
    k = np.arange(steps)[None, :, None]
    ins = start[:, None, :] + k * np.array([200.0, 0.0])
    err = rng.normal(0.0, SIGMA0, (n_runs, 2))
    return ins, err


def numpy_bilinear(heights: np.ndarray, origin, spacing, xy: np.ndarray) -> np.ndarray:
    ny, nx = heights.shape
    u = np.clip((xy[..., 0] - origin[0]) / spacing[0], 0.0, nx - 1.0)
    v = np.clip((xy[..., 1] - origin[1]) / spacing[1], 0.0, ny - 1.0)
    j = np.minimum(np.floor(u), nx - 2).astype(np.int64)
    i = np.minimum(np.floor(v), ny - 2).astype(np.int64)
    fu, fv = u - j, v - i
    h00, h01 = heights[i, j], heights[i, j + 1]
    h10, h11 = heights[i + 1, j], heights[i + 1, j + 1]
    return (h00 * (1 - fu) + h01 * fu) * (1 - fv) + (h10 * (1 - fu) + h11 * fu) * fv


def numpy_reference(heights, origin, spacing, ins, truth_err, radar, cells: int) -> float:
    """One run at a time, fixed grid, float64 NumPy/scipy; returns cell-updates/s."""
    from scipy.ndimage import convolve1d

    n, steps = ins.shape[0], ins.shape[1]
    half = 0.5 * (cells - 1)
    d = 4.0 * SIGMA0 / half
    off = (np.arange(cells) - half) * d
    sx, sy = np.meshgrid(off, off)
    sigma_cells = math.sqrt(Q_POS) / d
    hl = max(1, int(math.ceil(4 * sigma_cells)))
    kern = np.exp(-0.5 * (np.arange(-hl, hl + 1) / sigma_cells) ** 2)
    kern /= kern.sum()
    start = time.perf_counter()
    for r in range(n):
        logw = -0.5 * (sx**2 + sy**2) / SIGMA0**2
        w = np.exp(logw - logw.max())
        w /= w.sum()
        m = np.zeros_like(w)
        v = 900.0
        for k in range(steps):
            w = convolve1d(convolve1d(w, kern, axis=1, mode="constant"), kern, axis=0,
                           mode="constant")
            wm = convolve1d(convolve1d(w * m, kern, axis=1, mode="constant"), kern, axis=0,
                            mode="constant")
            m = wm / np.maximum(w, 1e-300)
            v += Q_ALT
            xy = np.stack([ins[r, k, 0] - sx, ins[r, k, 1] - sy], -1)
            g = numpy_bilinear(heights, origin, spacing, xy)
            y = radar[r, k]
            nu = y - g - m
            s = v + R_M2
            lw = np.log(np.maximum(w, 1e-300)) - 0.5 * nu * nu / s
            w = np.exp(lw - lw.max())
            w /= w.sum()
            m = m + v / s * nu
            v = v * R_M2 / s
    elapsed = time.perf_counter() - start
    return n * steps * cells * cells / elapsed


def stonesoup_reference(heights, origin, spacing, ins, radar, cells: int) -> float | None:
    """Stone Soup's PointMassPredictor + a NumPy Bayes update, one run at a time (no altitude
    part: the altitude error is taken as known); cell-updates/s, None without stonesoup."""
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

    n, steps = ins.shape[0], ins.shape[1]
    npa = np.array([cells, cells])
    predictor = PointMassPredictor(
        CombinedLinearGaussianTransitionModel([RandomWalk(Q_POS), RandomWalk(Q_POS)]))
    t0 = datetime(2026, 1, 1)
    start = time.perf_counter()
    for r in range(n):
        cov = np.eye(2) * SIGMA0**2
        grid, delta, dims, centre, eig = grid_creation(np.zeros((2, 1)), cov, 4.0, 2, npa)
        pdf = np.exp(-0.5 * np.sum(grid**2, axis=0) / SIGMA0**2)
        state = PointMassState(state_vector=StateVectors(grid), weight=pdf.reshape(-1, 1),
                               grid_delta=delta, grid_dim=dims, center=centre, eigVec=eig,
                               Npa=npa, timestamp=t0)
        for k in range(steps):
            state = predictor.predict(state, timestamp=t0 + timedelta(seconds=k + 1))
            pts = np.asarray(state.state_vector, dtype=float)
            xy = np.stack([ins[r, k, 0] - pts[0], ins[r, k, 1] - pts[1]], -1)
            g = numpy_bilinear(heights, origin, spacing, xy)
            w = np.asarray(state.weight, dtype=float).reshape(-1)
            w = w * np.exp(-0.5 * (radar[r, k] - g) ** 2 / (R_M2 + 900.0))
            w = w / (w.sum() * np.prod(state.grid_delta))
            state = PointMassState(state_vector=state.state_vector, weight=w.reshape(-1, 1),
                                   grid_delta=state.grid_delta, grid_dim=state.grid_dim,
                                   center=state.center, eigVec=state.eigVec, Npa=npa,
                                   timestamp=state.timestamp)
    elapsed = time.perf_counter() - start
    return n * steps * cells * cells / elapsed


def _sync(device: torch.device) -> None:
    """Waits for the device's queued work (CUDA), so a timed region holds all of it."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def batched(heights_grid, ins, radar, cells: int, dtype: torch.dtype,
            adaptive: bool = True, device: torch.device = CPU) -> float:
    n, steps = ins.shape[0], ins.shape[1]
    kw = {"dtype": dtype, "device": device}
    f = PointMassFilter(torch.zeros(n, 2, **kw), torch.eye(2, **kw) * SIGMA0**2,
                        scalar_var=900.0, config=PointMassConfig(cells=cells, adaptive=adaptive),
                        dtype=dtype)
    ins_t = torch.as_tensor(ins).to(device)
    y = torch.as_tensor(radar).to(**kw)
    _sync(device)
    start = time.perf_counter()
    for k in range(steps):
        f.predict(Q=Q_POS, scalar_q=Q_ALT)
        pred = lattice_bilinear(heights_grid, ins_t[:, k], f.centre, f.spacing, f.offsets)
        f.update(y[:, k], pred, R=R_M2)
    _sync(device)
    elapsed = time.perf_counter() - start
    return n * steps * cells * cells / elapsed


def tracker(terrain, ins, radar, cells: int, dtype: torch.dtype,
            device: torch.device = CPU) -> float:
    """Cell-updates/s of the point-mass tracker (2-D grid + altitude Kalman part per cell)."""
    from neuralmap.filters.point_mass_tracker import PointMassTracker, TrackerConfig

    n, steps = ins.shape[0], ins.shape[1]
    kw = {"dtype": dtype, "device": device}
    cov = torch.diag(torch.tensor([SIGMA0**2, SIGMA0**2, 900.0], **kw))
    f = PointMassTracker(torch.zeros(n, 3, **kw), cov, E=torch.zeros(2, 1, **kw),
                         F=torch.eye(1, **kw), c=torch.ones(1, **kw),
                         config=TrackerConfig(cells=cells), dtype=dtype)
    ins_t = torch.as_tensor(ins).to(**kw)
    y = torch.as_tensor(radar).to(**kw)
    qs, qz = Q_POS * torch.eye(2, **kw), Q_ALT * torch.eye(1, **kw)
    _sync(device)
    start = time.perf_counter()
    for k in range(steps):
        f.predict(Q_s=qs, Q_z=qz)
        xy = ins_t[:, k, None, None, :] - f.points()
        f.update(y[:, k], terrain(xy.reshape(-1, 2)).reshape(xy.shape[:-1]), R=R_M2)
    _sync(device)
    elapsed = time.perf_counter() - start
    return n * steps * cells * cells / elapsed


def copy_bandwidth(megabytes: int = 256, repeats: int = 5) -> float:
    """Memory bandwidth (bytes read + written per second) of a NumPy copy, best of repeats."""
    src = np.ones(megabytes * 2**20 // 8)
    dst = np.empty_like(src)
    np.copyto(dst, src)  # page the destination in
    best = math.inf
    for _ in range(repeats):
        start = time.perf_counter()
        np.copyto(dst, src)
        best = min(best, time.perf_counter() - start)
    return 2.0 * src.nbytes / best


def device_copy_bandwidth(device: torch.device, megabytes: int = 256, repeats: int = 5) -> float:
    """Memory bandwidth (bytes read + written per second) of a torch copy on ``device``."""
    src = torch.ones(megabytes * 2**20 // 8, dtype=torch.float64, device=device)
    dst = torch.empty_like(src)
    dst.copy_(src)
    best = math.inf
    for _ in range(repeats):
        _sync(device)
        start = time.perf_counter()
        dst.copy_(src)
        _sync(device)
        best = min(best, time.perf_counter() - start)
    return 2.0 * src.nbytes / best


def _has_stonesoup() -> bool:
    import importlib.util

    return importlib.util.find_spec("stonesoup") is not None


class _Grid:
    def __init__(self, heights: torch.Tensor, origin, spacing) -> None:
        self.heights, self.origin, self.spacing = heights, origin, spacing
        self.shape = tuple(heights.shape)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=1000)
    parser.add_argument("--steps", type=int, default=20)
    parser.add_argument("--cells", type=int, default=32)
    parser.add_argument("--ref_runs", type=int, default=5)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--device", default="cpu",
                        help="torch device of the batched rows (cpu, cuda, cuda:<i>)")
    add_out_option(parser, "bench_point_mass")
    args = parser.parse_args()
    try:
        device = check_device(args.device)
    except NeuralMapError as exc:
        print(f"error: {exc}", file=sys.stderr)
        raise SystemExit(2) from None
    bench = start_bench(__file__, args)
    if args.quick:
        args.runs, args.steps, args.ref_runs, args.repeats = 50, 5, 1, 1
    torch.set_num_threads(args.threads)
    from neuralmap.dem import load_tile

    tile = load_tile("jacksboro")
    heights = np.asarray(tile.heights, dtype=np.float64)
    heights = np.where(np.isfinite(heights), heights, np.nanmean(heights))
    origin, spacing = tuple(tile.origin), tuple(tile.spacing)
    ins, err = track(args.runs, args.steps, tile.extent)
    rng = np.random.default_rng(1)
    radar_truth = numpy_bilinear(heights, origin, spacing, ins - err[:, None, :])
    radar = radar_truth + rng.normal(0.0, 10.0, radar_truth.shape)  # y = h_ins − h_radar
    print(f"point-mass benchmark: {platform.processor() or platform.machine()}, torch "
          f"{torch.__version__}, {args.threads} thread(s); N = {args.runs}, G = {args.cells}, "
          f"{args.steps} steps, sigma0 = {SIGMA0:g} m; torch rows on {device}")
    rows = []
    for dtype, adaptive in ((torch.float32, True), (torch.float32, False),
                            (torch.float64, True)):
        grid = _Grid(torch.as_tensor(heights, dtype=dtype, device=device), origin, spacing)
        batched(grid, ins[: min(10, args.runs), :2], radar[: min(10, args.runs), :2],
                args.cells, dtype, adaptive, device)  # warm-up
        rates = [batched(grid, ins, radar, args.cells, dtype, adaptive, device)
                 for _ in range(args.repeats)]
        label = "adaptive" if adaptive else "fixed grid"
        rows.append((f"batched torch {str(dtype).replace('torch.', '')} {label}, "
                     f"N = {args.runs}", statistics.median(rates), max(rates),
                     4 * dtype.itemsize))
    from neuralmap.terrain.grid import GridTerrain

    for dtype in (torch.float32, torch.float64):
        terrain = GridTerrain(tile, method="bilinear", dtype=dtype).to(device)
        name = f"point-mass tracker {str(dtype).replace('torch.', '')}, N = {args.runs}"
        try:
            tracker(terrain, ins[: min(10, args.runs), :2], radar[: min(10, args.runs), :2],
                    args.cells, dtype, device)  # warm-up
            rates = [tracker(terrain, ins, radar, args.cells, dtype, device)
                     for _ in range(args.repeats)]
        except NeuralMapError as exc:  # reported, not hidden
            print(f"({name} failed: {exc})")
            continue
        rows.append((name, statistics.median(rates), max(rates), 4 * dtype.itemsize))
    n_torch = len(rows)  # the rows measured on the device
    ref_rates = [numpy_reference(heights, origin, spacing, ins[: args.ref_runs],
                                 err[: args.ref_runs], radar[: args.ref_runs], args.cells)
                 for _ in range(args.repeats)]
    ref = statistics.median(ref_rates)
    rows.append((f"NumPy/scipy loop, one run at a time ({args.ref_runs} runs)", ref,
                 max(ref_rates), 32))
    import warnings

    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            ss = stonesoup_reference(heights, origin, spacing, ins[: args.ref_runs],
                                     radar[: args.ref_runs], args.cells)
    except (np.linalg.LinAlgError, ValueError) as exc:
        ss = None
        print(f"(Stone Soup reference failed on this problem: {type(exc).__name__}: {exc}; "
              "its predictor's re-grid produced non-finite values after the first "
              "terrain update)")
    if ss is not None:
        rows.append((f"Stone Soup PointMassPredictor loop ({args.ref_runs} runs)", ss, ss, 16))
    elif not _has_stonesoup():
        print("(stonesoup not installed: pip install -e .[anchors] for its reference row)")
    bandwidth = copy_bandwidth()
    print(f"memory bandwidth (NumPy copy, read + write): {bandwidth / 1e9:.2f} GB/s; roofline "
          "= bandwidth / (bytes a cell-update must read and write)")
    device_bw = bandwidth
    if device.type != "cpu":  # the torch rows' roofline is the device's own memory
        device_bw = device_copy_bandwidth(device)
        print(f"{device} memory bandwidth (torch copy, read + write): {device_bw / 1e9:.2f} "
              "GB/s (the roofline of the torch rows)")
    print(f"{'what':58s} {'median cell-upd/s':>18s} {'best':>12s} {'ratio':>7s} "
          f"{'B/cell':>6s} {'roofline':>9s}")
    for i, (name, rate, best, nbytes) in enumerate(rows):
        bw = device_bw if i < n_torch else bandwidth
        print(f"{name:58s} {rate:18.3e} {best:12.3e} {rate / ref:7.2f}x {nbytes:6d} "
              f"{rate * nbytes / bw:9.2%}")
    print("target: the batched rows >= 10x the NumPy loop per cell-update (N = 1000, 32², "
          "one thread)")
    bench.finish()


if __name__ == "__main__":
    main()
