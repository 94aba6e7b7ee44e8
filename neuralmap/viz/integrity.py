"""The Stanford diagram: position error against protection level, every epoch of a flight.

The integrity picture of GNSS augmentation (the Stanford GPS group's diagram of WAAS
performance): a 2-D histogram of (HPL, error) over all epochs, with the diagonal error =
HPL and the alert limit splitting it into four regions — normal operation (error < HPL ≤
AL), misleading information (HPL < error, HPL ≤ AL), hazardously misleading (error > AL ≥
HPL) and unavailable (HPL > AL).
"""

from __future__ import annotations

from typing import Any

import numpy as np

__all__ = ["plot_stanford"]


def plot_stanford(error_m: np.ndarray, hpl_m: np.ndarray, *, alert_limit_m: float,
                  title: str = "", risk: float | None = None) -> Any:
    """A Stanford diagram of the epochs ``(error_m, hpl_m)`` (flattened, finite ones).

    Args:
        error_m: Horizontal errors, m (any shape).
        hpl_m: Horizontal protection levels, m (same shape).
        alert_limit_m: Horizontal alert limit, m.
        title: Figure title.
        risk: The integrity risk the HPL was computed at (in the axis label).

    Returns:
        A matplotlib figure (log-log axes; epochs per bin on a log colour scale; each
        region's epoch count in its corner).
    """
    from matplotlib.colors import LogNorm
    from matplotlib.figure import Figure

    err = np.asarray(error_m, dtype=float).ravel()
    hpl = np.asarray(hpl_m, dtype=float).ravel()
    keep = np.isfinite(err) & np.isfinite(hpl) & (err > 0) & (hpl > 0)
    err, hpl = err[keep], hpl[keep]
    fig = Figure(figsize=(6.4, 5.4), layout="constrained")
    ax = fig.add_subplot()
    if err.size == 0:
        ax.text(0.5, 0.5, "no scored epochs", ha="center", va="center", transform=ax.transAxes)
        return fig
    lo = max(min(err.min(), hpl.min()) * 0.8, 1e-2)
    hi = max(err.max(), hpl.max(), alert_limit_m) * 1.25
    bins = np.geomspace(lo, hi, 90)
    counts, xe, ye = np.histogram2d(hpl, err, bins=[bins, bins])
    mesh = ax.pcolormesh(xe, ye, np.ma.masked_equal(counts.T, 0), norm=LogNorm(),
                         cmap="viridis", shading="flat")
    fig.colorbar(mesh, ax=ax, label="epochs per bin")
    al = alert_limit_m
    ax.plot([lo, hi], [lo, hi], color="k", lw=1.0)
    ax.axvline(al, color="tab:red", lw=1.0)
    ax.axhline(al, color="tab:red", lw=1.0, ls="--")
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlim(lo, hi)
    ax.set_ylim(lo, hi)
    label = "HPL [m]" if risk is None else f"HPL at risk {risk:g} [m]"
    ax.set_xlabel(label)
    ax.set_ylabel("horizontal error [m]")
    normal = int(((err <= hpl) & (hpl <= al)).sum())
    misleading = int(((err > hpl) & (hpl <= al) & (err <= al)).sum())
    hazardous = int(((err > al) & (hpl <= al)).sum())
    unavailable = int((hpl > al).sum())
    box = {"boxstyle": "round", "facecolor": "white", "alpha": 0.8}
    ax.text(0.03, 0.03, f"normal\n{normal}", transform=ax.transAxes, fontsize=8, bbox=box)
    ax.text(0.03, 0.62, f"misleading\n{misleading}", transform=ax.transAxes, fontsize=8,
            bbox=box)
    ax.text(0.03, 0.9, f"hazardous\n{hazardous}", transform=ax.transAxes, fontsize=8, bbox=box)
    ax.text(0.78, 0.03, f"unavailable\n{unavailable}", transform=ax.transAxes, fontsize=8,
            bbox=box)
    ax.set_title(title or f"Stanford diagram (alert limit {al:g} m)")
    return fig
