"""``neuralmap-gins``: the 15-state GNSS/INS filter on a log in the KF-GINS formats.

::

    neuralmap-gins kf-gins.yaml                       # as KF-GINS: one run, results at IMU rate
    neuralmap-gins kf-gins.yaml --truthpath truth.nav # + errors against a reference
    neuralmap-gins kf-gins.yaml --n_runs 50 --output_every 200   # + 49 runs with noise draws

The config is KF-GINS's own ``kf-gins.yaml`` (`neuralmap.ins.kfgins.read_config`).
Written to ``outputpath``: ``KF_GINS_Navresult.nav``, ``KF_GINS_IMU_ERR.txt`` and
``KF_GINS_STD.txt`` of run 0 (KF-GINS's names and columns), and with a reference
``comparison.json`` (position, velocity and attitude errors of every run). The output
folder is checked before any work; the files are written all or nothing (hidden temporary
names, renamed together at the end), so a failed rerun (a full disk, Ctrl-C) leaves the
previous run's files as they were, and a run without a reference removes an earlier
``comparison.json``, which would not be about its results. Bad input, a bad option value
and a full disk print one ``error:`` line and exit 2; Ctrl-C prints one line and exits 130.

A GNSS epoch updates at its own time (the IMU interval is split there, as KF-GINS does). A
logging gap in the IMU file is refused unless ``--max_gap S`` accepts it (`MAX_GAP_HELP`):
gaps up to S seconds are propagated across as one interval of their true length and
counted in the printed summary (``counts`` of the returned summary); a longer one is
refused with its time and line. torch runs on one thread by default (``--threads``): on a
busy machine a second thread made the run twice as slow.
"""

from __future__ import annotations

import math
import sys
from pathlib import Path

from jsonargparse import ArgumentParser

from neuralmap.exceptions import NeuralMapError

__all__ = ["main"]

PROG = "neuralmap-gins"
EXIT_BAD_INPUT = 2
NAV_FILE = "KF_GINS_Navresult.nav"
IMU_ERROR_FILE = "KF_GINS_IMU_ERR.txt"
STD_FILE = "KF_GINS_STD.txt"
COMPARISON_FILE = "comparison.json"


#: ``--max_gap`` as ``--help`` and the docs state it.
MAX_GAP_HELP = (
    "Longest IMU logging gap (s, a finite number > 0) to propagate across as one interval "
    "of its true length; a longer gap is refused with its time and line. Default: no gap "
    "(an interval > 1.5 nominal ones) accepted. A KF-GINS IMU record holds the increments "
    "of one nominal interval, so missing records mean missing increments: the rate of the "
    "record after a gap is held over the gap. A record whose velocity increment shows it "
    "accumulated the whole gap (|dv| > g*sqrt(dt*gap)) is used as it is. Gaps are counted "
    "in the printed summary."
)

#: What each option accepts, for the one-line refusal of a value the parser rejects.
EXPECTED = {
    "max_gap": "a finite number of seconds > 0 (the longest IMU logging gap to propagate "
               "across), e.g. --max_gap 1.0; leave it out to refuse every gap",
    "n_runs": "an integer >= 1",
    "output_every": "an integer >= 1",
    "propagate_every": "an integer >= 1",
    "r_scale": "a finite number > 0",
    "use_velocity": "true, false or null",
    "seed": "an integer",
    "threads": "an integer >= 1",
}


def _parser() -> ArgumentParser:
    parser = ArgumentParser(prog=PROG, description="Run the 15-state loosely coupled GNSS/INS "
                            "filter on a KF-GINS-format log.",
                            exit_on_error=False)  # parse errors: one line (main)
    parser.add_argument("config", type=str, help="KF-GINS configuration YAML (kf-gins.yaml).")
    parser.add_argument("--truthpath", type=str | None, default=None,
                        help="Reference trajectory (KF-GINS navigation format); overrides the "
                             "config's truthpath.")
    parser.add_argument("--outputpath", type=str | None, default=None,
                        help="Output folder; overrides the config's outputpath.")
    parser.add_argument("--n_runs", type=int, default=1,
                        help="Runs: 1 = the log; more add runs with noise draws.")
    parser.add_argument("--output_every", type=int, default=1,
                        help="Record every this many IMU epochs.")
    parser.add_argument("--propagate_every", type=int, default=10,
                        help="IMU samples per covariance propagation.")
    parser.add_argument("--r_scale", type=float, default=1.0, help="Factor on the GNSS σ.")
    parser.add_argument("--use_velocity", type=bool | None, default=None,
                        help="Update with the GNSS velocity (13-column files); default: when "
                             "present.")
    parser.add_argument("--seed", type=int, default=0, help="Seed of the noise draws.")
    parser.add_argument("--max_gap", type=float | None, default=None, help=MAX_GAP_HELP)
    parser.add_argument("--threads", type=int, default=1,
                        help="torch CPU threads (1: measured fastest, twice as fast as 2 on a "
                             "shared 2-core machine).")
    return parser


