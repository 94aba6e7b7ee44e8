"""Lightning training of neural terrain maps: data module, module, callbacks and the CLI."""

from neuralmap.training.datamodule import DemDataModule
from neuralmap.training.evaluation import FitEvaluation, evaluate_fit
from neuralmap.training.module import TerrainFitModule

__all__ = ["DemDataModule", "FitEvaluation", "TerrainFitModule", "evaluate_fit", "main"]


def main(args: list[str] | None = None) -> object:
    """Entry point of ``train.py`` (see `neuralmap.training.cli.main`)."""
    from neuralmap.training.cli import main as cli_main

    return cli_main(args)
