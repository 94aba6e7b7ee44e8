"""Validation of a 1-D error sequence before identification."""

from __future__ import annotations

from typing import Any

import numpy as np

from neuralmap.exceptions import NeuralMapError


def as_sequence(sequence: Any, *, where: str, min_length: int = 2, why: str = "") -> np.ndarray:
    """Converts an error sequence to a finite, non-constant float64 array, or raises.

    Args:
        sequence: ``(n,)`` array-like or tensor of error samples in time (or grid) order.
        where: The calling function, for the message.
        min_length: Smallest accepted length ``n``.
        why: What the length is needed for (e.g. ``"ARMA(2, 2) and its F-test"``).

    Returns:
        ``(n,)`` float64 NumPy array (a copy).
    """
    if hasattr(sequence, "detach"):
        sequence = sequence.detach().cpu().numpy()
    try:
        x = np.array(sequence, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise NeuralMapError(
            f"{where}: the error sequence must be numeric, got {type(sequence).__name__}."
        ) from exc
    if x.ndim != 1:
        raise NeuralMapError(
            f"{where}: the error sequence must be 1-D (n samples), got shape {x.shape}. "
            "Identify one sequence at a time (e.g. loop over rows, or flatten a repeat survey "
            "in measurement order)."
        )
    if x.size < min_length:
        reason = f" for {why}" if why else ""
        raise NeuralMapError(
            f"{where}: the error sequence has {x.size} samples; at least {min_length} are "
            f"needed{reason}. Pass a longer sequence or lower the model order."
        )
    bad = np.flatnonzero(~np.isfinite(x))
    if bad.size:
        raise NeuralMapError(
            f"{where}: the error sequence has {bad.size} non-finite value(s) (NaN/inf), the "
            f"first at index {int(bad[0])}. Remove or interpolate them (e.g. DEM voids) first."
        )
    scale = max(1.0, float(np.max(np.abs(x))))
    if float(np.ptp(x)) <= 1e-12 * scale:
        raise NeuralMapError(
            f"{where}: the error sequence is constant ({float(x[0]):g} everywhere); it has no "
            "correlation structure to identify. Check that the errors were computed (e.g. "
            "measured minus truth, not truth minus truth)."
        )
    return x
