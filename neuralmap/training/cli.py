"""``train.py``: every trainer of the toolkit behind one command, one option style, and one
class per mode.

``python train.py [map|noise|latent|region] [--config FILE] [--data.* --model.* --trainer.* ...]``

**How the mode is chosen** (this is the one place it is documented): the first word, when it
is not an option, names the mode; otherwise the ``--config`` files' top-level ``learn:`` key
does (the last file that has one, as jsonargparse layers configs); otherwise ``map``. A mode
word that disagrees with the config's ``learn:`` is refused, so ``python train.py --config
configs/latent_map.yaml`` runs the mode the config is written for.

The modes (`MODES`, one class each, sharing `TrainMode`):

- `MapMode` (``map``): fit a neural map to a DEM tile, or to a mosaic of tiles
  (``--data.path "srtm/*.hgt"`` or a list), with LightningCLI. ``python train.py`` fits the
  jacksboro sample with ``configs/train.yaml``; ``--config configs/paper_bp.yaml`` uses the
  SEEDS 004 preset; ``--data.path my_tile.hgt``, ``--trainer.max_epochs 5``,
  ``--trainer.strategy ddp --trainer.devices 2 --trainer.accelerator cpu`` and every other
  Lightning trainer flag work as usual; ``--ckpt_path`` resumes. Outputs go to
  ``runs/<experiment>/version_N/`` (experiment = tile name unless ``--experiment``):
  TensorBoard events, ``config.yaml``, checkpoints, PNG figures, ``metrics.json`` and
  ``neural_map.pt``, whose path is the last line printed on stdout. Every run gets its own
  ``version_N``, also with ``--trainer.logger false`` (then reserved here).
- `NoiseMode` (``noise``): learn the TAN filter's Q and R from flights
  (``python train.py noise --config configs/learn_noise.yaml``); the last stdout line is the
  learned scenario YAML, ready for ``python evaluate.py --scenario <that file>``.
- `LatentMode` (``latent``): fit a latent-grid map (``python train.py latent --config
  configs/latent_map.yaml``); the last stdout line is the bitstream ``latent_map.nlat``.
  With ``--data.path 'tiles/*.hgt'`` (a glob or a list of DEM files) or
  ``--data.tile_nodes N`` it fits a latent tileset, one map per tile with an overlap
  (`neuralmap.training.latent_tileset`); the last stdout line is ``latent_tileset.json``.
- `RegionMode` (``region``): fit a region-scale sharded map on several processes on
  Lightning Fabric (``python train.py region --config configs/train_region.yaml --out
  runs/paper_region``; ``--data.path`` a ``.npy`` region, DEM files / globs, or
  ``synthetic-region``). The map goes to ``OUT/map_index.json`` + ``OUT/shards/``, published
  whole (built under a hidden name beside ``OUT``, `neuralmap.io.replacing_dir`), so a
  refused mosaic, a failed or interrupted run, or ``kill -9`` leaves the previous output
  untouched. With ``--trainer.strategy ddp`` (Lightning's script launcher, or ``torchrun``
  over several nodes) every rank re-runs this command and only rank 0 publishes; ``--out``
  must be on a disk every node sees (`neuralmap.training.region_staging`).

The Lightning modes share `NeuralMapCLI`: ``--experiment``, ``--runs_dir``, ``--ckpt_path``
and ``--threads``, checked before anything is built, and a ``version_N`` folder per run,
reserved atomically.

Exit codes: 0 with the exported path as the last stdout line (region: the summary as JSON);
2 for bad input (a one-line ``error:`` message on stderr, checked before training where
possible: ``max_epochs 0``, an ``--experiment`` leaving ``--runs_dir``, a ``--runs_dir``
that is a file, an unusable or exhausted ``--ckpt_path``, an accelerator that is not there);
1 when a run ends without exporting (including Ctrl-C, which for ``map`` prints the command
that resumes from ``last.ckpt``). A failed run leaves no empty ``version_N`` behind.
"""

from __future__ import annotations

import json
import os
import shutil
import sys
import time
import warnings
from argparse import ArgumentError
from contextlib import ExitStack
from pathlib import Path
from typing import Any, ClassVar

