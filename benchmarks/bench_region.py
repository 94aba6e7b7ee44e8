"""Region-scale benchmark: sharded training vs area and processes; chunked Monte Carlo.

Every measurement runs in a fresh child process (so peak RSS is its own):

* **Training** (`neuralmap.training.region.fit_region`): synthetic regions with the
  jacksboro spectrum of 138 k (372 × 372), 1 M (1000 × 1000) and 4.6 M (1270 × 3610,
  SEEDS 004's map) nodes at 100 m, memory-mapped; the same number of shards (``--shards``,
  8 × 8 blocks of 24 node intervals each) trained for ``--steps`` steps on 1 and 2
  processes. Reported: points/s (block samples per second of the slowest rank), the
  2-process/1-process ratio, the peak RSS of the largest rank, and the projected time of
  a whole map (every block, ``--full_steps`` steps of 256 points: the trainer's defaults)
  for the paper's region and an SRTM 1″ tile (3601 × 3601 at 30 m).
* **Monte Carlo** (`neuralmap.lab.chunked.run_monte_carlo_chunked`): the jacksboro
  scenario (200 steps), bilinear method, at ``--mc_runs`` runs; runs/s and the peak RSS
  of the chunked run itself (the peak is reset after the setup through
  ``/proc/self/clear_refs``, so the truth-terrain build is not counted; its own peak is
  reported apart).

Usage::

    python benchmarks/bench_region.py                    # everything (tens of minutes)
    python benchmarks/bench_region.py --quick            # small sizes, to check the script
    python benchmarks/bench_region.py --skip_mc --areas 138k 4.6M
"""

from __future__ import annotations

import argparse
import json
import math
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from neuralmap.docs.bench_run import add_out_option, start_bench

REPO = Path(__file__).resolve().parents[1]
AREAS = {"138k": (372, 372), "1M": (1000, 1000), "4.6M": (1270, 3610)}
SRTM_1ARCSEC = (3601, 3601)


def _vm(key: str) -> float:
    """A ``/proc/self/status`` memory line (VmHWM, VmRSS) in MiB (0 where unavailable)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith(key + ":"):
                return float(line.split()[1]) / 1024.0
    except OSError:
        pass
    return 0.0


def _reset_peak() -> bool:
    """Resets this process's peak RSS (Linux ``clear_refs`` 5); False where refused."""
    try:
        Path("/proc/self/clear_refs").write_text("5")
        return True
    except OSError:
        return False


def _child_generate(job: dict) -> dict:
    from neuralmap.dem.region import synthetic_region

    tick = time.perf_counter()
    synthetic_region(job["path"], shape=tuple(job["shape"]), seed=0)
    return {"seconds": time.perf_counter() - tick, "peak_rss_mb": _vm("VmHWM")}


def _child_train(job: dict) -> dict:
    from neuralmap.terrain.sharded import shard_block_ranges
    from neuralmap.training.region import RegionData, fit_region, plan_layout

    data = RegionData.open(job["path"])
    available = len(shard_block_ranges(plan_layout(data).num_blocks, (8, 8)))
    job["shards"] = min(job["shards"], available)
    summary = fit_region(data, job["out"], shard_blocks=(8, 8), steps=job["steps"],
                         devices=job["devices"], shard_ids=list(range(job["shards"])),
                         strategy=None)
    ranks = summary["per_rank"]
    return {"points_per_s": summary["points_per_s"], "points": summary["points"],
            "points_per_cpu_s": summary["points_per_cpu_s"],
            "peak_rss_mb": max([r["peak_rss_mb"] for r in ranks] + [_vm("VmHWM")]),
            "rank_rss_mb": [r["peak_rss_mb"] for r in ranks],
            "blocks": summary["layout"]["num_blocks"], "wall_s": summary["wall_s"]}


def _child_mc(job: dict) -> dict:
    import torch

    from neuralmap.lab.chunked import run_monte_carlo_chunked
    from neuralmap.lab.scenario import load_scenario, scenario_tile
    from neuralmap.lab.truth_terrain import true_terrain
    from neuralmap.linearize.factory import make_linearizer

    torch.set_num_threads(1)
    scenario = load_scenario(job["scenario"])
    tile = scenario_tile(scenario)
    world = true_terrain(scenario, tile, seed=scenario.seed)
    methods = {"bilinear": make_linearizer("bilinear", tile=tile)}
    setup_peak = _vm("VmHWM")
    reset = _reset_peak()
    base = _vm("VmRSS")
    tick = time.perf_counter()
    result = run_monte_carlo_chunked(scenario, methods, n_runs=job["runs"],
                                     chunk_runs=job["chunk_runs"], tile=tile,
                                     truth_terrain=world)
    wall = time.perf_counter() - tick
    metrics = result.summaries["bilinear"].metrics()
    return {"runs_per_s": job["runs"] / wall, "wall_s": wall, "setup_peak_mb": setup_peak,
            "rss_before_mb": base, "peak_rss_mb": _vm("VmHWM") if reset else float("nan"),
            "peak_reset": reset, "n_steps": scenario.n_steps, "chunks": result.n_chunks,
            "final_pos_m": metrics["final_pos_m"]}


def _spawn(job: dict) -> dict:
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(REPO)}
    proc = subprocess.run([sys.executable, __file__, "--child", json.dumps(job)], env=env,
                          capture_output=True, text=True, check=False)
    if proc.returncode != 0:
        raise RuntimeError(f"child {job['kind']} failed:\n{proc.stderr[-3000:]}")
    return json.loads(proc.stdout.strip().splitlines()[-1])


