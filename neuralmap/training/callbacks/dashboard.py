"""TensorBoard custom-scalars layout: the dashboard opens with the fit's curves grouped."""

from __future__ import annotations

import lightning.pytorch as pl
from lightning.pytorch.loggers import TensorBoardLogger
from lightning.pytorch.utilities.rank_zero import rank_zero_only

#: Custom-scalars layout (``SummaryWriter.add_custom_scalars``): category -> chart ->
#: ``["Multiline", [tags]]``.
SCALAR_LAYOUT: dict[str, dict[str, list]] = {
    "loss": {
        "training loss (normalised MSE)": ["Multiline", ["train/loss"]],
    },
    "accuracy": {
        "RMSE (m)": ["Multiline", ["val/rmse_m", "final/rmse_m"]],
        "max |error| (m)": ["Multiline", ["val/max_abs_m", "final/max_abs_m"]],
        "mean error (m)": ["Multiline", ["val/mean_m", "final/mean_m"]],
    },
    "slope": {
        "slope RMSE vs bicubic DEM (m/m)": ["Multiline", ["val/slope_rmse", "final/slope_rmse"]],
    },
    "lr": {
        "learning rate": ["Multiline", ["train/lr"]],
    },
}


class DashboardLayout(pl.Callback):
    """Writes `SCALAR_LAYOUT` to every TensorBoard logger at the start of the fit."""

    @rank_zero_only
    def on_fit_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        for logger in trainer.loggers:
            if isinstance(logger, TensorBoardLogger):
                logger.experiment.add_custom_scalars(SCALAR_LAYOUT)
