"""Sage-Husa adaptive measurement (and process) noise with a fading memory (SEEDS 002).

Per sample, at its k-th applied update (k = 0, 1, ...; SEEDS 002, reconstructed)::

    d_k = (1 − b) / (1 − b^{k+1})                     forgetting weight, b ∈ (0, 1)
    R̂_k = (1 − d_k) R̂_{k−1} + d_k (ε_k ε_kᵀ − H P⁻ Hᵀ)   clamped to [R_min, R_max]
    Q̂_k = (1 − d_k) Q̂_{k−1} + d_k (K ε εᵀ Kᵀ + P_k − Φ P_{k−1} Φᵀ)   (optional)

``ε_k`` is the innovation, ``P⁻ = Φ P_{k−1} Φᵀ + Q`` the prediction (so
``Φ P_{k−1} Φᵀ = P⁻ − Q`` with the Q used), ``P_k`` the updated covariance. R̂_k is used
in the update of epoch k itself (as in PSINS' Sage-Husa filter); Q̂_k in the following
predicts (through `SageHusa.process_noise`). d_0 = 1, so the first estimate forgets
the starting value.

Clamps keep the estimates positive definite: by default (``diagonal=True``) each
variance ``R̂_ii`` is clipped to ``[R_min_i, R_max_i]``, each ``Q̂_ii`` to ``≥ Q_min``, and
the covariances are dropped (the usual practice, e.g. PSINS); with ``diagonal=False`` the
full matrix recursions are kept and their eigenvalues clipped (R̂ to
``[min R_min, max R_max]``, Q̂ to ``≥ Q_min``; an ``eigh`` per sample, several times
dearer).
"""

from __future__ import annotations

from collections.abc import Sequence

import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.filters.policies._common import check_state_shape, diagonal
from neuralmap.filters.policy import Adaptation, FilterPolicy, Posterior, UpdateContext
from neuralmap.filters.stats import symmetrize

__all__ = ["SageHusa", "sage_husa_weight"]


def sage_husa_weight(b: float, k: torch.Tensor) -> torch.Tensor:
    """Fading-memory weight ``d_k = (1 − b) / (1 − b^{k+1})`` (SEEDS 002).

    Args:
        b: Forgetting factor in (0, 1).
        k: ``(...)`` number of earlier updates of each sample (integer or float tensor).

    Returns:
        ``(...)`` weights in ``(1 − b, 1]`` (1 at k = 0), in ``k``'s float dtype (float64
        for integer ``k``).
    """
    if not 0.0 < float(b) < 1.0:
        raise NeuralMapError(f"sage_husa_weight: 'b' = {b!r} must lie in (0, 1).")
    kf = k if k.is_floating_point() else k.to(torch.float64)
    return (1.0 - b) / (1.0 - torch.pow(torch.as_tensor(b, dtype=kf.dtype), kf + 1.0))


def _clamp_eigen(A: torch.Tensor, low: float, high: float | None) -> torch.Tensor:
    """Symmetric ``A`` with its eigenvalues clipped to ``[low, high]``."""
    A = symmetrize(A)
    lam, V = torch.linalg.eigh(A)
    lam = lam.clamp(min=low, max=high)
    out = (V * lam.unsqueeze(-2)) @ V.transpose(-1, -2)
    return symmetrize(out)


def _bounds(value: float | Sequence[float] | torch.Tensor, name: str) -> torch.Tensor:
    t = torch.as_tensor(value, dtype=torch.float64).reshape(-1)
    if t.numel() == 0 or not bool(torch.isfinite(t).all()) or bool((t <= 0).any()):
        raise NeuralMapError(
            f"SageHusa: '{name}' = {value!r} must be finite and > 0 (a scalar or one "
            "variance per measurement component); clamps keep R̂ positive definite."
        )
    return t


