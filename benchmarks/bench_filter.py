"""Filter and terrain-query throughput: batched torch TAN EKF vs FilterPy + scipy.

Measures in one run, on the scenario's tile (default: jacksboro), and prints ratios:

(a) the 5-state TAN filter step (predict + linearise + update,
    `neuralmap.tan.ekf_step.tan_filter_step` on `neuralmap.filters.ekf.BatchedEKF`)
    with the bilinear grid (first-order Taylor), float32 and float64, N = 100 000;
(b) the same step with the neural map and autograd linearisation (the newest trained
    ``runs/*/version_*/neural_map.pt`` of the tile when present, else an untrained
    ``BlockwiseTerrainNet.from_tile`` with the default configuration: same cost);
(c) FilterPy's ``ExtendedKalmanFilter`` in a Python loop over trajectories and steps, with
    scipy's ``RegularGridInterpolator`` (linear, the same bilinear surface; slope by
    central differences), for the same problem at small N;
(d) height + slope queries per second: neural map (autograd), torch bilinear and bicubic
    (``GridTerrain.height_and_slope``) and scipy ``RegularGridInterpolator`` (cubic, slope
    from its spline derivatives ``nu=(1, 0)``, ``(0, 1)``);
(f) height + slope queries of latent-grid neural maps
    (`neuralmap.terrain.latent.LatentTerrainMap.height_and_slope`, float32, one
    thread, no grid evaluated first) against the torch bicubic grid in the same run,
    interleaved repeats, ratio = latent / bicubic throughput (target ≥ 1.0x); linear
    synthesis (hidden 0) and the 8-unit MLP; ``--latent_only`` runs just this section;
(e) the float32 bilinear TAN step of (a) with every robust/adaptive update policy
    (`neuralmap.filters.policies`), each with its cost ratio to the plain step
    measured in the same run (targets: weight/factor policies ≤ 1.5×, the variational
    filter ≤ 10× at 3 iterations).

Throughput is trajectory-steps (or queries) per second: the median over repeats after a
warm-up (the fastest repeat is printed too: on a shared machine it shows what the code does
without interference). ``torch.set_num_threads(2)`` unless ``--threads`` says otherwise.
(c) is one pass (it is slow and steady); its ratio is against the median of the others.

``--device cuda`` runs the torch rows ((a), (b), (d), (e), (f): filters, maps and their
inputs) on the GPU, each timed region between ``torch.cuda.synchronize()`` calls; FilterPy,
scipy and the float64 cross-check of (c) stay on the CPU.

Usage:
    python benchmarks/bench_filter.py            # full run (about a minute)
    python benchmarks/bench_filter.py --quick    # smoke test (a few seconds)
    python benchmarks/bench_filter.py --device cuda
"""

from __future__ import annotations

import argparse
import dataclasses
import platform
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch

REPO_ROOT = Path(__file__).resolve().parents[1]
if str(REPO_ROOT) not in sys.path:  # run as a script from anywhere
    sys.path.insert(0, str(REPO_ROOT))

from neuralmap.dem.tile import DemTile  # noqa: E402
from neuralmap.docs.bench_run import add_out_option, start_bench  # noqa: E402
from neuralmap.exceptions import NeuralMapError  # noqa: E402
from neuralmap.studies.base import check_device  # noqa: E402

CPU = torch.device("cpu")


@dataclasses.dataclass
class Row:
    """One benchmark result line.

    Attributes:
        group: Benchmark letter and name.
        name: What was measured.
        rate: Median throughput (per second).
        best: Best (fastest repeat) throughput, per second.
        unit: Unit of ``rate``.
        detail: Problem size and notes.
    """

    group: str
    name: str
    rate: float
    best: float
    unit: str
    detail: str


