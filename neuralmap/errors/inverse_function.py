"""The fit residual by the inverse-function method (SEEDS 000, identification step 4).

The inverse function of an ARMA model is the expansion ``a_t = x_t − Σ_{j≥1} I_j x_{t-j}``
of ``π(B) = φ(B) / θ(B)``: it turns the observed sequence back into the model's innovations.
Applied to the sample with zero pre-sample values it is the recursion
``a_t = x_t − Σ φ_i x_{t-i} + Σ θ_j a_{t-j}``; the fit residual is the mean square of
``a_t`` after the first ``start`` samples.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from neuralmap.errors.arma import ArmaModel, ar_polynomial, ma_polynomial
from neuralmap.exceptions import NeuralMapError


def inverse_function_weights(model: ArmaModel, n: int) -> np.ndarray:
    """Inverse-function weights ``I_1 … I_n`` with ``a_t = x_t − Σ I_j x_{t-j}``.

    For AR(p) they are ``φ_1 … φ_p`` followed by zeros; for ARMA(1, 1)
    ``I_j = (φ − θ) θ^{j-1}``.

    Args:
        model: The ARMA model (should be invertible, else the weights grow).
        n: Number of weights.

    Returns:
        ``(n,)`` float64 array.
    """
    from scipy.signal import lfilter

    impulse = np.zeros(n + 1)
    impulse[0] = 1.0
    pi = lfilter(ar_polynomial(model.phi), ma_polynomial(model.theta), impulse)
    return -pi[1:]


def innovations(sequence: Any, model: ArmaModel, *, demean: bool = True) -> np.ndarray:
    """Innovations ``a_t`` of sequences under an ARMA model (inverse function, zero start).

    Args:
        sequence: ``(..., n)`` samples; the recursion runs along the last axis.
        model: An invertible ARMA model.
        demean: Subtract each sequence's mean first (the models are zero-mean).

    Returns:
        ``(..., n)`` float64 innovations.
    """
    x = np.asarray(sequence, dtype=np.float64)
    if demean:
        x = x - x.mean(axis=-1, keepdims=True)
    if not model.is_invertible:
        raise NeuralMapError(
            f"innovations: {model.name} with theta={model.theta} is not invertible; its "
            "inverse function diverges. Use the invertible moment solution."
        )
    from scipy.signal import lfilter

    return lfilter(ar_polynomial(model.phi), ma_polynomial(model.theta), x, axis=-1)


def fit_residual(sequence: Any, model: ArmaModel, *, start: int | None = None) -> float:
    """Fit residual: mean square of the innovations ``a_t`` for ``t ≥ start``.

    Args:
        sequence: ``(n,)`` samples.
        model: An invertible ARMA model.
        start: First index counted (default ``p``: the first sample with a full AR history).
            Use one common ``start`` when residuals of several orders are compared.

    Returns:
        The residual variance estimate ``Σ_{t≥start} a_t² / (n − start)``.
    """
    a = innovations(sequence, model)
    start = model.p if start is None else int(start)
    if not 0 <= start < a.shape[-1]:
        raise NeuralMapError(
            f"fit_residual: start must be in [0, {a.shape[-1]}), got {start}."
        )
    return float(np.mean(a[..., start:] ** 2))
