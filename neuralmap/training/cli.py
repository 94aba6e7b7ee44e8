"""``train.py``: every trainer of the toolkit behind one command and one option style.

``python train.py [map|noise|region] [--config FILE] [--data.* --model.* --trainer.* ...]``:

- ``map`` (the default when the first word is an option): fit a neural map to a DEM tile,
  or to a mosaic of tiles (``--data.path "srtm/*.hgt"`` or a list), with LightningCLI;
- ``noise``: learn the TAN filter's Q and R from flights (`neuralmap.training.noise_cli`,
  ``python train.py noise --config configs/learn_noise.yaml``);
- ``region``: fit a region-scale sharded map on several processes
  (`neuralmap.training.region_cli`, ``python train.py region --config
  configs/train_region.yaml``);
- ``latent``: fit a latent-grid map (`neuralmap.training.latent_cli`,
  ``python train.py latent --config configs/latent_map.yaml``).

Map fit: ``python train.py`` fits the jacksboro sample with ``configs/train.yaml``;
``python train.py --config configs/paper_bp.yaml`` uses the SEEDS 004 preset;
``--data.path my_tile.hgt``, ``--trainer.max_epochs 5``,
``--trainer.strategy ddp --trainer.devices 2 --trainer.accelerator cpu`` and every other
Lightning trainer flag work as usual; ``--ckpt_path`` resumes. Outputs go to
``runs/<experiment>/version_N/`` (experiment = tile name unless ``--experiment``): TensorBoard
events, ``config.yaml``, checkpoints, PNG figures, ``metrics.json`` and ``neural_map.pt``,
whose path is the last line printed on stdout. Every run gets its own ``version_N``, also
with ``--trainer.logger false`` (then reserved here).

Exit codes: 0 with the map path as the last stdout line; 2 for bad input (a one-line
``error:`` message on stderr, checked before training where possible: ``max_epochs 0``,
an ``--experiment`` leaving ``--runs_dir``, a ``--runs_dir`` that is a file, an unusable
or exhausted ``--ckpt_path``, an accelerator that is not there); 1 when a run ends without
exporting a map (including Ctrl-C, which prints the command that resumes from
``last.ckpt``). A failed run leaves no empty ``version_N`` behind.
"""

from __future__ import annotations

import os
import sys
import warnings
from argparse import ArgumentError
from pathlib import Path
from typing import Any

from jsonargparse import ArgumentParser

from neuralmap.exceptions import NeuralMapError
from neuralmap.training.callbacks import DashboardLayout, EpochLines, FitReport, ResumeHint
from neuralmap.training.callbacks.heldout_checkpoint import HeldOutCheckpoint
from neuralmap.training.cli_base import (
    EXIT_BAD_INPUT,
    EXIT_NO_MAP,
    NeuralMapCLI,
    remove_orphan_run_dir,
)
from neuralmap.training.datamodule import DemDataModule
from neuralmap.training.latent_cli import main_latent
from neuralmap.training.module import TerrainFitModule
from neuralmap.training.noise_cli import main_noise
from neuralmap.training.quiet import quiet_lightning
from neuralmap.training.region_cli import main_region

__all__ = ["MODES", "config_learn", "config_mode", "default_config_path", "main", "main_map",
           "mode_parser"]

#: The modes of ``train.py``: its first word (default ``map``).
MODES = ("map", "noise", "region", "latent")

def default_config_path() -> Path | None:
    """The shipped ``configs/train.yaml`` (package data), else one in the cwd."""
    from neuralmap.resources import config_file

    candidates = [config_file("train.yaml"), Path.cwd() / "configs" / "train.yaml"]
    for candidate in candidates:
        if candidate.is_file():
            return candidate
    return None


def _trainer_callbacks() -> tuple[list[Any], FitReport]:
    report = FitReport()
    callbacks = [
        HeldOutCheckpoint(  # best-*.ckpt ranks held-out epochs only (not the refit)
            monitor="val/rmse_m", mode="min", save_last=True, save_top_k=1,
            filename="best-epoch{epoch:04d}", auto_insert_metric_name=False,
        ),
        DashboardLayout(),
        report,
        ResumeHint(),
        EpochLines(),
    ]
    return callbacks, report


def _config_files(argv: list[str]) -> list[str]:
    """The ``--config`` / ``-c`` files of ``argv`` (``--config FILE`` and ``--config=FILE``)."""
    files = [value for flag, value in zip(argv, argv[1:], strict=False)
             if flag in ("--config", "-c")]
    return files + [a.split("=", 1)[1] for a in argv if a.startswith("--config=")]


def mode_parser() -> ArgumentParser:
    """The jsonargparse pre-parser of ``train.py``'s mode: the ``learn`` key of a config.

    Only ``learn`` is declared; the rest of the file is parsed in full, and checked, by the
    chosen mode's LightningCLI afterwards.
    """
    parser = ArgumentParser(prog="train.py", exit_on_error=False)
    parser.add_argument("--learn", type=str | None, default=None,
                        help=f"What train.py learns: one of {', '.join(MODES)}.")
    return parser


