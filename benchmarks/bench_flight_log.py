"""A long flight log through ``neuralmap-navigate``: wall time, epochs/s and peak memory.

Synthesizes an N-row map-frame log (``time, ins_x, ins_y, ins_h, radar, ref_x, ref_y,
ref_h``; default N = 1 000 000, one epoch per second: 11.6 days of flight) over the embedded
``jacksboro`` tile and navigates it with ``neuralmap-navigate`` in a child process (the
product path: read, datum check, chunked replay, navigation.csv, navigation.geojson, the
report with its errors against the reference), one torch thread. Printed:

* wall time of the child, epochs/s over the whole command and over the replay alone (the
  ``replay_seconds`` of its results.json), the replay's share of the wall time;
* its peak resident memory (``ru_maxrss`` of the child from ``wait4``, kernel-measured) against the
  target: **peak < 500 MB** for N = 1 000 000 (met / missed), and the resident memory sampled
  every second (at 10 %, 50 %, 90 % of the run, and its largest sample), which shows
  whether memory grows with the flight or stays bounded;
* beside it, in the same run, the bare `Navigator.replay` of the log's first epochs in this
  process (``--bare_epochs``, the Navigator's own speed, what bench_navigator measures) and,
  for N ≤ 100 000 (or with ``--unchunked``), the same command replaying the whole log as
  one chunk (``--chunk_epochs N``: the whole `FixTrack` in memory at once).

The flight: a racetrack loiter (two 12 km straights, 4 km turn radius) at 50 m/s and
1500 m ± 50 m altitude, so it stays on the 30 × 32 km tile however long it is; the truth is
the reference. The INS error is bounded and smooth like a real one: a Schuler oscillation
(84.4 min, 60 m per axis) plus a first-order Gauss–Markov drift (τ = 20 000 s, σ = 60 m:
about 0.6 m per second, inside the navigator's 1 m process noise); the INS altitude carries
a Gauss–Markov bias (τ = 3000 s, σ = 10 m). The radar clearance is the INS-free truth
(1500 m ± 50 m − the bicubic map height) plus 10 m white noise (the altimeter σ of the
shipped navigator config); 0.1 % of the samples are missing.

Usage:
    OMP_NUM_THREADS=1 python benchmarks/bench_flight_log.py                 # 1e6 rows, ~1 h
    OMP_NUM_THREADS=1 python benchmarks/bench_flight_log.py --rows 100000
    OMP_NUM_THREADS=1 python benchmarks/bench_flight_log.py --quick         # 3000 rows
"""

from __future__ import annotations

import argparse
import json
import math
import os
import shutil
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import numpy as np

from neuralmap.docs.bench_run import add_out_option, start_bench

TARGET_MB = 500.0
TARGET_ROWS = 1_000_000
TILE = "jacksboro"
SPEED = 50.0          # m/s
STRAIGHT = 12_000.0   # m
RADIUS = 4_000.0      # m
ALTITUDE = 1_500.0    # m
BLOCK = 100_000       # rows synthesized at a time


def racetrack(s: np.ndarray, centre: tuple[float, float]) -> np.ndarray:
    """``(M, 2)`` positions at arc length ``s`` (m) along the racetrack about ``centre``:
    east along the south straight, the east turn, west along the north straight, the west
    turn."""
    cx, cy = centre
    half, r = STRAIGHT / 2.0, RADIUS
    lap = 2.0 * STRAIGHT + 2.0 * math.pi * r
    u = np.mod(s, lap)
    xy = np.empty((u.size, 2))
    a = u < STRAIGHT                                       # south straight, eastwards
    xy[a] = np.stack([cx - half + u[a], np.full(a.sum(), cy - r)], -1)
    b = (u >= STRAIGHT) & (u < STRAIGHT + math.pi * r)     # east turn
    ang = -math.pi / 2 + (u[b] - STRAIGHT) / r
    xy[b] = np.stack([cx + half + r * np.cos(ang), cy + r * np.sin(ang)], -1)
    c = (u >= STRAIGHT + math.pi * r) & (u < 2 * STRAIGHT + math.pi * r)  # north, westwards
    xy[c] = np.stack([cx + half - (u[c] - STRAIGHT - math.pi * r), np.full(c.sum(), cy + r)],
                     -1)
    d = u >= 2 * STRAIGHT + math.pi * r                    # west turn
    ang = math.pi / 2 + (u[d] - 2 * STRAIGHT - math.pi * r) / r
    xy[d] = np.stack([cx - half + r * np.cos(ang), cy + r * np.sin(ang)], -1)
    return xy


