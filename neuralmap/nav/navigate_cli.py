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
`neuralmap.studies.flight`). A refused log or bad option prints one ``error:`` line,
exits 2 and writes nothing.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

__all__ = ["build_parser", "main"]

PROG = "neuralmap-navigate"
EXIT_BAD_INPUT = 2


class _Parser(argparse.ArgumentParser):
    """argparse with the toolkit's refusal style: one ``error:`` line, exit 2."""

    def error(self, message: str) -> None:  # type: ignore[override]
        self.exit(EXIT_BAD_INPUT, f"{self.prog}: error: {message} (see {self.prog} --help)\n")


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
    from neuralmap.io import check_writable_dir
    from neuralmap.studies.flight import FlightStudyConfig, navigate_flight, write_flight
    from neuralmap.studies.outputs import StudyOutputs
    from neuralmap.studies.registry import STUDIES

    previous = torch.get_num_threads()
    try:
        config = FlightStudyConfig(
            experiment="navigate", runs_dir=str(Path(args.out).parent), log=args.log,
            map=args.map, navigator=args.config, format=args.format, radar=args.radar,
            reference=args.reference, alt_datum=args.alt_datum,
            geoid_undulation=args.geoid_undulation, dem_accuracy_m=args.dem_accuracy_m,
            datum_check=not args.no_datum_check, dtype=args.dtype, threads=args.threads,
            tensorboard=args.tensorboard == "true", progress=args.progress == "true")
        config.validate()
        if config.threads is not None:
            torch.set_num_threads(config.threads)
        root = check_writable_dir(args.out, option="--out")
        nav = navigate_flight(config)  # every refusal happens here, before any write
        with StudyOutputs(root, config=config, title=STUDIES["flight"].description,
                          tensorboard=config.tensorboard) as outputs:
            write_flight(nav, outputs)
            out_dir = outputs.finalize()
    except NeuralMapError as exc:
        print(f"{PROG}: error: {' '.join(str(exc).split())}", file=sys.stderr)
        return EXIT_BAD_INPUT
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted; nothing was written.", file=sys.stderr)
        return 130
    finally:
        torch.set_num_threads(previous)
    print(f"results written to {out_dir}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
