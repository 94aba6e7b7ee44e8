"""Figures of a terrain fit: residual map, hillshades, residual histogram and autocorrelation.

All functions build a `matplotlib.figure.Figure` without pyplot (safe in any
backend and thread); `figure_to_rgb` renders one for TensorBoard. Grids follow the
DEM convention: row 0 is south (drawn with ``origin="lower"``).
"""

from __future__ import annotations

import math

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.colors import Colormap
from matplotlib.figure import Figure

from neuralmap.viz.hillshade import hillshade


def _km_extent(extent: tuple[float, float, float, float]) -> list[float]:
    return [e / 1000.0 for e in extent]


def _diverging_cmap() -> Colormap:
    from matplotlib import colormaps

    cmap = colormaps["RdBu_r"].copy()
    cmap.set_bad("0.6")
    return cmap


def figure_to_rgb(figure: Figure) -> np.ndarray:
    """Renders a figure to an ``(H, W, 3)`` uint8 RGB array (for ``add_image``)."""
    canvas = FigureCanvasAgg(figure)
    canvas.draw()
    return np.asarray(canvas.buffer_rgba())[..., :3].copy()


def residual_map_figure(
    residual: np.ndarray,
    extent: tuple[float, float, float, float],
    *,
    title: str = "fit residual",
    percentile: float = 99.5,
) -> Figure:
    """Map of ``fitted - DEM`` in metres, diverging colours with symmetric limits.

    The colour limits are ``±`` the ``percentile``-th percentile of ``|residual|`` (so a
    few outlier nodes do not wash out the map; they saturate, and the colourbar shows
    arrows); the title gives the true maximum.

    Args:
        residual: ``(ny, nx)`` metres, NaN at voids (drawn grey), row 0 south.
        extent: ``(xmin, xmax, ymin, ymax)`` metres.
        title: Axes title.
        percentile: Percentile of ``|residual|`` used as the colour limit (100 = max).

    Returns:
        The figure (one axes and a colourbar).
    """
    finite = residual[np.isfinite(residual)]
    largest = float(np.abs(finite).max()) if finite.size else 0.0
    limit = float(np.percentile(np.abs(finite), percentile)) if finite.size else 1.0
    limit = limit if limit > 0 else (largest or 1.0)
    ny, nx = residual.shape
    aspect_hw = (extent[3] - extent[2]) / max(extent[1] - extent[0], 1e-9)
    figure = Figure(figsize=(7.0, max(3.0, min(9.0, 5.5 * aspect_hw + 0.8))))
    ax = figure.add_subplot()
    image = ax.imshow(
        np.ma.masked_invalid(residual), origin="lower", extent=_km_extent(extent),
        cmap=_diverging_cmap(), vmin=-limit, vmax=limit, interpolation="nearest",
    )
    colourbar = figure.colorbar(image, ax=ax, extend="both" if largest > limit else "neither")
    colourbar.set_label("fitted − DEM (m)")
    rms = math.sqrt(float(np.mean(finite**2))) if finite.size else float("nan")
    ax.set_title(f"{title} ({nx} × {ny} nodes)\nRMSE {rms:.2f} m, max |e| {largest:.2f} m")
    ax.set_xlabel("east (km)")
    ax.set_ylabel("north (km)")
    figure.tight_layout()
    return figure


