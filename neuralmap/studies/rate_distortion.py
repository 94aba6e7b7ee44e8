"""Rate-distortion fronts: Pareto fronts, bytes at equal error, and the Bjøntegaard delta rate.

A map format is a curve of stored bytes against error. Comparisons between two formats are
made on their fronts (the points no other point of the same format beats in both bytes and
error):

* :func:`bytes_at_error`: the bytes a front needs for a given error, interpolated linearly
  in ``log(bytes)`` over ``log(error)`` between its points (None outside the front's range);
* :func:`bd_rate`: the Bjøntegaard delta rate (G. Bjøntegaard, VCEG-M33, 2001): the mean
  relative difference in bytes of curve B against curve A over their common error range,
  ``exp(mean(log R_B - log R_A)) - 1`` with the mean taken uniformly in ``log(error)``
  (the distortion axis; ``-20 log10(error)`` is a PSNR up to a constant, so this is the
  usual BD-rate with PSNR). The log-rates are interpolated piecewise linearly (robust with
  few points, unlike the original cubic fit) on a fine grid of the common range. Negative
  values: B needs fewer bytes than A at equal error.
"""

from __future__ import annotations

import math

import numpy as np

__all__ = ["bd_rate", "bytes_at_error", "pareto_front"]


def pareto_front(sizes: list[float], errors: list[float | None]) -> list[int]:
    """Indices of the rate-distortion front: no other point is smaller and more accurate.

    Args:
        sizes: Stored bytes per point.
        errors: Error per point (NaN / None points are skipped).

    Returns:
        Indices on the front, by increasing size (and decreasing error).
    """
    points = [
        (s, e, i) for i, (s, e) in enumerate(zip(sizes, errors, strict=True))
        if e is not None and math.isfinite(e)
    ]
    points.sort(key=lambda p: (p[0], p[1]))
    front: list[int] = []
    best = math.inf
    for _, err, index in points:
        if err < best:
            front.append(index)
            best = err
    return front


def _curve(sizes: list[float], errors: list[float]) -> tuple[np.ndarray, np.ndarray]:
    """``(log error, log bytes)`` of the front, by increasing log error; errors > 0 only."""
    idx = pareto_front(sizes, errors)
    pts = [(math.log(errors[i]), math.log(sizes[i])) for i in idx if errors[i] > 0]
    pts.sort()
    if not pts:
        return np.zeros(0), np.zeros(0)
    log_e, log_r = (np.asarray(v, dtype=np.float64) for v in zip(*pts, strict=True))
    return log_e, log_r


def bytes_at_error(sizes: list[float], errors: list[float], error: float) -> float | None:
    """Bytes the front of ``(sizes, errors)`` needs for ``error`` (log-log interpolation).

    Returns:
        The interpolated bytes; None when ``error`` is outside the front's error range
        (no extrapolation) or the front is empty.
    """
    log_e, log_r = _curve(sizes, errors)
    if log_e.size == 0 or not (error > 0):
        return None
    x = math.log(error)
    if x < log_e[0] - 1e-12 or x > log_e[-1] + 1e-12:
        return None
    return float(math.exp(np.interp(x, log_e, log_r)))


def bd_rate(
    sizes_a: list[float], errors_a: list[float], sizes_b: list[float], errors_b: list[float],
    *, n_grid: int = 256,
) -> float | None:
    """Bjøntegaard delta rate of curve B against curve A (see the module docstring).

    Args:
        sizes_a: Bytes of the anchor's points (e.g. JPEG 2000).
        errors_a: Their errors (> 0; e.g. node RMSE).
        sizes_b: Bytes of the tested format's points.
        errors_b: Their errors.
        n_grid: Points of the integration grid over the common log-error range.

    Returns:
        The BD-rate as a fraction (``-0.3`` = B needs 30 % fewer bytes); None when the two
        fronts do not overlap in error (or one has fewer than 2 points).
    """
    ea, ra = _curve(sizes_a, errors_a)
    eb, rb = _curve(sizes_b, errors_b)
    if ea.size < 2 or eb.size < 2:
        return None
    lo, hi = max(ea[0], eb[0]), min(ea[-1], eb[-1])
    if not hi > lo:
        return None
    grid = np.linspace(lo, hi, int(n_grid))
    diff = np.interp(grid, eb, rb) - np.interp(grid, ea, ra)
    return float(math.expm1(float(np.trapezoid(diff, grid) / (hi - lo))))