import torch
from jsonargparse import ActionConfigFile, ArgumentParser
from lightning.fabric.utilities.exceptions import MisconfigurationException
from lightning.pytorch.callbacks import ModelCheckpoint
from lightning.pytorch.cli import LightningArgumentParser, LightningCLI
from lightning.pytorch.loggers import TensorBoardLogger

from neuralmap.exceptions import NeuralMapError
from neuralmap.io import (
    atomic_write_text,
    check_experiment_name,
    check_writable_dir,
    next_version_dir,
    replacing_dir,
)
from neuralmap.training.quiet import quiet_lightning, silence_lightning_notices
from neuralmap.training.resume import inspect_checkpoint

__all__ = ["EXIT_BAD_INPUT", "EXIT_NO_MAP", "MODES", "RUN_DIR_ENV", "LatentMode", "MapMode",
           "NeuralMapCLI", "NoiseMode", "RegionMode", "TrainMode", "check_experiment_name",
           "config_learn", "config_mode", "default_config_path", "main", "mode_parser",
           "region_parser", "remove_orphan_run_dir"]

#: Exit status for bad user input (NeuralMapError), as argparse uses for bad arguments.
EXIT_BAD_INPUT = 2
#: Exit status of a run that ended without exporting a map.
EXIT_NO_MAP = 1
#: Environment variable through which DDP worker processes learn rank 0's run folder.
RUN_DIR_ENV = "NEURALMAP_RUN_DIR"


# ----------------------------------------------------------------------------- shared CLI
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


def _refuse(error: NeuralMapError | str) -> SystemExit:
    """Prints the one ``error:`` line of bad input and returns the exit to raise."""
    sys.stdout.flush()
    print(f"error: {error}", file=sys.stderr, flush=True)
    return SystemExit(EXIT_BAD_INPUT)


def _lightning_cli(cli_class: type[NeuralMapCLI], model: type, data: type, args: list[str] | None,
                   parser_kwargs: dict[str, Any], callbacks: list[Any]) -> NeuralMapCLI:
    """Parses the arguments and instantiates data module, model and trainer (no fit)."""
    with warnings.catch_warnings():
        # main(args) from Python (tests, benchmarks) is the intended use of `args`.
        warnings.filterwarnings("ignore", message="LightningCLI's args parameter")
        return cli_class(
            model, data, run=False, args=args, seed_everything_default=0,
            auto_configure_optimizers=False, save_config_kwargs={"overwrite": True},
            parser_kwargs=parser_kwargs, trainer_defaults={"callbacks": callbacks})


def _write_summary(mode: str, args: list[str] | None, cli: Any, map_path: Path,
                   metrics: dict[str, Any], start: float, defaults: list[str]) -> None:
    """The run folder's stamped ``summary.md`` (`neuralmap.training.run_summary`)."""
    from neuralmap.training.run_summary import write_train_summary

    argv = list(sys.argv[1:] if args is None else args)
    configs = defaults + _config_files(argv)
    seed = cli.config.get("seed_everything")
    write_train_summary(map_path.parent, mode=mode, argv=argv, configs=configs,
                        metrics=metrics, seed=seed if isinstance(seed, int) else None,
                        wall_s=time.perf_counter() - start,
                        experiment=map_path.parent.parent.name)


# ----------------------------------------------------------------------------- the modes
class TrainMode:
    """One mode of ``train.py``: its name and how it parses, fits and exports.

    Attributes:
        name: The mode word (``train.py <name>``) and the configs' ``learn:`` value.
        summary: One line for ``--help`` and errors.
    """

    name: ClassVar[str]
    summary: ClassVar[str]

    def run(self, args: list[str]) -> Path | None:
        """Parses ``args`` (the words after the mode), fits, exports.

        Returns:
            The exported file (also printed as the last stdout line); ``None`` on worker
            ranks.

        Raises:
            SystemExit: 2 on bad input (one ``error:`` line on stderr), 1 when nothing was
                exported.
        """
        raise NotImplementedError


