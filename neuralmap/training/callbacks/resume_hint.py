"""On Ctrl-C, say which checkpoint resumes the run and the command that does it."""

from __future__ import annotations

import sys
from pathlib import Path

import lightning.pytorch as pl

from neuralmap.training.resume import resume_command


class ResumeHint(pl.Callback):
    """Prints how to resume after a keyboard interrupt (Lightning then exits with code 1).

    The run folder is the checkpoint callback's parent folder; ``last.ckpt`` there is the
    end of the last completed epoch. Without one (interrupted in the first epoch) it says
    that nothing can be resumed.

    Attributes:
        message: The text printed (for tests), or None before an interrupt.
    """

    def __init__(self) -> None:
        self.message: str | None = None

    def on_exception(
        self, trainer: pl.Trainer, pl_module: pl.LightningModule, exception: BaseException
    ) -> None:
        if not isinstance(exception, KeyboardInterrupt) or not trainer.is_global_zero:
            return
        checkpoint = trainer.checkpoint_callback
        dirpath = getattr(checkpoint, "dirpath", None)
        run_dir = Path(dirpath).parent if dirpath else Path(trainer.default_root_dir)
        command = resume_command(run_dir)
        epoch = int(trainer.current_epoch)
        if command is None:
            self.message = (
                f"interrupted in epoch {epoch} before the first checkpoint was written; nothing "
                f"to resume from in {run_dir}: start the run again."
            )
        else:
            self.message = (
                f"interrupted in epoch {epoch}; no map was exported. The last completed epoch "
                f"is saved in {run_dir / 'checkpoints' / 'last.ckpt'}. Resume with:\n  {command}"
            )
        print(self.message, file=sys.stderr, flush=True)
