"""Windowed, block-restricted adaptive factor on the predicted covariance (SEEDS 003).

Paper 003 tunes the system noise by comparing the predicted-residual covariance with its
theoretical value. Its literal single-epoch form (`InnovationInflation`) takes one
epoch's ``λ = rᵀr / tr(S)`` — a χ²-like ratio that exceeds c0 on a large share of clean
epochs — and inflates all of ``P⁻``. The working forms of the literature estimate the
residual covariance over a *window* of epochs (covariance matching: Mohamed & Schwarz,
J. Geodesy 1999; Yang & Xu, J. Geodesy 2003, "adaptive factor from the predicted
residuals") and apply the factor to the states that the dynamic-model error concerns::

    Ĉ_V,k = (1/W_k) Σ_{j = k−W+1..k} r_j r_jᵀ        (W_k ≤ W epochs that this sample updated)
    λ_k   = tr(Ĉ_V,k) / tr(H P⁻ Hᵀ + R)_k
    α_k   = min(cap, λ_k / c0) if λ_k > c0 else 1      (paper 003's factor, capped)
    P⁻    ← D (Φ P Φᵀ) D + Q,   D = diag(√α on the block B, 1 elsewhere)

so the block's variances are scaled by α, its cross-covariances with the other states by
√α, and the rest of ``P⁻`` is untouched (a congruence: positive definiteness is kept).
``Φ P Φᵀ = P⁻ − Q`` with the Q of the last predict (``context.process_noise``); without a
known Q the policy scales ``P⁻`` itself (``D P⁻ D``). With ``window = 1``, the whole state
as the block and no cap this is exactly `InnovationInflation`.

Float32 caution: like the literal form, inflating the block of a state that no
measurement observes grows its variance without bound; use float64 (the default) for long
runs, and read ``healthy`` (frozen samples) from the filter.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.filters.policies._common import check_positive, diagonal, kept
from neuralmap.filters.policy import Adaptation, FilterPolicy, Posterior, UpdateContext

__all__ = ["WindowedInflation", "windowed_inflation_factor"]

#: Default block: position and velocity of the 15-state GNSS/INS error state
#: ``[δr, δv, ψ, δb_g, δb_a]`` (SEEDS 003).
POSITION_VELOCITY = (0, 1, 2, 3, 4, 5)


def windowed_inflation_factor(lam: torch.Tensor, c0: float, cap: float) -> torch.Tensor:
    """Capped adaptive factor ``α = min(cap, λ / c0)`` when ``λ > c0``, else 1.

    Args:
        lam: ``(...)`` windowed statistics ``λ = tr(Ĉ_V) / tr(S)``.
        c0: Threshold, > 0 (1–1.5 in SEEDS 003).
        cap: Largest factor, ≥ 1 (``math.inf`` = uncapped).

    Returns:
        ``(...)`` factors in ``[1, cap]``.

    Raises:
        NeuralMapError: ``c0`` not > 0 or ``cap`` below 1.
    """
    c0 = check_positive(c0, name="c0", where="windowed_inflation_factor")
    cap = _check_cap(cap, "windowed_inflation_factor")
    alpha = torch.where(lam > c0, lam / c0, torch.ones_like(lam))
    return alpha.clamp_max(cap) if math.isfinite(cap) else alpha


def _check_cap(cap: float, where: str) -> float:
    try:
        value = float(cap)
    except (TypeError, ValueError) as exc:
        raise NeuralMapError(f"{where}: 'cap' must be a number >= 1, got {cap!r}.") from exc
    if not value >= 1.0:  # also rejects NaN
        raise NeuralMapError(
            f"{where}: 'cap' = {value!r} must be >= 1 (the largest inflation factor α; "
            "α < 1 would shrink P⁻); pass e.g. cap=10, or math.inf for no cap."
        )
    return value


class WindowedInflation(FilterPolicy):
    """Covariance-matching adaptive factor over a window, applied to a state block.

    Args:
        c0: Threshold on λ (1–1.5 in SEEDS 003).
        window: Number of epochs W in the residual-covariance estimate (the current one
            included); must be at least the measurement dimension m.
        block: State indices the factor inflates (default: position and velocity of the
            15-state GNSS/INS error state, indices 0–5); all of them must lie in the state.
        cap: Largest factor α (≥ 1; ``math.inf`` for none).

    Reports ``alpha`` ``(N,)``, ``lambda`` ``(N,)`` and ``window`` ``(N,)`` (epochs in
    the estimate). Per-sample state (the last W − 1 values ``r_jᵀ r_j``) belongs to one
    filter: call `reset` before a new batch.

    Raises:
        NeuralMapError: ``window`` not an integer >= 1, a repeated or negative block
            index, ``cap`` below 1 (at construction); a window shorter than the
            measurement dimension or a block index outside the state (at the first update).
    """

    name = "windowed_inflation"

    def __init__(
        self,
        c0: float = 1.2,
        *,
        window: int = 10,
        block: Sequence[int] | None = POSITION_VELOCITY,
        cap: float = 10.0,
    ) -> None:
        where = "WindowedInflation"
        self.c0 = check_positive(c0, name="c0", where=where)
        if isinstance(window, bool) or not isinstance(window, int) or window < 1:
            raise NeuralMapError(
                f"{where}: 'window' = {window!r} must be an integer >= 1 (epochs of "
                "innovations in the covariance estimate; at least the measurement dimension)."
            )
        self.window = window
        if block is None:
            self.block: tuple[int, ...] | None = None
        else:
            try:
                idx = tuple(int(i) for i in block)
            except (TypeError, ValueError) as exc:
                raise NeuralMapError(
                    f"{where}: 'block' must be a sequence of state indices, got {block!r}."
                ) from exc
            if not idx or min(idx) < 0 or len(set(idx)) != len(idx):
                raise NeuralMapError(
                    f"{where}: 'block' = {list(block)} must be distinct state indices >= 0 "
                    "(e.g. [0, 1, 2, 3, 4, 5] for position and velocity), or None for the "
                    "whole state."
                )
            self.block = idx
        self.cap = _check_cap(cap, where)
        self._sq: torch.Tensor | None = None  # (N, W − 1) last rᵀr, newest last
        self._count: torch.Tensor | None = None  # (N,) stored epochs
        self._current: torch.Tensor | None = None

    def reset(self) -> None:
        """Forgets the stored innovations."""
        self._sq = self._count = self._current = None

    def _check(self, context: UpdateContext) -> None:
        n, m = context.P_prior.shape[-1], context.residual.shape[-1]
        if self.window < m:
            raise NeuralMapError(
                f"WindowedInflation: 'window' = {self.window} is shorter than the measurement "
                f"dimension m = {m}; a covariance estimate of {m} components needs at least "
                f"{m} epochs. Pass window >= {m}."
            )
        if self.block is not None and max(self.block) >= n:
            raise NeuralMapError(
                f"WindowedInflation: 'block' = {list(self.block)} has indices outside the "
                f"state (n = {n}, indices 0..{n - 1}); pass indices below {n}."
            )

    def _scale_vector(self, alpha: torch.Tensor, n: int) -> torch.Tensor:
        """``(N, n)`` diagonal of D: √α on the block, 1 elsewhere."""
        root = alpha.sqrt().unsqueeze(-1).expand(-1, n)
        if self.block is None:
            return root
        inside = torch.zeros(n, dtype=torch.bool, device=alpha.device)
        inside[list(self.block)] = True
        return torch.where(inside, root, torch.ones_like(root))

    def adapt(self, context: UpdateContext) -> Adaptation:
        """α from the windowed λ; ``P⁻ ← D (P⁻ − Q) D + Q`` (``D P⁻ D`` without Q)."""
        self._check(context)
        batch, n = context.x_prior.shape
        rr = context.residual.square()
        tr = diagonal(context.HPHt) + diagonal(context.R)
        keep = kept(context)
        if keep is not None:
            rr, tr = torch.where(keep, rr, 0.0), torch.where(keep, tr, 0.0)
        current = rr.sum(-1)
        tr_sum = tr.sum(-1)
        if self._sq is None or self._count is None:
            self._sq = context.residual.new_zeros(batch, self.window - 1)
            self._count = torch.zeros(batch, dtype=torch.long, device=context.residual.device)
        elif self._sq.shape[0] != batch:
            raise NeuralMapError(
                f"WindowedInflation: the policy holds innovations of {self._sq.shape[0]} "
                f"samples but this update has {batch}; call policy.reset() before a new "
                "batch (or use one policy object per filter)."
            )
        self._current = current
        used = self._count.clamp_max(self.window - 1)
        epochs = (used + 1).to(current.dtype)
        lam_num = (self._sq.sum(-1) + current) / epochs  # tr(Ĉ_V) (stored slots are 0 beyond count)
        lam = torch.where(tr_sum > 0, lam_num / torch.where(tr_sum > 0, tr_sum, 1.0), 0.0)
        alpha = torch.where(context.mask, windowed_inflation_factor(lam, self.c0, self.cap), 1.0)
        info = {"alpha": alpha, "lambda": lam, "window": epochs}
        if not alpha.requires_grad and bool((alpha == 1).all()):
            return Adaptation(info=info)  # no sample inflated: P⁻ unchanged
        d = self._scale_vector(alpha, n)
        outer = d.unsqueeze(-1) * d.unsqueeze(-2)  # (N, n, n) D·D entries
        Q = context.process_noise
        P = context.P_prior
        # D (P⁻ − Q) D + Q: exactly symmetric for symmetric P⁻ and Q; P⁻ itself where α = 1
        inflated = outer * P if Q is None else torch.addcmul(Q, outer, P - Q)
        return Adaptation(P_prior=torch.where((alpha > 1).reshape(-1, 1, 1), inflated, P),
                          info=info)

    def commit(
        self,
        context: UpdateContext,
        adaptation: Adaptation,
        posterior: Posterior,
        applied: torch.Tensor,
    ) -> None:
        """Stores this epoch's ``rᵀr`` for the samples that were updated."""
        if self._sq is None or self._count is None or self._current is None:
            return
        if self.window > 1:
            shifted = torch.cat([self._sq[:, 1:], self._current.unsqueeze(-1)], dim=1)
            self._sq = torch.where(applied.unsqueeze(-1), shifted, self._sq)
        self._count = torch.where(applied, self._count + 1, self._count)
        self._current = None
