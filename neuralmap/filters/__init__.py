"""Batched filters: the functional Kalman core, the N-sample EKF, policies, diagnostics."""

from neuralmap.filters.diagnostics import UpdateDiagnostics
from neuralmap.filters.ekf import BatchedEKF, positive_definite_batchlast
from neuralmap.filters.kalman import KalmanUpdate, kalman_predict, kalman_update
from neuralmap.filters.policy import Adaptation, FilterPolicy, Posterior, UpdateContext

__all__ = [
    "Adaptation",
    "BatchedEKF",
    "FilterPolicy",
    "KalmanUpdate",
    "Posterior",
    "UpdateContext",
    "UpdateDiagnostics",
    "kalman_predict",
    "kalman_update",
    "positive_definite_batchlast",
]
