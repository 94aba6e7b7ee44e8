"""The product: the Navigator and what a user needs around it to navigate a flight.

* `Navigator` (`neuralmap.nav.navigator`): terrain-aided fixes of N vehicles, epoch by
  epoch (`Navigator.step`) or for a whole log (`Navigator.replay`), over any map with any
  registered navigation method (`neuralmap.tan`); its config (`NavigatorConfig`,
  `load_navigator_config`); the fixes (`Fix`, `FixTrack`, `STATUS`) with their protection
  levels (`neuralmap.nav.integrity`).
* Flight logs in (`read_flight_input`, `FlightInput`), maps in (`resolve_map`, `MapSource`,
  `MapFrame`), navigation out (CSV, GeoJSON, report: `neuralmap.nav.outputs`), the
  ``neuralmap-navigate`` command (`neuralmap.nav.cli`, `neuralmap.nav.flight`).

The lab (`neuralmap.lab`) flies its simulated vehicles through this Navigator; this package
never uses the lab.
"""

from neuralmap.nav.config import NavigatorConfig, load_navigator_config
from neuralmap.nav.fix import STATUS, STATUS_CODE, Fix, FixTrack
from neuralmap.nav.flight import FlightOptions, navigate_flight, write_flight
from neuralmap.nav.flight_input import FlightInput, read_flight_input
from neuralmap.nav.georef import MapFrame
from neuralmap.nav.integrity import protection_levels
from neuralmap.nav.map_noise import MapNoise, measurement_noise
from neuralmap.nav.map_source import MapSource, resolve_map
from neuralmap.nav.navigator import COUNT_KEYS, Navigator

__all__ = [
    "COUNT_KEYS", "STATUS", "STATUS_CODE", "Fix", "FixTrack", "FlightInput", "FlightOptions",
    "MapFrame", "MapNoise", "MapSource", "Navigator", "NavigatorConfig",
    "load_navigator_config", "measurement_noise", "navigate_flight", "protection_levels",
    "read_flight_input", "resolve_map", "write_flight",
]
