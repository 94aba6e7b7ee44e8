"""``train.py``: fit a neural map to a DEM tile with LightningCLI.

``python train.py`` fits the jacksboro sample with ``configs/train.yaml``;
``python train.py --config configs/paper_bp.yaml`` uses the SEEDS 004 preset;
``--data.path my_tile.hgt``, ``--trainer.max_epochs 5``,
``--trainer.strategy ddp --trainer.devices 2 --trainer.accelerator cpu`` and every other
Lightning trainer flag work as usual; ``--ckpt_path`` resumes. Outputs go to
``runs/<experiment>/version_N/`` (experiment = tile name unless ``--experiment``): TensorBoard
events, ``config.yaml``, checkpoints, PNG figures, ``metrics.json`` and ``neural_map.pt``,
whose path is the last line printed on stdout.
"""

from __future__ import annotations

import os
import sys
import warnings
from pathlib import Path
from typing import Any

import torch
from lightning.pytorch.callbacks import ModelCheckpoint
from lightning.pytorch.cli import LightningArgumentParser, LightningCLI
from lightning.pytorch.loggers import TensorBoardLogger

from neuralmap.exceptions import NeuralMapError
from neuralmap.training.callbacks import DashboardLayout, FitReport
from neuralmap.training.datamodule import DemDataModule
from neuralmap.training.module import TerrainFitModule

#: Exit status for bad user input (NeuralMapError), as argparse uses for bad arguments.
EXIT_BAD_INPUT = 2


def default_config_path() -> Path | None:
    """The shipped ``configs/train.yaml`` (package data), else one in the cwd."""
    from neuralmap.resources import config_file

    candidates = [config_file("train.yaml"), Path.cwd() / "configs" / "train.yaml"]
    for candidate in candidates:
        if candidate.is_file():
            return candidate
    return None


class NeuralMapCLI(LightningCLI):
    """LightningCLI for :class:`TerrainFitModule` + :class:`DemDataModule`.

    Adds ``--experiment`` (run folder name, default the tile name), ``--runs_dir``
    (default ``runs``), ``--ckpt_path`` (resume) and ``--threads`` (torch CPU threads).
    Unless the config sets ``trainer.logger``, a :class:`TensorBoardLogger` writes to
    ``<runs_dir>/<experiment>/version_N``.
    """

    def add_arguments_to_parser(self, parser: LightningArgumentParser) -> None:
        parser.add_argument(
            "--experiment", type=str | None, default=None,
            help="Run folder name under runs_dir (default: the tile name).",
        )
        parser.add_argument(
            "--runs_dir", type=str, default="runs", help="Root folder of the runs."
        )
        parser.add_argument(
            "--ckpt_path", type=str | None, default=None,
            help="Checkpoint to resume from, e.g. "
            "runs/<experiment>/version_0/checkpoints/last.ckpt.",
        )
        parser.add_argument(
            "--threads", type=int | None, default=None,
            help="torch CPU threads per process (default: torch's choice, all physical cores).",
        )

    def before_instantiate_classes(self) -> None:
        threads = self.config.get("threads")
        if threads is not None:
            if threads < 1:
                raise NeuralMapError(f"--threads must be >= 1, got {threads}.")
            torch.set_num_threads(int(threads))
        ckpt = self.config.get("ckpt_path")
        if ckpt is not None and not Path(ckpt).is_file():
            raise NeuralMapError(
                f"--ckpt_path {ckpt}: no such checkpoint file. Checkpoints are written to "
                "runs/<experiment>/version_N/checkpoints/ (last.ckpt, best-*.ckpt)."
            )

    def experiment_name(self) -> str:
        """``--experiment`` or the tile's name."""
        name = self.config_init.get("experiment")
        return str(name) if name else self.datamodule.experiment_name

    def instantiate_trainer(self, **kwargs: Any) -> Any:
        trainer_config = self._get(self.config_init, "trainer", default={})
        runs_dir = Path(self.config_init.get("runs_dir") or "runs")
        experiment = self.experiment_name()
        if trainer_config.get("logger") in (None, True):
            kwargs["logger"] = TensorBoardLogger(
                save_dir=str(runs_dir), name=experiment, default_hp_metric=False
            )
        if trainer_config.get("default_root_dir") is None:
            kwargs["default_root_dir"] = str(runs_dir / experiment)
        return super().instantiate_trainer(**kwargs)


def _trainer_callbacks() -> tuple[list[Any], FitReport]:
    report = FitReport()
    callbacks = [
        ModelCheckpoint(
            monitor="val/rmse_m", mode="min", save_last=True, save_top_k=1,
            filename="best-epoch{epoch:04d}", auto_insert_metric_name=False,
        ),
        DashboardLayout(),
        report,
    ]
    return callbacks, report


def main(args: list[str] | None = None) -> Path | None:
    """Runs ``train.py``: parse, fit, export; returns the exported map path.

    Args:
        args: Command-line arguments (``None`` = ``sys.argv[1:]``). Without ``--config``
            the repository's ``configs/train.yaml`` is the default config file.

    Returns:
        Path of ``neural_map.pt`` (rank 0; ``None`` on other DDP ranks). It is also printed
        as the last line of stdout.

    Raises:
        SystemExit: Code 2 on bad input (:class:`NeuralMapError`: the message goes to
            stderr without a traceback) or bad arguments.
    """
    default_config = default_config_path()
    parser_kwargs: dict[str, Any] = {
        "description": "Fit a neural terrain map (blockwise MLPs) to a DEM tile.",
        "default_config_files": [str(default_config)] if default_config else [],
    }
    callbacks, report = _trainer_callbacks()
    try:
        with warnings.catch_warnings():
            # main(args) from Python (tests, benchmarks) is the intended use of `args`.
            warnings.filterwarnings("ignore", message="LightningCLI's args parameter")
            cli = _build_cli(args, parser_kwargs, callbacks)
        ckpt_path = cli.config.get("ckpt_path")
        cli.trainer.fit(cli.model, datamodule=cli.datamodule, ckpt_path=ckpt_path)
    except NeuralMapError as error:
        sys.stdout.flush()
        print(f"error: {error}", file=sys.stderr, flush=True)
        raise SystemExit(EXIT_BAD_INPUT) from None
    if report.map_path is not None and cli.trainer.is_global_zero:
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
