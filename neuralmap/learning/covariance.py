"""Learnable covariance matrices that stay positive definite: log-diagonal and log-Cholesky.

An unconstrained parameter vector ``θ`` maps to a symmetric positive-definite matrix, so any
torch optimiser can move ``θ`` freely and the filter never sees an indefinite Q or R:

* log-diagonal: ``C = diag(exp(θ))`` (``n`` parameters, independent variances);
* log-Cholesky: ``C = L Lᵀ`` with ``L`` lower triangular, ``L_ii = exp(θ_ii)`` and free
  off-diagonal entries (``n (n + 1) / 2`` parameters; Pinheiro & Bates 1996), every
  symmetric positive-definite matrix is reached exactly once.

Both are built from an initial matrix, which must itself be symmetric positive definite:
an indefinite (or semi-definite, NaN, non-symmetric) start raises `NeuralMapError`
naming the matrix and the fix.
"""

from __future__ import annotations

import torch
from torch import nn

from neuralmap.exceptions import NeuralMapError
from neuralmap.filters.stats import symmetrize

__all__ = [
    "COVARIANCE_KINDS",
    "LogCholeskyCovariance",
    "LogDiagonalCovariance",
    "check_positive_definite",
    "make_covariance",
]

#: Parametrisation names accepted by `make_covariance`.
COVARIANCE_KINDS = ("log_diagonal", "log_cholesky")


def check_positive_definite(matrix: torch.Tensor, *, name: str) -> torch.Tensor:
    """Checks that ``matrix`` is a finite, symmetric, positive-definite ``(n, n)`` matrix.

    Args:
        matrix: ``(n, n)`` candidate covariance.
        name: What it is (``"Q"``, ``"R"``), for the message.

    Returns:
        The matrix as float64.

    Raises:
        NeuralMapError: Wrong shape, non-finite, not symmetric or not positive definite.
    """
    m = torch.as_tensor(matrix, dtype=torch.float64)
    if m.ndim == 0:
        m = m.reshape(1, 1)
    if m.ndim != 2 or m.shape[0] != m.shape[1] or m.shape[0] == 0:
        raise NeuralMapError(f"{name}: a covariance must be a square (n, n) matrix, got shape "
                             f"{tuple(m.shape)}.")
    if not bool(torch.isfinite(m).all()):
        raise NeuralMapError(f"{name}: the initial covariance has NaN/inf entries: {m.tolist()}.")
    scale = float(m.abs().max()) or 1.0
    if float((m - m.T).abs().max()) > 1e-9 * scale:
        raise NeuralMapError(f"{name}: the initial covariance is not symmetric: {m.tolist()}.")
    eig = torch.linalg.eigvalsh(symmetrize(m))
    if float(eig.min()) <= 0.0:
        raise NeuralMapError(
            f"{name}: the initial covariance is not positive definite (smallest eigenvalue "
            f"{float(eig.min()):.3g}); the log-diagonal and log-Cholesky parametrisations can "
            "only represent positive-definite matrices. Start from variances > 0 (e.g. a small "
            "positive value instead of 0) and a correlation inside (-1, 1)."
        )
    return m


class LogDiagonalCovariance(nn.Module):
    """``C = diag(exp(θ))``: independent variances (SEEDS 004's diagonal Q).

    Args:
        initial: ``(n, n)`` positive-definite start (its diagonal is used; off-diagonal
            entries must be 0), or ``(n,)`` variances > 0, or a scalar variance.

    Raises:
        NeuralMapError: A variance ≤ 0, non-finite, or off-diagonal entries.
    """

    def __init__(self, initial: torch.Tensor | list[float] | float) -> None:
        super().__init__()
        init = torch.as_tensor(initial, dtype=torch.float64)
        if init.ndim <= 1:
            init = torch.diag(init.reshape(-1))
        m = check_positive_definite(init, name="LogDiagonalCovariance")
        if float((m - torch.diag(torch.diagonal(m))).abs().max()) > 0.0:
            raise NeuralMapError(
                "LogDiagonalCovariance: the initial covariance has off-diagonal entries; use "
                "the log_cholesky parametrisation for a full matrix."
            )
        self.theta = nn.Parameter(torch.diagonal(m).log().clone())

    @property
    def n(self) -> int:
        """Matrix size."""
        return int(self.theta.shape[0])

    def forward(self) -> torch.Tensor:
        """The ``(n, n)`` covariance, positive definite for every θ."""
        return torch.diag(self.theta.exp())


class LogCholeskyCovariance(nn.Module):
    """``C = L Lᵀ``, ``L_ii = exp(θ_ii)``, free strictly-lower entries (log-Cholesky).

    Args:
        initial: ``(n, n)`` symmetric positive-definite start (or ``(n,)`` variances).

    Raises:
        NeuralMapError: The start is not symmetric positive definite.
    """

    def __init__(self, initial: torch.Tensor | list[float] | float) -> None:
        super().__init__()
        init = torch.as_tensor(initial, dtype=torch.float64)
        if init.ndim <= 1:
            init = torch.diag(init.reshape(-1))
        m = check_positive_definite(init, name="LogCholeskyCovariance")
        chol = torch.linalg.cholesky(m)
        n = m.shape[0]
        rows, cols = torch.tril_indices(n, n)
        values = chol[rows, cols].clone()
        diag = rows == cols
        values[diag] = values[diag].log()
        self.register_buffer("rows", rows, persistent=False)
        self.register_buffer("cols", cols, persistent=False)
        self.register_buffer("diag", diag, persistent=False)
        self._n = n
        self.theta = nn.Parameter(values)

    @property
    def n(self) -> int:
        """Matrix size."""
        return self._n

    def forward(self) -> torch.Tensor:
        """The ``(n, n)`` covariance ``L Lᵀ``, positive definite for every θ."""
        entries = torch.where(self.diag, self.theta.exp(), self.theta)
        chol = torch.zeros(self._n, self._n, dtype=self.theta.dtype, device=self.theta.device)
        chol = chol.index_put((self.rows, self.cols), entries)
        cov = chol @ chol.T
        return symmetrize(cov)


def make_covariance(kind: str, initial: torch.Tensor | list[float] | float) -> nn.Module:
    """A learnable covariance by parametrisation name (`COVARIANCE_KINDS`).

    Raises:
        NeuralMapError: Unknown kind, or a start that is not positive definite.
    """
    if kind == "log_diagonal":
        return LogDiagonalCovariance(initial)
    if kind == "log_cholesky":
        return LogCholeskyCovariance(initial)
    raise NeuralMapError(
        f"covariance parametrisation {kind!r} is unknown; use one of {', '.join(COVARIANCE_KINDS)}."
    )
