"""The lab: simulated flights, Monte Carlo, the Cramér-Rao bound and the metrics.

* scenarios (`Scenario`, `load_scenario`) and the truth simulator (`simulate`, `Truth`:
  trajectories, INS errors, altimeter with faults, a truth terrain with DEM error);
* Monte Carlo through the product: `fly` flies every simulated vehicle through one
  `neuralmap.nav.Navigator` (batched) and scores the fixes (`FilterRun`); `run_filter`,
  `run_filters`, `run_monte_carlo`, chunked and Dask-distributed runs
  (`run_monte_carlo_chunked`);
* the posterior Cramér-Rao bound (`neuralmap.lab.pcrb.pcrb`, `map_aware_pcrb`; the
  function is not re-exported here, where its name would hide its module), navigation
  metrics
  (`navigation_metrics`, `nees`, divergence), bootstrap intervals, noise calibration.

The lab uses the product and the methods; neither uses the lab.
"""

from neuralmap.lab.metrics import DIVERGENCE_RULE, divergence_rule, navigation_metrics, nees
from neuralmap.lab.monte_carlo import (
    FilterJob,
    FilterRun,
    MonteCarloResult,
    check_map_matches,
    fly,
    run_filter,
    run_filters,
    run_monte_carlo,
    study_navigator_config,
)
from neuralmap.lab.pcrb import map_aware_pcrb, pcrb_position
from neuralmap.lab.scenario import SCENARIO_NAMES, Scenario, load_scenario, save_scenario
from neuralmap.lab.simulator import Truth, dem_error_field, nominal_path, simulate

__all__ = [
    "DIVERGENCE_RULE", "SCENARIO_NAMES", "FilterJob", "FilterRun", "MonteCarloResult",
    "Scenario", "Truth", "check_map_matches", "dem_error_field", "divergence_rule", "fly",
    "load_scenario", "map_aware_pcrb", "navigation_metrics", "nees", "nominal_path", "pcrb_position", "run_filter", "run_filters", "run_monte_carlo", "save_scenario",
    "simulate", "study_navigator_config",
]
