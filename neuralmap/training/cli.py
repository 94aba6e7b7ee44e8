"""``train.py``: fit a neural map to a DEM tile with LightningCLI.

``python train.py`` fits the jacksboro sample with ``configs/train.yaml``;
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
import shutil
import sys
import warnings
from pathlib import Path
from typing import Any

import torch
from lightning.fabric.utilities.exceptions import MisconfigurationException
from lightning.pytorch.callbacks import ModelCheckpoint
from lightning.pytorch.cli import LightningArgumentParser, LightningCLI
from lightning.pytorch.loggers import TensorBoardLogger

from neuralmap.exceptions import NeuralMapError
from neuralmap.io import check_writable_dir, next_version_dir
from neuralmap.training.callbacks import DashboardLayout, EpochLines, FitReport, ResumeHint
from neuralmap.training.datamodule import DemDataModule
from neuralmap.training.module import TerrainFitModule
from neuralmap.training.resume import inspect_checkpoint

#: Exit status for bad user input (NeuralMapError), as argparse uses for bad arguments.
EXIT_BAD_INPUT = 2
#: Exit status of a run that ended without exporting a map.
EXIT_NO_MAP = 1
#: Environment variable through which DDP worker processes learn rank 0's run folder.
RUN_DIR_ENV = "NEURALMAP_RUN_DIR"


def check_experiment_name(name: str) -> None:
    """Refuses experiment names that would leave ``runs_dir`` (``..``, separators)."""
    if name in ("", ".", "..") or "/" in name or "\\" in name or os.sep in name:
        raise NeuralMapError(
            f"--experiment {name!r} must be a plain folder name inside --runs_dir (no '/', "
            "'\\', '.' or '..'); choose the parent folder with --runs_dir instead."
        )


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
        experiment = self.config.get("experiment")
        if experiment is not None:
            check_experiment_name(str(experiment))
        check_writable_dir(Path(self.config.get("runs_dir") or "runs"), option="--runs_dir")
        max_epochs = self.config.get("trainer.max_epochs")
        max_steps = self.config.get("trainer.max_steps")
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
        (:func:`neuralmap.io.next_version_dir`): TensorBoard's ``version_N`` is that folder,
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


def _trainer_callbacks() -> tuple[list[Any], FitReport]:
    report = FitReport()
    callbacks = [
        ModelCheckpoint(
            monitor="val/rmse_m", mode="min", save_last=True, save_top_k=1,
            filename="best-epoch{epoch:04d}", auto_insert_metric_name=False,
        ),
        DashboardLayout(),
        report,
        ResumeHint(),
        EpochLines(),
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
    from neuralmap.training.noise_cli import learn_mode, main_noise

    try:
        mode = learn_mode(args)
    except NeuralMapError as error:
        print(f"error: {error}", file=sys.stderr, flush=True)
        raise SystemExit(EXIT_BAD_INPUT) from None
    if mode == "noise":
        return main_noise(args)
    if mode == "latent":
        from neuralmap.training.latent_cli import main_latent

        return main_latent(args)
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
