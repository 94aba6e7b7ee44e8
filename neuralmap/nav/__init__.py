"""Terrain-aided navigation: scenarios, truth simulator, 5-state TAN EKF, Monte Carlo, metrics.

Names are imported lazily from their submodules (``from neuralmap.nav import simulate``
works; importing `neuralmap.nav` itself loads nothing heavy), so a submodule whose
dependencies are missing does not break the others.
"""

from __future__ import annotations

import importlib
from typing import Any

_EXPORTS: dict[str, str] = {
    "Scenario": "scenario",
    "SCENARIO_NAMES": "scenario",
    "load_scenario": "scenario",
    "save_scenario": "scenario",
    "scenario_tile": "scenario",
    "Truth": "simulator",
    "simulate": "simulator",
    "nominal_path": "simulator",
    "dem_error_field": "simulator",
    "StepDiagnostics": "tan",
    "transition_matrix": "tan",
    "measurement_jacobian": "tan",
    "tan_filter_step": "tan",
    "FilterRun": "monte_carlo",
    "MonteCarloResult": "monte_carlo",
    "run_filter": "monte_carlo",
    "run_monte_carlo": "monte_carlo",
    "run_filters": "monte_carlo",
    "FilterJob": "monte_carlo",
    "check_map_matches": "monte_carlo",
    "DIVERGENCE_RULE": "metrics",
    "divergence_rule": "metrics",
    "navigation_metrics": "metrics",
    "nees": "metrics",
    "pcrb": "pcrb",
    "pcrb_position": "pcrb",
    "AugmentedTanModel": "augmented",
    "augment_information": "augmented",
    "paper_tan_model": "augmented",
    "MapFrame": "georef",
    "FlightInput": "flight_input",
    "read_flight_input": "flight_input",
    "MapSource": "map_source",
    "resolve_map": "map_source",
}

__all__ = sorted(_EXPORTS)


def __getattr__(name: str) -> Any:
    """Imports an exported name from its submodule on first use."""
    module = _EXPORTS.get(name)
    if module is None:
        raise AttributeError(f"module 'neuralmap.nav' has no attribute {name!r}")
    value = getattr(importlib.import_module(f"neuralmap.nav.{module}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    """Module attributes including the lazily exported names."""
    return sorted(set(globals()) | set(__all__))
