"""The robust adaptive filter (RAF) of SEEDS 002: IGG-III weights, then Yang's factor.

Per update: standardised residuals ``ṽ_i = |r_i| / sqrt(S_ii)`` → IGG-III weights →
equivalent ``R̄`` (rejections for weight 0); then
``Δ = sqrt(V̄ᵀV̄ / tr(H P⁻ Hᵀ + R̄))`` over the kept components → adaptive factor α →
gain ``K = (1/α) P⁻ Hᵀ ((1/α) H P⁻ Hᵀ + R̄)⁻¹`` (SEEDS 002). On clean data (every
``ṽ ≤ k0`` and ``Δ ≤ c0``) it is the plain Kalman update.
"""

from __future__ import annotations

from neuralmap.filters.policies.compose import Compose
from neuralmap.filters.policies.igg3 import IGG3
from neuralmap.filters.policies.yang import ALPHA_FLOOR, YangAdaptive

__all__ = ["RobustAdaptive"]


class RobustAdaptive(Compose):
    """IGG-III equivalent weights followed by Yang's three-segment adaptive factor.

    Args:
        k0: First IGG-III breakpoint (1.0–1.5).
        k1: Second IGG-III breakpoint (2.5–8.0).
        c0: First adaptive-factor breakpoint (1.0–1.5).
        c1: Second adaptive-factor breakpoint (3.0–8.5).
        segments: 3 (default) or 2 for the adaptive factor.
        floor: Smallest α.

    Reports ``igg3.weight``, ``igg3.standardised_residual``, ``yang.alpha``,
    ``yang.delta``.
    """

    name = "raf"

    def __init__(
        self,
        k0: float = 1.5,
        k1: float = 4.5,
        c0: float = 1.0,
        c1: float = 3.0,
        segments: int = 3,
        floor: float = ALPHA_FLOOR,
    ) -> None:
        super().__init__(IGG3(k0, k1), YangAdaptive(c0, c1, segments=segments, floor=floor))
