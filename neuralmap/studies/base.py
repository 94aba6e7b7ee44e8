"""What every study shares: the base configuration and its checks."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.io import check_experiment_name

__all__ = ["StudyConfig", "check_device", "torch_dtype"]


@dataclass
class StudyConfig:
    """Options every study has (a study's own config dataclass subclasses this).

    Attributes:
        study: Which study runs (the ``study:`` key of a config; see
            `neuralmap.studies.registry`).
        experiment: Output folder name: results go to
            ``<runs_dir>/<experiment>/version_<N>/``.
        runs_dir: Root of the run folders.
        seed: Seed of every random draw of the study (default 0, fixed, printed at the
            start, so a rerun reproduces the report; ``None`` = the scenario's seed).
        device: Torch device (``cpu``, ``cuda``, ``cuda:1``...).
        dtype: Filter precision.
        threads: ``torch.set_num_threads`` for the run (restored afterwards); ``None``
            keeps torch's setting (all physical cores). Default 1, measured: on the
            2-core machine with a second job running, the TAN study's R derivation took
            95 s on one thread and 1212 s on two; the studies' batched filter steps
            are too small to gain from a second thread (README, "Threads").
        progress: Show progress bars.
        tensorboard: Write TensorBoard event files.
    """

    study: str = "tan"
    experiment: str = "evaluate"
    runs_dir: str = "runs"
    seed: int | None = 0
    device: str = "cpu"
    dtype: Literal["float64", "float32"] = "float64"
    threads: int | None = 1
    progress: bool = True
    tensorboard: bool = True

    def validate(self) -> None:
        """Checks the shared options; subclasses call ``super().validate()`` first.

        Raises:
            NeuralMapError: A value out of range, naming the option and the fix.
        """
        check_experiment_name(self.experiment)
        if self.seed is not None and self.seed < 0:
            raise NeuralMapError(f"--seed must be >= 0 (or null), got {self.seed}.")
        if self.threads is not None and self.threads < 1:
            raise NeuralMapError(f"--threads must be >= 1 (or null), got {self.threads}.")
        if self.dtype not in ("float64", "float32"):
            raise NeuralMapError(f"--dtype must be float64 or float32, got {self.dtype!r}.")
        check_device(self.device)

    @property
    def torch_dtype(self) -> torch.dtype:
        """The torch dtype of `dtype`."""
        return torch_dtype(self.dtype)

    @property
    def torch_device(self) -> torch.device:
        """The torch device of `device` (checked)."""
        return check_device(self.device)


def torch_dtype(name: str) -> torch.dtype:
    """``"float64"``/``"float32"`` to the torch dtype."""
    return {"float64": torch.float64, "float32": torch.float32}[name]


def check_device(device: str) -> torch.device:
    """The torch device named ``device``; a clear error when it is unknown or absent.

    Raises:
        NeuralMapError: Not a torch device, or CUDA asked for on a machine without it.
    """
    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError) as exc:
        raise NeuralMapError(
            f"--device {device!r} is not a torch device; use cpu, cuda or cuda:<i>."
        ) from exc
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise NeuralMapError(
            f"--device {device}: CUDA is not available on this machine; use --device cpu."
        )
    return dev
