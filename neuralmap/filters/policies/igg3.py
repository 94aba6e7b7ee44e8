"""IGG-III equivalent weights (Yang Yuanxi's robust estimation; SEEDS 002).

Standardised residual of component i: ``ṽ_i = |r_i| / sqrt(S_ii)``, ``S = H P⁻ Hᵀ + R``.
Equivalent-weight factor (SEEDS 002, IGG-III)::

    w(ṽ) = 1                                   ṽ ≤ k0
           (k0 / ṽ) · ((k1 − ṽ) / (k1 − k0))²  k0 < ṽ ≤ k1
           0                                   ṽ > k1

``p̄_i = p_i · w_i``: the equivalent covariance divides the variances by the weights
(``R̄_ii = R_ii / w_i``; for a full R the bifactor form ``R̄_ij = R_ij / sqrt(w_i w_j)``),
and a weight of 0 rejects the component. Typical constants: k0 = 1.0–1.5, k1 = 2.5–8.0.
"""

from __future__ import annotations

import torch

from neuralmap.filters.policies._common import (
    check_ordered,
    scale_variances,
    standardised_residual,
)
from neuralmap.filters.policy import Adaptation, FilterPolicy, UpdateContext

__all__ = ["IGG3", "igg3_weights"]


def igg3_weights(v_std: torch.Tensor, k0: float, k1: float) -> torch.Tensor:
    """IGG-III weight factors of standardised residuals (SEEDS 002, IGG-III).

    Args:
        v_std: ``(...)`` standardised residuals ``ṽ ≥ 0``.
        k0: Lower breakpoint (full weight up to it), > 0.
        k1: Upper breakpoint (zero weight beyond it), > k0.

    Returns:
        ``(...)`` factors in ``[0, 1]``: 1 for ``ṽ ≤ k0``,
        ``(k0/ṽ)((k1 − ṽ)/(k1 − k0))²`` for ``k0 < ṽ ≤ k1``, 0 for ``ṽ > k1``.

    Raises:
        NeuralMapError: Unless ``0 < k0 < k1``.
    """
    check_ordered(k0, k1, names=("k0", "k1"), where="igg3_weights")
    v = v_std.abs()
    mid = (v > k0) & (v <= k1)
    vs = torch.where(mid, v, k0)  # no division by 0 (and clean gradients) off the middle
    taper = (k0 / vs) * ((k1 - vs) / (k1 - k0)).square()
    return torch.where(v <= k0, 1.0, torch.where(mid, taper, 0.0))


class IGG3(FilterPolicy):
    """IGG-III robust update: per-component equivalent weights on standardised residuals.

    ``ṽ_i = |r_i| / sqrt(S_ii)`` with ``S`` from the context's ``R``; ``R̄ = R / w``
    (bifactor form for a full R); ``w_i = 0`` rejects component i (``keep`` False).

    Args:
        k0: Lower breakpoint (1.0–1.5 in SEEDS 002).
        k1: Upper breakpoint (2.5–8.0), > k0.

    Reports ``weight`` ``(N, m)`` and ``standardised_residual`` ``(N, m)``.

    Raises:
        NeuralMapError: Unless ``0 < k0 < k1``.
    """

    name = "igg3"

    def __init__(self, k0: float = 1.5, k1: float = 4.5) -> None:
        check_ordered(k0, k1, names=("k0", "k1"), where="IGG3")
        self.k0 = float(k0)
        self.k1 = float(k1)

    def adapt(self, context: UpdateContext) -> Adaptation:
        """Weights from the standardised residuals; the equivalent R and the rejections."""
        v = standardised_residual(context)
        w = igg3_weights(v, self.k0, self.k1)
        info = {"weight": w, "standardised_residual": v}
        if bool((w == 1).all()):
            return Adaptation(info=info)  # clean epoch: R unchanged, nothing rejected
        keep = w > 0
        R = scale_variances(context.R, torch.where(keep, w, 1.0))
        return Adaptation(R=R, keep=keep, info=info)
