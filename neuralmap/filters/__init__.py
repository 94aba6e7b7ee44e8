"""Batched filters: the N-sample EKF, its diagnostics and input checks, the point-mass
filter and the EKF bank (Gaussian sum)."""

from neuralmap.filters.diagnostics import UpdateDiagnostics
from neuralmap.filters.ekf import BatchedEKF, positive_definite_batchlast
from neuralmap.filters.ekf_bank import GaussianSumEKF, lattice_prior
from neuralmap.filters.point_mass import PointMassConfig, PointMassFilter, PointMassUpdate

__all__ = [
    "BatchedEKF",
    "GaussianSumEKF",
    "PointMassConfig",
    "PointMassFilter",
    "PointMassUpdate",
    "UpdateDiagnostics",
    "lattice_prior",
    "positive_definite_batchlast",
]
