"""Innovation-based inflation of the predicted covariance (SEEDS 003, system-noise tuning).

Predicted-residual statistic and factor (SEEDS 003, reconstructed)::

    λ = V̄ᵀV̄ / tr(H (Φ P Φᵀ + Q) Hᵀ + R)
    α = 1 (λ ≤ c0),  λ / c0 (λ > c0)          c0 = 1–1.5
    P⁻ = α Φ P Φᵀ + Q

The filter's ``P⁻ = Φ P Φᵀ + Q`` is given, so ``α Φ P Φᵀ + Q = α P⁻ − (α − 1) Q`` with the
Q of the last predict (``context.process_noise``); without a known Q the policy inflates
the whole ``P⁻`` (``α P⁻``). α ≥ 1 keeps ``P⁻`` positive definite.

Float32 caution: used alone (without a robust R policy), this factor inflates ``P⁻`` in
every direction, including directions no measurement sees; their variances then grow
epoch after epoch until, in float32, samples lose positive definiteness and the filter
freezes them (``healthy`` False), and long before that a float32 run departs from the
float64 one. Run it in float64 (the default), or pass ``scope="observed"`` (the same gain,
only the measured directions inflated), or use the windowed factor on the observed block,
`WindowedInflation`.
"""

from __future__ import annotations

import torch

from neuralmap.filters.policies._common import check_positive, residual_statistic
from neuralmap.filters.policies.observed import check_scope, observed_increase, resolve_scope
from neuralmap.filters.policy import Adaptation, FilterPolicy, UpdateContext

__all__ = ["InnovationInflation", "innovation_inflation_factor"]


def innovation_inflation_factor(lam: torch.Tensor, c0: float) -> torch.Tensor:
    """Paper 003's adaptive factor: ``α = λ / c0`` when ``λ > c0``, else 1.

    Args:
        lam: ``(...)`` statistics ``λ = rᵀr / tr(S)``.
        c0: Threshold, > 0 (1–1.5 in the paper).

    Returns:
        ``(...)`` factors ``α ≥ 1``.
    """
    c0 = check_positive(c0, name="c0", where="innovation_inflation_factor")
    return torch.where(lam > c0, lam / c0, torch.ones_like(lam))


class InnovationInflation(FilterPolicy):
    """Inflates ``P⁻`` to ``α Φ P Φᵀ + Q`` when ``λ = rᵀr / tr(H P⁻ Hᵀ + R)`` exceeds c0.

    Args:
        c0: Threshold on λ (1–1.5 in SEEDS 003).
        scope: ``"full"`` (SEEDS 003's ``α Φ P Φᵀ + Q``), ``"observed"``: the same gain
            and state update with only the measured directions inflated
            (`observed`), which keeps ``P`` conditioned
            along a whole trajectory, in float32 too; or ``"auto"`` (default): ``"full"``
            in float64, ``"observed"`` in float32.

    Reports ``alpha`` ``(N,)`` and ``lambda`` ``(N,)``.
    """

    name = "inflation"

    def __init__(self, c0: float = 1.2, scope: str = "auto") -> None:
        self.c0 = check_positive(c0, name="c0", where="InnovationInflation")
        self.scope = check_scope(scope, "InnovationInflation")

    def adapt(self, context: UpdateContext) -> Adaptation:
        """α from λ; ``P⁻ = α P⁻ − (α − 1) Q`` (``α P⁻`` when Q is unknown)."""
        lam = residual_statistic(context)
        alpha = torch.where(context.mask, innovation_inflation_factor(lam, self.c0), 1.0)
        info = {"alpha": alpha, "lambda": lam}
        Q = context.process_noise
        if not alpha.requires_grad and bool((alpha == 1).all()):
            return Adaptation(info=info)  # clean epoch: P⁻ unchanged
        if resolve_scope(self.scope, context.P_prior.dtype) == "observed":  # Δ = (α − 1) Φ P Φᵀ (or (α − 1) P⁻), seen through H
            a = alpha.reshape(-1, 1, 1)
            spread = context.P_prior if Q is None else context.P_prior - Q
            return Adaptation(P_prior=observed_increase(context, (a - 1.0) * spread),
                              info=info)
        if Q is None:
            return Adaptation(p_scale=alpha, info=info)
        a = alpha.reshape(-1, 1, 1)
        # α P⁻ − (α − 1) Q: exactly symmetric for symmetric P⁻ and Q (entry (i, j) and
        # (j, i) see the same operands), and P⁻ itself where α = 1
        P = torch.addcmul(a * context.P_prior, a - 1.0, Q, value=-1.0)
        return Adaptation(P_prior=P, info=info)
