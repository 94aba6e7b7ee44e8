"""``best-*.ckpt`` chosen on held-out epochs only; ``last.ckpt`` at every epoch."""

from __future__ import annotations

from typing import Any

import lightning.pytorch as pl
from lightning.pytorch.callbacks import ModelCheckpoint

__all__ = ["HeldOutCheckpoint", "in_refit"]


def in_refit(trainer: pl.Trainer) -> bool:
    """Whether the trainer's current epoch belongs to the data module's refit phase
    (``data.refit_epochs``: the validation nodes are trained on)."""
    check = getattr(getattr(trainer, "datamodule", None), "in_refit", None)
    return bool(check is not None and check(int(trainer.current_epoch)))


class HeldOutCheckpoint(ModelCheckpoint):
    """A `ModelCheckpoint` that ranks only epochs whose
    validation nodes are still held out.

    In the refit phase (the last ``data.refit_epochs`` epochs) every valid node is trained
    on, so the module logs its node error as ``refit/rmse_m`` (in-sample) and no
    ``val/rmse_m``; ranking those epochs would pick a checkpoint by an error on its own
    training data. Here ``best-*.ckpt`` is the best held-out epoch (epochs before the
    refit) and ``last.ckpt`` is written at every epoch, refit included.

    Args:
        **kwargs: As `ModelCheckpoint` (monitor the
            held-out metric, ``"val/rmse_m"``).
    """

    def _save_topk_checkpoint(self, trainer: pl.Trainer, monitor_candidates: dict[str, Any]
                              ) -> None:
        if in_refit(trainer):
            return  # no held-out metric in this epoch: nothing to rank
        super()._save_topk_checkpoint(trainer, monitor_candidates)
