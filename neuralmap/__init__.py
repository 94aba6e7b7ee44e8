"""neuralmap: neural terrain maps and batched terrain-aided navigation in PyTorch.

The front door::

    from neuralmap import Navigator, load_map, read_flight_input

* `Navigator` — terrain-aided fixes from a map, an INS and a radar altimeter
  (`neuralmap.nav.navigator.Navigator`, documented with the product package `neuralmap.nav`);
* `load_map` — a trained map file (`neuralmap.terrain.export.load_map`), or `resolve_map`
  for a DEM file or a tile name (`neuralmap.nav.map_source.resolve_map`);
* `read_flight_input` — a recorded flight log in the map's frame
  (`neuralmap.flights.flight_input.read_flight_input`).

These names load on first use, so that ``import neuralmap`` (and the console commands,
whose start-up must stay quick and interruptible) loads no torch; the packages themselves
export their names explicitly. The packages, lowest first: `neuralmap.dem` (DEM tiles),
`neuralmap.terrain` (maps), `neuralmap.linearize`, `neuralmap.filters` (Kalman core,
policies, the point-mass lattice), `neuralmap.tan` (the TAN model and the navigation
methods), `neuralmap.nav` (the product: the Navigator), `neuralmap.lab` (scenarios,
simulation, Monte Carlo, the bound, metrics), `neuralmap.studies` (one module per study),
`neuralmap.training`.
"""

from __future__ import annotations

import importlib
from typing import Any

__version__ = "0.1.0"

#: The front door: name -> the module that defines it.
_FRONT_DOOR = {
    "Navigator": "neuralmap.nav.navigator",
    "NavigatorConfig": "neuralmap.nav.config",
    "load_navigator_config": "neuralmap.nav.config",
    "Fix": "neuralmap.nav.fix",
    "FixTrack": "neuralmap.nav.fix",
    "read_flight_input": "neuralmap.flights.flight_input",
    "resolve_map": "neuralmap.nav.map_source",
    "load_map": "neuralmap.terrain.export",
}

__all__ = sorted(_FRONT_DOOR)


def __getattr__(name: str) -> Any:
    """Loads a front-door name from its module on first use."""
    module = _FRONT_DOOR.get(name)
    if module is None:
        raise AttributeError(f"module 'neuralmap' has no attribute {name!r}")
    value = getattr(importlib.import_module(module), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    """Module attributes including the front-door names."""
    return sorted(set(globals()) | set(__all__))
