"""Hillshade of a height grid, for map backgrounds."""

from __future__ import annotations

import numpy as np
from matplotlib.colors import LightSource


def hillshade(
    heights: np.ndarray,
    spacing: tuple[float, float],
    *,
    azimuth: float = 315.0,
    altitude: float = 45.0,
    vertical_exaggeration: float = 1.0,
) -> np.ndarray:
    """Lambertian hillshade of a grid whose row 0 is south.

    Args:
        heights: ``(ny, nx)`` metres; NaN voids are shaded mid-grey.
        spacing: ``(dx, dy)`` metres.
        azimuth: Light azimuth, degrees clockwise from north.
        altitude: Light elevation, degrees.
        vertical_exaggeration: Factor applied to heights.

    Returns:
        ``(ny, nx)`` intensities in ``[0, 1]``, row 0 south (plot with ``origin="lower"``).
    """
    filled = np.where(np.isfinite(heights), heights, np.nanmean(heights))
    light = LightSource(azdeg=azimuth, altdeg=altitude)
    # LightSource expects row 0 at the top (north); flip in and out.
    shade = light.hillshade(
        filled[::-1], vert_exag=vertical_exaggeration, dx=spacing[0], dy=spacing[1]
    )[::-1]
    return np.where(np.isfinite(heights), shade, 0.5)
