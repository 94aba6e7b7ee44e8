"""Navigation figures: error vs time with the PCRB, trajectories over a hillshade, histograms.

Every function builds a `matplotlib.figure.Figure` without pyplot (no global state,
no display needed) and can save it atomically as PNG.
"""

from __future__ import annotations

import os
from collections.abc import Collection, Mapping
from pathlib import Path

import numpy as np
from matplotlib import patheffects
from matplotlib.figure import Figure

from neuralmap.dem.tile import DemTile
from neuralmap.exceptions import NeuralMapError
from neuralmap.io import atomic_write_figure
from neuralmap.viz.hillshade import hillshade


def save_figure(fig: Figure, path: str | os.PathLike[str], *, dpi: int = 120) -> Path:
    """Saves a figure as PNG atomically (`neuralmap.io.atomic_write_figure`)."""
    return atomic_write_figure(path, fig, dpi=dpi)


def _curve(values: object, n: int, what: str) -> np.ndarray:
    if isinstance(values, (list, tuple)):  # results.json curves hold None for no data
        values = [np.nan if v is None else v for v in values]
    array = np.asarray(values, dtype=np.float64).reshape(-1)
    if array.shape != (n,):
        raise NeuralMapError(f"{what}: expected {n} values (one per time step), got {array.size}.")
    return array


#: Markers that tell the curves apart where they lie on top of each other (one per curve).
_MARKERS = ("o", "s", "^", "v", "D", "P", "X", "<", ">", "*")
#: Markers drawn per curve (spread over the time axis, staggered between curves).
_MARKS_PER_CURVE = 10


def coinciding_curves(curves: Mapping[str, np.ndarray], *, rtol: float = 1e-9
                      ) -> dict[str, str]:
    """Which curves equal an earlier one (to ``rtol``, NaN gaps equal).

    Args:
        curves: Label -> ``(K+1,)`` values, in drawing order.
        rtol: Relative tolerance of "equal".

    Returns:
        Label -> the first earlier label it coincides with (only labels that do).
    """
    same: dict[str, str] = {}
    names = list(curves)
    for i, name in enumerate(names):
        for other in names[:i]:
            if other in same:
                continue
            a, b = curves[name], curves[other]
            if a.shape == b.shape and np.allclose(a, b, rtol=rtol, atol=0.0, equal_nan=True):
                same[name] = other
                break
    return same


