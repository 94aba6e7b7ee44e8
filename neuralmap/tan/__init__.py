"""TAN methods: the terrain-aided navigation model and the filters that plug into the Navigator.

* `TanModel` (`neuralmap.tan.model`): the 5-state error model of SEEDS 004 — Φ(Δt), Q(Δt),
  the measurement row, the altitude error as a random walk or a Gauss-Markov process — one
  source for the simulator, every method and the PCRB; `AugmentedTanModel` adds the AR
  map-error states of SEEDS 000.
* The navigation-method protocol (`NavigationMethod`, `MethodContext`, `Innovation`) and its
  registry (`register_method`, `method_names`, `resolve_method`): a method is one class and
  one registry line.
* The built-in methods (`neuralmap.tan.methods`): the point-mass tracker, the EKF with any
  linearisation and update policy, the EKF started by the point-mass grid, the EKF bank, the
  point-mass grid.
* The EKF step (`tan_filter_step`) and the map on a lattice's cells (`neuralmap.tan.cells`).

The product (`neuralmap.nav`: the Navigator) uses this package; this package never uses it.
"""

from neuralmap.tan.augmented import AugmentedTanModel
from neuralmap.tan.ekf_step import StepDiagnostics, tan_filter_step
from neuralmap.tan.method import ACQUISITION_RULES, Innovation, MethodContext, NavigationMethod
from neuralmap.tan.methods import (
    EkfBank,
    EkfBankOptions,
    EkfMethod,
    EkfOptions,
    PointMassEkf,
    PointMassGrid,
    PointMassOptions,
    PointMassTrackerMethod,
    TrackerOptions,
)
from neuralmap.tan.model import (
    N_STATES,
    LatticeForm,
    TanModel,
    measurement_jacobian,
    transition_matrix,
)
from neuralmap.tan.registry import (
    all_method_names,
    method_class,
    method_names,
    register_method,
    resolve_method,
)

__all__ = [
    "ACQUISITION_RULES", "N_STATES", "AugmentedTanModel", "EkfBank", "EkfBankOptions",
    "EkfMethod", "EkfOptions", "Innovation", "LatticeForm", "MethodContext",
    "NavigationMethod", "PointMassEkf", "PointMassGrid", "PointMassOptions",
    "PointMassTrackerMethod", "StepDiagnostics", "TanModel", "TrackerOptions",
    "all_method_names", "measurement_jacobian", "method_class", "method_names",
    "register_method", "resolve_method", "tan_filter_step", "transition_matrix",
]
