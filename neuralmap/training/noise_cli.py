"""``train.py`` in noise-learning mode: ``python train.py --config configs/learn_noise.yaml``.

A config (or the command line) with ``learn: noise`` trains
:class:`~neuralmap.training.noise_module.NoiseLearningModule` on
:class:`~neuralmap.training.flight_datamodule.FlightDataModule` with the same CLI habits as
the map fit (``--trainer.*``, ``--experiment``, ``--runs_dir``, ``--threads``, TensorBoard
in ``runs/<experiment>/version_N``). The last stdout line is the learned scenario YAML,
ready for ``python evaluate.py --scenario <that file>``.
"""

from __future__ import annotations

import sys
import warnings
from pathlib import Path
from typing import Any

from lightning.pytorch.callbacks import ModelCheckpoint
from lightning.pytorch.cli import LightningArgumentParser

from neuralmap.exceptions import NeuralMapError
from neuralmap.io import load_yaml
from neuralmap.training.callbacks.epoch_lines import EpochLines

__all__ = ["learn_mode", "main_noise"]

#: Values of the ``learn:`` switch.
LEARN_MODES = ("map", "noise", "latent")


def learn_mode(args: list[str] | None) -> str:
    """``"noise"`` / ``"latent"`` when ``--learn X`` or a ``--config`` file with ``learn: X``."""
    argv = list(sys.argv[1:] if args is None else args)
    mode = "map"
    for i, arg in enumerate(argv):
        value = None
        if arg in ("--config", "-c") and i + 1 < len(argv):
            try:
                data = load_yaml(Path(argv[i + 1]).read_text(encoding="utf-8"))
            except (OSError, ValueError):
                continue  # the regular CLI reports unreadable configs
            if isinstance(data, dict) and "learn" in data:
                value = data["learn"]
        elif arg == "--learn" and i + 1 < len(argv):
            value = argv[i + 1]
        elif arg.startswith("--learn="):
            value = arg.split("=", 1)[1]
        if value is not None:
            if value not in LEARN_MODES:
                raise NeuralMapError(f"learn: must be one of {LEARN_MODES}, got {value!r}.")
            mode = str(value)
    return mode


def _noise_cli_class() -> Any:
    from neuralmap.training.cli import NeuralMapCLI

    class NoiseCLI(NeuralMapCLI):
        """NeuralMapCLI with ``--learn`` (always ``noise`` here)."""

        def add_arguments_to_parser(self, parser: LightningArgumentParser) -> None:
            super().add_arguments_to_parser(parser)
            parser.add_argument("--learn", type=str, default="noise",
                                help="What train.py learns: map (default) or noise.")

    return NoiseCLI


def main_noise(args: list[str] | None = None) -> Path | None:
    """Parses, fits, exports; returns the learned scenario YAML path (also printed last).

    Raises:
        SystemExit: 2 on bad input (message on stderr), 1 when nothing was learned.
    """
    from neuralmap.training.cli import EXIT_BAD_INPUT, EXIT_NO_MAP, remove_orphan_run_dir
    from neuralmap.training.flight_datamodule import FlightDataModule
    from neuralmap.training.noise_module import NoiseLearningModule

    checkpoint = ModelCheckpoint(monitor="val/nll", mode="min", save_last=True, save_top_k=1,
                                 filename="best-epoch{epoch:04d}", auto_insert_metric_name=False)
    cli = None
    try:
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message="LightningCLI's args parameter")
            cli = _noise_cli_class()(
                NoiseLearningModule, FlightDataModule, run=False, args=args,
                seed_everything_default=0, auto_configure_optimizers=False,
                save_config_kwargs={"overwrite": True},
                parser_kwargs={"description": "Learn the TAN filter's Q and R from flights."},
                trainer_defaults={"callbacks": [checkpoint, EpochLines()]},
            )
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