class MapMode(TrainMode):
    """``train.py map``: fit a blockwise neural map (`TerrainFitModule` on `DemDataModule`);
    exports ``neural_map.pt``. Without ``--config`` the shipped ``configs/train.yaml`` is
    the default config file."""

    name = "map"
    summary = "Fit a neural terrain map (blockwise MLPs) to a DEM tile."

    @staticmethod
    def callbacks() -> tuple[list[Any], Any]:
        """The trainer's callbacks and the `FitReport` among them."""
        from neuralmap.training.callbacks import DashboardLayout, EpochLines, FitReport, ResumeHint
        from neuralmap.training.callbacks.heldout_checkpoint import HeldOutCheckpoint

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

    @staticmethod
    def build(args: list[str] | None, parser_kwargs: dict[str, Any],
              callbacks: list[Any]) -> NeuralMapCLI:
        """Parses the arguments and instantiates data module, model and trainer."""
        from neuralmap.training.datamodule import DemDataModule
        from neuralmap.training.module import TerrainFitModule

        return _lightning_cli(NeuralMapCLI, TerrainFitModule, DemDataModule, args,
                              parser_kwargs, callbacks)

    def run(self, args: list[str] | None) -> Path | None:
        start = time.perf_counter()
        default_config = default_config_path()
        parser_kwargs: dict[str, Any] = {
            "description": self.summary,
            "default_config_files": [str(default_config)] if default_config else [],
        }
        callbacks, report = self.callbacks()
        cli: NeuralMapCLI | None = None
        new_dirs: set[Path] = set()
        try:
            cli = self.build(args, parser_kwargs, callbacks)
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
            raise _refuse(error) from None
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
            _write_summary(self.name, args, cli, report.map_path, report.metrics, start,
                           [str(default_config)] if default_config else [])
            sys.stderr.flush()
            print(os.fspath(report.map_path), flush=True)
        return report.map_path


class NoiseMode(TrainMode):
    """``train.py noise``: learn the TAN filter's Q and R from flights
    (`NoiseLearningModule` on `FlightDataModule`); exports the learned scenario YAML. A run
    that fails on bad input leaves no run folder behind."""

    name = "noise"
    summary = "Learn the TAN filter's Q and R from flights."

    def run(self, args: list[str] | None) -> Path | None:
        from neuralmap.training.callbacks.epoch_lines import EpochLines
        from neuralmap.training.flight_datamodule import FlightDataModule
        from neuralmap.training.noise_module import NoiseLearningModule

        checkpoint = ModelCheckpoint(monitor="val/nll", mode="min", save_last=True,
                                     save_top_k=1, filename="best-epoch{epoch:04d}",
                                     auto_insert_metric_name=False)
        cli: NeuralMapCLI | None = None
        try:
            cli = _lightning_cli(NeuralMapCLI, NoiseLearningModule, FlightDataModule, args,
                                 {"prog": "train.py noise", "description": self.summary},
                                 [checkpoint, EpochLines()])
            with quiet_lightning():  # Lightning's tips and its torch deprecation warning
                cli.trainer.fit(cli.model, datamodule=cli.datamodule,
                                ckpt_path=cli.config.get("ckpt_path"))
        except NeuralMapError as error:
            if cli is not None:  # no run folder holding only an event file
                remove_orphan_run_dir(cli.reserved_dir)
            raise _refuse(error) from None
        path = cli.model.learned_path
        if cli.trainer.is_global_zero:
            if path is None:
                print("error: no learned scenario was written (the fit did not finish).",
                      file=sys.stderr, flush=True)
                raise SystemExit(EXIT_NO_MAP)
            print(str(path), flush=True)
        return path


class _LatentCLI(NeuralMapCLI):
    """`NeuralMapCLI` with ``--learn`` (always ``latent`` here: the key the configs carry)."""

    def add_arguments_to_parser(self, parser: LightningArgumentParser) -> None:
        super().add_arguments_to_parser(parser)
        parser.add_argument("--learn", type=str, default="latent",
                            help=f"What train.py learns: one of {', '.join(MODES)}.")


