"""Wind-estimation figures (SEEDS 002, figures 2–5): estimates against truth, error bands.

Every function builds a `matplotlib.figure.Figure` without pyplot.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np
from matplotlib.figure import Figure

from neuralmap.exceptions import NeuralMapError

__all__ = ["plot_wind_estimates", "plot_bands"]


def _series(values: object, n: int, what: str) -> np.ndarray:
    array = np.asarray(values, dtype=np.float64).reshape(-1)
    if array.shape != (n,):
        raise NeuralMapError(f"{what}: expected {n} values (one per sample), got {array.size}.")
    return array


def plot_wind_estimates(
    t: object,
    truth: object,
    measured: object,
    estimates: Mapping[str, object],
    *,
    outlier: object | None = None,
    window: tuple[float, float] | None = None,
    ylabel: str = "east wind [m/s]",
    title: str = "Wind estimates",
) -> Figure:
    """One run's wind component: truth, measurement and every filter's estimate.

    Args:
        t: ``(T,)`` time (s).
        truth: ``(T,)`` true wind component.
        measured: ``(T,)`` measured wind component (grey dots).
        estimates: Filter name -> ``(T,)`` estimate.
        outlier: ``(T,)`` bool, samples to shade as outliers.
        window: ``(t0, t1)`` zoom; the y range follows the truth and estimates inside it,
            clipped to ±4 × the truth's spread so a diverged filter does not flatten
            the others.
        ylabel: Y label.
        title: Title.

    Returns:
        The figure.
    """
    time = np.asarray(t, dtype=np.float64).reshape(-1)
    n = time.size
    true = _series(truth, n, "truth")
    meas = _series(measured, n, "measured")
    fig = Figure(figsize=(9.0, 4.6))
    ax = fig.add_subplot(1, 1, 1)
    sel = np.ones(n, dtype=bool) if window is None else (time >= window[0]) & (time <= window[1])
    if outlier is not None:
        mask = np.asarray(outlier, dtype=bool).reshape(-1)
        if mask.shape != (n,):
            raise NeuralMapError(f"outlier: expected {n} flags, got {mask.size}.")
        for k in np.flatnonzero(mask & sel):
            ax.axvspan(time[k] - 0.5 * (time[1] - time[0]), time[k] + 0.5 * (time[1] - time[0]),
                       color="tab:red", alpha=0.08, lw=0)
    ax.plot(time[sel], meas[sel], ".", color="0.6", ms=2.5, label="measured")
    ax.plot(time[sel], true[sel], "k-", lw=1.6, label="truth")
    for name, values in estimates.items():
        ax.plot(time[sel], _series(values, n, name)[sel], lw=1.1, label=name)
    centre = float(np.median(true[sel]))
    spread = float(np.ptp(true[sel])) + 2.0
    ax.set_ylim(centre - 4.0 * spread, centre + 4.0 * spread)
    ax.set_xlabel("time [s]")
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.grid(alpha=0.3)
    ax.legend(loc="best", fontsize=8, ncol=2)
    fig.tight_layout()
    return fig


def plot_bands(
    t: object,
    bands: Mapping[str, tuple[object, object, object]],
    *,
    ylabel: str,
    title: str,
    log: bool = False,
) -> Figure:
    """Curves with shaded bands (e.g. mean and 10–90 % over Monte Carlo runs).

    Args:
        t: ``(T,)`` time (s).
        bands: Name -> ``(centre, low, high)``, each ``(T,)``.
        ylabel: Y label.
        title: Title.
        log: Logarithmic y axis (non-positive values are left out).

    Returns:
        The figure.
    """
    time = np.asarray(t, dtype=np.float64).reshape(-1)
    n = time.size
    fig = Figure(figsize=(9.0, 4.6))
    ax = fig.add_subplot(1, 1, 1)
    for name, (centre, low, high) in bands.items():
        c, lo, hi = (_series(v, n, name) for v in (centre, low, high))
        if log:  # zero errors (an exact start) have no place on a log axis
            c, lo, hi = (np.where(v > 0, v, np.nan) for v in (c, lo, hi))
        (line,) = ax.plot(time, c, lw=1.4, label=name)
        ax.fill_between(time, lo, hi, color=line.get_color(), alpha=0.15, lw=0)
    if log:
        ax.set_yscale("log")
    ax.set_xlabel("time [s]")
    ax.set_ylabel(ylabel)
    ax.set_title(title)
    ax.grid(alpha=0.3, which="both")
    ax.legend(loc="best", fontsize=8)
    fig.tight_layout()
    return fig
