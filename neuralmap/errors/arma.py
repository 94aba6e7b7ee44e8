"""The ARMA(p, q) error model and its stationarity / invertibility conditions.

Convention (Box–Jenkins, the signs of the paper's Table 1, SEEDS 000):

    x_t = φ_1 x_{t-1} + … + φ_p x_{t-p} + a_t − θ_1 a_{t-1} − … − θ_q a_{t-q},

with white innovations ``a_t`` of variance ``σ_a²``. In backshift form ``φ(B) x = θ(B) a`` with
``φ(B) = 1 − Σ φ_i Bⁱ`` and ``θ(B) = 1 − Σ θ_j Bʲ``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from neuralmap.exceptions import NeuralMapError

#: Roots of φ(z) or θ(z) closer than this to the unit circle count as on it.
UNIT_ROOT_TOL = 1e-8


def ar_polynomial(phi: Sequence[float]) -> np.ndarray:
    """``φ(B)`` coefficients ``[1, −φ_1, …, −φ_p]`` (ascending powers of B)."""
    return np.concatenate([[1.0], -np.asarray(phi, dtype=np.float64).reshape(-1)])


def ma_polynomial(theta: Sequence[float]) -> np.ndarray:
    """``θ(B)`` coefficients ``[1, −θ_1, …, −θ_q]`` (ascending powers of B)."""
    return np.concatenate([[1.0], -np.asarray(theta, dtype=np.float64).reshape(-1)])


def polynomial_roots(coefficients: np.ndarray) -> np.ndarray:
    """Roots in z of ``c_0 + c_1 z + … + c_k z^k`` (ascending coefficients); empty for k = 0."""
    c = np.trim_zeros(np.asarray(coefficients, dtype=np.float64), "b")
    if c.size <= 1:
        return np.zeros(0, dtype=np.complex128)
    return np.roots(c[::-1])


def check_stationary(phi: Sequence[float], *, where: str) -> np.ndarray:
    """Raises NeuralMapError unless the AR part ``φ`` is stationary.

    Stationary means every root of ``φ(z) = 1 − Σ φ_i zⁱ`` lies strictly outside the unit
    circle (equivalently the companion matrix, e.g. the augmented filter's AR block, has all
    eigenvalues strictly inside it).

    Args:
        phi: AR coefficients ``(φ_1, …, φ_p)``.
        where: Caller, for the message.

    Returns:
        ``(p,)`` float64 array of the coefficients.
    """
    coef = np.asarray(phi, dtype=np.float64).reshape(-1)
    if not np.all(np.isfinite(coef)):
        raise NeuralMapError(f"{where}: AR coefficients must be finite, got {coef.tolist()}.")
    roots = polynomial_roots(ar_polynomial(coef))
    if roots.size and np.min(np.abs(roots)) <= 1.0 + UNIT_ROOT_TOL:
        hint = (
            "For AR(1) use |φ_1| < 1"
            if coef.size == 1
            else "For AR(2) use φ_1 + φ_2 < 1, φ_2 − φ_1 < 1 and |φ_2| < 1"
            if coef.size == 2
            else "Re-identify the model or shrink the coefficients"
        )
        raise NeuralMapError(
            f"{where}: AR coefficients {coef.tolist()} are not stationary: the roots of "
            f"φ(z) = 1 − Σ φ_i zⁱ have moduli {np.round(np.abs(roots), 6).tolist()}, and all "
            f"must exceed 1 (a map-error state driven by them would grow without bound). "
            f"{hint}."
        )
    return coef


@dataclass(frozen=True)
class ArmaModel:
    """An ARMA(p, q) model with innovation variance (see the module docstring for signs).

    Attributes:
        phi: AR coefficients ``(φ_1, …, φ_p)``.
        theta: MA coefficients ``(θ_1, …, θ_q)``.
        sigma2: Innovation variance ``σ_a²`` (m² for map errors).
    """

    phi: tuple[float, ...] = ()
    theta: tuple[float, ...] = ()
    sigma2: float = 1.0

    def __post_init__(self) -> None:
        object.__setattr__(self, "phi", tuple(float(v) for v in np.ravel(self.phi)))
        object.__setattr__(self, "theta", tuple(float(v) for v in np.ravel(self.theta)))
        object.__setattr__(self, "sigma2", float(self.sigma2))
        values = (*self.phi, *self.theta, self.sigma2)
        if not all(math.isfinite(v) for v in values) or self.sigma2 < 0.0:
            raise NeuralMapError(
                f"ArmaModel: coefficients must be finite and sigma2 ≥ 0, got phi={self.phi}, "
                f"theta={self.theta}, sigma2={self.sigma2}."
            )

    @property
    def p(self) -> int:
        """AR order."""
        return len(self.phi)

    @property
    def q(self) -> int:
        """MA order."""
        return len(self.theta)

    @property
    def n_params(self) -> int:
        """Number of ARMA coefficients ``p + q`` (the F-test counts these)."""
        return self.p + self.q

    @property
    def name(self) -> str:
        """``"AR(p)"``, ``"MA(q)"``, ``"ARMA(p,q)"`` or ``"white noise"``."""
        return order_name(self.p, self.q)

    @property
    def is_stationary(self) -> bool:
        """True when every root of ``φ(z)`` lies strictly outside the unit circle."""
        roots = polynomial_roots(ar_polynomial(self.phi))
        return bool(roots.size == 0 or np.min(np.abs(roots)) > 1.0 + UNIT_ROOT_TOL)

    @property
    def is_invertible(self) -> bool:
        """True when every root of ``θ(z)`` lies strictly outside the unit circle."""
        roots = polynomial_roots(ma_polynomial(self.theta))
        return bool(roots.size == 0 or np.min(np.abs(roots)) > 1.0 + UNIT_ROOT_TOL)

    def psi_weights(self, n: int) -> np.ndarray:
        """First ``n`` weights of ``x_t = Σ ψ_j a_{t-j}`` (``ψ_0 = 1``); ``(n,)``."""
        from scipy.signal import lfilter

        impulse = np.zeros(n)
        impulse[0] = 1.0
        return lfilter(ma_polynomial(self.theta), ar_polynomial(self.phi), impulse)

    def autocovariance(self, nlags: int) -> np.ndarray:
        """Theoretical autocovariance ``γ_0 … γ_nlags`` of a stationary model; ``(nlags+1,)``.

        Sums ``γ_k = σ_a² Σ_j ψ_j ψ_{j+k}`` until the ψ weights fall below 1e-17 of the first.
        """
        if not self.is_stationary:
            raise NeuralMapError(
                f"ArmaModel.autocovariance: {self.name} with phi={self.phi} is not "
                "stationary; it has no autocovariance."
            )
        roots = polynomial_roots(ar_polynomial(self.phi))
        if roots.size:
            decay = 1.0 / float(np.min(np.abs(roots)))
            n = int(math.ceil(math.log(1e-17) / math.log(decay))) if decay > 0 else 1
        else:
            n = 1
        n = min(max(n, 1) + self.q + nlags + 1, 2_000_000)
        psi = self.psi_weights(n)
        return self.sigma2 * np.array(
            [float(np.dot(psi[: n - k], psi[k:])) for k in range(nlags + 1)]
        )

    @property
    def variance(self) -> float:
        """Process variance ``γ_0``."""
        return float(self.autocovariance(0)[0])

    def to_dict(self) -> dict[str, Any]:
        """JSON-serialisable summary."""
        return {
            "name": self.name,
            "p": self.p,
            "q": self.q,
            "phi": list(self.phi),
            "theta": list(self.theta),
            "sigma2": self.sigma2,
        }


def order_name(p: int, q: int) -> str:
    """Display name of the order ``(p, q)``."""
    if p == 0 and q == 0:
        return "white noise"
    if q == 0:
        return f"AR({p})"
    if p == 0:
        return f"MA({q})"
    return f"ARMA({p},{q})"
