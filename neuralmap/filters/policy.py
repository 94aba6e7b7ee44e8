"""The extension point of the batched Kalman update: per-sample filter *policies*.

A policy adapts one measurement update of every sample of a batch, on the sample's own
numbers, without Python loops over samples. It may

* rescale the predicted covariance ``P⁻`` (Yang's adaptive factor: ``P⁻/α``; innovation
  inflation: ``α P⁻``) or replace it (variational Bayes),
* rescale or replace ``R`` per component (IGG-III / Huber equivalent weights, quality
  factors, Sage-Husa estimates) or reject components outright,
* iterate the update (variational Bayes: fixed-point iterations on ``P⁻`` and ``R``),
* keep per-sample state between epochs (Sage-Husa's running ``R̂``),
* adapt the process noise at the time update,

and it reports what it did per sample (weights, factors, adapted variances) in
`UpdateDiagnostics.policy_info`.

How `BatchedEKF.update` drives a policy::

    adaptation = policy.adapt(context)                 # before the first pass
    for _ in range(policy.iterations):
        posterior = kalman_update(x⁻, P⁻ as adapted, r, H, R as adapted)
        adaptation = policy.refine(context, adaptation, posterior)
        if adaptation is None: break                   # converged / not iterative
    policy.commit(context, last adaptation, posterior, applied)

and `BatchedEKF.predict` calls
``policy.process_noise(F=..., Q=..., P=...)`` (None = keep ``Q``).

Shapes (batch first): ``N`` samples, ``n`` states, ``m`` measurement components.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch

__all__ = ["Adaptation", "FilterPolicy", "Posterior", "UpdateContext"]


@dataclass
class UpdateContext:
    """What a policy sees of one measurement update (all tensors batch first).

    Attributes:
        x_prior: ``(N, n)`` predicted state ``x⁻``.
        P_prior: ``(N, n, n)`` predicted covariance ``P⁻``.
        residual: ``(N, m)`` innovation ``r = z − h(x⁻)``; 0 for masked samples.
        H: ``(N, m, n)`` measurement Jacobian; 0 rows for masked samples.
        R: ``(N, m, m)`` measurement-noise covariance as given by the caller.
        HPHt: ``(N, m, m)`` ``H P⁻ Hᵀ`` (the predicted measurement covariance without R).
        mask: ``(N,)`` bool, True where the sample will be updated (healthy, unmasked).
        process_noise: ``(N, n, n)`` Q of the last predict (None before any predict).
        step: Number of updates the filter has made before this one (0 for the first).
        keep: ``(N, m)`` bool, components already rejected by an earlier policy of a
            composition (`Compose`); None = all kept.
            The filter itself never sets it; a policy that sums over components should
            skip the rejected ones.
    """

    x_prior: torch.Tensor
    P_prior: torch.Tensor
    residual: torch.Tensor
    H: torch.Tensor
    R: torch.Tensor
    HPHt: torch.Tensor
    mask: torch.Tensor
    process_noise: torch.Tensor | None = None
    step: int = 0
    keep: torch.Tensor | None = None

    @property
    def S(self) -> torch.Tensor:
        """``(N, m, m)`` innovation covariance ``H P⁻ Hᵀ + R`` with the caller's R."""
        return self.HPHt + self.R


@dataclass
class Adaptation:
    """How a policy changes one update, per sample. ``None`` fields change nothing.

    Attributes:
        p_scale: ``(N,)`` factor on the predicted covariance, ``P⁻ ← p_scale·P⁻``
            (``1/α`` for Yang's adaptive factor α; ``α`` for innovation inflation). Must be
            finite and > 0.
        P_prior: ``(N, n, n)`` replacement predicted covariance (applied before
            ``p_scale``); symmetric positive definite.
        R: ``(N, m, m)`` replacement measurement covariance (rescaled or estimated);
            symmetric positive definite on the kept components.
        keep: ``(N, m)`` bool, False rejects that measurement component (its row of H and
            its residual are dropped exactly; a sample with no kept component is not
            updated).
        info: Per-sample reports (``(N,)`` or ``(N, m)`` tensors: weights, factors, ...),
            copied into the update diagnostics under these names.
    """

    p_scale: torch.Tensor | None = None
    P_prior: torch.Tensor | None = None
    R: torch.Tensor | None = None
    keep: torch.Tensor | None = None
    info: dict[str, torch.Tensor] = field(default_factory=dict)


@dataclass
class Posterior:
    """One pass of the update under an adaptation (every sample; read with the mask).

    Attributes:
        x: ``(N, n)`` updated state ``x⁺``.
        P: ``(N, n, n)`` updated covariance ``P⁺`` (Joseph form, symmetric).
        P_prior: ``(N, n, n)`` the predicted covariance actually used (after adaptation).
        R: ``(N, m, m)`` the measurement covariance actually used.
        S: ``(N, m, m)`` innovation covariance used.
        gain: ``(N, n, m)`` Kalman gain.
        residual: ``(N, m)`` innovation (rejected components set to 0).
    """

    x: torch.Tensor
    P: torch.Tensor
    P_prior: torch.Tensor
    R: torch.Tensor
    S: torch.Tensor
    gain: torch.Tensor
    residual: torch.Tensor


class FilterPolicy:
    """Base class of update/predict policies: every hook defaults to "change nothing".

    Subclasses override `adapt` (and, as needed, `refine`, `commit`,
    `process_noise`, `reset`). A policy holding per-sample state sizes it on
    the first call (or in `reset`) and must keep the state of samples that are not
    updated (``context.mask`` False) unchanged.

    Attributes:
        iterations: Maximum number of update passes (1 = no iteration).
        name: Short name used in reports.
    """

    iterations: int = 1
    name: str = "policy"

    def reset(self) -> None:
        """Forgets per-sample state (a new Monte Carlo batch starts)."""

    def adapt(self, context: UpdateContext) -> Adaptation:
        """The adaptation of the first update pass (default: none)."""
        return Adaptation()

    def refine(
        self, context: UpdateContext, adaptation: Adaptation, posterior: Posterior
    ) -> Adaptation | None:
        """After a pass: a new adaptation for another pass, or None to stop (default)."""
        return None

    def commit(
        self,
        context: UpdateContext,
        adaptation: Adaptation,
        posterior: Posterior,
        applied: torch.Tensor,
    ) -> None:
        """After the last pass: update per-sample state where ``applied`` (``(N,)`` bool)."""

    def process_noise(
        self, *, F: torch.Tensor, Q: torch.Tensor, P: torch.Tensor
    ) -> torch.Tensor | None:
        """At predict: an adapted ``(N, n, n)`` process noise, or None to keep ``Q``.

        Args:
            F: ``(N, n, n)`` transition matrix.
            Q: ``(N, n, n)`` process noise given by the caller.
            P: ``(N, n, n)`` covariance before the prediction.
        """
        return None
