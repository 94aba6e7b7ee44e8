"""Yang's adaptive factor on the predicted covariance (SEEDS 002, robust adaptive filter).

Predicted-residual statistic (SEEDS 002, reconstructed)::

    Δ = sqrt(V̄ᵀV̄ / tr(A Σ_x̄ Aᵀ + Σ̄))          (here: rᵀr / tr(H P⁻ Hᵀ + R))

three-segment adaptive factor::

    α = 1                                    Δ ≤ c0
        (c0 / Δ) · ((c1 − Δ) / (c1 − c0))²  c0 < Δ ≤ c1
        0  (a small floor instead)           Δ > c1

and the two-segment form ``α = 1`` (Δ ≤ c0), ``c0 / Δ`` (Δ > c0). The gain
``K = (1/α) Σ_x̄ Aᵀ ((1/α) A Σ_x̄ Aᵀ + Σ̄)⁻¹`` is the Kalman gain with ``P⁻ / α``:
the policy sets ``p_scale = 1/α`` (the prediction is trusted less when the residuals are
too large for it). Typical constants: c0 = 1.0–1.5, c1 = 3.0–8.5.

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

from neuralmap.exceptions import NeuralMapError
from neuralmap.filters.policies._common import (
    check_ordered,
    check_positive,
    residual_statistic,
)
from neuralmap.filters.policies.observed import check_scope, observed_increase, resolve_scope
from neuralmap.filters.policy import Adaptation, FilterPolicy, UpdateContext

__all__ = ["YangAdaptive", "yang_factor"]

#: Default floor of the adaptive factor (α = 0 would divide P⁻ by zero).
ALPHA_FLOOR = 1e-3


def _check_yang(c0: float, c1: float | None, segments: int, floor: float, where: str) -> None:
    if segments not in (2, 3):
        raise NeuralMapError(
            f"{where}: 'segments' must be 2 or 3 (two- or three-segment adaptive factor), "
            f"got {segments!r}."
        )
    if segments == 3:
        if c1 is None:
            raise NeuralMapError(f"{where}: the three-segment factor needs 'c1' (> c0).")
        check_ordered(c0, c1, names=("c0", "c1"), where=where)
    else:
        check_positive(c0, name="c0", where=where)
    f = check_positive(floor, name="floor", where=where)
    if f > 1.0:
        raise NeuralMapError(f"{where}: 'floor' = {f!r} must lie in (0, 1].")


def yang_factor(
    delta: torch.Tensor,
    c0: float,
    c1: float | None = None,
    segments: int = 3,
    floor: float = ALPHA_FLOOR,
) -> torch.Tensor:
    """Yang's adaptive factor α of the predicted-residual statistic Δ (SEEDS 002).

    Args:
        delta: ``(...)`` statistics ``Δ ≥ 0``.
        c0: First breakpoint, > 0.
        c1: Second breakpoint, > c0 (three-segment form only).
        segments: 3 (default) or 2 (``α = c0/Δ`` beyond c0).
        floor: Smallest returned α, in ``(0, 1]`` (replaces the third segment's 0).

    Returns:
        ``(...)`` factors in ``[floor, 1]``.

    Raises:
        NeuralMapError: Bad breakpoints, segments or floor.
    """
    _check_yang(c0, c1, segments, floor, "yang_factor")
    d = delta.abs()
    if segments == 2:
        big = d > c0
        alpha = torch.where(big, c0 / torch.where(big, d, c0), 1.0)
    else:
        assert c1 is not None
        mid = (d > c0) & (d <= c1)
        ds = torch.where(mid, d, c0)
        taper = (c0 / ds) * ((c1 - ds) / (c1 - c0)).square()
        alpha = torch.where(d <= c0, 1.0, torch.where(mid, taper, 0.0))
    return alpha.clamp_min(floor)


class YangAdaptive(FilterPolicy):
    """Yang's adaptive factor: ``P⁻ ← P⁻ / α(Δ)``, ``Δ = sqrt(rᵀr / tr(H P⁻ Hᵀ + R))``.

    Sums run over the components still kept (after a robust policy in a composition);
    ``R`` is the context's (the equivalent ``R̄`` inside `RobustAdaptive`).

    Args:
        c0: First breakpoint (1.0–1.5 in SEEDS 002).
        c1: Second breakpoint (3.0–8.5), > c0; ignored by the two-segment form.
        segments: 3 (default) or 2.
        floor: Smallest α (so ``1/α`` stays finite), default 1e-3.
        scope: ``"full"`` (SEEDS 002's ``P⁻/α`` in every direction), ``"observed"``: the
            same gain and state update with only the measured directions inflated
            (`observed`), which keeps ``P`` conditioned
            along a whole trajectory, in float32 too; or ``"auto"`` (default): ``"full"``
            in float64, ``"observed"`` in float32.

    Reports ``alpha`` ``(N,)`` and ``delta`` ``(N,)``.
    """

    name = "yang"

    def __init__(
        self,
        c0: float = 1.0,
        c1: float | None = 3.0,
        segments: int = 3,
        floor: float = ALPHA_FLOOR,
        scope: str = "auto",
    ) -> None:
        _check_yang(c0, c1, segments, floor, "YangAdaptive")
        self.scope = check_scope(scope, "YangAdaptive")
        self.c0 = float(c0)
        self.c1 = None if c1 is None else float(c1)
        self.segments = int(segments)
        self.floor = float(floor)

    def adapt(self, context: UpdateContext) -> Adaptation:
        """α from Δ; ``p_scale = 1/α`` (1 on masked samples)."""
        delta = torch.sqrt(residual_statistic(context))
        alpha = yang_factor(delta, self.c0, self.c1, self.segments, self.floor)
        alpha = torch.where(context.mask, alpha, 1.0)
        info = {"alpha": alpha, "delta": delta}
        if not alpha.requires_grad and bool((alpha == 1).all()):
            return Adaptation(info=info)  # nothing to scale (clean epoch): skip the product
        if resolve_scope(self.scope, context.P_prior.dtype) == "observed":  # Δ = (1/α − 1) P⁻, seen through H only
            delta = context.P_prior * (1.0 / alpha - 1.0).reshape(-1, 1, 1)
            return Adaptation(P_prior=observed_increase(context, delta), info=info)
        return Adaptation(p_scale=1.0 / alpha, info=info)
