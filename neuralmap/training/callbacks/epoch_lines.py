"""One plain line per epoch instead of the progress bar when stdout is not a terminal."""

from __future__ import annotations

import sys
import time
from typing import IO, Any

import lightning.pytorch as pl

from neuralmap.progress import is_terminal, progress_line
from neuralmap.training.callbacks.heldout_checkpoint import in_refit


class EpochLines(pl.Callback):
    """Replaces the trainer's progress bar by one line per epoch in a log file.

    A progress bar redirected to a file writes a carriage-return update per step (megabytes
    for a few minutes of training). When the trainer has a progress bar and stdout is not
    a terminal, this callback disables the bar at the start of the fit and prints, after
    each training epoch (validation included), one line: epoch count, rate, elapsed time,
    time left (epochs left × mean epoch time), training steps per second and the
    progress-bar metrics (in a refit epoch ``refit/*``, the in-sample error, and not the
    last held-out epoch's ``val/*``). On a terminal, or with ``enable_progress_bar: false``, it does
    nothing. Only rank 0 prints.

    Args:
        stream: Where lines go (default ``sys.stdout``).
        force: True = print lines even on a terminal (tests); None = decide by the stream.
    """

    def __init__(self, stream: IO[str] | None = None, force: bool | None = None) -> None:
        self.stream = stream
        self.force = force
        self.active = False
        self._start = 0.0
        self._start_epoch = 0
        self._start_step = 0

    def on_fit_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        bar = trainer.progress_bar_callback
        plain = (not is_terminal(self.stream)) if self.force is None else self.force
        self.active = bool(bar is not None and plain and trainer.is_global_zero)
        if bar is not None and plain:
            bar.disable()
        self._start = time.perf_counter()
        self._start_epoch = trainer.current_epoch
        self._start_step = trainer.global_step

    def on_train_epoch_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        if not self.active:
            return
        elapsed = time.perf_counter() - self._start
        done = trainer.current_epoch + 1
        total = trainer.max_epochs if trainer.max_epochs and trainer.max_epochs > 0 else None
        parts = []
        if elapsed > 0:
            parts.append(f"{(trainer.global_step - self._start_step) / elapsed:.3g} step/s")
        refit = in_refit(trainer)  # val/* are then the last held-out epoch's: not shown
        parts += [f"{key} {_number(value)}"
                  for key, value in sorted(trainer.progress_bar_metrics.items())
                  if not (refit and key.startswith("val/"))]
        line = progress_line("train", done, total, elapsed, "epoch", ", ".join(parts),
                             done_in_elapsed=done - self._start_epoch)
        print(line, file=sys.stdout if self.stream is None else self.stream, flush=True)


def _number(value: Any) -> str:
    """A metric as a short number."""
    try:
        return f"{float(value):.4g}"
    except (TypeError, ValueError):
        return str(value)