class LatentMode(TrainMode):
    """``train.py latent``: fit a latent-grid map (`LatentFitModule` on `LatentDataModule`);
    exports the bitstream ``latent_map.nlat``, which ``load_map`` reads."""

    name = "latent"
    summary = ("Fit a latent-grid neural map (entropy-coded latents + tiny decoder) to a DEM "
               "tile.")

    def run(self, args: list[str] | None) -> Path | None:
        from neuralmap.training.callbacks.epoch_lines import EpochLines
        from neuralmap.training.callbacks.latent_report import LatentMapReport
        from neuralmap.training.latent_datamodule import LatentDataModule
        from neuralmap.training.latent_module import LatentFitModule

        renamed = _renamed_option(args or [], LATENT_RENAMED)
        if renamed is not None:
            raise _refuse(renamed)
        start = time.perf_counter()
        report = LatentMapReport()
        checkpoint = ModelCheckpoint(save_last=True, save_top_k=0)
        try:
            cli = _lightning_cli(_LatentCLI, LatentFitModule, LatentDataModule, args,
                                 {"description": self.summary},
                                 [checkpoint, report, EpochLines()])
            if cli.datamodule.tileset_plan is not None:
                return self.run_tileset(cli)
            with quiet_lightning():  # Lightning's tips and its torch deprecation warning
                cli.trainer.fit(cli.model, datamodule=cli.datamodule,
                                ckpt_path=cli.config.get("ckpt_path"))
        except NeuralMapError as error:
            raise _refuse(error) from None
        if cli.trainer.is_global_zero:
            if report.map_path is None:
                print("error: the run ended without exporting a latent map (no training step "
                      "completed). Check --trainer.max_epochs / max_steps.", file=sys.stderr,
                      flush=True)
                raise SystemExit(EXIT_NO_MAP)
            _write_summary(self.name, args, cli, report.map_path, report.metrics, start, [])
            sys.stderr.flush()
            print(os.fspath(report.map_path), flush=True)
        return report.map_path


    @staticmethod
    def run_tileset(cli: NeuralMapCLI) -> Path:
        """A tileset run (``--data.path`` a glob or list of DEM files, or
        ``--data.tile_nodes``): every tile fitted with the run's ``--model.*`` settings for
        ``max_epochs x steps_per_epoch`` steps (`neuralmap.training.latent_tileset`); the
        tile bitstreams and ``latent_tileset.json`` go into the run folder, whose index path
        is the last stdout line. A run that fails or is interrupted leaves no run folder.

        Raises:
            NeuralMapError: ``--ckpt_path`` (a tileset does not resume) or no step bound.
        """
        from neuralmap.training.latent_tileset import fit_options, fit_tileset

        trainer = cli.trainer
        run_dir = getattr(cli, "reserved_dir", None) or Path(trainer.default_root_dir)
        try:
            if cli.config.get("ckpt_path"):
                raise NeuralMapError(
                    "--ckpt_path: a tileset run does not resume from a checkpoint; run it "
                    "again without --ckpt_path (each tile is fitted from scratch).")
            epochs, max_steps = trainer.max_epochs, trainer.max_steps
            steps = (epochs * cli.datamodule.steps_per_epoch
                     if epochs is not None and epochs > 0 else None)
            if max_steps is not None and max_steps > 0:
                steps = max_steps if steps is None else min(steps, max_steps)
            if steps is None:
                raise NeuralMapError(
                    "a tileset run needs --trainer.max_epochs >= 1 (or --trainer.max_steps): "
                    "each tile is fitted for max_epochs x --data.steps_per_epoch steps.")
            if trainer.is_global_zero:
                run_dir.mkdir(parents=True, exist_ok=True)
                atomic_write_text(run_dir / "config.yaml",
                                  cli.parser.dump(cli.config, skip_none=False))
            index = fit_tileset(cli.datamodule.tileset_plan, run_dir, steps=int(steps),
                                options=fit_options(cli.model.hparams))
        except NeuralMapError as error:
            remove_orphan_run_dir(getattr(cli, "reserved_dir", None))
            raise _refuse(error) from None
        except KeyboardInterrupt:
            remove_orphan_run_dir(getattr(cli, "reserved_dir", None))
            print("error: interrupted; the tileset run folder was removed (no index was "
                  "written). Run the command again to train.", file=sys.stderr, flush=True)
            raise SystemExit(EXIT_NO_MAP) from None
        sys.stderr.flush()
        print(os.fspath(index), flush=True)
        return index


