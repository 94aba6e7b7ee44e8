"""``train.py latent``: latent-grid maps, ``python train.py latent --config configs/latent_map.yaml``.

It trains
`LatentFitModule` on
`LatentDataModule` with the same CLI habits as
the blockwise map fit (``--trainer.*``, ``--experiment``, ``--runs_dir``, ``--threads``,
``--ckpt_path``, TensorBoard in ``runs/<experiment>/version_N``). The last stdout line is
the exported bitstream ``latent_map.nlat``, which ``load_map`` reads.
"""

from __future__ import annotations

import os
import sys
import warnings
from pathlib import Path
from typing import Any

from lightning.pytorch.callbacks import ModelCheckpoint
from lightning.pytorch.cli import LightningArgumentParser

from neuralmap.exceptions import NeuralMapError
from neuralmap.training.quiet import quiet_lightning

__all__ = ["main_latent"]


def _latent_cli_class() -> Any:
    from neuralmap.training.cli_base import NeuralMapCLI

    class LatentCLI(NeuralMapCLI):
        """NeuralMapCLI with ``--learn`` (always ``latent`` here)."""

        def add_arguments_to_parser(self, parser: LightningArgumentParser) -> None:
            super().add_arguments_to_parser(parser)
            parser.add_argument("--learn", type=str, default="latent",
                                help="What train.py learns: map (default), noise or latent.")

    return LatentCLI


def main_latent(args: list[str] | None = None) -> Path | None:
    """Parses, fits, exports; returns the bitstream path (also printed last).

    Raises:
        SystemExit: 2 on bad input (message on stderr), 1 when no map was exported.
    """
    from neuralmap.training.callbacks.epoch_lines import EpochLines
    from neuralmap.training.callbacks.latent_report import LatentMapReport
    from neuralmap.training.cli_base import EXIT_BAD_INPUT, EXIT_NO_MAP
    from neuralmap.training.latent_datamodule import LatentDataModule
    from neuralmap.training.latent_module import LatentFitModule

    report = LatentMapReport()
    checkpoint = ModelCheckpoint(save_last=True, save_top_k=0)
    try:
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", message="LightningCLI's args parameter")
            cli = _latent_cli_class()(
                LatentFitModule, LatentDataModule, run=False, args=args,
                seed_everything_default=0, auto_configure_optimizers=False,
                save_config_kwargs={"overwrite": True},
                parser_kwargs={"description": "Fit a latent-grid neural map (entropy-coded "
                                              "latents + tiny decoder) to a DEM tile."},
                trainer_defaults={"callbacks": [checkpoint, report, EpochLines()]},
            )
        with quiet_lightning():  # Lightning's tips and its torch deprecation warning
            cli.trainer.fit(cli.model, datamodule=cli.datamodule,
                            ckpt_path=cli.config.get("ckpt_path"))
    except NeuralMapError as error:
        sys.stdout.flush()
        print(f"error: {error}", file=sys.stderr, flush=True)
        raise SystemExit(EXIT_BAD_INPUT) from None
    if cli.trainer.is_global_zero:
        if report.map_path is None:
            print("error: the run ended without exporting a latent map (no training step "
                  "completed). Check --trainer.max_epochs / max_steps.", file=sys.stderr,
                  flush=True)
            raise SystemExit(EXIT_NO_MAP)
        sys.stderr.flush()
        print(os.fspath(report.map_path), flush=True)
    return report.map_path
