"""``python train.py noise``: learn the TAN filter's Q and R from flights.

``python train.py noise --config configs/learn_noise.yaml`` trains
`NoiseLearningModule` on
`FlightDataModule` with the same CLI habits as
the map fit (``--trainer.*``, ``--experiment``, ``--runs_dir``, ``--threads``, TensorBoard
in ``runs/<experiment>/version_N``, reserved atomically). The last stdout line is the
learned scenario YAML, ready for ``python evaluate.py --scenario <that file>``. A run that
fails on bad input leaves no run folder behind.
"""

from __future__ import annotations

import sys
import warnings
from pathlib import Path

from lightning.pytorch.callbacks import ModelCheckpoint

from neuralmap.exceptions import NeuralMapError
from neuralmap.training.callbacks.epoch_lines import EpochLines
from neuralmap.training.cli_base import (
    EXIT_BAD_INPUT,
    EXIT_NO_MAP,
    NeuralMapCLI,
    remove_orphan_run_dir,
)
from neuralmap.training.flight_datamodule import FlightDataModule
from neuralmap.training.noise_module import NoiseLearningModule
from neuralmap.training.quiet import quiet_lightning

__all__ = ["main_noise"]


def main_noise(args: list[str] | None = None) -> Path | None:
    """Parses, fits, exports; returns the learned scenario YAML path (also printed last).

    Args:
        args: The arguments after ``train.py noise`` (``None`` = ``sys.argv[2:]``).

    Raises:
        SystemExit: 2 on bad input (message on stderr), 1 when nothing was learned.
    """
    if args is None:
        args = sys.argv[2:]
    checkpoint = ModelCheckpoint(monitor="val/nll", mode="min", save_last=True, save_top_k=1,
                                 filename="best-epoch{epoch:04d}", auto_insert_metric_name=False)
    cli: NeuralMapCLI | None = None
    try:
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message="LightningCLI's args parameter")
            cli = NeuralMapCLI(
                NoiseLearningModule, FlightDataModule, run=False, args=args,
                seed_everything_default=0, auto_configure_optimizers=False,
                save_config_kwargs={"overwrite": True},
                parser_kwargs={"prog": "train.py noise",
                               "description": "Learn the TAN filter's Q and R from flights."},
                trainer_defaults={"callbacks": [checkpoint, EpochLines()]},
            )
        with quiet_lightning():  # Lightning's tips and its torch deprecation warning
            cli.trainer.fit(cli.model, datamodule=cli.datamodule,
                            ckpt_path=cli.config.get("ckpt_path"))
    except NeuralMapError as error:
        if cli is not None:  # no run folder holding only an event file
            remove_orphan_run_dir(cli.reserved_dir)
        sys.stdout.flush()
        print(f"error: {error}", file=sys.stderr, flush=True)
        raise SystemExit(EXIT_BAD_INPUT) from None
    path = cli.model.learned_path
    if cli.trainer.is_global_zero:
        if path is None:
            print("error: no learned scenario was written (the fit did not finish).",
                  file=sys.stderr, flush=True)
            raise SystemExit(EXIT_NO_MAP)
        print(str(path), flush=True)
    return path
