"""Per-sample diagnostics returned by a batched filter update."""

from __future__ import annotations

from dataclasses import dataclass, field

import torch


@dataclass
class UpdateDiagnostics:
    """What one `BatchedEKF.update` computed, per sample.

    Values are reported for every sample, also for those whose update was not applied
    (masked out or unhealthy): there they are whatever the computation gave (possibly NaN)
    and must be read together with `applied`.

    Attributes:
        innovation: ``(N, m)`` residual ``z - h(x⁻)`` as passed by the caller.
        S: ``(N, m, m)`` innovation covariance ``H P⁻ Hᵀ + R``.
        nis: ``(N,)`` normalised innovation squared ``rᵀ S⁻¹ r`` (χ²(m) when consistent).
        gain: ``(N, n, m)`` Kalman gain ``K = P⁻ Hᵀ S⁻¹``.
        healthy: ``(N,)`` bool health flags after this update (False = frozen sample).
        applied: ``(N,)`` bool, True where the update changed the state (sample healthy,
            not masked out, and the result finite and positive definite).
        x_prior: ``(N, n)`` predicted state ``x⁻`` the update started from.
        P_prior: ``(N, n, n)`` predicted covariance ``P⁻`` (before any policy).
        log_likelihood: ``(N,)`` Gaussian log-likelihood of the innovation,
            ``−½ (m ln 2π + ln det S + NIS)`` (the loss for learning through the filter).
        policy_info: What the policy did, per sample (weights, factors, adapted
            variances), by name; empty without a policy.
    """

    innovation: torch.Tensor
    S: torch.Tensor
    nis: torch.Tensor
    gain: torch.Tensor
    healthy: torch.Tensor
    applied: torch.Tensor | None = None
    x_prior: torch.Tensor | None = None
    P_prior: torch.Tensor | None = None
    log_likelihood: torch.Tensor | None = None
    policy_info: dict[str, torch.Tensor] = field(default_factory=dict)
