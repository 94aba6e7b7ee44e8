"""The navigator's measurement noise from what a user has: the sensor and the map's own error.

In the studies the tracker's ``R`` is the altimeter variance plus the DEM error *measured
against the truth terrain* (`neuralmap.studies.setup.dem_error_model`). A real flight
has no truth terrain, so the navigator builds ``R`` from stated numbers (SEEDS 004: the map
error is white noise added to R)::

    R = σ_alt² + σ_dem² + σ_fit²

* ``σ_alt`` — the altimeter's noise (``sensor.altimeter_sigma_m``);
* ``σ_dem`` — the DEM's stated vertical accuracy (``map_error.dem_accuracy_m``; a
  producer's figure such as the 1 m σ of a lidar DTM; 0 when unknown);
* ``σ_fit`` — a neural map's fit error against its DEM: ``map_error.fit_rmse_m`` when
  given, else read from the map file's stored fit metrics (`map_fit_rmse`: the
  between-node error when stored — the aircraft flies between nodes — else the node RMSE);
  0 for a grid map (it *is* the DEM).

For EKF methods a measured linearisation table
(`NoiseTable`, ``map_error.linearisation_table``)
adds the linearisation miss as a function of the position σ on top (the EKF's ``R`` then
also carries the table's variance at the filter's σ); the grid methods evaluate the map at
every cell and need no linearisation term.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from neuralmap.exceptions import NeuralMapError

__all__ = ["MapNoise", "load_noise_table", "map_fit_rmse", "measurement_noise"]

#: Fit-metric keys read from a map file, in order of preference (between-node first).
FIT_METRIC_KEYS: tuple[str, ...] = ("offnode_rmse_m", "between_rmse_m", "rmse_m")


@dataclass(frozen=True)
class MapNoise:
    """The parts of the navigator's ``R`` (m² each) and where each came from.

    Attributes:
        altimeter_m2: ``σ_alt²``.
        dem_m2: ``σ_dem²`` (stated DEM accuracy).
        fit_m2: ``σ_fit²`` (neural map fit error).
        fit_source: Where ``σ_fit`` came from (``"config"``, ``"map metrics: <key>"``,
            ``"grid map"``, ``"override"`` or ``"none"``).
    """

    altimeter_m2: float
    dem_m2: float
    fit_m2: float
    fit_source: str

    @property
    def map_m2(self) -> float:
        """The map's error variance ``σ_dem² + σ_fit²``."""
        return self.dem_m2 + self.fit_m2

    @property
    def R(self) -> float:
        """``R = σ_alt² + σ_dem² + σ_fit²``, m²."""
        return self.altimeter_m2 + self.dem_m2 + self.fit_m2

    def to_dict(self) -> dict[str, Any]:
        """Plain form for reports."""
        return {"R_m2": self.R, "altimeter_m2": self.altimeter_m2, "dem_m2": self.dem_m2,
                "fit_m2": self.fit_m2, "fit_source": self.fit_source}


def map_fit_rmse(terrain: Any) -> tuple[float, str]:
    """A map's own fit error from its stored metrics.

    Blockwise maps (`neuralmap.terrain.export.load_map`) and latent maps
    (`LatentTerrainMap`) carry ``metrics`` written at
    training (``rmse_m`` at the nodes, ``offnode_rmse_m`` / ``between_rmse_m`` between
    them). A grid map (``heights`` buffer, no metrics) is the DEM itself: 0.

    Args:
        terrain: The map.

    Returns:
        ``(rmse_m, source)``; ``(0.0, "none")`` when nothing is stored.
    """
    metrics = getattr(terrain, "metrics", None)
    if isinstance(metrics, dict):
        for key in FIT_METRIC_KEYS:
            value = metrics.get(key)
            if isinstance(value, (int, float)) and math.isfinite(value) and value >= 0:
                return float(value), f"map metrics: {key}"
    if hasattr(terrain, "heights") and getattr(terrain, "method", None) is not None:
        return 0.0, "grid map"
    return 0.0, "none"


def measurement_noise(config: Any, terrain: Any = None, *,
                      map_error_variance: float | None = None,
                      altimeter_variance: float | None = None) -> MapNoise:
    """The navigator's ``R`` parts from its config and the map (module docstring).

    Args:
        config: A `NavigatorConfig`.
        terrain: The map (its stored fit metrics are read when ``fit_rmse_m`` is None).
        map_error_variance: Overrides the whole map term ``σ_dem² + σ_fit²`` (m²), e.g. the
            DEM error measured against a truth terrain in a study.
        altimeter_variance: The altimeter's variance (m²); None = ``sensor.altimeter_sigma_m``
            squared (a simulation study passes its scenario's).

    Returns:
        `MapNoise`.

    Raises:
        NeuralMapError: ``map_error_variance`` negative or not finite.
    """
    alt = (float(config.sensor.altimeter_sigma_m) ** 2 if altimeter_variance is None
           else float(altimeter_variance))
    if map_error_variance is not None:
        v = float(map_error_variance)
        if not (math.isfinite(v) and v >= 0):
            raise NeuralMapError(f"Navigator: map_error_variance must be a finite variance "
                                 f">= 0 m², got {map_error_variance!r}.")
        return MapNoise(altimeter_m2=alt, dem_m2=0.0, fit_m2=v, fit_source="override")
    me = config.map_error
    dem = 0.0 if me.dem_accuracy_m is None else float(me.dem_accuracy_m) ** 2
    if me.fit_rmse_m is not None:
        fit, source = float(me.fit_rmse_m), "config"
    else:
        fit, source = map_fit_rmse(terrain) if terrain is not None else (0.0, "none")
    return MapNoise(altimeter_m2=alt, dem_m2=dem, fit_m2=fit * fit, fit_source=source)


def load_noise_table(path: str | Path) -> Any:
    """A `NoiseTable` from its JSON form
    (`NoiseTable.to_dict`, or a results.json entry holding those keys).

    Raises:
        NeuralMapError: Missing file, not JSON, or keys missing (names them).
    """
    from neuralmap.linearize.measured_noise import NoiseTable

    p = Path(path)
    try:
        data = json.loads(p.read_text(encoding="utf-8"))
    except OSError as exc:
        raise NeuralMapError(f"{p}: cannot read the linearisation table ({exc}).") from exc
    except json.JSONDecodeError as exc:
        raise NeuralMapError(f"{p}: the linearisation table is not JSON (line {exc.lineno}, "
                             f"column {exc.colno}: {exc.msg}).") from exc
    need = ("sigmas_m", "map_mse_m2", "map_mean_m", "variance_m2", "flight_samples",
            "n_points", "draws", "seed")
    missing = [k for k in need if not isinstance(data, dict) or k not in data]
    if missing:
        raise NeuralMapError(f"{p}: the linearisation table lacks {', '.join(missing)} (write "
                             "it with NoiseTable.to_dict()).")
    tuples = {k: tuple(float(v) for v in data[k]) for k in
              ("sigmas_m", "map_mse_m2", "map_mean_m", "variance_m2", "flight_samples")}
    scale = tuple(float(v) for v in data.get("scale", ()))
    return NoiseTable(**tuples, n_points=int(data["n_points"]), draws=int(data["draws"]),
                      seed=int(data["seed"]), scale=scale)