class RegionMode(TrainMode):
    """``train.py region``: fit a region-scale map, shard by shard, on Lightning Fabric
    (jsonargparse options in the same style: `region_parser`); prints the summary as JSON
    and returns the published ``OUT/map_index.json`` (``None`` on script-launched ranks).
    Ctrl-C publishes nothing and exits 1."""

    name = "region"
    summary = "Fit a region-scale sharded neural map on several processes."

    def run(self, argv: list[str] | None) -> Path | None:
        from neuralmap.training.region import check_fit_options, check_spacing
        from neuralmap.training.region_staging import (
            STAGING_ENV,
            check_region_out,
            region_sources,
            torchrun_build,
            train_region,
            under_torchrun,
        )

        cfg = region_parser().parse_args(argv)
        out = Path(cfg.out)
        launched = os.environ.get("LOCAL_RANK", "0") != "0" or os.environ.get("RANK", "0") != "0"
        try:
            if cfg.data.spacing is not None:
                check_spacing(cfg.data.spacing, where="--data.spacing")
            check_fit_options(
                block_nodes=cfg.model.block_nodes, overlap_nodes=cfg.model.overlap_nodes,
                shard_blocks=tuple(cfg.model.shard_blocks), steps=cfg.model.steps,
                points_per_block=cfg.model.points_per_block, lr=cfg.model.lr,
                devices=cfg.trainer.devices, num_nodes=cfg.trainer.num_nodes,
                strategy=cfg.trainer.strategy, threads=cfg.threads)
            region_sources(cfg.data.path)
            with ExitStack() as building:
                if launched and under_torchrun():  # rank 0's folder (torchrun ends us if it fails)
                    build = torchrun_build(None)
                elif launched and os.environ.get(STAGING_ENV):  # Lightning's script launcher
                    build = Path(os.environ[STAGING_ENV])
                else:
                    check_region_out(out)
                    build = building.enter_context(replacing_dir(out, option="--out"))
                    if under_torchrun():
                        torchrun_build(build)
                os.environ[STAGING_ENV] = str(build)
                summary = train_region(cfg, build, out, launched)
        except NeuralMapError as exc:
            raise _refuse(exc) from None
        except KeyboardInterrupt:
            sys.stdout.flush()
            print(f"error: interrupted; nothing was published to --out '{out}' (an earlier "
                  "output there is unchanged). Run the command again to train.",
                  file=sys.stderr, flush=True)
            raise SystemExit(EXIT_NO_MAP) from None
        finally:
            if not launched:
                os.environ.pop(STAGING_ENV, None)
        if launched:
            return None
        print(json.dumps(summary, indent=1, default=str), flush=True)
        return out / "map_index.json"


#: The modes of ``train.py`` by their word (default ``map``).
MODES: dict[str, type[TrainMode]] = {
    mode.name: mode for mode in (MapMode, NoiseMode, RegionMode, LatentMode)}


def default_config_path() -> Path | None:
    """The shipped ``configs/train.yaml`` (package data), else one in the cwd."""
    from neuralmap.resources import config_file

    candidates = [config_file("train.yaml"), Path.cwd() / "configs" / "train.yaml"]
    for candidate in candidates:
        if candidate.is_file():
            return candidate
    return None


def _config_files(argv: list[str]) -> list[str]:
    """The ``--config`` / ``-c`` files of ``argv`` (``--config FILE`` and ``--config=FILE``)."""
    files = [value for flag, value in zip(argv, argv[1:], strict=False)
             if flag in ("--config", "-c")]
    return files + [a.split("=", 1)[1] for a in argv if a.startswith("--config=")]


#: ``train.py latent`` options that were renamed: old dotted key -> new one.
LATENT_RENAMED = {"model.regions": "model.zones"}


