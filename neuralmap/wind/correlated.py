"""Kalman filter steps for measurement noise correlated with the process noise.

Model (batched, per sample, the differenced wind model of SEEDS 002 after linearisation):

    x_{k+1} = f(x_k) + u_k,   cov u_k = Q_k
    y_k     = h(x_k) + e_k,   cov e_k = R_k,   E[u_k e_kᵀ] = C_k,

``u`` and ``e`` white otherwise. The correlation is removed by the standard rewrite of
the process equation with the measurement (the paper's eqs. 13–15, Simon, *Optimal State
Estimation*, §7.1): with ``J_k = C_k R_k⁻¹``

    x_{k+1} = f(x_k) + J_k (y_k − h(x_k)) + (u_k − J_k e_k),

whose new process noise ``u_k − J_k e_k`` has covariance ``Q_k − C_k R_k⁻¹ C_kᵀ`` and is
uncorrelated with ``e_k``. One cycle is therefore

* update with ``y_k`` (:func:`correlated_update`): ``S = A P⁻ Aᵀ + R``,
  ``K = P⁻ Aᵀ S⁻¹`` (Cholesky solve), ``x⁺ = x⁻ + K r``, Joseph form
  ``P⁺ = (I − KA) P⁻ (I − KA)ᵀ + K R Kᵀ``;
* decorrelated predict (:func:`correlated_predict`): ``x⁻ = f(x⁺) + J (y − h(x⁺))``,
  ``F* = F − J A``, ``P⁻ = F* P⁺ F*ᵀ + Q − J Cᵀ`` (symmetrised),

with ``A = ∂h/∂x`` and ``F = ∂f/∂x`` evaluated at ``x⁺`` in the predict (EKF). For a
linear model this equals the one-step predictor ``K̄ = (F P⁻ Aᵀ + C) S⁻¹``,
``x⁻_{k+1} = F x⁻ + K̄ r``, ``P⁻_{k+1} = F P⁻ Fᵀ + Q − K̄ S K̄ᵀ`` exactly (tested).
Everything is batched: ``x`` ``(N, n)``, ``P`` ``(N, n, n)``; shared matrices may be given
without the batch dimension.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from neuralmap.exceptions import NeuralMapError

__all__ = ["CorrelatedUpdate", "correlated_update", "correlated_predict"]


@dataclass
class CorrelatedUpdate:
    """Per-sample results of :func:`correlated_update`.

    Attributes:
        innovation: ``(N, m)`` residual ``y − h(x⁻)``.
        S: ``(N, m, m)`` innovation covariance ``A P⁻ Aᵀ + R``.
        nis: ``(N,)`` normalised innovation squared ``rᵀ S⁻¹ r``.
        gain: ``(N, n, m)`` Kalman gain.
        applied: ``(N,)`` bool, samples whose state was updated.
    """

    innovation: torch.Tensor
    S: torch.Tensor
    nis: torch.Tensor
    gain: torch.Tensor
    applied: torch.Tensor


def _batched(value: torch.Tensor, batch: int, shape: tuple[int, ...], name: str,
             where: str) -> torch.Tensor:
    if tuple(value.shape) == shape:
        return value.expand(batch, *shape)
    if tuple(value.shape) == (batch, *shape):
        return value
    raise NeuralMapError(
        f"{where}: '{name}' has shape {tuple(value.shape)}, expected {shape} or "
        f"{(batch, *shape)} (batch first)."
    )


def _symmetrize(mat: torch.Tensor) -> torch.Tensor:
    return 0.5 * (mat + mat.transpose(-1, -2))


def correlated_update(
    x: torch.Tensor,
    P: torch.Tensor,
    *,
    residual: torch.Tensor,
    A: torch.Tensor,
    R: torch.Tensor,
    mask: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor, CorrelatedUpdate]:
    """Measurement update (Joseph form) of N filters at once.

    Args:
        x: ``(N, n)`` prior states ``x⁻``.
        P: ``(N, n, n)`` prior covariances.
        residual: ``(N, m)`` innovation ``y − h(x⁻)``.
        A: ``(N, m, n)`` or ``(m, n)`` measurement Jacobian at ``x⁻``.
        R: ``(N, m, m)`` or ``(m, m)`` measurement-noise covariance (positive definite).
        mask: ``(N,)`` bool, False = keep the prior (no measurement).

    Returns:
        ``(x⁺ (N, n), P⁺ (N, n, n), CorrelatedUpdate)``; samples whose ``S`` is not
        positive definite keep their prior (``applied`` False).

    Raises:
        NeuralMapError: Shape mismatches.
    """
    where = "correlated_update"
    batch, n = x.shape
    m = residual.shape[-1]
    if tuple(residual.shape) != (batch, m):
        raise NeuralMapError(f"{where}: 'residual' must be (N, m) with N = {batch}, got "
                             f"{tuple(residual.shape)}.")
    A = _batched(A, batch, (m, n), "A", where)
    R = _batched(R, batch, (m, m), "R", where)
    pat = P @ A.transpose(1, 2)  # (N, n, m)
    S = _symmetrize(A @ pat + R)
    chol, info = torch.linalg.cholesky_ex(S)
    gain = torch.cholesky_solve(pat.transpose(1, 2), chol).transpose(1, 2)  # P Aᵀ S⁻¹
    x_post = x + (gain @ residual.unsqueeze(-1)).squeeze(-1)
    ika = torch.eye(n, dtype=x.dtype, device=x.device) - gain @ A
    P_post = _symmetrize(ika @ P @ ika.transpose(1, 2) + gain @ R @ gain.transpose(1, 2))
    white = torch.linalg.solve_triangular(chol, residual.unsqueeze(-1), upper=False)
    nis = white.squeeze(-1).square().sum(-1)
    applied = (info == 0) & torch.isfinite(x_post).all(-1) & torch.isfinite(P_post).flatten(
        1).all(-1)
    if mask is not None:
        applied = applied & mask
    x_post = torch.where(applied[:, None], x_post, x)
    P_post = torch.where(applied[:, None, None], P_post, P)
    return x_post, P_post, CorrelatedUpdate(residual, S, nis, gain, applied)


def correlated_predict(
    x: torch.Tensor,
    P: torch.Tensor,
    *,
    fx: torch.Tensor,
    F: torch.Tensor,
    Q: torch.Tensor,
    C: torch.Tensor | None = None,
    R: torch.Tensor | None = None,
    A: torch.Tensor | None = None,
    residual: torch.Tensor | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Decorrelated time update ``x⁻ = f(x⁺) + J r⁺``, ``P⁻ = F* P⁺ F*ᵀ + Q − J Cᵀ``.

    ``J = C R⁻¹`` (Cholesky solve), ``F* = F − J A``, ``r⁺ = y − h(x⁺)``. With ``C``
    None this is the plain EKF predict ``x⁻ = f(x⁺)``, ``P⁻ = F P⁺ Fᵀ + Q``.

    Args:
        x: ``(N, n)`` posterior states ``x⁺`` (only the shape is used; pass ``f(x⁺)`` as
            ``fx``).
        P: ``(N, n, n)`` posterior covariances.
        fx: ``(N, n)`` ``f(x⁺)``.
        F: ``(N, n, n)`` or ``(n, n)`` ``∂f/∂x`` at ``x⁺``.
        Q: ``(N, n, n)`` or ``(n, n)`` process-noise covariance ``cov u``.
        C: ``(N, n, m)`` or ``(n, m)`` cross-covariance ``E[u eᵀ]``; None = uncorrelated.
        R: ``(N, m, m)`` or ``(m, m)`` ``cov e`` (needed with ``C``).
        A: ``(N, m, n)`` or ``(m, n)`` ``∂h/∂x`` at ``x⁺`` (needed with ``C``).
        residual: ``(N, m)`` post-fit residual ``y − h(x⁺)`` (needed with ``C``).

    Returns:
        ``(x⁻ (N, n), P⁻ (N, n, n))`` for the next step.

    Raises:
        NeuralMapError: Shape mismatches or ``C`` without ``R``, ``A``, ``residual``.
    """
    where = "correlated_predict"
    batch, n = x.shape
    F = _batched(F, batch, (n, n), "F", where)
    Q = _batched(Q, batch, (n, n), "Q", where)
    if C is None:
        return fx, _symmetrize(F @ P @ F.transpose(1, 2) + Q)
    if R is None or A is None or residual is None:
        raise NeuralMapError(f"{where}: with a cross-covariance 'C' pass 'R', 'A' and "
                             "'residual' (y − h(x⁺)) too.")
    m = residual.shape[-1]
    C = _batched(C, batch, (n, m), "C", where)
    R = _batched(R, batch, (m, m), "R", where)
    A = _batched(A, batch, (m, n), "A", where)
    chol, info = torch.linalg.cholesky_ex(_symmetrize(R))
    if bool((info != 0).any()):
        raise NeuralMapError(f"{where}: 'R' is not positive definite (sample "
                             f"{int(torch.nonzero(info)[0, 0])}); measurement-noise "
                             "variances must be > 0.")
    J = torch.cholesky_solve(C.transpose(1, 2), chol).transpose(1, 2)  # C R⁻¹ (N, n, m)
    F_star = F - J @ A
    x_prior = fx + (J @ residual.unsqueeze(-1)).squeeze(-1)
    Q_star = Q - J @ C.transpose(1, 2)
    P_prior = _symmetrize(F_star @ P @ F_star.transpose(1, 2) + Q_star)
    return x_prior, P_prior
