"""Small statistics every filter shares: χ² quantiles and thresholds, symmetrisation,
the NEES.

One home for them, so that the lost-lock test, the spike gate, the NEES band and the
protection levels all read the same quantile (`scipy.stats.chi2`), and every covariance
is symmetrised by the same line.
"""

from __future__ import annotations

import functools

import torch

__all__ = ["chi2_mean_threshold", "chi2_quantile", "nees", "symmetrize"]


@functools.lru_cache(maxsize=256)
def chi2_quantile(p: float, dof: int) -> float:
    """Quantile of the χ² distribution: ``x`` with ``P(χ²_ν ≤ x) = p``.

    Args:
        p: Probability in ``(0, 1)``.
        dof: Degrees of freedom ``ν ≥ 1``.

    Returns:
        The quantile (`scipy.stats.chi2.ppf`).
    """
    from scipy.stats import chi2

    return float(chi2.ppf(p, dof))


def chi2_mean_threshold(prob: float, window: int) -> float:
    """``χ²_prob(W) / W``: the mean of ``W`` consistent NIS values exceeds it with
    probability ``1 − prob`` (the windowed-NIS lost-lock test).

    Args:
        prob: Probability in ``(0, 1)``.
        window: ``W ≥ 1`` NIS values averaged.
    """
    return chi2_quantile(prob, int(window)) / int(window)


def symmetrize(A: torch.Tensor) -> torch.Tensor:
    """``(A + Aᵀ) / 2`` over the last two axes (a covariance after round-off)."""
    return 0.5 * (A + A.transpose(-1, -2))


def nees(err: torch.Tensor, P: torch.Tensor) -> torch.Tensor:
    """Normalised estimation error squared ``errᵀ P⁻¹ err`` (Cholesky solve, float64).

    Args:
        err: ``(..., n)`` estimation errors.
        P: ``(..., n, n)`` covariances (positive definite).

    Returns:
        ``(...)`` float64 NEES; NaN where ``P`` is not positive definite.
    """
    err = err.double()
    L, info = torch.linalg.cholesky_ex(P.double())
    ok = info == 0
    L = torch.where(ok[..., None, None], L,
                    torch.eye(P.shape[-1], dtype=L.dtype, device=L.device))
    y = torch.linalg.solve_triangular(L, err.unsqueeze(-1), upper=False).squeeze(-1)
    out = (y * y).sum(-1)
    return torch.where(ok, out, torch.full_like(out, float("nan")))
