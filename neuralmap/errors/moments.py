"""ARMA(p, q) parameters by the method of moments (SEEDS 000, identification step 3).

AR part: the (extended) Yule–Walker equations ``γ_k = Σ_i φ_i γ_{k-i}``, ``k = q+1 … q+p``
(for ``q = 0`` the ordinary Yule–Walker equations). MA part: the AR-filtered series
``w_t = φ(B) x_t`` is MA(q) with autocovariances
``c_j = Σ_{i,l} φ'_i φ'_l γ_{j+i-l}`` (``φ' = [1, −φ_1, …, −φ_p]``); its moment equations
``c_j = σ_a² Σ_k θ'_k θ'_{k+j}`` (``θ' = [1, −θ_1, …]``) are solved by factorising the
covariance generating function ``z^q Σ_{|j|≤q} c_|j| z^j`` and keeping the roots outside the
unit circle (the invertible solution). For ARMA(1, 1) this gives the paper's equations
``φ = ρ_2 / ρ_1`` and ``ρ_w θ² + θ + ρ_w = 0`` with ``ρ_w = c_1 / c_0``. An MA part has no
invertible moment solution when its generating function has roots on the unit circle (for
MA(1): ``|ρ_1| > 1/2``); then `MomentSolutionError` is raised.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from neuralmap.errors.arma import UNIT_ROOT_TOL, ArmaModel, ar_polynomial, order_name
from neuralmap.errors.sequence import as_sequence
from neuralmap.exceptions import NeuralMapError


class MomentSolutionError(NeuralMapError):
    """The moment equations of an order have no stationary, invertible real solution."""


def sample_autocovariance(sequence: Any, nlags: int) -> np.ndarray:
    """Biased sample autocovariance ``γ̂_k = (1/n) Σ_t (x_t − x̄)(x_{t+k} − x̄)``.

    The biased (divide-by-n) estimate keeps the Toeplitz matrix positive semi-definite, as
    the method of moments needs; it equals ``statsmodels.tsa.stattools.acovf``.

    Args:
        sequence: ``(n,)`` samples.
        nlags: Largest lag ``K < n``.

    Returns:
        ``(K + 1,)`` float64 array ``γ̂_0 … γ̂_K``.
    """
    x = as_sequence(sequence, where="sample_autocovariance", min_length=nlags + 1)
    xc = x - x.mean()
    n = xc.size
    return np.array([float(np.dot(xc[: n - k], xc[k:])) / n for k in range(nlags + 1)])


def arma_moments(autocovariance: np.ndarray, p: int, q: int) -> ArmaModel:
    """Method-of-moments ARMA(p, q) from autocovariances ``γ_0 … γ_{p+q}``.

    Args:
        autocovariance: ``(K + 1,)`` autocovariances with ``K ≥ p + q`` (sample or
            theoretical; autocorrelations also work, giving ``sigma2`` relative to ``γ_0``).
        p: AR order ≥ 0.
        q: MA order ≥ 0.

    Returns:
        The stationary, invertible `ArmaModel`; ``sigma2`` is the moment estimate of
        the innovation variance.

    Raises:
        MomentSolutionError: The extended Yule–Walker system is singular, its solution is not
            stationary, or the MA part has no invertible solution.
    """
    gamma = np.asarray(autocovariance, dtype=np.float64).reshape(-1)
    name = order_name(p, q)
    if p < 0 or q < 0:
        raise NeuralMapError(f"arma_moments: orders must be ≥ 0, got p={p}, q={q}.")
    if gamma.size < p + q + 1:
        raise NeuralMapError(
            f"arma_moments: {name} needs autocovariances up to lag {p + q}, got "
            f"{gamma.size - 1}. Pass more lags."
        )
    if not gamma[0] > 0.0:
        raise NeuralMapError(f"arma_moments: γ_0 must be > 0, got {gamma[0]!r}.")

    def acov(k: int) -> float:
        return float(gamma[abs(k)])

    phi = np.zeros(p)
    if p:
        a = np.array([[acov(q + k - i) for i in range(1, p + 1)] for k in range(1, p + 1)])
        b = np.array([acov(q + k) for k in range(1, p + 1)])
        try:
            phi = np.linalg.solve(a, b)
        except np.linalg.LinAlgError as exc:
            raise MomentSolutionError(
                f"arma_moments: the Yule–Walker system of {name} is singular."
            ) from exc
        if not ArmaModel(phi=tuple(phi)).is_stationary:
            raise MomentSolutionError(
                f"arma_moments: the moment AR coefficients {np.round(phi, 6).tolist()} of "
                f"{name} are not stationary."
            )
    ar = ar_polynomial(phi)
    c = np.array(
        [
            sum(ar[i] * ar[m] * acov(j + i - m) for i in range(p + 1) for m in range(p + 1))
            for j in range(q + 1)
        ]
    )
    if not c[0] > 0.0:
        raise MomentSolutionError(
            f"arma_moments: the AR-filtered series of {name} has variance {c[0]!r} ≤ 0."
        )
    if q == 0:
        return ArmaModel(phi=tuple(phi), theta=(), sigma2=float(c[0]))
    theta = _ma_from_covariances(c, name)
    ma = np.concatenate([[1.0], -theta])
    sigma2 = float(c[0] / np.dot(ma, ma))
    return ArmaModel(phi=tuple(phi), theta=tuple(theta), sigma2=sigma2)


def _ma_from_covariances(c: np.ndarray, name: str) -> np.ndarray:
    """Invertible MA(q) coefficients whose autocovariances are proportional to ``c``."""
    q = c.size - 1
    # z^q Σ_{|j|≤q} c_|j| z^j, coefficients from the highest power down (np.roots order).
    generating = np.concatenate([c[::-1], c[1:]])
    roots = np.roots(generating)
    moduli = np.abs(roots)
    outside = roots[moduli > 1.0 + UNIT_ROOT_TOL]
    at_infinity = 2 * q - roots.size  # np.roots drops vanishing leading coefficients
    if outside.size + at_infinity != q:
        raise MomentSolutionError(
            f"arma_moments: the MA part of {name} has no invertible moment solution (its "
            "covariance generating function has roots on the unit circle; for MA(1) this "
            "means |ρ_1| > 1/2)."
        )
    # θ(z) = Π (1 − z / r_k) = 1 − θ_1 z − … − θ_q z^q.
    poly = np.array([1.0 + 0j])
    for r in outside:
        poly = np.convolve(poly, np.array([1.0, -1.0 / r]))
    if np.max(np.abs(poly.imag)) > 1e-8 * max(1.0, float(np.max(np.abs(poly.real)))):
        raise MomentSolutionError(f"arma_moments: the MA part of {name} came out complex.")
    return -poly.real[1:]
