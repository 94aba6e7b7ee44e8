"""Protection levels: the radius that contains the true position except with a stated risk.

Aviation's integrity vocabulary (RTCA DO-229 for SBAS, the ICAO GNSS SARPs): a
**protection level** bounds the position error of a fix except with the **integrity risk**
(a probability per epoch); a fix whose error exceeds its protection level while the system
says it is usable is **misleading information**; an **alert limit** is the largest
protection level an operation tolerates (above it the navigation is **unavailable**). The
GNSS augmentation systems compute the horizontal level from the error covariance,
``HPL = K_H · d_major`` with ``d_major`` the semi-major axis of the error ellipse; the
toolkit follows that form with ``K_H`` from the risk:

* ``HPL = sqrt(λ_max(P_xy) · χ²₂(1 − risk))``, ``χ²₂(1 − risk) = −2 ln(risk)``: for a
  Gaussian error with covariance ``P_xy`` the probability outside this circle is at most
  the risk (exactly the risk when ``P_xy`` is circular: the Rayleigh tail
  ``exp(−r² / 2σ²)``), a conservative bound otherwise;
* ``VPL = sqrt(P_hh) · Φ⁻¹(1 − risk/2)`` (two-sided normal quantile).

The covariance is the method's own posterior covariance (`neuralmap.tan.method`): an EKF's,
or the moments of a point-mass lattice.
"""

from __future__ import annotations

import functools
import math

import torch

__all__ = ["horizontal_k", "largest_sigma", "protection_levels", "vertical_k"]


@functools.lru_cache(maxsize=64)
def horizontal_k(risk: float) -> float:
    """``K_H = sqrt(χ²₂(1 − risk)) = sqrt(−2 ln risk)``."""
    return math.sqrt(-2.0 * math.log(risk))


@functools.lru_cache(maxsize=64)
def vertical_k(risk: float) -> float:
    """``K_V = Φ⁻¹(1 − risk / 2)``: ``−ndtri(risk / 2)`` (`scipy.special.ndtri`, what
    ``scipy.stats.norm.isf`` computes, without importing scipy.stats)."""
    from scipy.special import ndtri

    return float(-ndtri(0.5 * risk))


def largest_sigma(cov: torch.Tensor) -> torch.Tensor:
    """``(N,)`` ``sqrt(λ_max)`` of the horizontal block of ``cov (N, ≥2, ≥2)`` (closed form of
    a symmetric 2 × 2: ``λ_max = (a + c)/2 + sqrt(((a − c)/2)² + b²)``)."""
    a, b, c = cov[:, 0, 0], 0.5 * (cov[:, 0, 1] + cov[:, 1, 0]), cov[:, 1, 1]
    lam = 0.5 * (a + c) + torch.sqrt((0.5 * (a - c)) ** 2 + b * b)
    return lam.clamp_min(0.0).sqrt()


def protection_levels(cov: torch.Tensor, risk: float, *, sigma: torch.Tensor | None = None
                      ) -> tuple[torch.Tensor, torch.Tensor]:
    """Horizontal and vertical protection levels ``(N,)`` each, m (module docstring).

    Args:
        cov: ``(N, 5, 5)`` covariance of ``[x, y, h, v_x, v_y]``.
        risk: Integrity risk per epoch, in ``(0, 0.5)``.
        sigma: ``(N,)`` `largest_sigma` of ``cov`` when the caller has it.
    """
    hpl = (largest_sigma(cov) if sigma is None else sigma) * horizontal_k(risk)
    vpl = cov[:, 2, 2].clamp_min(0.0).sqrt() * vertical_k(risk)
    return hpl, vpl
