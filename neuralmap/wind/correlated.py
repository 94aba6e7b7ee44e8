"""Kalman filtering with measurement noise correlated with the process noise.

Model (batched, per sample; the differenced wind model of SEEDS 002 after linearisation):

    x_{k+1} = f(x_k) + u_k,   cov u_k = Q_k
    y_k     = h(x_k) + e_k,   cov e_k = R_k,   E[u_k e_kᵀ] = C_k,

``u`` and ``e`` white otherwise. The correlation is removed by the standard rewrite of
the process equation with the measurement (the paper's eqs. 13–15; Simon, *Optimal State
Estimation*, §7.1): with ``J_k = C_k R_k⁻¹``

    x_{k+1} = f(x_k) + J_k (y_k − h(x_k)) + (u_k − J_k e_k),

whose new process noise ``u_k − J_k e_k`` has covariance ``Q_k − C_k R_k⁻¹ C_kᵀ`` (a Schur
complement, positive semi-definite) and is uncorrelated with ``e_k``. One cycle is then a
plain EKF cycle:

* update with ``y_k``: `BatchedEKF.update`
  (Joseph form, Cholesky solves, health flags, optional robust/adaptive policy);
* decorrelated predict: ``x⁻ = f(x⁺) + J (y − h(x⁺))``, ``P⁻ = F* P⁺ F*ᵀ + Q*`` with
  ``F* = F − J A``, ``Q* = Q − J Cᵀ``, ``F = ∂f/∂x`` and ``A = ∂h/∂x`` at ``x⁺``
  (`decorrelate`; the covariance propagation is ``BatchedEKF.predict(F*, Q*)``).

For a linear model this equals the one-step predictor ``K̄ = (F P⁻ Aᵀ + C) S⁻¹``,
``x⁻_{k+1} = F x⁻ + K̄ r``, ``P⁻_{k+1} = F P⁻ Fᵀ + Q − K̄ S K̄ᵀ`` (tested to 1e-10 against
a NumPy implementation of that form).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.filters import BatchedEKF, FilterPolicy, UpdateDiagnostics
from neuralmap.filters.stats import symmetrize

__all__ = ["CorrelatedNoiseEKF", "DecorrelatedTransition", "decorrelate"]


@dataclass
class DecorrelatedTransition:
    """The rewritten process equation of one step (batch first).

    Attributes:
        x_prior: ``(N, n)`` ``f(x⁺) + J (y − h(x⁺))``.
        F: ``(N, n, n)`` ``F* = F − J A``.
        Q: ``(n, n)`` or ``(N, n, n)`` ``Q* = Q − J Cᵀ`` (symmetrised).
        gain: ``(n, m)`` or ``(N, n, m)`` ``J = C R⁻¹``.
    """

    x_prior: torch.Tensor
    F: torch.Tensor
    Q: torch.Tensor
    gain: torch.Tensor




def decorrelate(
    *,
    fx: torch.Tensor,
    F: torch.Tensor,
    Q: torch.Tensor,
    C: torch.Tensor,
    R: torch.Tensor,
    A: torch.Tensor,
    residual: torch.Tensor,
    keep: torch.Tensor | None = None,
) -> DecorrelatedTransition:
    """Rewrites ``x' = f(x) + u`` with the measurement so that its noise is uncorrelated.

    ``R`` is the covariance the update actually used: after a robust down-weighting
    (``R/weight``) the rewrite uses that inflated ``R`` so that an outlier enters neither
    the update nor the predict; a rejected measurement (``keep`` False) gives ``J = 0``
    (the plain predict).

    Args:
        fx: ``(N, n)`` ``f(x⁺)``.
        F: ``(N, n, n)`` or ``(n, n)`` ``∂f/∂x`` at ``x⁺``.
        Q: ``(n, n)`` or ``(N, n, n)`` ``cov u``.
        C: ``(n, m)`` or ``(N, n, m)`` ``E[u eᵀ]``.
        R: ``(m, m)`` or ``(N, m, m)`` ``cov e`` (positive definite).
        A: ``(N, m, n)`` or ``(m, n)`` ``∂h/∂x`` at ``x⁺``.
        residual: ``(N, m)`` post-fit residual ``y − h(x⁺)``.
        keep: ``(N,)`` bool, False where the update rejected the measurement.

    Returns:
        `DecorrelatedTransition` (``J`` by a Cholesky solve ``R Jᵀ = Cᵀ``).

    Raises:
        NeuralMapError: ``R`` not positive definite or inconsistent shapes.
    """
    where = "decorrelate"
    batch, n = fx.shape
    m = residual.shape[-1]
    if C.shape[-2:] != (n, m) or R.shape[-2:] != (m, m) or A.shape[-2:] != (m, n):
        raise NeuralMapError(
            f"{where}: inconsistent shapes C {tuple(C.shape)}, R {tuple(R.shape)}, "
            f"A {tuple(A.shape)} for n = {n} states and m = {m} measurements; expected "
            f"(…, {n}, {m}), (…, {m}, {m}), (…, {m}, {n})."
        )
    chol, info = torch.linalg.cholesky_ex(symmetrize(R))
    if bool((info != 0).any()):
        raise NeuralMapError(f"{where}: 'R' is not positive definite; measurement-noise "
                             "variances must be > 0.")
    J = torch.cholesky_solve(C.transpose(-1, -2), chol).transpose(-1, -2)  # C R⁻¹
    if keep is not None:
        J = torch.where(keep.reshape(-1, 1, 1), J.expand(batch, n, m), 0.0)
    x_prior = fx + (J @ residual.unsqueeze(-1)).squeeze(-1)
    F_star = (F - J @ A).expand(batch, n, n)
    Q_star = symmetrize(Q - J @ C.transpose(-1, -2))
    return DecorrelatedTransition(x_prior=x_prior, F=F_star, Q=Q_star, gain=J)


class CorrelatedNoiseEKF:
    """N extended Kalman filters with correlated process and measurement noise.

    A thin layer over `BatchedEKF` (which holds ``x``
    ``(N, n)``, ``P`` ``(N, n, n)``, the health flags and runs the Joseph-form update and
    any robust/adaptive policy); the predict is the decorrelated one of
    `decorrelate`.

    Args:
        x0: ``(N, n)`` initial states.
        P0: ``(n, n)`` or ``(N, n, n)`` initial covariances.
        dtype: Floating dtype (default that of ``x0``).
    """

    def __init__(self, x0: torch.Tensor, P0: torch.Tensor, *,
                 dtype: torch.dtype | None = None) -> None:
        self.ekf = BatchedEKF(x0, P0, dtype=dtype)

    @property
    def x(self) -> torch.Tensor:
        """``(N, n)`` state estimates."""
        return self.ekf.x

    @property
    def P(self) -> torch.Tensor:
        """``(N, n, n)`` covariances."""
        return self.ekf.P

    @property
    def healthy(self) -> torch.Tensor:
        """``(N,)`` bool health flags of the underlying filter."""
        return self.ekf.healthy

    def update(
        self,
        residual: torch.Tensor,
        A: torch.Tensor,
        R: torch.Tensor | float,
        *,
        mask: torch.Tensor | None = None,
        policy: FilterPolicy | None = None,
    ) -> UpdateDiagnostics:
        """Measurement update (Joseph form): see `BatchedEKF.update`."""
        return self.ekf.update(residual, A, R, mask=mask, policy=policy)

    def predict(
        self,
        *,
        fx: torch.Tensor,
        F: torch.Tensor,
        Q: torch.Tensor,
        C: torch.Tensor | None = None,
        R: torch.Tensor | None = None,
        A: torch.Tensor | None = None,
        residual: torch.Tensor | None = None,
        keep: torch.Tensor | None = None,
        policy: FilterPolicy | None = None,
    ) -> None:
        """Decorrelated time update from the current (posterior) state.

        Args:
            fx: ``(N, n)`` ``f(x⁺)``.
            F: ``(N, n, n)`` or ``(n, n)`` ``∂f/∂x`` at ``x⁺``.
            Q: ``(n, n)`` or ``(N, n, n)`` process-noise covariance ``cov u``.
            C: ``(n, m)`` or ``(N, n, m)`` cross-covariance ``E[u eᵀ]``; None = plain
                EKF predict ``x⁻ = f(x⁺)``, ``P⁻ = F P⁺ Fᵀ + Q``.
            R: ``cov e`` of the update just made (with ``C``).
            A: ``∂h/∂x`` at ``x⁺`` (with ``C``).
            residual: ``(N, m)`` post-fit residual ``y − h(x⁺)`` (with ``C``).
            keep: ``(N,)`` bool, False where the update rejected the measurement.
            policy: Optional policy whose ``process_noise`` hook may adapt ``Q*``.

        Raises:
            NeuralMapError: ``C`` without ``R``, ``A``, ``residual``; bad shapes.
        """
        if C is None:
            x_prior, F_use, Q_use = fx, F, Q
        else:
            if R is None or A is None or residual is None:
                raise NeuralMapError("CorrelatedNoiseEKF.predict: with a cross-covariance "
                                     "'C' pass 'R', 'A' and 'residual' (y − h(x⁺)) too.")
            dec = decorrelate(fx=fx, F=F, Q=Q, C=C, R=R, A=A, residual=residual, keep=keep)
            x_prior, F_use, Q_use = dec.x_prior, dec.F, dec.Q
        self.ekf.predict(F_use, Q_use, policy=policy)
        healthy = self.ekf.healthy.unsqueeze(-1)
        self.ekf.x = torch.where(healthy, x_prior.to(self.ekf.dtype), self.ekf.x)
