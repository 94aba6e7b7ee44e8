"""Seeded synthetic fractal terrain (spectral synthesis with a power-law spectrum)."""

from __future__ import annotations

import math

import numpy as np

from neuralmap.dem.tile import DemTile, broadcast_pair
from neuralmap.exceptions import NeuralMapError

#: Mean height added to the synthetic relief, metres (the surface spans
#: ``[SYNTHETIC_BASE_HEIGHT, SYNTHETIC_BASE_HEIGHT + relief]``).
SYNTHETIC_BASE_HEIGHT = 500.0


def _as_pair(value: object, what: str, cast: type) -> tuple:
    """Broadcasts a scalar or a length-2 sequence to a pair of ``cast``, or raises."""
    return tuple(cast(v) for v in broadcast_pair(value, what, "synthetic_tile"))


def fast_length(n: int) -> int:
    """Smallest 5-smooth integer ≥ n (fast FFT length; unchanged when n already is one)."""
    best = 2 * n
    p2 = 1
    while p2 < best:
        p3 = p2
        while p3 < best:
            p5 = p3
            while p5 < n:
                p5 *= 5
            best = min(best, p5)
            p3 *= 3
            if p3 >= n:
                best = min(best, p3)
        p2 *= 2
        if p2 >= n:
            best = min(best, p2)
    return best


def fractal_surface(
    shape: tuple[int, int], *, hurst: float = 0.8, seed: int = 0
) -> np.ndarray:
    """Unit-range fractional Brownian surface by spectral synthesis.

    Each Fourier coefficient gets a complex Gaussian amplitude with power spectral density
    ``S(k) ∝ |k|^-(2H + 2)`` (fractional Brownian surface of Hurst exponent ``H``, fractal
    dimension ``3 - H``; Voss 1988). The field is synthesised on a grid padded to twice the
    requested size (rounded up to a fast FFT length) and cropped, so it is not periodic
    across the tile's edges.

    Args:
        shape: ``(ny, nx)`` node counts, each ≥ 2.
        hurst: Hurst exponent in ``(0, 1]``; larger is smoother.
        seed: Seed of the NumPy generator; equal seeds and shapes give equal surfaces.

    Returns:
        ``(ny, nx)`` float64 array scaled to ``[0, 1]``.
    """
    ny, nx = shape
    py, px = fast_length(2 * ny), fast_length(2 * nx)
    rng = np.random.default_rng(seed)
    ky = np.fft.fftfreq(py)[:, None]
    kx = np.fft.rfftfreq(px)[None, :]
    k = np.sqrt(kx**2 + ky**2)
    k[0, 0] = 1.0
    amplitude = k ** (-(hurst + 1.0))  # sqrt of the PSD |k|^-(2H+2)
    amplitude[0, 0] = 0.0
    spectrum = amplitude * (
        rng.standard_normal(amplitude.shape) + 1j * rng.standard_normal(amplitude.shape)
    )
    field = np.fft.irfft2(spectrum, s=(py, px))[:ny, :nx]
    span = float(field.max() - field.min())
    if span <= 0.0:  # pragma: no cover - only for degenerate shapes
        return np.zeros((ny, nx))
    return (field - field.min()) / span


def synthetic_tile(
    shape: tuple[int, int] | int = (128, 128),
    spacing: tuple[float, float] | float = (30.0, 30.0),
    *,
    seed: int = 0,
    relief: float = 300.0,
    hurst: float = 0.8,
    name: str = "synthetic",
) -> DemTile:
    """Seeded fractal terrain of any size, for tests and scale runs.

    Heights are the `fractal_surface` of the given Hurst exponent scaled to
    ``relief`` metres peak-to-peak and lifted by `SYNTHETIC_BASE_HEIGHT` (500 m), so
    they span ``[500, 500 + relief]`` m. Node ``[0, 0]`` is at the metric origin ``(0, 0)``.
    A 1000 × 1000 tile takes well under a second.

    Args:
        shape: ``(ny, nx)`` node counts (each ≥ 2), or one int for a square tile.
        spacing: ``(dx, dy)`` grid spacing in metres, or one float for both.
        seed: Random seed; the same ``(shape, seed, hurst)`` gives the same heights.
        relief: Peak-to-peak height range in metres (≥ 0).
        hurst: Hurst exponent in ``(0, 1]``: 0.8 gives hills, 0.3 rough ground.
        name: Tile name.

    Returns:
        The tile (``geo`` is None; ``meta`` records the generator settings).

    Raises:
        NeuralMapError: On a shape below 2 × 2, bad spacing, negative relief or a Hurst
            exponent outside ``(0, 1]``.
    """
    ny, nx = _as_pair(shape, "shape", int)
    if ny < 2 or nx < 2 or (ny, nx) != tuple(np.broadcast_to(np.asarray(shape), (2,))):
        raise NeuralMapError(
            f"synthetic_tile: shape must be whole node counts ≥ 2, got {shape!r}. "
            "Pass e.g. shape=(128, 128)."
        )
    spacing_pair = _as_pair(spacing, "spacing", float)
    if not (math.isfinite(relief) and relief >= 0.0):
        raise NeuralMapError(f"synthetic_tile: relief must be finite and ≥ 0 m, got {relief!r}.")
    if not (math.isfinite(hurst) and 0.0 < hurst <= 1.0):
        raise NeuralMapError(
            f"synthetic_tile: hurst must be in (0, 1], got {hurst!r} (0.8 = smooth hills)."
        )
    heights = SYNTHETIC_BASE_HEIGHT + relief * fractal_surface((ny, nx), hurst=hurst, seed=seed)
    return DemTile(
        heights=heights,
        spacing=spacing_pair,
        origin=(0.0, 0.0),
        name=name,
        source=f"synthetic(seed={seed}, hurst={hurst}, relief={relief})",
        meta={"generator": "spectral fBm", "seed": int(seed), "hurst": float(hurst),
              "relief": float(relief), "base_height": SYNTHETIC_BASE_HEIGHT},
    )
