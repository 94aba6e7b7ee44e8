"""Batched filters: the functional Kalman core, the N-sample EKF, policies, diagnostics."""

from neuralmap.filters.diagnostics import UpdateDiagnostics
from neuralmap.filters.ekf import BatchedEKF, positive_definite_batchlast
from neuralmap.filters.kalman import KalmanUpdate, kalman_predict, kalman_update
from neuralmap.filters.policies import (
    IGG3,
    ChiSquareGate,
    Compose,
    Huber,
    InnovationInflation,
    QualityIndicator,
    QualityR,
    RobustAdaptive,
    SageHusa,
    VariationalAdaptive,
    YangAdaptive,
)
from neuralmap.filters.policy import Adaptation, FilterPolicy, Posterior, UpdateContext

__all__ = [
    "IGG3",
    "Adaptation",
    "BatchedEKF",
    "ChiSquareGate",
    "Compose",
    "FilterPolicy",
    "Huber",
    "InnovationInflation",
    "KalmanUpdate",
    "Posterior",
    "QualityIndicator",
    "QualityR",
    "RobustAdaptive",
    "SageHusa",
    "UpdateContext",
    "UpdateDiagnostics",
    "VariationalAdaptive",
    "YangAdaptive",
    "kalman_predict",
    "kalman_update",
    "positive_definite_batchlast",
]