def hillshade_comparison_figure(
    dem: np.ndarray,
    fitted: np.ndarray,
    spacing: tuple[float, float],
    extent: tuple[float, float, float, float],
) -> Figure:
    """DEM hillshade next to the fitted map's hillshade (same light, same scale).

    Args:
        dem: ``(ny, nx)`` DEM heights, metres (NaN voids).
        fitted: ``(ny, nx)`` fitted heights at the same nodes.
        spacing: ``(dx, dy)`` metres.
        extent: ``(xmin, xmax, ymin, ymax)`` metres.

    Returns:
        The figure (two axes).
    """
    aspect_hw = (extent[3] - extent[2]) / max(extent[1] - extent[0], 1e-9)
    figure = Figure(figsize=(11.0, max(3.0, min(8.0, 5.0 * aspect_hw + 0.8))))
    axes = figure.subplots(1, 2, sharex=True, sharey=True)
    fitted_masked = np.where(np.isfinite(dem), fitted, np.nan)
    for ax, grid, title in (
        (axes[0], dem, "DEM"),
        (axes[1], fitted_masked, "neural map"),
    ):
        ax.imshow(hillshade(grid, spacing), origin="lower", extent=_km_extent(extent),
                  cmap="gray", vmin=0.0, vmax=1.0, interpolation="nearest")
        ax.set_title(f"{title} (hillshade)")
        ax.set_xlabel("east (km)")
    axes[0].set_ylabel("north (km)")
    figure.tight_layout()
    return figure


def residual_histogram_figure(residual: np.ndarray, *, bins: int = 100) -> Figure:
    """Histogram of the fit residuals with the normal density of the same mean and std.

    Args:
        residual: Residuals in metres (any shape; NaN ignored).
        bins: Number of histogram bins.

    Returns:
        The figure (log-scaled counts, so the tails show).
    """
    values = residual[np.isfinite(residual)].ravel()
    figure = Figure(figsize=(7.0, 4.0))
    ax = figure.add_subplot()
    if values.size:
        mean, std = float(values.mean()), float(values.std())
        counts, edges, _ = ax.hist(values, bins=bins, color="tab:blue", alpha=0.8,
                                   label="residuals")
        if std > 0:
            centres = 0.5 * (edges[1:] + edges[:-1])
            width = float(edges[1] - edges[0])
            normal = values.size * width * np.exp(-0.5 * ((centres - mean) / std) ** 2) / (
                std * math.sqrt(2 * math.pi)
            )
            normal = np.where(normal >= 0.1, normal, np.nan)  # keep the log axis readable
            ax.plot(centres, normal, color="tab:red", lw=1.2, label="normal, same mean/std")
        ax.set_yscale("log")
        ax.set_ylim(0.5, 2.0 * max(float(counts.max()), 1.0))
        ax.set_title(
            f"fit residuals (n = {values.size})\nmean {mean:.3f} m, std {std:.3f} m, "
            f"max |e| {float(np.abs(values).max()):.2f} m"
        )
        ax.legend()
    ax.set_xlabel("fitted − DEM (m)")
    ax.set_ylabel("nodes")
    figure.tight_layout()
    return figure


def residual_autocorrelation_figure(
    acf_x: np.ndarray,
    acf_y: np.ndarray,
    spacing: tuple[float, float],
    n_nodes: int,
) -> Figure:
    """Residual autocorrelation along rows (east) and columns (north) vs lag in metres.

    A white fit error stays inside the 95 % band ``±1.96 / sqrt(n)`` for every lag > 0
    (SEEDS 004 fig. 3d).

    Args:
        acf_x: ``(Lx + 1,)`` autocorrelation along rows for lags ``0..Lx`` nodes.
        acf_y: ``(Ly + 1,)`` along columns.
        spacing: ``(dx, dy)`` metres, to convert lags to metres.
        n_nodes: Number of residuals used (for the white-noise band).

    Returns:
        The figure.
    """
    figure = Figure(figsize=(7.0, 4.0))
    ax = figure.add_subplot()
    ax.plot(np.arange(acf_x.size) * spacing[0], acf_x, "o-", ms=3, label="along east (rows)")
    ax.plot(np.arange(acf_y.size) * spacing[1], acf_y, "s-", ms=3, label="along north (columns)")
    if n_nodes > 0:
        band = 1.96 / math.sqrt(n_nodes)
        ax.axhspan(-band, band, color="0.8", alpha=0.7, label="95 % band of white noise")
    ax.axhline(0.0, color="k", lw=0.6)
    ax.set_xlabel("lag (m)")
    ax.set_ylabel("autocorrelation")
    ax.set_title("fit residual autocorrelation (white error: inside the band)")
    ax.legend()
    figure.tight_layout()
    return figure
