"""The simulated world's terrain: the DEM, its making error, and sub-grid detail.

A Monte Carlo study must not fly over the very surface its grid methods interpolate (the
"inverse crime": the truth would then be the bicubic interpolation of the map itself, and
every grid method would look better than it can be). `true_terrain` builds the
scenario's truth once and every consumer uses it: the simulator (altimeter clearances),
the PCRB (terrain slopes along the true path) and the map-error measurement.

Truth models (``scenario.truth_model``):

* ``"dem"``: bicubic interpolation of the DEM plus the DEM-making error field
  (``dem_error_sigma_m``; SEEDS 000's ``m_d``);
* ``"subgrid"``: the same on a grid ``subgrid_factor`` times finer, plus a seeded fractal
  field that carries the detail the DEM cannot resolve. Its spectrum continues the tile's
  own measured power spectrum below the grid spacing: a power law ``P(k) = A k^(−β)`` is
  fitted to the tile's radially averaged periodogram between 1/8 and 1/2 of the Nyquist
  wavenumber and extended over the band from the DEM's Nyquist wavenumber to the fine
  grid's; the field is band-limited to that band, so it adds only what the grid misses.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from neuralmap.dem.tile import DemTile
from neuralmap.exceptions import NeuralMapError
from neuralmap.terrain.grid import GridTerrain, fill_voids_nearest

__all__ = ["TrueTerrain", "dem_error_field", "spectral_slope", "subgrid_detail", "true_terrain"]


@dataclass
class TrueTerrain:
    """The truth terrain of a scenario and how it was made.

    Attributes:
        model: float64 bicubic `GridTerrain` of the truth (fine grid for
            ``subgrid``); ``forward(xy) -> height``.
        kind: ``"dem"`` or ``"subgrid"``.
        dem_error: ``(ny, nx)`` DEM-making error added at the DEM nodes (m), or None.
        detail_rms_m: RMS of the sub-grid detail field (0 for ``dem``).
        spectral_slope: Fitted β of ``P(k) ∝ k^(−β)`` (None for ``dem``).
        factor: Refinement factor of the truth grid (1 for ``dem``).
    """

    model: GridTerrain
    kind: str
    dem_error: np.ndarray | None = None
    detail_rms_m: float = 0.0
    spectral_slope: float | None = None
    factor: int = 1

    @property
    def description(self) -> str:
        """One line for the console and the report."""
        err = "" if self.dem_error is None else (
            f" + DEM-making error (σ {float(np.std(self.dem_error)):.2f} m)")
        if self.kind == "subgrid":
            return (f"bicubic DEM on a {self.factor}x finer grid{err} + sub-grid fractal detail "
                    f"(RMS {self.detail_rms_m:.2f} m, spectrum ∝ k^-{self.spectral_slope:.2f} "
                    "continued from the tile's own)")
        return f"bicubic DEM{err} (no sub-grid detail: grid methods see the truth's own surface)"

    def summary(self) -> dict[str, Any]:
        """Plain-data description for results.json."""
        return {
            "kind": self.kind,
            "description": self.description,
            "factor": self.factor,
            "detail_rms_m": self.detail_rms_m,
            "spectral_slope": self.spectral_slope,
            "dem_error_sigma_m": None if self.dem_error is None else float(np.std(self.dem_error)),
        }


def dem_error_field(
    shape: tuple[int, int],
    spacing: tuple[float, float],
    *,
    sigma_m: float,
    corr_m: float,
    seed: int,
) -> np.ndarray:
    """Smooth Gaussian random field modelling the DEM-making error (SEEDS 000, ``m_d``).

    White noise on a padded grid is convolved (via FFT) with a Gaussian kernel of standard
    deviation ``corr_m / 2`` metres, which gives the correlation function
    ``exp(−r² / corr_m²)``; the cropped field is shifted to zero mean and scaled to the
    sample standard deviation ``sigma_m`` exactly.

    Args:
        shape: ``(ny, nx)`` grid nodes.
        spacing: ``(dx, dy)`` grid spacing, m.
        sigma_m: Standard deviation, m (0 gives zeros).
        corr_m: Correlation length, m (> 0).
        seed: Seed of the NumPy generator.

    Returns:
        ``(ny, nx)`` float64 field in metres.
    """
    ny, nx = shape
    if sigma_m == 0.0:
        return np.zeros((ny, nx))
    s_nodes = (0.5 * corr_m / spacing[0], 0.5 * corr_m / spacing[1])
    pad_x = int(math.ceil(4.0 * s_nodes[0])) + 1
    pad_y = int(math.ceil(4.0 * s_nodes[1])) + 1
    py, px = ny + 2 * pad_y, nx + 2 * pad_x
    rng = np.random.default_rng([int(seed), 0xD3E])
    noise = rng.standard_normal((py, px))
    fy = np.fft.fftfreq(py)[:, None]
    fx = np.fft.rfftfreq(px)[None, :]
    transfer = np.exp(-2.0 * np.pi**2 * ((s_nodes[0] * fx) ** 2 + (s_nodes[1] * fy) ** 2))
    smooth = np.fft.irfft2(np.fft.rfft2(noise) * transfer, s=(py, px))
    smooth = smooth[pad_y : pad_y + ny, pad_x : pad_x + nx]
    smooth = smooth - smooth.mean()
    std = float(smooth.std())
    if std <= 0.0:  # pragma: no cover - degenerate single-node field
        return np.zeros((ny, nx))
    return smooth * (sigma_m / std)


def _radial_wavenumber(ny: int, nx: int, spacing: tuple[float, float]) -> np.ndarray:
    ky = np.fft.fftfreq(ny, d=spacing[1])[:, None]
    kx = np.fft.fftfreq(nx, d=spacing[0])[None, :]
    return np.sqrt(kx**2 + ky**2)  # cycles per metre


def spectral_slope(heights: np.ndarray, spacing: tuple[float, float]) -> tuple[float, float]:
    """Power-law fit ``P(k) = A k^(−β)`` to a DEM's periodogram near its Nyquist band.

    The heights (voids filled, plane removed, Hann-windowed) are transformed; the 2-D
    periodogram ``P = |FFT|² dx dy / (Nx Ny)`` is fitted in log–log by least squares over
    ``k_N/8 ≤ |k| ≤ k_N/2``, ``k_N = 1/(2 max(dx, dy))``.

    Returns:
        ``(A, β)`` in m⁴ (two-sided 2-D PSD units, m² per (cycle/m)²) and the exponent.
    """
    h = fill_voids_nearest(heights, spacing)
    ny, nx = h.shape
    yy, xx = np.mgrid[0:ny, 0:nx]
    design = np.column_stack([np.ones(h.size), xx.ravel(), yy.ravel()])
    coef, *_ = np.linalg.lstsq(design, h.ravel(), rcond=None)
    h = h - (design @ coef).reshape(ny, nx)
    window = np.outer(np.hanning(ny), np.hanning(nx))
    h = h * window / math.sqrt(float((window**2).mean()))
    psd = np.abs(np.fft.fft2(h)) ** 2 * spacing[0] * spacing[1] / (nx * ny)
    k = _radial_wavenumber(ny, nx, spacing)
    k_nyq = 0.5 / max(spacing)
    band = (k >= k_nyq / 8) & (k <= k_nyq / 2)
    if int(band.sum()) < 10:
        raise NeuralMapError(
            f"spectral_slope: the tile ({ny} x {nx} nodes) is too small to measure its "
            "spectrum; use truth_model: dem for tiles under about 32 x 32 nodes."
        )
    slope, intercept = np.polyfit(np.log(k[band]), np.log(psd[band]), 1)
    return float(math.exp(intercept)), float(-slope)


def subgrid_detail(
    shape: tuple[int, int],
    spacing: tuple[float, float],
    *,
    amplitude: float,
    beta: float,
    k_min: float,
    seed: int,
) -> np.ndarray:
    """Gaussian field with PSD ``amplitude · k^(−β)`` for ``|k| > k_min``, zero below.

    White noise is shaped in the Fourier domain on the (fine) grid and scaled so that its
    variance equals the PSD integrated over the band, ``Σ_k P(k) Δk_x Δk_y``.

    Args:
        shape: ``(ny, nx)`` fine grid.
        spacing: Fine ``(dx, dy)``, m.
        amplitude: ``A`` of the power law.
        beta: Exponent β.
        k_min: Lower band edge (cycles/m): the coarse DEM's Nyquist wavenumber.
        seed: Seed.

    Returns:
        ``(ny, nx)`` field in metres.
    """
    ny, nx = shape
    k = _radial_wavenumber(ny, nx, spacing)
    band = k > k_min
    psd = np.zeros_like(k)
    psd[band] = amplitude * k[band] ** (-beta)
    rng = np.random.default_rng([int(seed), 0x5B6])
    spectrum = np.fft.fft2(rng.standard_normal((ny, nx))) * np.sqrt(psd)
    field = np.real(np.fft.ifft2(spectrum))
    target_var = float(psd.sum()) / (nx * spacing[0] * ny * spacing[1])
    std = float(field.std())
    return field * (math.sqrt(target_var) / std) if std > 0 else field


def true_terrain(scenario: Any, tile: DemTile, *, seed: int) -> TrueTerrain:
    """Builds the scenario's truth terrain (see the module docstring).

    Args:
        scenario: A `Scenario` (its ``truth_model``,
            ``subgrid_factor``, ``dem_error_sigma_m``, ``dem_error_corr_m``).
        tile: The scenario's DEM tile.
        seed: The run's seed (one world per seed, shared by every run and method).

    Returns:
        `TrueTerrain`.
    """
    dem_error = None
    heights = tile.heights
    if scenario.dem_error_sigma_m > 0.0:
        dem_error = dem_error_field(tile.shape, tile.spacing, sigma_m=scenario.dem_error_sigma_m,
                                    corr_m=scenario.dem_error_corr_m, seed=seed)
        heights = heights + dem_error
    coarse = DemTile(heights=heights, spacing=tile.spacing, origin=tile.origin, name=tile.name,
                     source=tile.source)
    if scenario.truth_model == "dem":
        return TrueTerrain(GridTerrain(coarse, method="bicubic", dtype=torch.float64), "dem",
                           dem_error)
    factor = int(scenario.subgrid_factor)
    amplitude, beta = spectral_slope(tile.heights, tile.spacing)
    ny, nx = tile.shape
    fine_shape = ((ny - 1) * factor + 1, (nx - 1) * factor + 1)
    fine_spacing = (tile.spacing[0] / factor, tile.spacing[1] / factor)
    xs = tile.origin[0] + fine_spacing[0] * np.arange(fine_shape[1])
    ys = tile.origin[1] + fine_spacing[1] * np.arange(fine_shape[0])
    xy = np.stack(np.meshgrid(xs, ys), axis=-1)
    coarse_model = GridTerrain(coarse, method="bicubic", dtype=torch.float64)
    with torch.no_grad():
        fine = coarse_model(torch.from_numpy(xy)).numpy()
    k_nyq = 0.5 / max(tile.spacing)
    detail = subgrid_detail(fine_shape, fine_spacing, amplitude=amplitude, beta=beta,
                            k_min=k_nyq, seed=seed)
    fine_tile = DemTile(heights=fine + detail, spacing=fine_spacing, origin=tile.origin,
                        name=tile.name, source=tile.source)
    return TrueTerrain(GridTerrain(fine_tile, method="bicubic", dtype=torch.float64), "subgrid",
                       dem_error, float(detail.std()), beta, factor)
