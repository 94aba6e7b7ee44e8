"""The linearisation layer: terrain height, slope and linearisation variance at estimates.

Autograd on any terrain model (neural maps, SEEDS 004) and the classical DEM methods of
SEEDS 000: first-order Taylor on the bilinear grid, nine-point fit, mean-point selection,
least-squares plane over a fixed or covariance-adaptive window Omega around the estimate
(SEEDS 000 calls it the region).
"""

from neuralmap.linearize.autograd import AutogradLinearizer
from neuralmap.linearize.base import Linearization, Linearizer
from neuralmap.linearize.factory import LINEARIZER_NAMES, describe_linearizer, make_linearizer
from neuralmap.linearize.mean_point import MeanPointLinearizer
from neuralmap.linearize.nine_point import NinePointLinearizer
from neuralmap.linearize.plane_fit import PlaneFitLinearizer
from neuralmap.linearize.region_variance import RegionReport, region_miss_variance
from neuralmap.linearize.taylor import TaylorLinearizer
from neuralmap.linearize.window import (
    SIGMA_MAX_M,
    SIGMA_MEAN_M,
    SIGMA_MIN_M,
    WindowPlaneLinearizer,
)

__all__ = [
    "LINEARIZER_NAMES",
    "SIGMA_MAX_M",
    "SIGMA_MEAN_M",
    "SIGMA_MIN_M",
    "AutogradLinearizer",
    "Linearization",
    "Linearizer",
    "MeanPointLinearizer",
    "NinePointLinearizer",
    "PlaneFitLinearizer",
    "RegionReport",
    "TaylorLinearizer",
    "WindowPlaneLinearizer",
    "describe_linearizer",
    "make_linearizer",
    "region_miss_variance",
]