def sync(device: torch.device) -> None:
    """Waits for the device's queued work (CUDA), so a timed region holds all of it."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def timed(fn: Callable[[], Any], *, repeats: int, warmup: int = 2,
          device: torch.device = CPU) -> tuple[float, float]:
    """Median and minimum wall-clock seconds of ``fn()`` over ``repeats`` calls.

    ``warmup`` untimed calls come first (allocator and thread-pool warm-up: the first
    calls on large batches are several times slower). On CUDA each timed call starts and
    ends with a `sync`.
    """
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        sync(device)
        start = time.perf_counter()
        fn()
        sync(device)
        times.append(time.perf_counter() - start)
    return statistics.median(times), min(times)


def _rates(work: float, times: tuple[float, float]) -> tuple[float, float]:
    """(median, best) throughput of ``work`` units from (median, min) seconds."""
    return work / times[0], work / times[1]


def load_bench_tile(scenario_name: str) -> tuple[Any, DemTile, str]:
    """The scenario and its tile (falls back to the tiny synthetic scenario)."""
    from neuralmap.lab.scenario import load_scenario, scenario_tile

    try:
        scenario = load_scenario(scenario_name)
        return scenario, scenario_tile(scenario), scenario_name
    except NeuralMapError as exc:
        print(f"note: scenario {scenario_name!r} unavailable ({exc}); using 'tiny'")
        scenario = load_scenario("tiny")
        return scenario, scenario_tile(scenario), "tiny"


def neural_map_for(tile: DemTile, runs_dir: Path) -> tuple[torch.nn.Module, str]:
    """The newest trained map of ``tile`` under ``runs_dir``, else an untrained default net."""
    from neuralmap.studies.maps import find_latest_map
    from neuralmap.terrain.blockwise import BlockwiseTerrainNet
    from neuralmap.terrain.export import load_map

    path = find_latest_map(runs_dir, tile_fingerprint=tile.fingerprint())
    if path is not None:
        try:
            model = load_map(path)
        except NeuralMapError:
            model = None
        if model is not None and getattr(model, "tile_fingerprint", "") == tile.fingerprint():
            return model, f"trained map {path}"
    net = BlockwiseTerrainNet.from_tile(tile)
    return net, "untrained BlockwiseTerrainNet.from_tile(tile) (default config; same cost)"


def bench_tan_step(
    truth: Any,
    scenario: Any,
    linearizer: torch.nn.Module,
    *,
    dtype: torch.dtype,
    repeats: int,
    device: torch.device = CPU,
) -> tuple[float, float]:
    """(median, best) trajectory-steps per second of the batched TAN filter over K steps
    (filter, inputs and ``linearizer`` on ``device``)."""
    from neuralmap.filters.ekf import BatchedEKF
    from neuralmap.tan.ekf_step import tan_filter_step
    from neuralmap.tan.model import N_STATES, TanModel

    n, k_steps = truth.n_runs, truth.n_steps
    ins_pos = truth.ins_pos.to(device, dtype)
    radar = truth.radar.to(device, dtype)
    model = TanModel.from_scenario(scenario)
    p0 = model.filter_prior(dtype=dtype).to(device)
    F = model.transition(dtype=dtype).to(device)
    Q = model.filter_process_noise(dtype=dtype).to(device)
    R = model.base_R
    linearizer = linearizer.to(device)

    def run() -> None:
        ekf = BatchedEKF(torch.zeros(n, N_STATES, dtype=dtype, device=device), p0)
        with torch.no_grad():
            for k in range(1, k_steps + 1):
                tan_filter_step(
                    ekf,
                    ins_pos[:, k],
                    radar[:, k],
                    linearizer,
                    F=F,
                    Q=Q,
                    R=R,
                    extent=truth.extent,
                )

    return _rates(n * k_steps, timed(run, repeats=repeats, warmup=1, device=device))


def policy_factories() -> dict[str, Callable[[], Any]]:
    """The policies of benchmark (e), by report name (fresh objects: per-sample state), all
    from the policy registry (`neuralmap.filters.policies.make_policy`) with its
    defaults: the same filters the studies run."""
    from neuralmap.filters.policies import make_policy

    sage_husa = {"R_min": 1.0, "R_max": 1e4}
    entries: dict[str, tuple[str, dict[str, Any]]] = {
        "plain EKF": ("ekf", {}),
        "ChiSquareGate(0.99)": ("chi2", {}),
        "Huber(1.345)": ("huber", {}),
        "IGG3(1.5, 4.5)": ("igg3", {}),
        "YangAdaptive(1, 3)": ("yang", {}),
        "RobustAdaptive (RAF)": ("raf", {}),
        "InnovationInflation(1.2)": ("inflation", {}),
        "QualityR.altimeter": ("quality", {}),
        "QualityR + InnovationInflation": ("quality_inflation", {}),
        "SageHusa(0.97)": ("sage_husa", sage_husa),
        "SageHusa(0.97, adapt_Q)": ("sage_husa", {**sage_husa, "adapt_Q": True}),
        "VariationalAdaptive(3)": ("variational", {}),
    }
    return {label: (lambda n=name, a=args: make_policy(n, a))
            for label, (name, args) in entries.items()}


def bench_policy_steps(
    truth: Any,
    scenario: Any,
    linearizer: torch.nn.Module,
    *,
    dtype: torch.dtype,
    repeats: int,
    device: torch.device = CPU,
) -> list[tuple[str, float, float, float]]:
    """(name, median, best trajectory-steps/s, median CPU seconds) of the TAN step per policy.

    The quality policies get per-epoch altimeter indicators (roughness, height above
    ground, lock; drawn once, outside the timing) through ``set_quality`` before each
    step. Repeats are interleaved (each repeat runs every policy once). The process CPU
    time is recorded too: on a shared machine its ratio is the steadier cost measure.
    """
    from neuralmap.filters.ekf import BatchedEKF
    from neuralmap.filters.policies import quality_members
    from neuralmap.tan.ekf_step import tan_filter_step
    from neuralmap.tan.model import N_STATES, transition_matrix

    n, k_steps = truth.n_runs, truth.n_steps
    ins_pos = truth.ins_pos.to(device, dtype)
    radar = truth.radar.to(device, dtype)
    p0 = torch.diag(torch.tensor(scenario.P0_diag, dtype=dtype, device=device))
    F = transition_matrix(scenario.dt, dtype=dtype, device=device)
    Q = torch.diag(torch.tensor(scenario.Q_diag, dtype=dtype, device=device))
    linearizer = linearizer.to(device)
    R = scenario.R_m2 + scenario.fit_variance_m2
    gen = torch.Generator().manual_seed(1)
    quality = torch.stack(
        [
            20.0 * torch.rand(k_steps + 1, n, generator=gen),
            torch.full((k_steps + 1, n), 500.0),
            (torch.rand(k_steps + 1, n, generator=gen) > 0.01).float(),
        ],
        dim=-1,
    ).to(device, dtype)

    def runner(make: Callable[[], Any]) -> Callable[[], None]:
        def run() -> None:
            policy = make()
            takes_quality = bool(quality_members(policy))
            ekf = BatchedEKF(torch.zeros(n, N_STATES, dtype=dtype, device=device), p0)
            with torch.no_grad():
                for k in range(1, k_steps + 1):
                    if takes_quality:
                        policy.set_quality(quality[k])
                    tan_filter_step(ekf, ins_pos[:, k], radar[:, k], linearizer, F=F, Q=Q,
                                    R=R, extent=truth.extent, policy=policy)

        return run

    # interleaved: every repeat times each policy once, so that slow phases of a shared
    # machine hit all of them alike
    runs = {name: runner(make) for name, make in policy_factories().items()}
    for run in runs.values():
        run()  # warm-up
    times: dict[str, list[float]] = {name: [] for name in runs}
    cpu: dict[str, list[float]] = {name: [] for name in runs}
    for _ in range(repeats):
        for name, run in runs.items():
            sync(device)
            start, start_cpu = time.perf_counter(), time.process_time()
            run()
            sync(device)
            times[name].append(time.perf_counter() - start)
            cpu[name].append(time.process_time() - start_cpu)
    return [
        (name, *_rates(n * k_steps, (statistics.median(t), min(t))),
         statistics.median(cpu[name]))
        for name, t in times.items()
    ]


def filterpy_tan(
    truth: Any, scenario: Any, tile: DemTile, *, n_runs: int, interp: str = "linear"
) -> tuple[float, np.ndarray]:
    """FilterPy EKF in a Python loop with scipy interpolation; returns (rate, final states).

    The measurement model matches `neuralmap.tan.ekf_step.tan_filter_step`:
    ``z = −h_radar``, ``h(δX) = −(h_ins − δh) + h_map(p_ins − δX[:2])`` so that the
    innovation ``z − h(δX̂⁻) = (ĥ − h_map(p̂)) − h_radar`` and the Jacobian is
    ``H = [−h_x, −h_y, 1, 0, 0]`` (SEEDS 004). The slope is the central difference of the
    interpolant over ±1 mm (exact for the bilinear surface inside a cell).
    """
    from filterpy.kalman import ExtendedKalmanFilter
    from scipy.interpolate import RegularGridInterpolator

    from neuralmap.terrain.grid import fill_voids_nearest

    heights = fill_voids_nearest(tile.heights, tile.spacing)
    ny, nx = tile.shape
    ys = tile.origin[1] + np.arange(ny) * tile.spacing[1]
    xs = tile.origin[0] + np.arange(nx) * tile.spacing[0]
    interp_fn = RegularGridInterpolator(
        (ys, xs), heights, method=interp, bounds_error=False, fill_value=None
    )
    step = 1e-3
    offsets = np.array([[0, 0], [step, 0], [-step, 0], [0, step], [0, -step]], dtype=float)
    ins_pos = truth.ins_pos[:n_runs].double().numpy()
    radar = truth.radar[:n_runs].double().numpy()
    k_steps = truth.n_steps
    F = np.eye(5)
    F[0, 3] = F[1, 4] = scenario.dt
    Q = np.diag(scenario.Q_diag)
    R = np.array([[scenario.R_m2 + scenario.fit_variance_m2]])
    finals = np.zeros((n_runs, 5))

    start = time.perf_counter()
    for i in range(n_runs):
        ekf = ExtendedKalmanFilter(dim_x=5, dim_z=1)
        ekf.x = np.zeros((5, 1))
        ekf.P = np.diag(scenario.P0_diag).astype(float)
        ekf.F, ekf.Q, ekf.R = F, Q, R
        for k in range(1, k_steps + 1):
            ekf.predict()
            px, py, ph = ins_pos[i, k]
            p_hat = np.array([px - ekf.x[0, 0], py - ekf.x[1, 0]])
            pts = (p_hat + offsets)[:, ::-1]  # (y, x) order for the interpolator
            vals = interp_fn(pts)
            slope = np.array([vals[1] - vals[2], vals[3] - vals[4]]) / (2 * step)
            h_map = vals[0]
            H = np.array([[-slope[0], -slope[1], 1.0, 0.0, 0.0]])

            def jac(x: np.ndarray, H: np.ndarray = H) -> np.ndarray:
                return H

            def hx(x: np.ndarray, ph: float = ph, h_map: float = h_map) -> np.ndarray:
                return np.array([[-(ph - x[2, 0]) + h_map]])

            ekf.update(np.array([[-radar[i, k]]]), jac, hx)
        finals[i] = ekf.x[:, 0]
    elapsed = time.perf_counter() - start
    return n_runs * k_steps / elapsed, finals


def torch_final_states(truth: Any, scenario: Any, tile: DemTile, *, n_runs: int) -> np.ndarray:
    """Final states of the batched float64 torch filter on the first ``n_runs`` runs.

    Uses the bilinear Taylor linearizer with zero linearisation variance so that the
    problem equals `filterpy_tan`'s exactly (a cross-check of the comparison).
    """
    from neuralmap.filters.ekf import BatchedEKF
    from neuralmap.linearize.factory import make_linearizer
    from neuralmap.tan.ekf_step import tan_filter_step
    from neuralmap.tan.model import N_STATES, TanModel

    lin = make_linearizer("bilinear", tile=tile, variance="zero")
    dtype = torch.float64
    model = TanModel.from_scenario(scenario)
    ekf = BatchedEKF(torch.zeros(n_runs, N_STATES, dtype=dtype), model.filter_prior(dtype=dtype))
    F = model.transition(dtype=dtype)
    Q = model.filter_process_noise(dtype=dtype)
    with torch.no_grad():
        for k in range(1, truth.n_steps + 1):
            tan_filter_step(
                ekf,
                truth.ins_pos[:n_runs, k].double(),
                truth.radar[:n_runs, k].double(),
                lin,
                F=F,
                Q=Q,
                R=model.base_R,
                extent=truth.extent,
            )
    return ekf.x.numpy()


def bench_queries(
    tile: DemTile, neural: torch.nn.Module, *, n_points: int, n_scipy: int, repeats: int,
    device: torch.device = CPU,
) -> list[Row]:
    """Height + slope queries per second for the neural map, torch grids (on ``device``) and
    scipy (CPU)."""
    from scipy.interpolate import RegularGridInterpolator

    from neuralmap.linearize.autograd import AutogradLinearizer
    from neuralmap.terrain.grid import GridTerrain, fill_voids_nearest

    gen = torch.Generator().manual_seed(0)
    xmin, xmax, ymin, ymax = tile.extent
    lo = torch.tensor([xmin, ymin], dtype=torch.float64)
    span = torch.tensor([xmax - xmin, ymax - ymin], dtype=torch.float64)
    xy64 = lo + span * torch.rand(n_points, 2, generator=gen, dtype=torch.float64)
    xy32 = xy64.float().to(device)
    xy64_dev = xy64.to(device)
    rows: list[Row] = []

    lin = AutogradLinearizer(neural.to(device))
    rate, best = _rates(n_points, timed(lambda: lin(xy32), repeats=repeats, device=device))
    rows.append(
        Row(
            "(d) queries",
            "neural map, autograd (float32)",
            rate,
            best,
            "queries/s",
            f"{n_points} points",
        )
    )
    for method in ("bilinear", "bicubic"):
        for dtype, xy in ((torch.float32, xy32), (torch.float64, xy64_dev)):
            grid = GridTerrain(tile, method=method, dtype=dtype).to(device)
            rate, best = _rates(
                n_points, timed(lambda g=grid, p=xy: g.height_and_slope(p), repeats=repeats,
                                device=device)
            )
            rows.append(
                Row(
                    "(d) queries",
                    f"torch {method} grid, analytic ({str(dtype)[6:]})",
                    rate,
                    best,
                    "queries/s",
                    f"{n_points} points",
                )
            )

    heights = fill_voids_nearest(tile.heights, tile.spacing)
    ny, nx = tile.shape
    ys = tile.origin[1] + np.arange(ny) * tile.spacing[1]
    xs = tile.origin[0] + np.arange(nx) * tile.spacing[0]
    rgi = RegularGridInterpolator((ys, xs), heights, method="cubic")
    pts = xy64[:n_scipy].numpy()[:, ::-1].copy()

    def scipy_query() -> None:
        rgi(pts)
        rgi(pts, nu=(1, 0))
        rgi(pts, nu=(0, 1))

    rate, best = _rates(n_scipy, timed(scipy_query, repeats=repeats))
    rows.append(
        Row(
            "(d) queries",
            "scipy RegularGridInterpolator cubic (float64)",
            rate,
            best,
            "queries/s",
            f"{n_scipy} points; slope from its derivatives nu",
        )
    )
    return rows


def latent_maps_for(tile: DemTile, hidden: list[int]) -> list[tuple[torch.nn.Module, str]]:
    """Latent maps of the tile: freshly initialised (the default wavelet basis, exact start,
    untrained decoder; the query cost does not depend on the values) for each ``hidden``."""
    from neuralmap.terrain.latent import LatentGrid, export_map

    return [(export_map(LatentGrid(tile, hidden=h)), f"wavelet basis, hidden {h}") for h in hidden]


def bench_latent_queries(tile: DemTile, *, n_points: int, repeats: int,
                         hidden: list[int], device: torch.device = CPU) -> list[Row]:
    """Latent-map vs torch bicubic height + slope queries, float32, one thread, same run."""
    from neuralmap.terrain.grid import GridTerrain

    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        gen = torch.Generator().manual_seed(1)
        xmin, xmax, ymin, ymax = tile.extent
        xy = (torch.tensor([xmin, ymin]) + torch.tensor([xmax - xmin, ymax - ymin])
              * torch.rand(n_points, 2, generator=gen, dtype=torch.float64)).float().to(device)
        bicubic = GridTerrain(tile, method="bicubic", dtype=torch.float32).to(device)
        maps = [(m.to(device), what) for m, what in latent_maps_for(tile, hidden)]
        times: dict[str, list[float]] = {"bicubic": []}
        times.update({what: [] for _, what in maps})
        fns = [("bicubic", lambda: bicubic.height_and_slope(xy))]
        fns += [(what, lambda m=m: m.height_and_slope(xy)) for m, what in maps]
        for _, fn in fns:
            fn()
        for _ in range(max(repeats, 3)):  # interleaved: machine load hits every method alike
            for what, fn in fns:
                sync(device)
                start = time.perf_counter()
                fn()
                sync(device)
                times[what].append(time.perf_counter() - start)
    finally:
        torch.set_num_threads(previous)
    med = {k: statistics.median(v) for k, v in times.items()}
    best = {k: min(v) for k, v in times.items()}
    rows = [Row("(f) latent queries", "torch bicubic grid, analytic (float32, 1 thread)",
                n_points / med["bicubic"], n_points / best["bicubic"], "queries/s",
                f"{n_points} points")]
    for _, what in maps:
        rows.append(Row(
            "(f) latent queries", f"latent-grid map, analytic ({what}; float32, 1 thread)",
            n_points / med[what], n_points / best[what], "queries/s",
            f"{n_points} points; {med['bicubic'] / med[what]:.2f}x bicubic (median), "
            f"{best['bicubic'] / best[what]:.2f}x (best repeat)"))
    return rows


def run(args: argparse.Namespace) -> list[Row]:
    """Runs every benchmark and returns the rows (also printed)."""
    from neuralmap.lab.simulator import simulate
    from neuralmap.linearize.factory import make_linearizer

    torch.set_num_threads(args.threads)
    device = check_device(args.device)
    scenario, tile, scenario_name = load_bench_tile(args.scenario)
    if args.latent_only:
        print(f"# bench_filter (f) only: torch {torch.__version__}; tile {tile.name} "
              f"{tile.shape[0]}x{tile.shape[1]}; torch rows on {device}")
        return bench_latent_queries(tile, n_points=args.n_queries, repeats=args.repeats,
                                    hidden=args.latent_hidden, device=device)
    scenario = dataclasses.replace(scenario, duration_s=args.steps * scenario.dt)
    n, n_neural = args.n, args.n_neural
    print(
        f"# bench_filter: torch {torch.__version__}, {torch.get_num_threads()} threads, "
        f"{platform.processor() or platform.machine()}; scenario {scenario_name} "
        f"(tile {tile.name} {tile.shape[0]}x{tile.shape[1]}), {args.steps} steps; torch rows "
        f"on {device}"
    )
    clock = time.perf_counter()

    def stage(name: str) -> None:
        nonlocal clock
        now = time.perf_counter()
        print(f"#   {name}: {now - clock:.1f} s", flush=True)
        clock = now

    truth = simulate(scenario, tile, n_runs=max(n, n_neural), seed=0, dtype=torch.float64)
    stage("simulate")
    rows: list[Row] = []

    for dtype in (torch.float32, torch.float64):
        lin = make_linearizer("bilinear", tile=tile, dtype=dtype)
        rate, best = bench_tan_step(truth, scenario, lin, dtype=dtype, repeats=args.repeats,
                                    device=device)
        rows.append(
            Row(
                "(a) TAN step",
                f"torch bilinear Taylor ({str(dtype)[6:]})",
                rate,
                best,
                "traj-steps/s",
                f"N = {n}, {args.steps} steps",
            )
        )

    stage("(a) bilinear TAN step")
    neural, neural_what = neural_map_for(tile, Path(args.runs_dir))
    lin = make_linearizer("neural", tile=tile, terrain=neural)
    sub = _subset(truth, n_neural)
    for dtype in (torch.float32, torch.float64):
        rate, best = bench_tan_step(sub, scenario, lin, dtype=dtype, repeats=args.repeats,
                                    device=device)
        rows.append(
            Row(
                "(b) TAN step",
                f"torch neural map, autograd ({str(dtype)[6:]} filter)",
                rate,
                best,
                "traj-steps/s",
                f"N = {n_neural}, {args.steps} steps; {neural_what}",
            )
        )

    stage("(b) neural TAN step")
    fp_rate, fp_final = filterpy_tan(truth, scenario, tile, n_runs=args.n_filterpy)
    rows.append(
        Row(
            "(c) TAN step",
            "FilterPy EKF loop + scipy RGI linear (float64)",
            fp_rate,
            fp_rate,
            "traj-steps/s",
            f"N = {args.n_filterpy}, {args.steps} steps",
        )
    )
    torch_final = torch_final_states(truth, scenario, tile, n_runs=args.n_filterpy)
    deviation = float(np.abs(torch_final - fp_final).max())
    print(
        f"# cross-check: max |torch float64 - FilterPy| over the final states of "
        f"{args.n_filterpy} runs = {deviation:.2e}"
    )

    stage("(c) FilterPy + cross-check")
    if not args.skip_policies:
        lin = make_linearizer("bilinear", tile=tile, dtype=torch.float32)
        policy_rows = bench_policy_steps(truth, scenario, lin, dtype=torch.float32,
                                         repeats=args.repeats, device=device)
        plain_med, plain_cpu = policy_rows[0][1], policy_rows[0][3]
        for name, rate, best, cpu_s in policy_rows:
            rows.append(
                Row(
                    "(e) TAN step + policy",
                    f"{name} (float32)",
                    rate,
                    best,
                    "traj-steps/s",
                    f"N = {n}, {args.steps} steps; cost {plain_med / rate:.2f}x the plain "
                    f"step (CPU time: {cpu_s / plain_cpu:.2f}x)",
                )
            )
        stage("(e) policies")
    rows += bench_queries(
        tile, neural, n_points=args.n_queries, n_scipy=args.n_scipy, repeats=args.repeats,
        device=device,
    )
    stage("(d) queries")
    rows += bench_latent_queries(tile, n_points=args.n_queries, repeats=args.repeats,
                                 hidden=args.latent_hidden, device=device)
    stage("(f) latent queries")
    return rows


def _subset(truth: Any, n: int) -> Any:
    """The first ``n`` runs of a Truth (tensors sliced along the run axis)."""
    if n >= truth.n_runs:
        return truth
    sliced = {}
    for f in dataclasses.fields(truth):
        value = getattr(truth, f.name)
        if isinstance(value, torch.Tensor) and value.ndim >= 2 and value.shape[0] == truth.n_runs:
            value = value[:n]
        sliced[f.name] = value
    return type(truth)(**sliced)


def format_rows(rows: list[Row]) -> str:
    """Markdown table with ratios: filters against FilterPy, queries against scipy, latent
    queries against the torch bicubic grid of (f)."""
    ref_filter = next((r.rate for r in rows if r.group.startswith("(c)")), float("nan"))
    ref_query = next(
        (r.rate for r in rows if r.group.startswith("(d)") and "scipy" in r.name), float("nan")
    )
    ref_latent = next((r.rate for r in rows if r.group.startswith("(f)")), float("nan"))
    lines = [
        "| benchmark | implementation | median throughput | ratio | best repeat | problem |",
        "|---|---|---:|---:|---:|---|",
    ]
    for r in rows:
        if r.group.startswith("(f)"):
            ref, ref_name = ref_latent, "bicubic"
        elif r.group.startswith("(d)"):
            ref, ref_name = ref_query, "scipy"
        else:
            ref, ref_name = ref_filter, "FilterPy"
        lines.append(
            f"| {r.group} | {r.name} | {r.rate:,.0f} {r.unit} | {r.rate / ref:,.1f}x {ref_name} "
            f"| {r.best:,.0f} | {r.detail} |"
        )
    return "\n".join(lines)


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    """Command-line options."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="small sizes: a smoke test")
    parser.add_argument("--scenario", default="jacksboro", help="scenario whose tile is used")
    parser.add_argument("--n", type=int, default=100_000, help="trajectories, (a)")
    parser.add_argument("--n_neural", type=int, default=100_000, help="trajectories, (b)")
    parser.add_argument("--n_filterpy", type=int, default=200, help="trajectories, (c)")
    parser.add_argument("--n_queries", type=int, default=100_000, help="points, (d) torch")
    parser.add_argument("--n_scipy", type=int, default=20_000, help="points, (d) scipy")
    parser.add_argument("--steps", type=int, default=20, help="filter steps per run")
    parser.add_argument("--repeats", type=int, default=5, help="timed repeats (median)")
    parser.add_argument("--threads", type=int, default=2, help="torch.set_num_threads")
    parser.add_argument("--runs_dir", default="runs", help="where to look for a trained map")
    parser.add_argument("--skip_policies", action="store_true", help="skip benchmark (e)")
    parser.add_argument("--latent_only", action="store_true", help="run benchmark (f) only")
    parser.add_argument("--latent_hidden", type=int, nargs="+", default=[0, 8],
                        help="MLP widths of the latent maps in (f)")
    parser.add_argument("--device", default="cpu",
                        help="torch device of the torch rows (cpu, cuda, cuda:<i>)")
    add_out_option(parser, "bench_filter")
    args = parser.parse_args(argv)
    if args.quick:
        args.n, args.n_neural, args.n_filterpy = 2000, 1000, 10
        args.n_queries, args.n_scipy, args.steps, args.repeats = 2000, 1000, 5, 2
    return args


def main(argv: list[str] | None = None) -> int:
    """Runs the benchmarks and prints the markdown table."""
    args = parse_args(argv)
    try:
        check_device(args.device)
    except NeuralMapError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    bench = start_bench(__file__, args, argv)
    previous = torch.get_num_threads()
    try:
        rows = run(args)
    finally:
        torch.set_num_threads(previous)
    print()
    print(format_rows(rows))
    bench.finish()
    return 0


if __name__ == "__main__":
    sys.exit(main())
