"""Synthetic mission regions at the papers' size, written to a memory-mapped ``.npy``.

SEEDS 004's map is 361 km × 127 km at 100 m (3610 × 1270 nodes, about 4.6 M). The region
is a Gaussian random field with the jacksboro sample's measured power spectrum: a power law
``P(k) = A k^(−β)`` (two-sided 2-D PSD, m⁴, ``k`` in cycles/m) with ``A`` and ``β`` fitted to
jacksboro's periodogram near its Nyquist band (``neuralmap.lab.truth_terrain.spectral_slope``
gives `JACKSBORO_SPECTRUM`). The power law cannot hold down to ``k = 0`` (its variance
diverges), so it is held flat below a corner wavenumber ``k_c`` chosen in closed form so
that the field's height standard deviation equals jacksboro's (`JACKSBORO_STD_M`):
``σ² = 2π A k_c^(2−β) (1/(β−2) + 1/2)``. Heights are lifted by `REGION_BASE_HEIGHT`.

The field is synthesised on a grid padded by a quarter (fast FFT lengths) and cropped, so
it is not periodic across the region's edges; it is written row-block by row-block into an
``np.lib.format.open_memmap`` file (float32, row 0 south), with a ``.json`` sidecar holding
the spacing and the generator settings.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np

from neuralmap.dem.synthetic import fast_length
from neuralmap.exceptions import NeuralMapError

__all__ = [
    "JACKSBORO_SPECTRUM",
    "JACKSBORO_STD_M",
    "PAPER_REGION_SHAPE",
    "PAPER_REGION_SPACING_M",
    "corner_wavenumber",
    "synthetic_region",
]

#: ``(A, β)`` of jacksboro's periodogram fit (``spectral_slope`` on ``load_tile("jacksboro")``).
JACKSBORO_SPECTRUM = (5.920157598185486e-07, 4.760593546953916)
#: Height standard deviation of the jacksboro sample, metres.
JACKSBORO_STD_M = 162.4566510964769
#: SEEDS 004's map: ``(ny, nx)`` nodes (127 km north-south, 361 km east-west).
PAPER_REGION_SHAPE = (1270, 3610)
#: SEEDS 004's grid spacing, metres.
PAPER_REGION_SPACING_M = 100.0
#: Mean height of the synthetic region, metres.
REGION_BASE_HEIGHT = 600.0


def corner_wavenumber(amplitude: float, beta: float, std_m: float) -> float:
    """The ``k_c`` (cycles/m) at which a flat-below power law has standard deviation ``std_m``.

    Args:
        amplitude: ``A`` of ``P(k) = A k^(−β)``, m⁴.
        beta: ``β > 2``.
        std_m: Target height standard deviation, metres.

    Returns:
        ``k_c = (σ² / (2π A (1/(β−2) + 1/2)))^(1/(2−β))``.
    """
    if not (beta > 2.0 and amplitude > 0.0 and std_m > 0.0):
        raise NeuralMapError(
            f"synthetic_region: need beta > 2, A > 0 and std > 0, got beta={beta}, "
            f"A={amplitude}, std={std_m}."
        )
    scale = 2.0 * math.pi * amplitude * (1.0 / (beta - 2.0) + 0.5)
    return (std_m**2 / scale) ** (1.0 / (2.0 - beta))


def synthetic_region(
    path: str | Path,
    shape: tuple[int, int] = PAPER_REGION_SHAPE,
    spacing: float = PAPER_REGION_SPACING_M,
    *,
    seed: int = 0,
    spectrum: tuple[float, float] = JACKSBORO_SPECTRUM,
    std_m: float = JACKSBORO_STD_M,
) -> dict[str, Any]:
    """Writes a fractal region with a given spectrum to a float32 ``.npy`` (memory-mapped).

    Args:
        path: Destination ``.npy``; ``<path>.json`` gets the description.
        shape: ``(ny, nx)`` nodes (default the paper's 1270 × 3610).
        spacing: Grid spacing, metres (default 100).
        seed: Seed of the NumPy generator (same seed, shape, spacing: same region).
        spectrum: ``(A, β)`` of the power law (default jacksboro's).
        std_m: Height standard deviation that sets the corner wavenumber.

    Returns:
        The description written to the sidecar (``shape``, ``spacing``, ``spectrum``,
        ``corner_wavenumber``, ``seed``, ``path``).

    Raises:
        NeuralMapError: Bad shape, spacing or spectrum.
    """
    ny, nx = (int(shape[0]), int(shape[1]))
    if ny < 8 or nx < 8 or not (math.isfinite(spacing) and spacing > 0):
        raise NeuralMapError(
            f"synthetic_region: shape must be at least 8 x 8 nodes and spacing > 0 m, got "
            f"{shape} and {spacing}."
        )
    amplitude, beta = float(spectrum[0]), float(spectrum[1])
    k_c = corner_wavenumber(amplitude, beta, std_m)
    py, px = fast_length(ny + ny // 4), fast_length(nx + nx // 4)
    rng = np.random.default_rng([int(seed), 0x5E610])
    ky = np.fft.fftfreq(py, d=spacing)[:, None]
    kx = np.fft.rfftfreq(px, d=spacing)[None, :]
    k = np.maximum(np.sqrt(kx**2 + ky**2), k_c)
    # E|c|^2 = P(k) / (N dx dy): the periodogram |FFT h|^2 dx dy / N then has mean P(k)
    coeff = np.sqrt(amplitude * k ** (-beta) / (py * px * spacing * spacing))
    del k
    coeff[0, 0] = 0.0
    noise = rng.standard_normal(coeff.shape) + 1j * rng.standard_normal(coeff.shape)
    coeff = coeff * noise * math.sqrt(0.5)
    del noise
    field = np.fft.irfft2(coeff * (py * px), s=(py, px))[:ny, :nx]
    del coeff
    field = field - field.mean() + REGION_BASE_HEIGHT
    path = Path(path)
    out = np.lib.format.open_memmap(path, mode="w+", dtype=np.float32, shape=(ny, nx))
    for start in range(0, ny, 256):
        out[start:start + 256] = field[start:start + 256]
    out.flush()
    del out
    info = {
        "path": str(path),
        "shape": [ny, nx],
        "spacing": [float(spacing), float(spacing)],
        "spectrum": {"A_m4": amplitude, "beta": beta, "source": "jacksboro periodogram fit"
                     if tuple(spectrum) == JACKSBORO_SPECTRUM else "given"},
        "corner_wavenumber_cpm": k_c,
        "target_std_m": std_m,
        "measured_std_m": float(field.std()),
        "seed": int(seed),
        "generator": "Gaussian random field, power law flat below k_c, padded FFT",
    }
    Path(str(path) + ".json").write_text(json.dumps(info, indent=1))
    return info