class SageHusa(FilterPolicy):
    """Sage-Husa adaptive R (and optionally Q) with per-sample running estimates.

    Args:
        b: Forgetting factor in (0, 1) (0.95–0.99 in SEEDS 002).
        R_min: Smallest variance: scalar or ``(m,)`` per component, > 0.
        R_max: Largest variance, ≥ R_min (same forms).
        adapt_Q: Also estimate Q (used by ``predict(..., policy=this)``).
        diagonal: Estimate variances only (default); False keeps the full matrices.
        Q_min: Eigenvalue floor of Q̂ (≥ 0).

    State: ``R̂`` ``(N, m, m)``, the per-sample update count, ``Q̂`` ``(N, n, n)``; only
    samples whose update was applied change it. Reports ``R`` (the variances used,
    ``(N, m)``) and ``d`` ``(N,)``.

    Raises:
        NeuralMapError: b outside (0, 1), non-positive or unordered clamps.
    """

    name = "sage_husa"

    def __init__(
        self,
        b: float = 0.97,
        R_min: float | Sequence[float] = 1e-6,
        R_max: float | Sequence[float] = 1e6,
        adapt_Q: bool = False,
        diagonal: bool = True,
        Q_min: float = 0.0,
    ) -> None:
        b = float(b)
        if not 0.0 < b < 1.0:
            raise NeuralMapError(
                f"SageHusa: forgetting factor 'b' = {b!r} must lie in (0, 1) "
                "(0.95–0.99 is usual)."
            )
        self.b = b
        self.R_min = _bounds(R_min, "R_min")
        self.R_max = _bounds(R_max, "R_max")
        if self.R_min.numel() != self.R_max.numel() and 1 not in (
            self.R_min.numel(), self.R_max.numel()
        ):
            raise NeuralMapError("SageHusa: 'R_min' and 'R_max' have different lengths.")
        if bool((torch.broadcast_tensors(self.R_min, self.R_max)[0]
                 > torch.broadcast_tensors(self.R_min, self.R_max)[1]).any()):
            raise NeuralMapError(
                f"SageHusa: clamps must satisfy R_min <= R_max, got {R_min!r} > {R_max!r}."
            )
        if not 0.0 <= float(Q_min) < float("inf"):
            raise NeuralMapError(f"SageHusa: 'Q_min' = {Q_min!r} must be finite and >= 0.")
        self.adapt_Q = bool(adapt_Q)
        self.diagonal = bool(diagonal)
        self.Q_min = float(Q_min)
        self.reset()

    def reset(self) -> None:
        """Forgets the running estimates (a new batch starts)."""
        self._R_hat: torch.Tensor | None = None
        self._count: torch.Tensor | None = None
        self._Q_hat: torch.Tensor | None = None
        self._Q_known: torch.Tensor | None = None
        self._pending: torch.Tensor | None = None
        self._d: torch.Tensor | None = None

    @property
    def R_hat(self) -> torch.Tensor | None:
        """``(N, m, m)`` current estimates (None before the first update)."""
        return self._R_hat

    @property
    def Q_hat(self) -> torch.Tensor | None:
        """``(N, n, n)`` current process-noise estimates (None until estimated)."""
        return self._Q_hat

    def _clamp(self, R: torch.Tensor) -> torch.Tensor:
        m = R.shape[-1]
        lo = self.R_min.to(R.dtype).to(R.device)
        hi = self.R_max.to(R.dtype).to(R.device)
        for t, name in ((lo, "R_min"), (hi, "R_max")):
            if t.numel() not in (1, m):
                raise NeuralMapError(
                    f"SageHusa: '{name}' has {t.numel()} entries but the measurement has "
                    f"{m} components; pass a scalar or {m} variances."
                )
        if self.diagonal or m == 1:
            return torch.diag_embed(torch.maximum(torch.minimum(diagonal(R), hi), lo))
        return _clamp_eigen(R, float(lo.min()), float(hi.max()))

    def adapt(self, context: UpdateContext) -> Adaptation:
        """``R̂_k`` from the innovation and the running estimate; used in this update."""
        r = context.residual
        batch, m = r.shape
        check_state_shape(self._R_hat, (batch, m, m), where="SageHusa")
        if self._R_hat is None or self._count is None:
            self._R_hat = self._clamp(context.R)
            self._count = torch.zeros(batch, dtype=torch.long, device=r.device)
        d = sage_husa_weight(self.b, self._count.to(r.dtype))
        dd = d.reshape(-1, 1, 1)
        sample = r.unsqueeze(-1) * r.unsqueeze(-2) - context.HPHt  # ε εᵀ − H P⁻ Hᵀ
        R_new = self._clamp((1.0 - dd) * self._R_hat.to(r.dtype) + dd * sample)
        self._pending, self._d = R_new, d
        R_use = torch.where(context.mask.reshape(-1, 1, 1), R_new, context.R)
        return Adaptation(R=R_use, info={"R": diagonal(R_use), "d": d})

    def commit(
        self,
        context: UpdateContext,
        adaptation: Adaptation,
        posterior: Posterior,
        applied: torch.Tensor,
    ) -> None:
        """Stores ``R̂_k`` (and ``Q̂_k``) and counts the update where it was applied."""
        assert self._pending is not None and self._count is not None and self._d is not None
        assert self._R_hat is not None
        a3 = applied.reshape(-1, 1, 1)
        self._R_hat = torch.where(a3, self._pending, self._R_hat)
        if self.adapt_Q and context.process_noise is not None:
            Q_used = context.process_noise
            dd = self._d.reshape(-1, 1, 1)
            kr = torch.matmul(posterior.gain, posterior.residual.unsqueeze(-1))  # K ε
            sample = kr * kr.transpose(1, 2) + posterior.P - (context.P_prior - Q_used)
            check_state_shape(self._Q_hat, tuple(Q_used.shape), where="SageHusa")
            if self._Q_hat is None or self._Q_known is None:
                prev = Q_used
                known = applied
            else:
                prev = torch.where(self._Q_known.reshape(-1, 1, 1), self._Q_hat, Q_used)
                known = self._Q_known | applied
            Q_new = (1.0 - dd) * prev + dd * sample
            if self.diagonal:
                Q_new = torch.diag_embed(diagonal(Q_new).clamp_min(self.Q_min))
            else:
                Q_new = _clamp_eigen(Q_new, self.Q_min, None)
            self._Q_hat = torch.where(a3, Q_new, prev)
            self._Q_known = known
        self._count = self._count + applied.to(torch.long)
        self._pending = None

    def process_noise(
        self, *, F: torch.Tensor, Q: torch.Tensor, P: torch.Tensor
    ) -> torch.Tensor | None:
        """``Q̂`` where estimated (the caller's ``Q`` elsewhere); None without ``adapt_Q``."""
        if not self.adapt_Q or self._Q_hat is None or self._Q_known is None:
            return None
        check_state_shape(self._Q_hat, tuple(Q.shape), where="SageHusa")
        return torch.where(self._Q_known.reshape(-1, 1, 1), self._Q_hat, Q)