def config_learn(argv: list[str]) -> str | None:
    """The mode the ``--config`` files of ``argv`` name with their top-level ``learn:`` key
    (the last file that has one, as jsonargparse layers configs); None when none does.

    Files that are missing or not YAML are left to the mode's LightningCLI, which reports
    them.

    Raises:
        SystemExit: 2 (one ``error:`` line) when ``learn`` is not a mode of `MODES`.
    """
    parser = mode_parser()
    mode = None
    for path in _config_files(argv):
        try:  # _skip_validation: the other keys belong to the mode's parser
            learn = parser.parse_path(path, _skip_validation=True).get("learn")
        except (ArgumentError, TypeError, OSError):
            continue
        if learn is None:
            continue
        if learn not in MODES:
            print(f"error: {path}: learn: {learn!r} is not a train.py mode; use one of "
                  f"{', '.join(MODES)}.", file=sys.stderr, flush=True)
            raise SystemExit(EXIT_BAD_INPUT)
        mode = str(learn)
    return mode


def config_mode(argv: list[str]) -> str:
    """The mode of ``train.py`` without a mode word: the configs' ``learn`` key
    (`config_learn`), else ``map``. Lets ``python train.py --config
    configs/latent_map.yaml`` run the mode the config is written for."""
    return config_learn(argv) or "map"


def main(args: list[str] | None = None) -> Path | None:
    """Runs ``train.py``: picks the mode from the first word, then parses, fits, exports.

    Args:
        args: Command-line arguments (``None`` = ``sys.argv[1:]``); a first word of
            `MODES` selects the mode (default ``map``).

    Returns:
        The exported file: ``neural_map.pt`` (map), ``learned_scenario.yaml`` (noise) or
        ``map_index.json`` (region); ``None`` on DDP worker ranks.

    Raises:
        SystemExit: 2 on bad input (one ``error:`` line on stderr), 1 when nothing was
            exported (see each mode).
    """
    argv = list(sys.argv[1:] if args is None else args)
    mode = argv[0] if argv and not argv[0].startswith("-") else config_mode(argv)
    if argv and not argv[0].startswith("-"):
        argv = argv[1:]
        if mode not in MODES:
            print(f"error: train.py mode {mode!r} is unknown; the first word is one of "
                  f"{', '.join(MODES)} (or an option, for map).", file=sys.stderr, flush=True)
            raise SystemExit(EXIT_BAD_INPUT)
        learn = config_learn(argv)
        if learn is not None and learn != mode:
            print(f"error: train.py {mode}: the config is written for `learn: {learn}`; run "
                  f"`train.py {learn} ...` (or drop the mode word).", file=sys.stderr,
                  flush=True)
            raise SystemExit(EXIT_BAD_INPUT)
    if mode == "noise":
        return main_noise(argv)
    if mode == "region":
        return main_region(argv)
    if mode == "latent":
        return main_latent(argv)
    return main_map(argv)


def main_map(args: list[str] | None = None) -> Path | None:
    """``train.py map``: parse, fit, export; returns the exported map path.

    Args:
        args: Command-line arguments (``None`` = ``sys.argv[1:]``). Without ``--config``
            the repository's ``configs/train.yaml`` is the default config file.

    Returns:
        Path of ``neural_map.pt`` (rank 0; ``None`` on other DDP ranks). It is also printed
        as the last line of stdout.

    Raises:
        SystemExit: Code 2 on bad input (`NeuralMapError`: the message goes to
            stderr without a traceback) or bad arguments.
    """
    default_config = default_config_path()
    parser_kwargs: dict[str, Any] = {
        "description": "Fit a neural terrain map (blockwise MLPs) to a DEM tile.",
        "default_config_files": [str(default_config)] if default_config else [],
    }
    callbacks, report = _trainer_callbacks()
    cli: NeuralMapCLI | None = None
    new_dirs: set[Path] = set()
    try:
        with warnings.catch_warnings():
            # main(args) from Python (tests, benchmarks) is the intended use of `args`.
            warnings.filterwarnings("ignore", message="LightningCLI's args parameter")
            cli = _build_cli(args, parser_kwargs, callbacks)
        ckpt_path = cli.config.get("ckpt_path")
        experiment_dir = Path(cli.config_init.get("runs_dir") or "runs") / cli.experiment_name()
        before = set(experiment_dir.glob("version_*"))
        try:
            with quiet_lightning():  # Lightning's tips and its torch deprecation warning
                cli.trainer.fit(cli.model, datamodule=cli.datamodule, ckpt_path=ckpt_path)
        finally:
            new_dirs = set(experiment_dir.glob("version_*")) - before
    except NeuralMapError as error:
        for run_dir in new_dirs:  # a failed run leaves no empty version folder behind
            remove_orphan_run_dir(run_dir)
        if cli is not None:
            cli.remove_reserved_dir()
        sys.stdout.flush()
        print(f"error: {error}", file=sys.stderr, flush=True)
        raise SystemExit(EXIT_BAD_INPUT) from None
    if cli.trainer.is_global_zero:
        if report.map_path is None:
            sys.stdout.flush()
            print(
                f"error: the run ended after {cli.trainer.current_epoch} epoch(s) without "
                "exporting a map (no training step completed); nothing was written to use. "
                "Check --trainer.max_epochs / max_steps / max_time and the log above.",
                file=sys.stderr, flush=True,
            )
            raise SystemExit(EXIT_NO_MAP)
        sys.stderr.flush()
        print(os.fspath(report.map_path), flush=True)
    return report.map_path


def _build_cli(
    args: list[str] | None, parser_kwargs: dict[str, Any], callbacks: list[Any]
) -> NeuralMapCLI:
    """Parses the arguments and instantiates data module, model and trainer."""
    return NeuralMapCLI(
        TerrainFitModule,
        DemDataModule,
        run=False,
        args=args,
        seed_everything_default=0,
        auto_configure_optimizers=False,
        save_config_kwargs={"overwrite": True},
        parser_kwargs=parser_kwargs,
        trainer_defaults={"callbacks": callbacks},
    )