def run(args: object) -> dict[str, object]:
    """Reads, filters, writes; returns the summary (paths and, with a reference, errors)."""
    from neuralmap.ins.kfgins import (
        imu_error_text,
        nav_text,
        read_config,
        read_gnss,
        read_imu,
        read_nav,
        std_text,
    )
    from neuralmap.ins.log_run import compare_with_reference, run_on_log
    from neuralmap.ins.loosely_coupled import LooselyCoupledConfig
    from neuralmap.io import atomic_files, check_writable_dir
    from neuralmap.threads import set_threads

    if args.max_gap is not None and not (math.isfinite(args.max_gap) and args.max_gap > 0):
        raise NeuralMapError(f"--max_gap: {args.max_gap!r} is not valid; expected "
                             f"{EXPECTED['max_gap']}.")
    set_threads(args.threads)
    cfg = read_config(args.config)
    out_dir = Path(args.outputpath) if args.outputpath else cfg.outputpath
    check_writable_dir(out_dir, option="outputpath")
    truth = Path(args.truthpath) if args.truthpath else cfg.reference
    imu = read_imu(cfg.imupath, rate_hz=cfg.imudatarate, columns=cfg.imudatalen,
                   max_gap=args.max_gap)
    gnss = read_gnss(cfg.gnsspath)
    reference = read_nav(truth) if truth is not None else None
    filter_config = LooselyCoupledConfig(
        propagate_every=args.propagate_every, r_scale=args.r_scale,
        init_pos_sigma=cfg.init_pos_sigma, init_vel_sigma=cfg.init_vel_sigma,
        init_att_sigma_deg=cfg.init_att_sigma_deg)
    print(f"{PROG}: {imu.n_samples} IMU records ({1.0 / imu.dt:.4g} Hz, {imu.time[0]:.3f}–"
          f"{imu.time[-1]:.3f} s), {gnss.n_epochs} GNSS epochs"
          f"{' with velocity' if gnss.velocity is not None else ''}, {args.n_runs} run(s)",
          flush=True)
    solution = run_on_log(
        imu, gnss, grade=cfg.imu_grade(), initial_position=cfg.init_position,
        initial_velocity=cfg.init_velocity, initial_euler=cfg.init_euler,
        lever_arm=cfg.lever_arm, filter_config=filter_config,
        initial_gyro_bias=cfg.init_gyro_bias, initial_accel_bias=cfg.init_accel_bias,
        start=cfg.starttime, end=cfg.endtime, n_runs=args.n_runs,
        output_every=args.output_every, seed=args.seed, use_velocity=args.use_velocity)
    c = solution.counts
    held, accumulated = c["imu_gaps_rate_held"], c["imu_gaps"] - c["imu_gaps_rate_held"]
    gaps = "" if not c["imu_gaps"] else (
        f" (longest {c['imu_longest_gap_s']:.3f} s; {held} with the rate of the record after "
        "the gap held over it" + (f", {accumulated} with the increments the record after it "
                                  "accumulated over the gap" if accumulated else "") + ")")
    print(f"{PROG}: {c['updates']} GNSS updates ({c['gnss_between_records']} between two IMU "
          f"records, at the GNSS time), {c['gnss_outside']} epochs outside the processed "
          f"interval; {c['imu_gaps']} IMU logging gap(s) propagated across{gaps}", flush=True)
    time = solution.time.numpy()
    comparison = None
    if reference is not None:
        comparison = compare_with_reference(solution, reference)
        comparison["reference"] = str(truth)
    with atomic_files(option="outputpath") as files:  # all files or none
        paths = {
            "navigation": files.write_text(out_dir / NAV_FILE, nav_text(solution.nav_log(0))),
            "imu_error": files.write_text(out_dir / IMU_ERROR_FILE, imu_error_text(
                time, solution.gyro_bias[0].numpy(), solution.accel_bias[0].numpy())),
            "std": files.write_text(out_dir / STD_FILE, std_text(time, solution.std[0].numpy())),
        }
        if comparison is not None:
            paths["comparison"] = files.write_json(out_dir / COMPARISON_FILE, comparison)
        else:  # an earlier run's comparison is not about these results
            files.remove(out_dir / COMPARISON_FILE)
    summary: dict[str, object] = {"files": {k: str(v) for k, v in paths.items()},
                                  "counts": solution.counts}
    if comparison is not None:
        summary["comparison"] = comparison
        e = comparison["all_runs"]
        print(f"{PROG}: against {truth}: RMSE horizontal {e['rmse_horizontal_m']:.3f} m, "
              f"vertical {e['rmse_vertical_m']:.3f} m, velocity {e['rmse_velocity_mps']:.3f} m/s, "
              f"roll/pitch/heading {e['rmse_roll_deg']:.3f}/{e['rmse_pitch_deg']:.3f}/"
              f"{e['rmse_heading_deg']:.3f} deg", flush=True)
    print(f"{PROG}: results written to {out_dir}", flush=True)
    return summary


def main(argv: list[str] | None = None) -> None:
    """Console entry point: exit code 2 with one ``error:`` line on bad input (an option
    value the parser rejects included) or a full disk, 130 with one line on Ctrl-C."""
    from jsonargparse import ArgumentError

    from neuralmap.entry import EXIT_INTERRUPTED, interrupted_line, parse_error_message

    try:
        try:
            args = _parser().parse_args(argv)
        except ArgumentError as exc:
            raise NeuralMapError(parse_error_message(exc, PROG, EXPECTED)) from None
        run(args)
    except NeuralMapError as exc:
        sys.stdout.flush()
        print(f"{PROG}: error: {' '.join(str(exc).split())}", file=sys.stderr, flush=True)
        raise SystemExit(EXIT_BAD_INPUT) from None
    except PermissionError as exc:
        sys.stdout.flush()
        print(f"{PROG}: error: cannot write the results ({exc}); pick a writable outputpath.",
              file=sys.stderr, flush=True)
        raise SystemExit(EXIT_BAD_INPUT) from None
    except KeyboardInterrupt:
        sys.stdout.flush()
        print(interrupted_line(PROG), file=sys.stderr, flush=True)
        raise SystemExit(EXIT_INTERRUPTED) from None


if __name__ == "__main__":  # pragma: no cover
    main()
