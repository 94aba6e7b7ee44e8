"""``neuralmap-navigate``: terrain-aided fixes for a recorded flight.

::

    neuralmap-navigate flight.csv --map dem.tif                      # lat/lon or map-frame log
    neuralmap-navigate flight.csv --map jacksboro --config nav.yaml --out runs/navigate
    neuralmap-navigate KF_GINS_Navresult.nav --radar radar.csv --map dem.tif \\
        --geoid_undulation -27.5                                     # GNSS/INS result as INS

Writes ``<out>/version_<N>/``: navigation.csv, navigation.geojson (georeferenced maps),
report.md, results.json, config.yaml and, when the log carries a reference, the errors
against it (track on the hillshade with σ ellipses, error against time with ±3σ, status
timeline, TensorBoard events). The same implementation runs as the ``flight`` study
(``python evaluate.py --config configs/flight.yaml --log LOG``;
`neuralmap.flights.flight`). A refused log or bad option prints one ``error:`` line,
exits 2 and writes nothing.
"""

from __future__ import annotations

import argparse
import sys

__all__ = ["build_parser", "main"]

PROG = "neuralmap-navigate"
EXIT_BAD_INPUT = 2


class _Parser(argparse.ArgumentParser):
    """argparse with the toolkit's refusal style: one ``error:`` line, exit 2."""

    def error(self, message: str) -> None:  # type: ignore[override]
        self.exit(EXIT_BAD_INPUT, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


def _seconds(text: str) -> float:
    """A finite number of seconds > 0 (argparse type)."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number of seconds") from None
    if not (value > 0 and value < float("inf")):
        raise argparse.ArgumentTypeError(f"{text!r}: give a finite number of seconds > 0")
    return value


def build_parser() -> argparse.ArgumentParser:
    """The command-line parser."""
    p = _Parser(
        prog=PROG, description="Navigate a recorded flight (INS + radar altimeter) over a map "
        "with terrain-aided navigation; writes fixes with covariance and status.")
    p.add_argument("log", help="Flight log: map-frame CSV/NPZ (time, ins_x, ins_y, ins_h, "
                   "radar), geographic CSV/NPZ (time, lat, lon, alt, radar) or a KF-GINS "
                   "navigation result (with --radar).")
    p.add_argument("--map", required=True, help="DEM file (GeoTIFF, .asc, .hgt, .npy/.npz), "
                   "trained map (neural_map.pt) or embedded tile name (jacksboro).")
    p.add_argument("--config", default=None, help="Navigator YAML (default: the shipped "
                   "configs/navigator.yaml).")
    p.add_argument("--out", default="runs/navigate",
                   help="Output folder; results go to <out>/version_<N> (default %(default)s).")
    p.add_argument("--format", default="auto",
                   choices=("auto", "map_frame", "geographic", "kfgins"))
    p.add_argument("--radar", default=None, help="Radar log of a KF-GINS input (time, radar).")
    p.add_argument("--reference", default=None,
                   help="Reference trajectory of a KF-GINS input (KF-GINS navigation format).")
    p.add_argument("--alt_datum", default=None, choices=("dem", "ellipsoidal"),
                   help="Vertical datum of the log's altitude: dem (above the DEM's datum; "
                   "default for CSV/NPZ) or ellipsoidal (WGS-84; default for KF-GINS).")
    p.add_argument("--geoid_undulation", type=float, default=None,
                   help="Geoid undulation N, m, for ellipsoidal altitudes (uses h - N).")
    p.add_argument("--max_gap", type=_seconds, default=None, metavar="S",
                   help="Longest interval (s) the INS error is predicted across; after a "
                   "longer gap every vehicle restarts acquisition from the INS prior "
                   "(default: the navigator config's sensor.max_gap_s).")
    p.add_argument("--dem_accuracy_m", type=float, default=None,
                   help="The DEM's stated vertical accuracy (1 sigma), m.")
    p.add_argument("--no_datum_check", action="store_true",
                   help="Skip the altitude / map / clearance consistency check.")
    p.add_argument("--dtype", default="float64", choices=("float64", "float32"))
    p.add_argument("--threads", type=int, default=1, help="torch threads (default 1).")
    p.add_argument("--tensorboard", default="true", choices=("true", "false"),
                   help="Write TensorBoard events (default true).")
    p.add_argument("--progress", default="true", choices=("true", "false"),
                   help="Progress bar on a terminal, heartbeat lines otherwise (default true).")
    p.add_argument("--chunk_epochs", type=int, default=50_000, metavar="K",
                   help="Epochs replayed at a time: memory holds K x vehicles full fixes "
                   "(~330 bytes each); the results do not depend on it (default %(default)s).")
    return p


def main(argv: list[str] | None = None) -> int:
    """Console entry point.

    Returns:
        0 on success, 2 on bad input (one ``error:`` line on stderr, nothing written), 130
        when interrupted.
    """
    try:
        args = build_parser().parse_args(argv)
    except SystemExit as exc:  # --help (0) or a bad option (2, one error line printed)
        return exc.code if isinstance(exc.code, int) else 0
    import torch

    from neuralmap.exceptions import NeuralMapError
    from neuralmap.flights.flight import FLIGHT_TITLE, FlightOptions, navigate_flight, write_flight
    from neuralmap.io import check_writable_dir
    from neuralmap.outputs import StudyOutputs

    previous = torch.get_num_threads()
    try:
        config = FlightOptions(
            log=args.log, map=args.map, navigator=args.config, format=args.format,
            radar=args.radar, reference=args.reference, alt_datum=args.alt_datum,
            geoid_undulation=args.geoid_undulation, dem_accuracy_m=args.dem_accuracy_m,
            datum_check=not args.no_datum_check, dtype=args.dtype,
            progress=args.progress == "true", chunk_epochs=args.chunk_epochs,
            navigator_options={} if args.max_gap is None else {
                "sensor": {"max_gap_s": args.max_gap}})
        config.validate()
        if args.threads is not None:
            if args.threads < 1:
                raise NeuralMapError(f"--threads must be >= 1, got {args.threads}.")
            torch.set_num_threads(args.threads)
        root = check_writable_dir(args.out, option="--out")
        with StudyOutputs(root, config=config, title=FLIGHT_TITLE,
                          tensorboard=args.tensorboard == "true") as outputs:
            # every refusal happens before the replay, and the outputs' folder is made only
            # when the replay starts: a refused log writes nothing
            nav = navigate_flight(config, outputs=outputs)
            write_flight(nav, outputs)
            out_dir = outputs.finalize()
    except NeuralMapError as exc:
        print(f"{PROG}: error: {' '.join(str(exc).split())}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except OSError as exc:  # a full disk, a folder that became unwritable, ...
        where = exc.filename or args.out
        print(f"{PROG}: error: cannot write the results under --out {args.out} "
              f"({exc.strerror or exc} at {where}); free space there or choose another "
              "--out. Nothing was written.", file=sys.stderr)
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted; nothing was written (earlier outputs are unchanged).",
              file=sys.stderr)
        return 130
    finally:
        torch.set_num_threads(previous)
    print(f"results written to {out_dir}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