def plot_error_vs_time(
    t: object,
    curves: Mapping[str, object],
    pcrb_pos: object | None,
    *,
    converged_curves: Mapping[str, object] | None = None,
    references: Collection[str] = (),
    xlabel: str = "time [s]",
    ylabel: str = "horizontal position RMSE [m]",
    title: str = "Horizontal position error vs time",
) -> Figure:
    """RMSE curves with the horizontal PCRB (log scale): the one error-vs-time figure of
    every study.

    Each curve has its own colour and marker (the markers staggered along the time axis),
    so a curve lying on another stays visible; a curve equal to an earlier one is also
    labelled "= <that one>" in the legend (`coinciding_curves`).

    Args:
        t: ``(K+1,)`` seconds (or steps, with ``xlabel``).
        curves: Label -> ``(K+1,)`` RMSE over all on-map runs (solid lines; None entries
            are gaps).
        pcrb_pos: ``(K+1,)`` horizontal PCRB, metres (black dashed); None = no bound.
        converged_curves: Label -> ``(K+1,)`` RMSE over the non-diverged runs (dotted,
            same colour), optional.
        references: Labels of ``curves`` drawn as black dash-dot reference lines (e.g. the
            clean-data run).
        xlabel: X axis label.
        ylabel: Y axis label.
        title: Figure title.

    Returns:
        The figure.
    """
    time = np.asarray(t, dtype=np.float64).reshape(-1)
    n = time.size
    fig = Figure(figsize=(8.0, 4.8))
    ax = fig.add_subplot()
    colors = [f"C{i}" for i in range(10)]
    arrays = {name: _curve(values, n, f"curve '{name}'") for name, values in curves.items()}
    same = coinciding_curves(arrays)
    every = max(n // _MARKS_PER_CURVE, 1)
    for i, (name, values) in enumerate(arrays.items()):
        color = colors[i % len(colors)]
        style = {"color": "k", "ls": "-."} if name in references else {"color": color}
        label = f"{name} (= {same[name]})" if name in same else name
        ax.plot(time, values, lw=1.4, label=label, marker=_MARKERS[i % len(_MARKERS)], ms=4,
                markevery=((i * every) // max(len(arrays), 1), every), **style)
        if converged_curves and name in converged_curves:
            ax.plot(
                time,
                _curve(converged_curves[name], n, f"converged curve '{name}'"),
                color=color,
                lw=1.0,
                ls=":",
            )
    lines = list(arrays.values())
    if pcrb_pos is not None:
        bound = _curve(pcrb_pos, n, "pcrb_pos")
        ax.plot(time, bound, color="k", lw=1.6, ls="--", label="PCRB")
        lines.append(bound)
    if any((v > 0).any() for v in lines):
        ax.set_yscale("log")
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title + ("  (dotted: non-diverged runs)" if converged_curves else ""))
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8, ncol=2)
    fig.tight_layout()
    return fig


def plot_trajectories(
    tile: DemTile,
    truth_xy: object,
    estimates: Mapping[str, object],
    *,
    title: str = "Trajectories over the tile (truth and estimates)",
) -> Figure:
    """Truth trajectories over the tile's hillshade, and beside them each estimate's error.

    At the tile's scale a 20 m error is a fraction of a line width, so the estimates hide
    under the truth. The left panel shows where the flights are (truth, estimates over the
    hillshade); the right panel zooms on the error: the path of ``estimate − truth`` (east,
    north, metres) of every drawn run and method, from its start (o) to its end (x), with
    the truth at the origin.

    Args:
        tile: The DEM tile (background).
        truth_xy: ``(M, K+1, 2)`` true horizontal positions, metres (white lines).
        estimates: Method -> ``(M, K+1, 2)`` estimated positions, metres (coloured).

    Returns:
        The figure (two panels: ``fig.axes[0]`` the tile, ``fig.axes[1]`` the error).
    """
    truth = np.asarray(truth_xy, dtype=np.float64)
    if truth.ndim != 3 or truth.shape[-1] != 2:
        raise NeuralMapError(
            f"plot_trajectories: truth_xy must have shape (M, K+1, 2), got {truth.shape}."
        )
    arrays = {}
    for name, values in estimates.items():
        est = np.asarray(values, dtype=np.float64)
        if est.shape != truth.shape:
            raise NeuralMapError(
                f"plot_trajectories: estimates['{name}'] has shape {est.shape}, expected "
                f"{truth.shape} like truth_xy."
            )
        arrays[name] = est
    xmin, xmax, ymin, ymax = tile.extent
    dx, dy = tile.spacing
    shade = hillshade(tile.heights, tile.spacing)
    aspect = (ymax - ymin + dy) / max(xmax - xmin + dx, 1e-9)
    width = 6.5
    fig = Figure(figsize=(2 * width, float(np.clip(width * aspect, 3.0, 10.0)) + 0.8))
    ax, zoom = fig.add_subplot(1, 2, 1), fig.add_subplot(1, 2, 2)
    ax.imshow(
        shade,
        origin="lower",
        cmap="gray",
        extent=(xmin - dx / 2, xmax + dx / 2, ymin - dy / 2, ymax + dy / 2),
        interpolation="bilinear",
    )
    outline = [patheffects.Stroke(linewidth=3.0, foreground="k"), patheffects.Normal()]
    for m in range(truth.shape[0]):
        ax.plot(
            truth[m, :, 0],
            truth[m, :, 1],
            color="w",
            lw=1.6,
            path_effects=outline,
            label="truth (o = start)" if m == 0 else None,
        )
        ax.plot(truth[m, 0, 0], truth[m, 0, 1], "o", color="w", mec="k", ms=5)
    for i, (name, est) in enumerate(arrays.items()):
        color = f"C{i % 10}"
        error = est - truth
        for m in range(est.shape[0]):
            ax.plot(est[m, :, 0], est[m, :, 1], color=color, lw=0.9, alpha=0.85,
                    label=name if m == 0 else None)
            zoom.plot(error[m, :, 0], error[m, :, 1], color=color, lw=0.7, alpha=0.6,
                      label=name if m == 0 else None)
            zoom.plot(error[m, 0, 0], error[m, 0, 1], "o", color=color, ms=3)
            zoom.plot(error[m, -1, 0], error[m, -1, 1], "x", color=color, ms=7, mew=2.0)
    ax.set_xlim(xmin - dx / 2, xmax + dx / 2)
    ax.set_ylim(ymin - dy / 2, ymax + dy / 2)
    ax.set_xlabel("east [m]")
    ax.set_ylabel("north [m]")
    ax.set_title(title, fontsize=10)
    ax.legend(fontsize=8, loc="upper right", framealpha=0.8)
    zoom.plot(0.0, 0.0, "+", color="k", ms=12, mew=1.5, label="truth")
    zoom.axhline(0.0, color="k", lw=0.5, alpha=0.4)
    zoom.axvline(0.0, color="k", lw=0.5, alpha=0.4)
    zoom.set_aspect("equal", adjustable="datalim")
    zoom.grid(True, alpha=0.3)
    zoom.set_xlabel("estimate − truth, east [m]")
    zoom.set_ylabel("estimate − truth, north [m]")
    zoom.set_title("Zoom on the error of the same runs (o start, x end)", fontsize=10)
    zoom.legend(fontsize=8, loc="upper right", framealpha=0.8)
    fig.tight_layout()
    return fig


def plot_final_error_histogram(
    final_errors: Mapping[str, object],
    *,
    pcrb_final: float | None = None,
    bins: int | None = None,
    title: str = "Final horizontal position error",
) -> Figure:
    """Histogram of the final horizontal error of every method (log-spaced bins, log counts).

    Args:
        final_errors: Method -> ``(N,)`` final horizontal errors in metres (off-map runs
            already removed; non-finite values are dropped).
        pcrb_final: Final horizontal PCRB, metres (vertical dashed line), optional.
        bins: Number of bins; ``None`` = ``2·sqrt(N)`` clipped to ``[10, 40]``.
        title: Figure title.

    Returns:
        The figure.
    """
    cleaned = {}
    for name, values in final_errors.items():
        array = np.asarray(values, dtype=np.float64).reshape(-1)
        cleaned[name] = array[np.isfinite(array)]
    everything = np.concatenate([v for v in cleaned.values()] + [np.zeros(0)])
    fig = Figure(figsize=(8.0, 4.8))
    ax = fig.add_subplot()
    if everything.size:
        low = max(float(everything[everything > 0].min()) if (everything > 0).any() else 1e-3, 1e-3)
        high = max(float(everything.max()), low * 10)
        if bins is None:
            n_max = max(v.size for v in cleaned.values())
            bins = int(np.clip(2 * np.sqrt(n_max), 10, 40))
        edges = np.geomspace(low, high, bins + 1)
        for i, (name, values) in enumerate(cleaned.items()):
            ax.hist(
                np.clip(values, low, high),
                bins=edges,
                histtype="step",
                lw=1.4,
                color=f"C{i % 10}",
                label=f"{name} (n={values.size})",
            )
        ax.set_xscale("log")
        ax.set_yscale("log")  # keeps the few diverged runs of the tail visible
        ax.set_ylim(bottom=0.7)
    if pcrb_final is not None and np.isfinite(pcrb_final) and pcrb_final > 0:
        ax.axvline(pcrb_final, color="k", ls="--", lw=1.4, label="final PCRB")
    ax.set_xlabel("final horizontal error [m]")
    ax.set_ylabel("runs")
    ax.set_title(title)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    return fig
