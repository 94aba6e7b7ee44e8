"""Input validation shared by the linearisation methods."""

from __future__ import annotations

import math

import torch

from neuralmap.exceptions import NeuralMapError


def check_points(xy: torch.Tensor, who: str) -> torch.Tensor:
    """Checks linearisation points and returns them as a floating tensor.

    Args:
        xy: ``(N, 2)`` east/north metres.
        who: Name of the calling linearizer, for the message.

    Returns:
        ``xy`` (non-floating input is converted to float64).

    Raises:
        NeuralMapError: Not a tensor of shape ``(N, 2)``.
    """
    if not isinstance(xy, torch.Tensor) or xy.ndim != 2 or xy.shape[1] != 2:
        shape = tuple(xy.shape) if isinstance(xy, torch.Tensor) else type(xy).__name__
        raise NeuralMapError(
            f"{who}: xy must be a tensor of shape (N, 2) (east, north metres), got {shape}. "
            "Flatten leading dimensions with xy.reshape(-1, 2)."
        )
    if not xy.is_floating_point():
        xy = xy.to(torch.float64)
    return xy


def check_pos_cov(pos_cov: torch.Tensor | None, n: int, who: str) -> torch.Tensor:
    """Checks the horizontal position covariance needed by covariance-adaptive methods.

    Args:
        pos_cov: ``(N, 2, 2)`` covariance in m^2.
        n: Expected batch size ``N``.
        who: Name of the calling linearizer, for the message.

    Returns:
        ``pos_cov``.

    Raises:
        NeuralMapError: Missing, or not of shape ``(N, 2, 2)``.
    """
    if pos_cov is None:
        raise NeuralMapError(
            f"{who}: the adaptive window needs the horizontal position covariance; call "
            "linearizer(xy, pos_cov) with pos_cov of shape (N, 2, 2) (the filter's P[:, :2, :2]) "
            "or use a fixed sigma."
        )
    if not isinstance(pos_cov, torch.Tensor) or tuple(pos_cov.shape) != (n, 2, 2):
        shape = tuple(pos_cov.shape) if isinstance(pos_cov, torch.Tensor) else type(pos_cov)
        raise NeuralMapError(
            f"{who}: pos_cov must have shape ({n}, 2, 2) to match xy ({n}, 2), got {shape}."
        )
    return pos_cov


def check_nonnegative(value: float, name: str, who: str) -> float:
    """Checks a finite, non-negative scalar (a variance or a length)."""
    try:
        value = float(value)
    except (TypeError, ValueError):
        raise NeuralMapError(f"{who}: {name} must be a number, got {value!r}.") from None
    if not math.isfinite(value) or value < 0.0:
        raise NeuralMapError(f"{who}: {name} must be finite and >= 0, got {value}.")
    return value