def _renamed_option(argv: list[str], renamed: dict[str, str]) -> str | None:
    """The error message for the first renamed option (``renamed``: old -> new dotted key)
    that ``argv`` or its ``--config`` files still use; None when none does.

    Files that are missing or not YAML are left to the mode's parser, which reports them.
    """
    import yaml

    for old, new in renamed.items():
        flag = f"--{old}"
        if any(word == flag or word.startswith(flag + "=") for word in argv):
            return f"{flag} is renamed --{new}; run it again with --{new}."
        for path in _config_files(argv):
            try:
                data: Any = yaml.safe_load(Path(path).read_text(encoding="utf-8"))
            except (OSError, UnicodeDecodeError, yaml.YAMLError):
                continue
            *parents, key = old.split(".")
            for part in parents:
                data = data.get(part) if isinstance(data, dict) else None
            if isinstance(data, dict) and key in data:
                return (f"{path}: the key {old} is renamed {new}; rename it in the file "
                        f"(or give --{new}).")
    return None


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
    """Runs ``train.py``: picks the mode (the module docstring says how), then parses, fits,
    exports.

    Args:
        args: Command-line arguments (``None`` = ``sys.argv[1:]``).

    Returns:
        The exported file: ``neural_map.pt`` (map), ``learned_scenario.yaml`` (noise),
        ``latent_map.nlat`` (latent) or ``map_index.json`` (region); ``None`` on worker
        ranks.

    Raises:
        SystemExit: 2 on bad input (one ``error:`` line on stderr), 1 when nothing was
            exported (see each mode).
    """
    argv = list(sys.argv[1:] if args is None else args)
    mode = argv[0] if argv and not argv[0].startswith("-") else config_mode(argv)
    if argv and not argv[0].startswith("-"):
        argv = argv[1:]
        if mode not in MODES:
            raise _refuse(f"train.py mode {mode!r} is unknown; the first word is one of "
                          f"{', '.join(MODES)} (or an option, for map).")
        learn = config_learn(argv)
        if learn is not None and learn != mode:
            raise _refuse(f"train.py {mode}: the config is written for `learn: {learn}`; "
                          f"run `train.py {learn} ...` (or drop the mode word).")
    return MODES[mode]().run(argv)


def region_parser() -> ArgumentParser:
    """The parser of ``train.py region`` (``--data.*``, ``--model.*``, ``--trainer.*``)."""
    from neuralmap.terrain.blockwise import NET_DEFAULTS
    from neuralmap.training.region_staging import SYNTHETIC

    p = ArgumentParser(prog="train.py region", description=RegionMode.summary,
                       exit_on_error=True)
    p.add_argument("--config", action=ActionConfigFile, help="YAML file of these options.")
    p.add_argument("--out", type=str, required=True,
                   help="Output folder (map_index.json, shards/, region.npy).")
    p.add_argument("--threads", type=int, default=1, help="torch threads per process.")
    p.add_argument("--data.path", type=str | list[str], required=True,
                   help=f".npy region, DEM files/globs (a list or one pattern), or {SYNTHETIC}.")
    p.add_argument("--data.spacing", type=float | None, default=None,
                   help="Grid spacing in metres, for a .npy without a sidecar.")
    p.add_argument("--data.region_shape", type=list[int] | None, default=None,
                   help=f"[ny, nx] of {SYNTHETIC} (default the paper's [1270, 3610]).")
    p.add_argument("--model.block_nodes", type=int | None, default=24)
    p.add_argument("--model.overlap_nodes", type=float, default=float(NET_DEFAULTS.overlap_nodes))
    p.add_argument("--model.shard_blocks", type=list[int], default=[8, 8],
                   help="[sbx, sby] blocks per shard.")
    p.add_argument("--model.steps", type=int, default=500, help="Adam steps per shard.")
    p.add_argument("--model.points_per_block", type=int, default=256)
    p.add_argument("--model.lr", type=float, default=1e-2)
    p.add_argument("--model.seed", type=int, default=0)
    p.add_argument("--trainer.devices", type=int, default=1, help="Processes per node.")
    p.add_argument("--trainer.num_nodes", type=int, default=1)
    p.add_argument("--trainer.strategy", type=str | None, default=None,
                   help="ddp_spawn (default for several devices) | ddp (script / torchrun).")
    return p


