"""Inflation of the predicted covariance in the measured directions only.

An adaptive factor on ``P⁻`` (Yang's ``P⁻/α``, SEEDS 002; the innovation inflation
``α Φ P Φᵀ + Q``, SEEDS 003) replaces ``P⁻`` by ``P_lit = P⁻ + Δ`` with ``Δ ⪰ 0``. The
update reads the prediction only through ``P⁻ Hᵀ`` and ``H P⁻ Hᵀ``, so the same update
(gain, innovation covariance, state step) follows from the smallest such increase that
keeps both products — the part of ``Δ`` the measurement sees (its Nyström projection on
``Hᵀ``)::

    P' = P⁻ + Δ Hᵀ (H Δ Hᵀ)⁺ H Δ          (⪯ P_lit;  P' Hᵀ = P_lit Hᵀ,  H P' Hᵀ = H P_lit Hᵀ)

The literal ``P_lit`` also inflates the directions no measurement sees; along a whole
trajectory their variances then grow epoch after epoch (jacksboro-like TAN with the
three-segment factor: ``max P`` 7e7 m², condition 2e7), which float32 cannot hold (the
float32 run departs from the float64 one by kilometres). ``P'`` bounds that growth by what
the measurements see, so float32 follows float64.
"""

from __future__ import annotations

import torch

from neuralmap.filters.policy import UpdateContext
from neuralmap.filters.stats import symmetrize

__all__ = ["SCOPES", "check_scope", "observed_increase", "resolve_scope"]

#: Where an adaptive factor on ``P⁻`` acts: ``"full"`` = every direction (the papers'
#: literal form), ``"observed"`` = the measured directions only (`observed_increase`),
#: ``"auto"`` = ``"full"`` in float64 and ``"observed"`` in lower precision
#: (`resolve_scope`).
SCOPES = ("auto", "full", "observed")


def resolve_scope(scope: str, dtype: torch.dtype) -> str:
    """The scope an update in ``dtype`` uses: ``"auto"`` is the papers' literal ``"full"``
    in float64 (every float64 result is that of the papers' form) and ``"observed"`` in
    float32 and below, which cannot hold the literal form's growth along a trajectory."""
    if scope != "auto":
        return scope
    return "full" if dtype == torch.float64 else "observed"


def check_scope(scope: str, where: str) -> str:
    """``scope`` if it is one of `SCOPES`, else a NeuralMapError naming the fix."""
    from neuralmap.exceptions import NeuralMapError

    if scope not in SCOPES:
        raise NeuralMapError(f"{where}: 'scope' must be one of {', '.join(SCOPES)} "
                             f"(full = the paper's P⁻ scaling, observed = only the measured "
                             f"directions, auto = full in float64 and observed in float32), got {scope!r}.")
    return scope


def observed_increase(context: UpdateContext, delta: torch.Tensor) -> torch.Tensor:
    """``P⁻ + Δ Hᵀ (H Δ Hᵀ)⁺ H Δ`` per sample (equation in the module docstring).

    Rejected components (``context.keep`` False) and masked samples (zero rows of ``H``)
    see nothing, so they add nothing; where ``H Δ Hᵀ`` is zero ``P⁻`` is returned as is.

    Args:
        context: The update context (``P_prior`` ``(N, n, n)``, ``H`` ``(N, m, n)``).
        delta: ``(N, n, n)`` symmetric positive semi-definite increase ``P_lit − P⁻``.

    Returns:
        ``(N, n, n)`` exactly symmetric predicted covariance.
    """
    H = context.H
    if context.keep is not None:
        H = H * context.keep.to(H.dtype).unsqueeze(-1)
    W = torch.matmul(delta, H.transpose(1, 2))  # (N, n, m) = Δ Hᵀ
    M = torch.matmul(H, W)  # (N, m, m) = H Δ Hᵀ
    if M.shape[-1] == 1:  # scalar measurement: (H Δ Hᵀ)⁺ is 1/v where v > 0
        v = M[..., 0, 0]
        inv = torch.where(v > 0, 1.0 / torch.where(v > 0, v, torch.ones_like(v)),
                          torch.zeros_like(v))
        D = torch.matmul(W, W.transpose(1, 2)) * inv.reshape(-1, 1, 1)
    else:
        M = symmetrize(M)
        D = torch.matmul(torch.matmul(W, torch.linalg.pinv(M, hermitian=True)),
                         W.transpose(1, 2))
    return context.P_prior + symmetrize(D)  # a + b == b + a: exact symmetry
