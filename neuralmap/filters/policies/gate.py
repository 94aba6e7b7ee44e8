"""Chi-square innovation gate: the classic outlier-rejection baseline.

Per sample: reject the measurement when ``NIS = rᵀ S⁻¹ r`` exceeds the χ² quantile
``χ²_m(p)`` (m = number of kept components), ``S = H P⁻ Hᵀ + R``. Per component
(``per_component=True``): reject component i when ``ṽ_i² = r_i² / S_ii > χ²_1(p)``.
Quantiles from `scipy.stats.chi2.ppf`.
"""

from __future__ import annotations

import math

import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.filters.policies._common import kept, standardised_residual
from neuralmap.filters.policy import Adaptation, FilterPolicy, UpdateContext

__all__ = ["ChiSquareGate", "chi_square_threshold"]


def chi_square_threshold(p: float, dof: int) -> float:
    """The ``p`` quantile of the χ² distribution with ``dof`` degrees of freedom."""
    from scipy.stats import chi2  # imported here: scipy.stats takes ~1 s to import

    return float(chi2.ppf(p, dof))


class ChiSquareGate(FilterPolicy):
    """Rejects samples (or components) whose innovation is beyond the χ² quantile ``p``.

    Args:
        p: Gate probability in (0, 1), e.g. 0.99 (1 % of good measurements rejected).
        per_component: Gate each component on ``ṽ_i²`` instead of the sample's NIS.

    Reports ``nis`` ``(N,)`` (or ``standardised_residual`` ``(N, m)``) and ``rejected``.

    Raises:
        NeuralMapError: ``p`` outside (0, 1).
    """

    name = "chi2"

    def __init__(self, p: float = 0.99, per_component: bool = False) -> None:
        p = float(p)
        if not 0.0 < p < 1.0 or math.isnan(p):
            raise NeuralMapError(
                f"ChiSquareGate: 'p' = {p!r} must lie in (0, 1) (the gate probability, "
                "e.g. 0.99)."
            )
        self.p = p
        self.per_component = bool(per_component)
        self._thresholds: dict[int, float] = {}

    def _threshold(self, dof: int) -> float:
        if dof not in self._thresholds:
            self._thresholds[dof] = chi_square_threshold(self.p, dof)
        return self._thresholds[dof]

    def adapt(self, context: UpdateContext) -> Adaptation:
        """The keep mask of the gate."""
        batch, m = context.residual.shape
        keep_in = kept(context)
        if self.per_component or m == 1:
            v = standardised_residual(context)
            ok = v.square() <= self._threshold(1)
            ok = ok | ~context.mask.unsqueeze(-1)
            keep = None if bool(ok.all()) else ok
            if self.per_component:
                return Adaptation(keep=keep, info={"standardised_residual": v, "rejected": ~ok})
            nis = v[:, 0].square()
            return Adaptation(keep=keep, info={"nis": nis, "rejected": ~ok[:, 0]})
        # NIS over the kept components: rejected ones get r = 0 and an identity row of S
        r, S = context.residual, context.S
        if keep_in is not None:
            both = keep_in.unsqueeze(-1) & keep_in.unsqueeze(-2)
            S = torch.where(both, S, torch.eye(m, dtype=S.dtype, device=S.device))
            r = torch.where(keep_in, r, 0.0)
            dof = keep_in.sum(-1)
        else:
            dof = torch.full((batch,), m, device=r.device)
        chol, _ = torch.linalg.cholesky_ex(S)
        white = torch.linalg.solve_triangular(chol, r.unsqueeze(-1), upper=False)
        nis = white.squeeze(-1).square().sum(-1)
        table = torch.tensor([math.inf] + [self._threshold(k) for k in range(1, m + 1)],
                             dtype=nis.dtype, device=nis.device)
        ok = (nis <= table[dof]) | ~context.mask
        keep = None if bool(ok.all()) else ok.unsqueeze(-1).expand(batch, m)
        return Adaptation(keep=keep, info={"nis": nis, "rejected": ~ok})