class GaussMarkov:
    """First-order Gauss–Markov sequences (``x+ = a x + w``, stationary σ), continued from
    block to block."""

    def __init__(self, rng: np.random.Generator, shape: tuple[int, ...], tau_s: float,
                 sigma: float, dt: float = 1.0) -> None:
        from scipy.signal import lfilter

        self.lfilter, self.rng = lfilter, rng
        self.a = math.exp(-dt / tau_s)
        self.q = sigma * math.sqrt(1.0 - self.a ** 2)
        self.state = rng.normal(0.0, sigma, shape)

    def block(self, m: int) -> np.ndarray:
        """The next ``m`` values, ``(*shape, m)``."""
        w = self.rng.normal(0.0, self.q, (*self.state.shape, m))
        w[..., 0] += self.a * self.state
        out = self.lfilter([1.0], [1.0, -self.a], w, axis=-1)
        self.state = out[..., -1]
        return out


def write_log(path: Path, rows: int, seed: int = 7) -> dict[str, float]:
    """Writes the racetrack log (module docstring) as CSV; returns what it holds."""
    import torch

    from neuralmap.nav.map_source import resolve_map

    source = resolve_map(TILE)
    xmin, xmax, ymin, ymax = source.extent
    centre = (0.5 * (xmin + xmax), 0.5 * (ymin + ymax))
    rng = np.random.default_rng(seed)
    drift = GaussMarkov(rng, (2,), tau_s=20_000.0, sigma=60.0)
    bias_h = GaussMarkov(rng, (), tau_s=3_000.0, sigma=10.0)
    phase = rng.uniform(0.0, 2.0 * math.pi, 2)
    schuler = 2.0 * math.pi / 5064.0
    clearances = []
    with path.open("w", encoding="utf-8", newline="") as handle:
        handle.write("time,ins_x,ins_y,ins_h,radar,ref_x,ref_y,ref_h\n")
        for a in range(0, rows, BLOCK):
            m = min(BLOCK, rows - a)
            t = np.arange(a, a + m, dtype=np.float64)
            truth = racetrack(SPEED * t, centre)
            h_true = ALTITUDE + 50.0 * np.sin(2.0 * math.pi * t / 600.0)
            with torch.no_grad():
                ground = source.terrain(torch.as_tensor(truth)).double().numpy()
            error = (60.0 * np.sin(schuler * t[:, None] + phase) + drift.block(m).T)
            ins = truth + error
            ins_h = h_true + bias_h.block(m)
            radar = h_true - ground + rng.normal(0.0, 10.0, m)
            radar[rng.random(m) < 1e-3] = np.nan
            clearances.append(np.nanmean(radar))
            cols = np.column_stack([t, ins, ins_h, radar, truth, h_true])
            text = "\n".join(",".join("" if v != v else repr(float(v)) for v in row)
                             for row in cols.tolist())
            handle.write(text + "\n")
    return {"rows": rows, "hours": rows / 3600.0, "laps": SPEED * rows / (
        2.0 * STRAIGHT + 2.0 * math.pi * RADIUS), "mean_clearance_m": float(np.mean(clearances)),
        "log_mb": path.stat().st_size / 1e6}


