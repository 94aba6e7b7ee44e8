"""The product's engine: the Navigator, its config, its fixes and the maps it flies over.

* `Navigator` (`neuralmap.nav.navigator`): terrain-aided fixes of N vehicles, epoch by
  epoch (`Navigator.step`) or for a whole log (`Navigator.replay`), over any map with any
  registered navigation method (`neuralmap.tan`); its config (`NavigatorConfig`,
  `load_navigator_config`); the fixes (`Fix`, `FixTrack`, `STATUS`) with their protection
  levels (`neuralmap.nav.integrity`).
* Maps in (`resolve_map`, `MapSource`), the map frame and its georeference (`MapFrame`),
  the measurement noise from the sensor and the map's error model (`MapNoise`,
  `measurement_noise`).

Recorded flights — logs in, the chunked replay, navigation.csv / .geojson and the report
out, the ``neuralmap-navigate`` command — are the package above this one,
`neuralmap.flights`; the lab (`neuralmap.lab`) flies its simulated vehicles through the
same Navigator. This package uses neither.
"""

from neuralmap.nav.config import NavigatorConfig, load_navigator_config
from neuralmap.nav.fix import STATUS, STATUS_CODE, Fix, FixTrack
from neuralmap.nav.georef import MapFrame
from neuralmap.nav.integrity import protection_levels
from neuralmap.nav.map_noise import MapNoise, measurement_noise
from neuralmap.nav.map_source import MapSource, resolve_map
from neuralmap.nav.navigator import COUNT_KEYS, Navigator

__all__ = [
    "COUNT_KEYS", "STATUS", "STATUS_CODE", "Fix", "FixTrack", "MapFrame", "MapNoise",
    "MapSource", "Navigator", "NavigatorConfig", "load_navigator_config",
    "measurement_noise", "protection_levels", "resolve_map",
]
