"""Resuming a fit: check a checkpoint before Lightning loads it, and say how to resume.

A Lightning checkpoint (``runs/<experiment>/version_N/checkpoints/last.ckpt``) holds the
weights, optimiser and loop state. Three mistakes used to end in a raw traceback or in a
run that silently trained and exported nothing: a truncated file, an exported
``neural_map.pt`` passed as ``--ckpt_path``, and ``--trainer.max_epochs`` not above the
epochs the checkpoint has already trained. `inspect_checkpoint` turns each into a
`NeuralMapError` before any run folder is created.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import torch

from neuralmap.exceptions import NeuralMapError

#: Checkpoint written at the end of every epoch (``ModelCheckpoint(save_last=True)``).
LAST_CHECKPOINT = "last.ckpt"
#: Format tag of an exported map (``neuralmap.terrain.export``), recognised to explain it.
MAP_FORMAT = "neuralmap-terrain-map"


def completed_epochs(checkpoint: dict[str, Any]) -> int:
    """Number of training epochs a Lightning checkpoint has completed.

    ``last.ckpt`` is written at the end of an epoch, after the epoch is "processed" but
    before it counts as "completed"; a resumed run starts at the next epoch, so processed
    epochs are the ones done.
    """
    try:
        progress = checkpoint["loops"]["fit_loop"]["epoch_progress"]["current"]
        return max(int(progress["completed"]), int(progress.get("processed", 0)))
    except (KeyError, TypeError, AttributeError):
        return int(checkpoint.get("epoch", -1)) + 1


def inspect_checkpoint(path: str | Path, *, max_epochs: int | None) -> dict[str, Any]:
    """Reads a checkpoint and checks that resuming from it can train.

    Args:
        path: The ``--ckpt_path`` value.
        max_epochs: ``trainer.max_epochs`` of the new run (None or -1 = unbounded).

    Returns:
        ``{"epochs": completed epochs, "global_step": steps}``.

    Raises:
        NeuralMapError: Missing, unreadable or truncated file; an exported map or another
            torch file instead of a Lightning checkpoint; ``max_epochs`` not above the
            checkpoint's completed epochs.
    """
    path = Path(path)
    where = f"--ckpt_path {path}"
    if not path.is_file():
        raise NeuralMapError(
            f"{where}: no such checkpoint file. Checkpoints are written to "
            "runs/<experiment>/version_N/checkpoints/ (last.ckpt, best-*.ckpt)."
        )
    try:
        # The same full load Lightning performs on resume (optimiser and loop state).
        checkpoint = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as exc:  # noqa: BLE001 - any failure means "not a usable checkpoint"
        raise NeuralMapError(
            f"{where}: the file could not be read as a checkpoint ({type(exc).__name__}: "
            f"{str(exc).splitlines()[0] if str(exc) else ''}). It is truncated (an interrupted "
            "copy or a full disk) or not a checkpoint; use another one, e.g. "
            "runs/<experiment>/version_N/checkpoints/last.ckpt."
        ) from None
    if isinstance(checkpoint, dict) and checkpoint.get("format") == MAP_FORMAT:
        raise NeuralMapError(
            f"{where} is an exported neural map (neural_map.pt), which holds the weights but "
            "no optimiser or training state, so a run cannot resume from it. Resume from "
            "the checkpoint beside it: <run folder>/checkpoints/last.ckpt."
        )
    if not isinstance(checkpoint, dict) or "state_dict" not in checkpoint or (
        "loops" not in checkpoint and "epoch" not in checkpoint
    ):
        raise NeuralMapError(
            f"{where} is not a Lightning training checkpoint (no state_dict and loop state). "
            "Use runs/<experiment>/version_N/checkpoints/last.ckpt."
        )
    epochs = completed_epochs(checkpoint)
    if max_epochs is not None and max_epochs >= 0 and epochs >= max_epochs:
        raise NeuralMapError(
            f"{where} has already trained {epochs} epoch(s), so --trainer.max_epochs "
            f"{max_epochs} leaves nothing to train and no map would be exported. "
            f"max_epochs counts from the start of the first run: pass more than {epochs} "
            f"(e.g. --trainer.max_epochs {epochs + max(max_epochs, 1)})."
        )
    return {"epochs": epochs, "global_step": int(checkpoint.get("global_step", 0))}


def resume_command(run_dir: Path) -> str | None:
    """The command that resumes the run in ``run_dir``, or None without a checkpoint yet."""
    last = run_dir / "checkpoints" / LAST_CHECKPOINT
    if not last.is_file():
        return None
    config = run_dir / "config.yaml"
    config_part = f"--config {config} " if config.is_file() else ""
    return f"python train.py {config_part}--ckpt_path {last}"


__all__ = ["LAST_CHECKPOINT", "completed_epochs", "inspect_checkpoint", "resume_command"]
