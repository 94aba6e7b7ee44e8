"""Autocorrelation and partial autocorrelation of an error sequence (statsmodels).

Identification step 2 (SEEDS 000): the autocorrelation ``ρ_k = γ_k / γ_0`` feeds the method
of moments; the partial autocorrelation cuts off after lag p for an AR(p) sequence.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from neuralmap.errors.optional import require_statsmodels
from neuralmap.errors.sequence import as_sequence


def autocorrelation(sequence: Any, *, nlags: int = 20) -> np.ndarray:
    """Sample autocorrelation ``ρ̂_0 … ρ̂_nlags`` (biased, ``statsmodels.tsa.stattools.acf``).

    Args:
        sequence: ``(n,)`` samples with ``n > nlags``.
        nlags: Largest lag.

    Returns:
        ``(nlags + 1,)`` float64 array with ``ρ̂_0 = 1``.
    """
    x = as_sequence(sequence, where="autocorrelation", min_length=nlags + 2, why=f"{nlags} lags")
    require_statsmodels("autocorrelation")
    from statsmodels.tsa.stattools import acf

    return np.asarray(acf(x, nlags=nlags, adjusted=False, fft=False), dtype=np.float64)


def partial_autocorrelation(sequence: Any, *, nlags: int = 20) -> np.ndarray:
    """Sample partial autocorrelation by Yule–Walker on the biased autocovariance.

    Calls ``statsmodels.tsa.stattools.pacf(method="ywm")``: the lag-k value is the last
    coefficient of the order-k Yule–Walker (method-of-moments) AR fit.

    Args:
        sequence: ``(n,)`` samples with ``n ≥ 2 (nlags + 1)``.
        nlags: Largest lag.

    Returns:
        ``(nlags + 1,)`` float64 array with value 1 at lag 0.
    """
    x = as_sequence(
        sequence, where="partial_autocorrelation", min_length=2 * (nlags + 1), why=f"{nlags} lags"
    )
    require_statsmodels("partial_autocorrelation")
    from statsmodels.tsa.stattools import pacf

    return np.asarray(pacf(x, nlags=nlags, method="ywm"), dtype=np.float64)


def confidence_band(n: int, *, level: float = 0.95) -> float:
    """Half-width ``z_{(1+level)/2} / √n`` of the white-noise band for ρ̂_k and partial ρ̂_k."""
    from scipy.stats import norm

    return float(norm.ppf(0.5 + level / 2.0) / np.sqrt(n))