def run_navigate(log: Path, out: Path, chunk: int | None, *, echo: bool) -> dict:
    """``neuralmap-navigate`` on ``log`` in a child process: wall time, ``ru_maxrss``, the
    resident memory sampled every second, and the run's results.json."""
    cmd = [sys.executable, "-m", "neuralmap.flights.cli", str(log), "--map", TILE, "--out",
           str(out), "--threads", "1", "--progress", "true"]
    if chunk is not None:
        cmd += ["--chunk_epochs", str(chunk)]
    env = {**os.environ, "OMP_NUM_THREADS": "1", "MKL_NUM_THREADS": "1"}
    start = time.perf_counter()
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
                            env=env)
    samples: list[tuple[float, float]] = []

    def sample() -> None:
        status = Path(f"/proc/{proc.pid}/status")
        while proc.poll() is None:
            try:
                for line in status.read_text().splitlines():
                    if line.startswith("VmRSS:"):
                        samples.append((time.perf_counter() - start,
                                        int(line.split()[1]) / 1024.0))
            except OSError:
                break
            time.sleep(1.0)

    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    lines = []
    for line in proc.stdout:
        lines.append(line.rstrip("\n"))
        if echo and (line.startswith(("navigate:", "flight:", "results written"))):
            print(f"  | {line.rstrip()}", flush=True)
    _, status, usage = os.wait4(proc.pid, 0)  # this child's own rusage (kB on Linux)
    wall = time.perf_counter() - start
    proc.returncode = code = os.waitstatus_to_exitcode(status)
    sampler.join(timeout=5.0)
    maxrss_mb = usage.ru_maxrss / 1024.0
    if code != 0:
        print("\n".join(lines[-30:]))
        raise SystemExit(f"neuralmap-navigate exited with {code}")
    folder = Path(lines[-1].split("results written to ", 1)[1].strip())
    results = json.loads((folder / "results.json").read_text())
    sizes = {p.name: p.stat().st_size / 1e6 for p in folder.iterdir() if p.is_file()}
    return {"wall_s": wall, "maxrss_mb": maxrss_mb, "samples": samples, "results": results, "folder": folder, "sizes_mb": sizes}


def rss_profile(samples: list[tuple[float, float]]) -> dict[str, float | None]:
    """Resident memory (MB) sampled at 10 %, 50 %, 90 % of the run, and the largest."""
    if not samples:
        return {"rss_10": None, "rss_50": None, "rss_90": None, "rss_max_sampled": None}
    values = [v for _, v in samples]

    def at(q: float) -> float:
        return values[min(len(values) - 1, int(q * len(values)))]

    return {"rss_10": at(0.1), "rss_50": at(0.5), "rss_90": at(0.9),
            "rss_max_sampled": max(values)}


