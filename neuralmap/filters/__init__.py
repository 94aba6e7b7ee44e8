"""Batched filters: the N-sample EKF, its diagnostics and input checks."""

from neuralmap.filters.diagnostics import UpdateDiagnostics
from neuralmap.filters.ekf import BatchedEKF, positive_definite_batchlast

__all__ = ["BatchedEKF", "UpdateDiagnostics", "positive_definite_batchlast"]
