"""Shared helpers of the update policies: parameter checks and per-component statistics.

Everything works batch first on the tensors of an
`UpdateContext`: ``N`` samples, ``m`` measurement
components.
"""

from __future__ import annotations

import math

import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.filters.policy import UpdateContext


def check_positive(value: float, *, name: str, where: str) -> float:
    """``value`` as a finite float > 0, else a NeuralMapError."""
    try:
        out = float(value)
    except (TypeError, ValueError) as exc:
        raise NeuralMapError(f"{where}: '{name}' must be a number, got {value!r}.") from exc
    if not 0.0 < out < math.inf:
        raise NeuralMapError(
            f"{where}: '{name}' = {out!r} must be finite and > 0; pass a positive number."
        )
    return out


def check_ordered(low: float, high: float, *, names: tuple[str, str], where: str) -> None:
    """Raises unless ``0 < low < high < inf`` (the breakpoints of a weight function)."""
    lo = check_positive(low, name=names[0], where=where)
    hi = check_positive(high, name=names[1], where=where)
    if not lo < hi:
        raise NeuralMapError(
            f"{where}: breakpoints must satisfy {names[0]} < {names[1]}, got "
            f"{names[0]} = {lo!r}, {names[1]} = {hi!r}; pass a smaller {names[0]} or a "
            f"larger {names[1]}."
        )


def diagonal(A: torch.Tensor) -> torch.Tensor:
    """``(N, m)`` diagonals of ``(N, m, m)`` matrices."""
    return torch.diagonal(A, dim1=-2, dim2=-1)


def kept(context: UpdateContext) -> torch.Tensor | None:
    """``(N, m)`` bool components still in play (None = all)."""
    return None if context.keep is None else context.keep.to(torch.bool)


def standardised_residual(context: UpdateContext) -> torch.Tensor:
    """``(N, m)`` standardised residuals ``ṽ_i = |r_i| / sqrt(S_ii)``, ``S = H P⁻ Hᵀ + R``.

    ``R`` is the context's (the caller's, or the one adapted by an earlier policy of a
    composition). Rejected components report 0.
    """
    s_ii = diagonal(context.HPHt) + diagonal(context.R)
    v = context.residual.abs() * torch.rsqrt(s_ii)
    keep = kept(context)
    return v if keep is None else torch.where(keep, v, 0.0)


def residual_statistic(context: UpdateContext, R: torch.Tensor | None = None) -> torch.Tensor:
    """``(N,)`` ratio ``rᵀr / tr(H P⁻ Hᵀ + R)`` over the kept components (0 if none).

    The squared predicted-residual statistic of Yang's adaptive factor (SEEDS 002:
    ``Δ² = V̄ᵀV̄ / tr(A Σ_x̄ Aᵀ + Σ̄)``) and paper 003's ``λ``.
    """
    R = context.R if R is None else R
    rr = context.residual.square()
    tr = diagonal(context.HPHt) + diagonal(R)
    keep = kept(context)
    if keep is None:  # every component kept: tr > 0 (R is positive definite)
        if rr.shape[-1] == 1:
            return rr[:, 0] / tr[:, 0]
        return rr.sum(-1) / tr.sum(-1)
    rr = torch.where(keep, rr, 0.0)
    tr = torch.where(keep, tr, 0.0)
    tr_sum = tr.sum(-1)
    return torch.where(tr_sum > 0, rr.sum(-1) / torch.where(tr_sum > 0, tr_sum, 1.0), 0.0)


def scale_variances(R: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """Equivalent covariance ``R̄_ij = R_ij / sqrt(w_i w_j)`` (Yang's bifactor form).

    For a diagonal ``R`` this divides each variance by its weight (``R̄_ii = R_ii / w_i``);
    the correlation structure of a full ``R`` is kept. Weights must be > 0 (rejected
    components are handled with ``keep``, not here).

    Args:
        R: ``(N, m, m)`` covariance.
        weights: ``(N, m)`` equivalent-weight factors in ``(0, 1]``.
    """
    return R / torch.sqrt(weights.unsqueeze(-1) * weights.unsqueeze(-2))


def and_keep(a: torch.Tensor | None, b: torch.Tensor | None) -> torch.Tensor | None:
    """Intersection of two keep masks (None = all kept)."""
    if a is None:
        return b
    if b is None:
        return a
    return a.to(torch.bool) & b.to(torch.bool)


def check_state_shape(
    state: torch.Tensor | None, shape: tuple[int, ...], *, where: str
) -> None:
    """Raises when per-sample state exists with another batch/measurement shape."""
    if state is not None and tuple(state.shape) != shape:
        raise NeuralMapError(
            f"{where}: the policy holds per-sample state of shape {tuple(state.shape)} but "
            f"this update needs {shape}; call policy.reset() before a new batch (or use "
            "one policy object per filter)."
        )
