"""Scalar input checks of the wind package: variances, scales, factors, steps.

Every check raises `NeuralMapError` naming the value, where
it was given and how to fix it.
"""

from __future__ import annotations

import math

from neuralmap.exceptions import NeuralMapError

__all__ = ["require_positive", "require_nonnegative", "require_open_unit", "require_in_range"]


def _as_float(value: object, name: str, where: str) -> float:
    try:
        out = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError) as exc:
        raise NeuralMapError(f"{where}: '{name}' must be a number, got {value!r}.") from exc
    if not math.isfinite(out):
        raise NeuralMapError(f"{where}: '{name}' must be finite, got {out!r}.")
    return out


def require_positive(value: object, name: str, where: str, hint: str = "") -> float:
    """Returns ``value`` as a float, raising unless it is finite and > 0.

    Args:
        value: The number to check (a variance, a scale, a step).
        name: Its name (config key or argument).
        where: The config or function that received it.
        hint: Extra advice appended to the message.

    Raises:
        NeuralMapError: Not a finite number > 0.
    """
    out = _as_float(value, name, where)
    if out <= 0.0:
        raise NeuralMapError(
            f"{where}: '{name}' = {out!r} must be > 0. {hint}".rstrip()
            + ("" if hint else " Give a positive value (variances, scales and steps "
               "cannot be zero or negative).")
        )
    return out


def require_nonnegative(value: object, name: str, where: str) -> float:
    """Returns ``value`` as a float, raising unless it is finite and ≥ 0."""
    out = _as_float(value, name, where)
    if out < 0.0:
        raise NeuralMapError(f"{where}: '{name}' = {out!r} must be >= 0 (use 0 to disable).")
    return out


def require_open_unit(value: object, name: str, where: str) -> float:
    """Returns ``value`` as a float, raising unless ``0 < value < 1`` (forgetting factors)."""
    out = _as_float(value, name, where)
    if not 0.0 < out < 1.0:
        raise NeuralMapError(
            f"{where}: '{name}' = {out!r} must lie in the open interval (0, 1); forgetting "
            "factors are typically 0.95-0.99."
        )
    return out


def require_in_range(value: object, name: str, where: str, low: float, high: float) -> float:
    """Returns ``value`` as a float, raising unless ``low <= value <= high``."""
    out = _as_float(value, name, where)
    if not low <= out <= high:
        raise NeuralMapError(
            f"{where}: '{name}' = {out!r} must lie in [{low!r}, {high!r}]."
        )
    return out
