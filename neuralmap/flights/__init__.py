"""Recorded flights through the Navigator: a log in, its fixes and report out.

* Flight logs in (`read_flight_input`, `FlightInput`; `neuralmap.flights.flight_input`):
  map-frame, lat/lon and KF-GINS logs, refused with file, line and column when they cannot
  be navigated; the vertical datum checked against the map (`check_datum`,
  `neuralmap.flights.vertical_datum`).
* The replay (`navigate_flight`, `FlightOptions`; `neuralmap.flights.flight`): the log
  through one `neuralmap.nav.Navigator` in chunks of epochs, the log's arrays memory-mapped
  (`neuralmap.flights.mapped_flight`), each chunk reduced to the compact record the report
  needs (`TrackSummary`, `neuralmap.flights.track_summary`).
* Navigation out (`write_flight`; `neuralmap.flights.outputs`): navigation.csv,
  navigation.geojson, report.md, results.json, figures, TensorBoard.
* The ``neuralmap-navigate`` command (`neuralmap.flights.cli`) and the ``flight`` study
  (`neuralmap.studies.flight`).

Layered above the product's engine (`neuralmap.nav`), which never imports this package.
"""

from neuralmap.flights.flight import FlightNavigation, FlightOptions, navigate_flight, write_flight
from neuralmap.flights.flight_input import FlightInput, read_flight_input
from neuralmap.flights.outputs import NavigationFiles
from neuralmap.flights.track_summary import TrackSummary
from neuralmap.flights.vertical_datum import check_datum

__all__ = [
    "FlightInput", "FlightNavigation", "FlightOptions", "NavigationFiles", "TrackSummary",
    "check_datum", "navigate_flight", "read_flight_input", "write_flight",
]