def bare_replay(log: Path, epochs: int) -> float:
    """Epochs/s of `Navigator.replay` over the log's first ``epochs`` epochs, in this
    process, one thread (the Navigator's own speed on this flight)."""
    import torch

    from neuralmap.nav.map_source import resolve_map
    from neuralmap.nav.navigator import Navigator

    torch.set_num_threads(1)
    data = np.genfromtxt(log, delimiter=",", skip_header=1, max_rows=epochs,
                         usecols=range(5))  # an empty radar field reads as NaN
    source = resolve_map(TILE)
    nav = Navigator(source.terrain, None, n_vehicles=1, map_frame=source.frame,
                    tile=source.tile)
    t = torch.as_tensor(data[:, 0])
    xy = torch.as_tensor(data[None, :, 1:3])
    h, radar = torch.as_tensor(data[None, :, 3]), torch.as_tensor(data[None, :, 4])
    nav.replay(t[:50], xy[:, :50], h[:, :50], radar[:, :50])  # warm-up
    start = time.perf_counter()
    nav.replay(t, xy, h, radar)
    return data.shape[0] / (time.perf_counter() - start)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--rows", type=int, default=TARGET_ROWS, help="epochs of the log")
    parser.add_argument("--quick", action="store_true", help="3000 rows (smoke test)")
    parser.add_argument("--chunk_epochs", type=int, default=None,
                        help="neuralmap-navigate --chunk_epochs (default: its own)")
    parser.add_argument("--bare_epochs", type=int, default=3000,
                        help="epochs of the in-process bare Navigator.replay")
    parser.add_argument("--unchunked", choices=("auto", "yes", "no"), default="auto",
                        help="also run the whole log as one chunk (auto: rows <= 100000)")
    parser.add_argument("--workdir", default=None,
                        help="where the log and the navigation runs go (default: a "
                        "temporary folder, removed at the end)")
    parser.add_argument("--keep", action="store_true", help="keep the log and the runs")
    parser.add_argument("--seed", type=int, default=7)
    add_out_option(parser, "bench_flight_log")
    args = parser.parse_args()
    bench = start_bench(__file__, args)
    if args.quick:
        args.rows, args.bare_epochs = 3000, min(args.bare_epochs, 500)
    unchunked = args.unchunked == "yes" or (args.unchunked == "auto" and args.rows <= 100_000)
    work = Path(args.workdir or tempfile.mkdtemp(prefix="bench_flight_log_"))
    work.mkdir(parents=True, exist_ok=True)
    try:
        log = work / f"racetrack_{args.rows}.csv"
        start = time.perf_counter()
        info = write_log(log, args.rows, seed=args.seed)
        print(f"log: {info['rows']} rows ({info['hours']:.1f} h at 1 Hz, {info['laps']:.0f} "
              f"racetrack laps, mean clearance {info['mean_clearance_m']:.0f} m), "
              f"{info['log_mb']:.1f} MB, written in {time.perf_counter() - start:.1f} s",
              flush=True)
        bare = bare_replay(log, min(args.bare_epochs, args.rows))
        print(f"bare Navigator.replay, first {min(args.bare_epochs, args.rows)} epochs, "
              f"in-process: {bare:.1f} epochs/s ({1e3 / bare:.2f} ms/epoch)", flush=True)
        runs = {"chunked": run_navigate(log, work / "chunked", args.chunk_epochs, echo=True)}
        if unchunked:
            runs["one chunk"] = run_navigate(log, work / "one_chunk", args.rows, echo=True)
        rows = []
        for name, r in runs.items():
            res = r["results"]
            chunk = res["config"]["chunk_epochs"]
            prof = rss_profile(r["samples"])
            rows.append([name, chunk, f"{r['wall_s']:.1f}", f"{args.rows / r['wall_s']:.1f}",
                         f"{res['replay_seconds']:.1f}", f"{res['epochs_per_second']:.1f}",
                         f"{res['epochs_per_second'] / bare:.2f}", f"{r['maxrss_mb']:.0f}",
                         " / ".join("n/a" if prof[k] is None else f"{prof[k]:.0f}"
                                    for k in ("rss_10", "rss_50", "rss_90"))])
            r["profile"] = prof
        print()
        print("| run | chunk_epochs | wall [s] | epochs/s (wall) | replay [s] | epochs/s "
              "(replay) | replay / bare Navigator | peak RSS [MB] | RSS at 10/50/90 % [MB] |")
        print("|---|---|---|---|---|---|---|---|---|")
        for row in rows:
            print("| " + " | ".join(str(v) for v in row) + " |")
        chunked = runs["chunked"]
        met = chunked["maxrss_mb"] < TARGET_MB
        scope = ("" if args.rows >= TARGET_ROWS else
                 f" (the target is stated for {TARGET_ROWS} rows; this run has {args.rows})")
        print(f"\ntarget: peak RSS < {TARGET_MB:.0f} MB: {'met' if met else 'missed'} "
              f"({chunked['maxrss_mb']:.0f} MB){scope}")
        sizes = chunked["sizes_mb"]
        print("outputs: " + ", ".join(f"{k} {v:.1f} MB" for k, v in sorted(sizes.items())
                                      if v >= 0.1))
        res = chunked["results"]
        print(f"navigated: rmse_horizontal {res['errors']['rmse_horizontal_m']:.1f} m "
              f"(INS {res['errors']['ins_rmse_horizontal_m']:.1f} m), tracking "
              f"{res['status_fraction']['tracking']:.3f} of the epochs, lost "
              f"{res['counts']['lost']}")
        summary = {name: {"wall_s": r["wall_s"], "maxrss_mb": r["maxrss_mb"],
                          "replay_seconds": r["results"]["replay_seconds"],
                          "epochs_per_second_replay": r["results"]["epochs_per_second"],
                          "epochs_per_second_wall": args.rows / r["wall_s"],
                          "chunk_epochs": r["results"]["config"]["chunk_epochs"],
                          **r["profile"], "sizes_mb": r["sizes_mb"]}
                   for name, r in runs.items()}
        bench.finish({"rows": args.rows, "log": info, "bare_epochs_per_second": bare,
                      "target_mb": TARGET_MB, "target_met": met, "runs": summary})
    finally:
        if not args.keep and args.workdir is None:
            shutil.rmtree(work, ignore_errors=True)


if __name__ == "__main__":
    main()
