"""The learnable noise model of the TAN filter: Q and R, positive definite by construction."""

from __future__ import annotations

from typing import Any

import torch
from torch import nn

from neuralmap.exceptions import NeuralMapError
from neuralmap.learning.covariance import make_covariance

__all__ = ["NoiseModel"]


class NoiseModel(nn.Module):
    """Process noise ``Q`` ``(n, n)`` and altimeter variance ``R`` (scalar), learnable.

    Args:
        Q0: ``(n, n)`` or ``(n,)`` positive-definite start of Q.
        R0: Start of R (> 0), m².
        q_kind: ``"log_diagonal"`` or ``"log_cholesky"`` (`neuralmap.learning.covariance`).

    Raises:
        NeuralMapError: A start that is not positive definite, or an unknown kind.
    """

    def __init__(self, Q0: Any, R0: float, *, q_kind: str = "log_diagonal") -> None:
        super().__init__()
        self.q_kind = q_kind
        self.q = make_covariance(q_kind, torch.as_tensor(Q0, dtype=torch.float64))
        r0 = float(R0)
        if not r0 > 0.0 or r0 != r0:
            raise NeuralMapError(
                f"NoiseModel: R0 must be a variance > 0 m^2, got {R0!r}; the log "
                "parametrisation cannot represent R <= 0.")
        self.log_r = nn.Parameter(torch.tensor(r0, dtype=torch.float64).log())

    def Q(self) -> torch.Tensor:
        """``(n, n)`` process noise."""
        return self.q()

    def R(self) -> torch.Tensor:
        """``()`` measurement variance, m²."""
        return self.log_r.exp()

    def values(self) -> dict[str, Any]:
        """Plain numbers: ``Q_diag`` (list), ``Q`` (nested list) and ``R``."""
        with torch.no_grad():
            q = self.Q().detach().cpu()
            return {"Q_diag": torch.diagonal(q).tolist(), "Q": q.tolist(),
                    "R": float(self.R())}