def _blocks(shape: tuple[int, int], block_nodes: int = 24) -> int:
    return math.ceil((shape[0] - 1) / block_nodes) * math.ceil((shape[1] - 1) / block_nodes)


def main(argv: list[str] | None = None) -> int:
    """Runs the benchmark and prints the markdown tables."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--child", default=None, help=argparse.SUPPRESS)
    parser.add_argument("--quick", action="store_true", help="small sizes, few steps")
    parser.add_argument("--areas", nargs="*", default=list(AREAS), choices=list(AREAS))
    parser.add_argument("--shards", type=int, default=4, help="shards trained per measurement")
    parser.add_argument("--steps", type=int, default=30, help="steps per shard measured")
    parser.add_argument("--full_steps", type=int, default=500, help="steps of a real fit")
    parser.add_argument("--mc_runs", type=int, nargs="*", default=[10_000, 100_000])
    parser.add_argument("--skip_mc", action="store_true")
    parser.add_argument("--skip_train", action="store_true")
    parser.add_argument("--json", default=None, help="also write the numbers here")
    add_out_option(parser, "bench_region")
    args = parser.parse_args(argv)
    if args.child is not None:
        job = json.loads(args.child)
        out = {"generate": _child_generate, "train": _child_train, "mc": _child_mc}[
            job["kind"]](job)
        print(json.dumps(out))
        return 0
    bench = start_bench(__file__, args, argv)
    areas = {k: AREAS[k] for k in args.areas}
    steps, shards, mc_runs = args.steps, args.shards, args.mc_runs
    if args.quick:
        areas, steps, shards, mc_runs = {"small": (97, 145)}, 5, 2, [1024, 2048]
    numbers: dict = {"train": {}, "mc": {}}
    tmp = Path(tempfile.mkdtemp(prefix="bench_region_"))
    if not args.skip_train:
        print("| area (nodes) | processes | points/s | 2p/1p | points per CPU-s | peak RSS (MiB) "
              "| blocks | projected full fit |\n|---|---:|---:|---:|---:|---:|---:|---:|",
              flush=True)
        for label, shape in areas.items():
            path = tmp / f"{label}.npy"
            gen = _spawn({"kind": "generate", "path": str(path), "shape": list(shape)})
            single = None
            for devices in (1, 2):
                res = _spawn({"kind": "train", "path": str(path), "out": str(tmp / "o"),
                              "steps": steps, "devices": devices, "shards": shards})
                res["generate"] = gen
                numbers["train"][f"{label}/{devices}"] = res
                single = res if devices == 1 else single
                ratio = res["points_per_s"] / single["points_per_s"]
                full_points = _blocks(shape) * 256 * args.full_steps
                hours = full_points / res["points_per_s"] / 3600
                print(f"| {label} ({shape[0]}×{shape[1]}) | {devices} | "
                      f"{res['points_per_s']:,.0f} | {ratio:.2f} | {res['points_per_cpu_s']:,.0f} | "
                      f"{res['peak_rss_mb']:.0f} | "
                      f"{_blocks(shape):,} | {hours:.2f} h |", flush=True)
            path.unlink()
        ref = numbers["train"].get(f"{list(areas)[-1]}/1")
        if ref:
            for name, shape in (("SEEDS 004 map", AREAS["4.6M"]), ("SRTM 1″ tile", SRTM_1ARCSEC)):
                pts = _blocks(shape) * 256 * args.full_steps
                for devices in (1, 2):
                    rate = numbers["train"][f"{list(areas)[-1]}/{devices}"]["points_per_s"]
                    print(f"projected: {name} {shape[0]}×{shape[1]}: {_blocks(shape):,} blocks × "
                          f"256 points × {args.full_steps} steps = {pts / 1e6:.0f} M points: "
                          f"{pts / rate / 3600:.2f} h on {devices} process(es) at "
                          f"{rate:,.0f} points/s", flush=True)
    if not args.skip_mc:
        print("\n| Monte Carlo runs | runs/s | wall | peak RSS of the run (MiB) "
              "| RSS before (MiB) | setup peak (MiB) |\n|---:|---:|---:|---:|---:|---:|",
              flush=True)
        for runs in mc_runs:
            res = _spawn({"kind": "mc", "runs": runs, "chunk_runs": 8192,
                          "scenario": "tiny" if args.quick else "jacksboro"})
            numbers["mc"][str(runs)] = res
            print(f"| {runs:,} | {res['runs_per_s']:,.0f} | {res['wall_s']:.0f} s | "
                  f"{res['peak_rss_mb']:.0f} | {res['rss_before_mb']:.0f} | "
                  f"{res['setup_peak_mb']:.0f} |", flush=True)
        last = numbers["mc"][str(mc_runs[-1])]
        print(f"extrapolated (not measured): 1,000,000 runs at {last['runs_per_s']:,.0f} runs/s "
              f"= {1e6 / last['runs_per_s'] / 60:.0f} min; kept per run and method: 2 float64 + 3 "
              "bool (19 B), i.e. ~18 MiB at 1 M runs on top of one seed block's working set",
              flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(numbers, indent=1))
    bench.finish(numbers)
    return 0


if __name__ == "__main__":
    sys.exit(main())
