"""The 15-state filter on a KF-GINS-format log: block form vs the record-by-record form.

Measures in one run and prints IMU records per second (records of the log / wall time,
whatever the run count) of

(a) :func:`neuralmap.ins.log_run.run_on_log` (block form: mechanisation of the IMU
    increments and covariance propagation of a whole stretch between GNSS epochs at once,
    compiled loops where numba is installed, :mod:`neuralmap.ins.increment_kernels`);
(b) the record-by-record form it replaced (one torch operation set per IMU record: the
    implementation of commit ``ecdd133``, loaded from git into a temporary module), on
    the first part of the same log (it is slow);

for one run (the log as recorded) and for N runs (Monte Carlo with noise draws), and the
largest difference of run 0 between the two on the common part. Target: (a)/(b) ≥ 10 for
one run and for N = 20. The log is simulated (short drive at 200 Hz, 1 Hz GNSS position
and velocity, tactical MEMS IMU) and written/read through the KF-GINS text formats' data
classes, as ``neuralmap-gins`` runs it.

Usage:
    python benchmarks/bench_gins_log.py            # 60 s log at 200 Hz (12 000 records)
    python benchmarks/bench_gins_log.py --quick    # smoke test
"""

from __future__ import annotations

import argparse
import platform
import sys
import time
from pathlib import Path

import numpy as np
import torch

REPO_ROOT = Path(__file__).resolve().parents[1]
if str(REPO_ROOT) not in sys.path:  # run as a script from anywhere
    sys.path.insert(0, str(REPO_ROOT))

from benchmarks.previous_code import load_previous  # noqa: E402
from neuralmap.ins.gnss import simulate_gnss  # noqa: E402
from neuralmap.ins.imu_model import ImuErrorProcess, imu_grade  # noqa: E402
from neuralmap.ins.kernels import HAVE_NUMBA  # noqa: E402
from neuralmap.ins.kfgins import simulated_logs  # noqa: E402
from neuralmap.ins.log_run import run_on_log  # noqa: E402
from neuralmap.ins.loosely_coupled import LooselyCoupledConfig  # noqa: E402
from neuralmap.ins.trajectory import short_drive  # noqa: E402

LEVER_ARM = (0.5, 0.2, -1.2)
PREVIOUS = "ecdd133"


def previous_driver() -> object:
    """``run_on_log`` of the record-by-record implementation (commit ecdd133), or None."""
    module = load_previous(PREVIOUS, "neuralmap/ins/log_run.py", "log_run_per_record")
    return None if module is None else module.run_on_log


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--quick", action="store_true", help="short smoke test")
    parser.add_argument("--duration", type=float, default=60.0, help="log length (s)")
    parser.add_argument("--old_duration", type=float, default=4.0,
                        help="part of the log the record-by-record form runs (s)")
    parser.add_argument("--n_runs", type=int, default=20)
    args = parser.parse_args(argv)
    if args.quick:
        args.duration, args.old_duration, args.n_runs = 6.0, 1.0, 3
    torch.set_num_threads(1)
    traj = short_drive(duration=args.duration, dt=0.005)
    gen = torch.Generator().manual_seed(3)
    gnss = simulate_gnss(traj, n_runs=1, lever_arm=list(LEVER_ARM), generator=gen)
    imu = ImuErrorProcess("tactical_mems", n_runs=1, dt=traj.dt, generator=gen,
                          scale_factor=False)
    imu_log, gnss_log, ref = simulated_logs(traj, gnss, imu=imu)
    lat, lon, h = ref.position[0]
    kwargs = {"grade": imu_grade("tactical_mems"),
              "initial_position": (np.radians(lat), np.radians(lon), h),
              "initial_velocity": tuple(ref.velocity[0]),
              "initial_euler": tuple(np.radians(ref.euler[0])), "lever_arm": LEVER_ARM,
              "filter_config": LooselyCoupledConfig()}
    t0 = float(imu_log.time[0])
    old_end = t0 + args.old_duration
    print(f"# {platform.processor() or platform.machine()}, torch {torch.__version__}, "
          f"1 thread, numba {'on' if HAVE_NUMBA else 'off (torch fallback)'}")
    print(f"# log: {imu_log.n_samples} IMU records at 200 Hz, {gnss_log.n_epochs} GNSS epochs")
    run_on_log(imu_log, gnss_log, end=t0 + 1.0, n_runs=2, **kwargs)  # compile / load
    previous = previous_driver()
    ratios = []
    for n in (1, args.n_runs):
        start = time.perf_counter()
        new = run_on_log(imu_log, gnss_log, n_runs=n, **kwargs)
        wall_new = time.perf_counter() - start
        rate_new = imu_log.n_samples / wall_new
        line = f"N = {n:3d}: block {rate_new:10.0f} records/s ({wall_new:.2f} s)"
        if previous is not None:
            start = time.perf_counter()
            old = previous(imu_log, gnss_log, end=old_end, n_runs=n, **kwargs)
            wall_old = time.perf_counter() - start
            k = old.states.shape[1]
            rate_old = k / wall_old
            diff = float((new.states[0, :k] - old.states[0]).abs().max())
            ratios.append(rate_new / rate_old)
            line += (f" | record-by-record {rate_old:8.0f} records/s ({k} records, "
                     f"{wall_old:.2f} s) | ratio {rate_new / rate_old:6.1f}x | "
                     f"run 0 max |Δ state| {diff:.1e}")
        print(line)
    if previous is None:
        print(f"# the record-by-record implementation (git commit {PREVIOUS}) is not "
              "available here")
    else:
        print(f"# target ratio >= 10: {'met' if min(ratios) >= 10 else 'NOT met'} "
              f"(min {min(ratios):.1f}x)")


if __name__ == "__main__":
    main()
