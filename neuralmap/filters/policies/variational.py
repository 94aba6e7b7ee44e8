"""Variational-Bayes adaptive Kalman filter with inaccurate P⁻ and R (Huang et al., 2018).

Y. Huang, Y. Zhang, Z. Wu, N. Li, J. Chambers, "A novel adaptive Kalman filter with
inaccurate process and measurement noise covariance matrices", IEEE Trans. Automatic
Control 63(2), 2018. The predicted covariance ``P_{k|k−1}`` and the measurement noise
``R_k`` get inverse-Wishart priors, ``IW(P; t, T)`` and ``IW(R; u, U)`` (mean
``T / (t − n − 1)``, ``U / (u − m − 1)``), and the joint posterior of ``(x, P, R)`` is
approximated by variational Bayes. Per step, with the nominal prediction ``x̂⁻``, ``P⁻``
(``P⁻ = Φ P Φᵀ + Q̃`` from the filter's predict):

Prior parameters (tuning τ ≥ 0, forgetting ρ ∈ (0, 1])::

    t̂ = n + τ + 1,            T̂ = τ P⁻
    û = ρ (û_{k−1} − m − 1) + m + 1,   Û = ρ Û_{k−1}

Fixed-point iterations ``i = 0 … N−1`` starting at ``x⁽⁰⁾ = x̂⁻``, ``P⁽⁰⁾ = P⁻``::

    A⁽ⁱ⁾ = P⁽ⁱ⁾ + (x⁽ⁱ⁾ − x̂⁻)(x⁽ⁱ⁾ − x̂⁻)ᵀ
    t⁽ⁱ⁺¹⁾ = t̂ + 1,           T⁽ⁱ⁺¹⁾ = A⁽ⁱ⁾ + T̂
    B⁽ⁱ⁾ = (z − H x⁽ⁱ⁾)(z − H x⁽ⁱ⁾)ᵀ + H P⁽ⁱ⁾ Hᵀ
    u⁽ⁱ⁺¹⁾ = û + 1,           U⁽ⁱ⁺¹⁾ = B⁽ⁱ⁾ + Û
    P̃ = T⁽ⁱ⁺¹⁾ / (t⁽ⁱ⁺¹⁾ − n − 1),   R̃ = U⁽ⁱ⁺¹⁾ / (u⁽ⁱ⁺¹⁾ − m − 1)
        (the inverses of E[P⁻¹] and E[R⁻¹])
    K = P̃ Hᵀ (H P̃ Hᵀ + R̃)⁻¹
    x⁽ⁱ⁺¹⁾ = x̂⁻ + K (z − H x̂⁻),     P⁽ⁱ⁺¹⁾ = P̃ − K H P̃

Result ``x̂_k = x⁽ᴺ⁾``, ``P_k = P⁽ᴺ⁾``; the R statistics ``û_k = û + 1``, ``Û_k = U⁽ᴺ⁾``
carry to the next step. The first iteration has ``P̃ = P⁻`` exactly
(``T⁽¹⁾ = (1 + τ) P⁻``, ``t⁽¹⁾ − n − 1 = τ + 1``).

In this toolkit ``z − H x⁽ⁱ⁾ = r − H (x⁽ⁱ⁾ − x̂⁻)`` with the caller's innovation ``r``
(exact for a linear measurement; the usual EKF linearisation otherwise); each pass is the
filter's Joseph-form update with ``(P̃, R̃)``, which equals ``P̃ − K H P̃`` for this gain.
The R statistics start per sample, at its first applied update, from the caller's R:
``û_0 = m + 1 + prior_dof``, ``Û_0 = prior_dof · R`` (prior mean R).
"""

from __future__ import annotations

import math

import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.filters.policies._common import check_positive, check_state_shape
from neuralmap.filters.policy import Adaptation, FilterPolicy, Posterior, UpdateContext
from neuralmap.filters.stats import symmetrize

__all__ = ["VariationalAdaptive"]




