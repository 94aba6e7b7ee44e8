"""Training benchmark: the default config and the SEEDS 004 paper preset on one tile.

Runs ``train.py``'s `neuralmap.training.cli.main` twice in this process (default
``configs/train.yaml``, then ``configs/paper_bp.yaml`` on top of it) and prints a markdown
table: config · parameters · bytes vs the raw float32 grid · RMSE · max |error| ·
slope RMSE (all over every valid node) · train time · points/s (training points processed
per second of training loop, validation included) · total wall time (setup, fit, final
evaluation and export).

Usage::

    python benchmarks/bench_train.py              # full runs on jacksboro (several minutes)
    python benchmarks/bench_train.py --quick      # 2 epochs each, to check the pipeline
    python benchmarks/bench_train.py --tile synthetic --trainer.max_epochs 5

Unknown arguments are passed to both runs (any ``train.py`` flag).
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from neuralmap.docs.bench_run import add_out_option, start_bench

REPO = Path(__file__).resolve().parents[1]

#: Benchmarked configurations: label -> extra ``train.py`` arguments.
CONFIGS: dict[str, list[str]] = {
    "default (train.yaml)": [],
    "paper BP 3x 2-30-1 (paper_bp.yaml)": ["--config", str(REPO / "configs" / "paper_bp.yaml")],
}


def _row(label: str, metrics: dict, wall_s: float) -> str:
    return (
        f"| {label} | {metrics['num_parameters']:,} | {metrics['bytes_ratio']:.3g}× "
        f"({metrics['param_bytes'] / 1024:.0f} KiB vs {metrics['raw_grid_bytes'] / 1024:.0f} KiB) "
        f"| {metrics['rmse_m']:.3f} m | {metrics['max_abs_m']:.2f} m "
        f"| {metrics['slope_rmse']:.4f} | {metrics['train_time_s']:.1f} s "
        f"| {metrics['points_per_s']:,.0f} | {wall_s:.1f} s |"
    )


def main(argv: list[str] | None = None) -> str:
    """Runs the benchmark and returns (and prints) the markdown table."""
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--quick", action="store_true", help="2 epochs per config")
    parser.add_argument("--tile", default="jacksboro", help="sample name or DEM path")
    parser.add_argument("--runs_dir", default="runs", help="where the runs are written")
    add_out_option(parser, "bench_train")
    args, passthrough = parser.parse_known_args(argv)
    bench = start_bench(__file__, args, argv)

    from neuralmap.training.cli import main as train_main

    rows, header = [], (
        "| config | parameters | bytes vs raw float32 grid | RMSE | max error "
        "| slope RMSE (m/m) | train time | points/s | wall time |\n"
        "|---|---:|---:|---:|---:|---:|---:|---:|---:|"
    )
    for index, (label, extra) in enumerate(CONFIGS.items()):
        run_args = [
            *extra,
            "--data.path", args.tile,
            "--runs_dir", args.runs_dir,
            "--experiment", f"bench_{index}",
            "--trainer.enable_progress_bar", "false",
        ]
        if args.quick:
            run_args += ["--trainer.max_epochs", "2"]
        run_args += passthrough
        start = time.perf_counter()
        path = train_main(run_args)
        wall = time.perf_counter() - start
        assert path is not None
        metrics = json.loads((path.parent / "metrics.json").read_text())
        rows.append(_row(label, metrics, wall))
    import torch

    table = "\n".join([header, *rows])
    print(f"\ntile: {args.tile}; torch threads: {torch.get_num_threads()}"
          f"{'; --quick' if args.quick else ''}\n")
    print(table)
    bench.finish(markdown=table)
    return table


if __name__ == "__main__":
    main()
