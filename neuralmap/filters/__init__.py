"""Batched filters: the functional Kalman core, the N-sample EKF, policies, diagnostics,
the point-mass filter and the EKF bank (Gaussian sum)."""

from neuralmap.filters.diagnostics import UpdateDiagnostics
from neuralmap.filters.ekf import BatchedEKF, positive_definite_batchlast
from neuralmap.filters.ekf_bank import GaussianSumEKF, lattice_prior
from neuralmap.filters.kalman import KalmanUpdate, kalman_predict, kalman_update
from neuralmap.filters.point_mass import PointMassConfig, PointMassFilter, PointMassUpdate
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
    WindowedInflation,
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
    "GaussianSumEKF",
    "Huber",
    "InnovationInflation",
    "KalmanUpdate",
    "PointMassConfig",
    "PointMassFilter",
    "PointMassUpdate",
    "Posterior",
    "QualityIndicator",
    "QualityR",
    "RobustAdaptive",
    "SageHusa",
    "UpdateContext",
    "UpdateDiagnostics",
    "VariationalAdaptive",
    "WindowedInflation",
    "YangAdaptive",
    "kalman_predict",
    "kalman_update",
    "lattice_prior",
    "positive_definite_batchlast",
]
