"""The Lightning command line shared by the ``train.py`` modes (map, noise, latent).

`NeuralMapCLI` adds ``--experiment``, ``--runs_dir``, ``--ckpt_path`` and
``--threads`` to LightningCLI, checks them before anything is built, and gives every run a
``version_N`` folder of its own, reserved atomically. The modes live in
`neuralmap.training.cli` (dispatch, map fit), `neuralmap.training.noise_cli`,
`neuralmap.training.latent_cli` and `neuralmap.training.region_cli` (the region
fit runs on Lightning Fabric, not a Trainer: the same option style on jsonargparse, the
parser LightningCLI is built on, and the exit codes defined here).
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path
from typing import Any

import torch
from lightning.fabric.utilities.exceptions import MisconfigurationException
from lightning.pytorch.cli import LightningArgumentParser, LightningCLI
from lightning.pytorch.loggers import TensorBoardLogger

from neuralmap.exceptions import NeuralMapError
from neuralmap.io import check_experiment_name, check_writable_dir, next_version_dir
from neuralmap.training.quiet import silence_lightning_notices
from neuralmap.training.resume import inspect_checkpoint

__all__ = ["EXIT_BAD_INPUT", "EXIT_NO_MAP", "RUN_DIR_ENV", "NeuralMapCLI",
           "check_experiment_name", "remove_orphan_run_dir"]

#: Exit status for bad user input (NeuralMapError), as argparse uses for bad arguments.
EXIT_BAD_INPUT = 2
#: Exit status of a run that ended without exporting a map.
EXIT_NO_MAP = 1
#: Environment variable through which DDP worker processes learn rank 0's run folder.
RUN_DIR_ENV = "NEURALMAP_RUN_DIR"


class NeuralMapCLI(LightningCLI):
    """LightningCLI for `TerrainFitModule` + `DemDataModule`.

    Adds ``--experiment`` (run folder name, default the tile name), ``--runs_dir``
    (default ``runs``), ``--ckpt_path`` (resume) and ``--threads`` (torch CPU threads).
    Unless the config sets ``trainer.logger``, a `TensorBoardLogger` writes to
    ``<runs_dir>/<experiment>/version_N``.
    """

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        silence_lightning_notices()  # no product tips (the fit itself: quiet_lightning)
        super().__init__(*args, **kwargs)

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
            "--threads", type=int | None, default=1,
            help="torch CPU threads per process (default 1, measured fastest on a shared "
                 "machine; null = torch's choice, all physical cores).",
        )

    def before_instantiate_classes(self) -> None:
        threads = self.config.get("threads")
        if threads is not None:
            if threads < 1:
                raise NeuralMapError(f"--threads must be >= 1, got {threads}.")
            torch.set_num_threads(int(threads))
        experiment = self.config.get("experiment")
        if experiment is not None:
            check_experiment_name(str(experiment))
        check_writable_dir(Path(self.config.get("runs_dir") or "runs"), option="--runs_dir")
        max_epochs = self.config.get("trainer.max_epochs")
        max_steps = self.config.get("trainer.max_steps")
        for which, value in (("max_epochs", max_epochs), ("max_steps", max_steps)):
            if isinstance(value, int) and value < -1:
                raise NeuralMapError(
                    f"--trainer.{which} {value}: give a count >= 1, or -1 for no limit "
                    f"(then bound the run with --trainer.max_time or the other of "
                    f"max_epochs / max_steps).")
        if max_epochs == 0 or max_steps == 0:
            which = "max_epochs" if max_epochs == 0 else "max_steps"
            raise NeuralMapError(
                f"--trainer.{which} 0 trains nothing, so no map would be exported; pass at "
                f"least 1 (or --trainer.fast_dev_run true for a one-batch smoke test)."
            )
        ckpt = self.config.get("ckpt_path")
        if ckpt is not None:
            inspect_checkpoint(ckpt, max_epochs=max_epochs)

    def experiment_name(self) -> str:
        """``--experiment`` or the tile's name."""
        name = self.config_init.get("experiment")
        return str(name) if name else self.datamodule.experiment_name

    def instantiate_trainer(self, **kwargs: Any) -> Any:
        """Trainer with a run folder of its own, reserved here with an atomic ``mkdir``
        (`neuralmap.io.next_version_dir`): TensorBoard's ``version_N`` is that folder,
        and without a logger it is the trainer's root (never the experiment folder itself).
        Two runs started at once into one experiment therefore never share a folder."""
        trainer_config = self._get(self.config_init, "trainer", default={})
        runs_dir = Path(self.config_init.get("runs_dir") or "runs")
        experiment = self.experiment_name()
        logger = trainer_config.get("logger")
        self.reserved_dir: Path | None = None
        own_root = trainer_config.get("default_root_dir") is None
        # fast_dev_run replaces every logger by a dummy one and writes no run folder
        reserve = not trainer_config.get("fast_dev_run") and (
            logger in (None, True) or (logger is False and own_root))
        run_dir = self._run_dir(runs_dir / experiment) if reserve else None
        if logger in (None, True):
            kwargs["logger"] = TensorBoardLogger(
                save_dir=str(runs_dir), name=experiment, default_hp_metric=False,
                version=None if run_dir is None else run_dir.name,
            )
        if own_root:
            kwargs["default_root_dir"] = str(
                run_dir if logger is False and run_dir is not None else runs_dir / experiment)
        try:
            return super().instantiate_trainer(**kwargs)
        except MisconfigurationException as exc:
            self.remove_reserved_dir()
            raise NeuralMapError(
                f"trainer settings cannot run here: {exc} Check --trainer.accelerator, "
                "--trainer.devices and --trainer.strategy (e.g. --trainer.accelerator cpu; "
                "'gpu' needs a CUDA or MPS device)."
            ) from None

    def _run_dir(self, experiment_dir: Path) -> Path:
        """The run folder: reserved here on rank 0, rank 0's one on DDP worker processes."""
        worker = os.environ.get("LOCAL_RANK", "0") != "0"
        if worker and os.environ.get(RUN_DIR_ENV):
            return Path(os.environ[RUN_DIR_ENV])
        run_dir = next_version_dir(experiment_dir)
        self.reserved_dir = run_dir
        os.environ[RUN_DIR_ENV] = str(run_dir)
        return run_dir

    def remove_reserved_dir(self) -> None:
        """Removes the version folder reserved for this run if it holds no checkpoint or map."""
        remove_orphan_run_dir(getattr(self, "reserved_dir", None))


def remove_orphan_run_dir(run_dir: Path | None) -> None:
    """Deletes a run folder created by a failed run, unless it holds a checkpoint or a map."""
    if run_dir is None or not run_dir.is_dir():
        return
    if any(run_dir.glob("checkpoints/*.ckpt")) or (run_dir / "neural_map.pt").exists():
        return
    shutil.rmtree(run_dir, ignore_errors=True)
