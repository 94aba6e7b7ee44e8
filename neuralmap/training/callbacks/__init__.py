"""Lightning callbacks of the terrain fit: target-RMSE stop, dashboard layout, fit report."""

from neuralmap.training.callbacks.dashboard import SCALAR_LAYOUT, DashboardLayout
from neuralmap.training.callbacks.fit_report import FitReport
from neuralmap.training.callbacks.target_rmse import TargetRmseStopping

__all__ = ["SCALAR_LAYOUT", "DashboardLayout", "FitReport", "TargetRmseStopping"]
