"""Stop training once the validation RMSE is below a target (SEEDS 004: stop when e < rho)."""

from __future__ import annotations

import math

import lightning.pytorch as pl
from lightning.pytorch.utilities.rank_zero import rank_zero_info


class TargetRmseStopping(pl.Callback):
    """Stops the fit at the end of the first validation whose RMSE is below ``target_m``.

    SEEDS 004 trains each BP net until the summed squared error ``e`` falls below a
    threshold ``rho``; here the threshold is on the validation RMSE in metres, which does
    not depend on the number of nodes. Every DDP rank sees the same all-reduced metric, so
    all ranks stop together. During a refit phase (``data.refit_epochs``) the validation
    nodes are trained on, so the rule is not applied there.

    Args:
        target_m: RMSE threshold in metres (> 0).
        monitor: Logged metric to compare.

    Attributes:
        stopped_epoch: Epoch at which the target was reached, or ``None``.
    """

    def __init__(self, target_m: float, monitor: str = "val/rmse_m") -> None:
        if not (math.isfinite(target_m) and target_m > 0):
            raise ValueError(f"target_m must be finite and > 0, got {target_m}")
        self.target_m = float(target_m)
        self.monitor = monitor
        self.stopped_epoch: int | None = None

    @property
    def state_key(self) -> str:
        return f"TargetRmseStopping[{self.monitor}]"

    def on_validation_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        if trainer.sanity_checking or self.monitor not in trainer.callback_metrics:
            return
        in_refit = getattr(getattr(trainer, "datamodule", None), "in_refit", None)
        if in_refit is not None and in_refit(int(trainer.current_epoch)):
            return  # the held-out nodes are being trained on: no longer a held-out metric
        value = float(trainer.callback_metrics[self.monitor])
        if value < self.target_m and self.stopped_epoch is None:
            self.stopped_epoch = trainer.current_epoch
            trainer.should_stop = True
            rank_zero_info(
                f"{self.monitor} = {value:.3f} m < target {self.target_m:.3f} m at epoch "
                f"{trainer.current_epoch}: stopping (SEEDS 004, e < rho)"
            )
