"""Lightning callbacks of the terrain fit: target-RMSE stop, dashboard, fit report, resume hint,
plain epoch lines for logs, held-out checkpoint ranking."""

from neuralmap.training.callbacks.dashboard import SCALAR_LAYOUT, DashboardLayout
from neuralmap.training.callbacks.epoch_lines import EpochLines
from neuralmap.training.callbacks.fit_report import FitReport
from neuralmap.training.callbacks.heldout_checkpoint import HeldOutCheckpoint
from neuralmap.training.callbacks.resume_hint import ResumeHint
from neuralmap.training.callbacks.target_rmse import TargetRmseStopping

__all__ = [
    "SCALAR_LAYOUT",
    "DashboardLayout",
    "EpochLines",
    "FitReport",
    "HeldOutCheckpoint",
    "ResumeHint",
    "TargetRmseStopping",
]
