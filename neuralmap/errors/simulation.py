"""Seeded, batched simulation of AR error sequences and AR error fields along grid lines.

Defaults are the paper's DEM-making error (SEEDS 000, Table 1): process standard deviation
σ = 1.0435 m and AR(1) coefficient φ = 0.5315 between neighbouring grid nodes. Sequences
start in the stationary distribution (the first p values are drawn with the model's
autocovariance), so there is no burn-in transient.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from neuralmap.errors.arma import ArmaModel, check_stationary
from neuralmap.exceptions import NeuralMapError

#: The paper's DEM-making error: standard deviation, m (SEEDS 000).
DEM_ERROR_SIGMA = 1.0435
#: The paper's AR(1) coefficient of the DEM-making error (SEEDS 000, Table 1).
DEM_ERROR_AR1 = (0.5315,)
#: The paper's AR(2) coefficients of the DEM-making error (SEEDS 000, Table 1).
DEM_ERROR_AR2 = (0.44417, 0.16430)


#: Grid spacing of the paper's map (SEEDS 000), m: its AR coefficients are per 100 m step.
PAPER_GRID_SPACING = 100.0


def ar1_coefficient(correlation_length_m: float, spacing_m: float) -> float:
    """AR(1) coefficient per grid step for an exponential correlation ``exp(−r / L)``.

    ``φ = exp(−d / L)``: the AR(1) sequence sampled every ``d`` metres has correlation
    ``φ^k = exp(−k d / L)``. The paper's φ = 0.5315 on its 100 m grid is ``L ≈ 158 m``
    (`correlation_length`); use this to carry it to a grid of another spacing.

    Args:
        correlation_length_m: ``L`` > 0, m.
        spacing_m: Grid step ``d`` > 0, m.
    """
    if not (correlation_length_m > 0.0 and spacing_m > 0.0):
        raise NeuralMapError(
            f"ar1_coefficient: correlation length and spacing must be > 0 m, got "
            f"{correlation_length_m!r} and {spacing_m!r}."
        )
    return float(np.exp(-spacing_m / correlation_length_m))


def correlation_length(phi: float, spacing_m: float = PAPER_GRID_SPACING) -> float:
    """Correlation length ``L = −d / ln φ`` of an AR(1) coefficient per grid step ``d``."""
    if not (0.0 < phi < 1.0 and spacing_m > 0.0):
        raise NeuralMapError(
            f"correlation_length: need 0 < phi < 1 and spacing > 0, got {phi!r}, {spacing_m!r}."
        )
    return float(-spacing_m / np.log(phi))


def unit_ar_model(phi: Sequence[float], *, where: str) -> ArmaModel:
    """The AR(p) model with coefficients ``phi`` scaled to unit process variance."""
    coef = check_stationary(phi, where=where)
    unit = ArmaModel(phi=tuple(coef), sigma2=1.0)
    return ArmaModel(phi=tuple(coef), sigma2=1.0 / unit.variance)


def ar_filter(white: np.ndarray, phi: Sequence[float], *, axis: int = -1) -> np.ndarray:
    """Turns unit-variance white lines into stationary unit-variance AR(p) lines.

    Along ``axis``: ``y_{0…p-1} = L w_{0…p-1}`` with ``L Lᵀ`` the AR(p) autocovariance
    Toeplitz matrix, then ``y_t = Σ φ_i y_{t-i} + σ_a w_t``. Lines that are correlated with
    each other across the other axes keep that correlation (so filtering rows, then columns,
    gives a separable field).

    Args:
        white: Array of independent (along ``axis``) unit-variance samples.
        phi: Stationary AR coefficients ``(φ_1, …, φ_p)``; empty for white output.
        axis: The axis the AR recursion runs along (loops over its length).

    Returns:
        Array of ``white``'s shape.
    """
    model = unit_ar_model(phi, where="ar_filter")
    w = np.moveaxis(np.asarray(white, dtype=np.float64), axis, 0)
    p = model.p
    n = w.shape[0]
    if p == 0:
        return np.moveaxis(w.copy(), 0, axis)
    if n < p:
        raise NeuralMapError(f"ar_filter: need at least {p} samples along the axis, got {n}.")
    gamma = model.autocovariance(p - 1)
    toeplitz = gamma[np.abs(np.subtract.outer(np.arange(p), np.arange(p)))]
    chol = np.linalg.cholesky(toeplitz)
    y = np.empty_like(w)
    y[:p] = np.tensordot(chol, w[:p], axes=(1, 0))
    std_a = float(np.sqrt(model.sigma2))
    for t in range(p, n):
        acc = std_a * w[t]
        for i, coef in enumerate(model.phi, start=1):
            acc = acc + coef * y[t - i]
        y[t] = acc
    return np.moveaxis(y, 0, axis)


def simulate_ar(
    n: int,
    *,
    phi: Sequence[float] = DEM_ERROR_AR1,
    sigma: float = DEM_ERROR_SIGMA,
    batch: int | None = None,
    seed: int = 0,
) -> np.ndarray:
    """Stationary AR(p) error sequences.

    Args:
        n: Samples per sequence.
        phi: Stationary AR coefficients (default the paper's AR(1) 0.5315; ``DEM_ERROR_AR2``
            for its AR(2)).
        sigma: Process standard deviation, m (not the innovation's).
        batch: Number of independent sequences (None: one, returned 1-D).
        seed: Seed of the NumPy generator.

    Returns:
        ``(batch, n)`` (or ``(n,)``) float64 array.
    """
    _check_sigma(sigma, "simulate_ar")
    if n < 1:
        raise NeuralMapError(f"simulate_ar: n must be ≥ 1, got {n}.")
    rng = np.random.default_rng(seed)
    white = rng.standard_normal((1 if batch is None else int(batch), int(n)))
    x = sigma * ar_filter(white, phi, axis=-1)
    return x[0] if batch is None else x


def ar_error_field(
    shape: tuple[int, int],
    *,
    phi: Sequence[float] = DEM_ERROR_AR1,
    phi_north: Sequence[float] | None = None,
    sigma: float = DEM_ERROR_SIGMA,
    batch: int | None = None,
    seed: int = 0,
) -> np.ndarray:
    """A separable AR error field: AR(p) along every grid row and every grid column.

    Correlation between nodes ``(i, j)`` and ``(i + k, j + l)`` is ``ρ_east(l) ρ_north(k)``,
    so every grid line (row or column) is a stationary AR sequence with the given
    coefficients and standard deviation ``sigma``.

    Args:
        shape: ``(ny, nx)`` grid size.
        phi: AR coefficients between east neighbours (per grid step).
        phi_north: AR coefficients between north neighbours (default ``phi``; ``()`` for
            independent rows).
        sigma: Standard deviation of the field, m.
        batch: Number of independent fields (None: one, returned 2-D).
        seed: Seed of the NumPy generator.

    Returns:
        ``(batch, ny, nx)`` (or ``(ny, nx)``) float64 array.
    """
    _check_sigma(sigma, "ar_error_field")
    ny, nx = (int(v) for v in shape)
    if ny < 1 or nx < 1:
        raise NeuralMapError(f"ar_error_field: shape must be positive, got {shape}.")
    rng = np.random.default_rng(seed)
    white = rng.standard_normal((1 if batch is None else int(batch), ny, nx))
    field = ar_filter(white, phi, axis=-1)
    field = ar_filter(field, phi if phi_north is None else phi_north, axis=-2)
    field = sigma * field
    return field[0] if batch is None else field


def _check_sigma(sigma: float, where: str) -> None:
    if not (np.isfinite(sigma) and sigma >= 0.0):
        raise NeuralMapError(f"{where}: sigma must be finite and ≥ 0 metres, got {sigma!r}.")