class VariationalAdaptive(FilterPolicy):
    """Huang et al.'s variational-Bayes adaptive update of ``P⁻`` and ``R`` (IEEE TAC 2018).

    Args:
        iterations: Fixed-point iterations N per update (≥ 1; the paper uses ~10, 3 is
            usually enough).
        tau: Tuning parameter τ ≥ 0 of the P⁻ prior (larger = trust the nominal P⁻ more;
            the paper suggests about 3).
        rho: Forgetting factor ρ ∈ (0, 1] of the R statistics (``1 − e⁻⁴`` in the paper).
        prior_dof: ``û_0 − m − 1`` > 0, the weight of the caller's R as the initial prior.

    State: ``û`` ``(N,)``, ``Û`` ``(N, m, m)``; only applied samples change it. Reports
    ``R`` (variances of the last R̃, ``(N, m)``) and ``dof`` (``û``, ``(N,)``).

    Raises:
        NeuralMapError: iterations < 1, τ < 0, ρ outside (0, 1], prior_dof ≤ 0.
    """

    name = "vb"

    def __init__(
        self,
        iterations: int = 3,
        tau: float = 3.0,
        rho: float = 1.0 - math.exp(-4.0),
        prior_dof: float = 3.0,
    ) -> None:
        where = "VariationalAdaptive"
        if int(iterations) != iterations or int(iterations) < 1:
            raise NeuralMapError(f"{where}: 'iterations' = {iterations!r} must be an int >= 1.")
        if not 0.0 <= float(tau) < math.inf:
            raise NeuralMapError(f"{where}: 'tau' = {tau!r} must be finite and >= 0.")
        if not 0.0 < float(rho) <= 1.0:
            raise NeuralMapError(f"{where}: forgetting factor 'rho' = {rho!r} must lie in (0, 1].")
        self.iterations = int(iterations)
        self.tau = float(tau)
        self.rho = float(rho)
        self.prior_dof = check_positive(prior_dof, name="prior_dof", where=where)
        self.reset()

    def reset(self) -> None:
        """Forgets the R statistics."""
        self._u: torch.Tensor | None = None
        self._U: torch.Tensor | None = None
        self._init: torch.Tensor | None = None
        self._pass = 0
        self._u_prior: torch.Tensor | None = None
        self._U_prior: torch.Tensor | None = None
        self._U_used: torch.Tensor | None = None

    def _step(self, context: UpdateContext, x: torch.Tensor, P: torch.Tensor) -> Adaptation:
        """``(P̃, R̃)`` from the current iterate ``(x⁽ⁱ⁾, P⁽ⁱ⁾)``."""
        assert self._u_prior is not None and self._U_prior is not None
        n, m = x.shape[1], context.residual.shape[1]
        H = context.H
        dx = x - context.x_prior
        A = P + dx.unsqueeze(-1) * dx.unsqueeze(-2)
        T = A + self.tau * context.P_prior
        P_tilde = symmetrize(T / (self.tau + 1.0))  # t⁽ⁱ⁺¹⁾ − n − 1 = τ + 1
        e = context.residual - torch.matmul(H, dx.unsqueeze(-1)).squeeze(-1)
        B = e.unsqueeze(-1) * e.unsqueeze(-2) + torch.matmul(torch.matmul(H, P), H.transpose(1, 2))
        U = symmetrize(B + self._U_prior)
        u = self._u_prior + 1.0
        R_tilde = U / (u - m - 1.0).reshape(-1, 1, 1)
        mask3 = context.mask.reshape(-1, 1, 1)
        R_tilde = torch.where(mask3, R_tilde, context.R)
        P_tilde = torch.where(mask3, P_tilde, context.P_prior)
        self._U_used = U
        del n
        return Adaptation(
            P_prior=P_tilde, R=R_tilde,
            info={"R": torch.diagonal(R_tilde, dim1=-2, dim2=-1), "dof": u},
        )

    def adapt(self, context: UpdateContext) -> Adaptation:
        """Prior statistics and the first iterate (``P̃ = P⁻``, ``R̃`` from ``x̂⁻``)."""
        r = context.residual
        batch, m = r.shape
        dtype = r.dtype
        check_state_shape(self._U, (batch, m, m), where="VariationalAdaptive")
        if self._U is None or self._u is None or self._init is None:
            self._U = torch.zeros(batch, m, m, dtype=dtype, device=r.device)
            self._u = torch.zeros(batch, dtype=dtype, device=r.device)
            self._init = torch.zeros(batch, dtype=torch.bool, device=r.device)
        # first applied update of a sample: û_0, Û_0 from the caller's R
        u0 = torch.full_like(self._u, m + 1.0 + self.prior_dof)
        u_prev = torch.where(self._init, self._u, u0)
        U_prev = torch.where(self._init.reshape(-1, 1, 1), self._U, self.prior_dof * context.R)
        self._u_prior = self.rho * (u_prev - m - 1.0) + m + 1.0
        self._U_prior = self.rho * U_prev
        self._pass = 0
        return self._step(context, context.x_prior, context.P_prior)

    def refine(
        self, context: UpdateContext, adaptation: Adaptation, posterior: Posterior
    ) -> Adaptation | None:
        """The next iterate from the pass's ``(x⁽ⁱ⁾, P⁽ⁱ⁾)``; None after N passes."""
        self._pass += 1
        if self._pass >= self.iterations:
            return None
        return self._step(context, posterior.x, posterior.P)

    def commit(
        self,
        context: UpdateContext,
        adaptation: Adaptation,
        posterior: Posterior,
        applied: torch.Tensor,
    ) -> None:
        """Stores ``û_k = û + 1`` and ``Û_k = U⁽ᴺ⁾`` where the update was applied."""
        assert self._u_prior is not None and self._U_used is not None
        assert self._u is not None and self._U is not None and self._init is not None
        self._u = torch.where(applied, self._u_prior + 1.0, self._u)
        self._U = torch.where(applied.reshape(-1, 1, 1), self._U_used, self._U)
        self._init = self._init | applied
