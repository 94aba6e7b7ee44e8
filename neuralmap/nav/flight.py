"""Navigating one recorded flight: the implementation behind ``neuralmap-navigate``.

``neuralmap-navigate LOG --map MAP`` and the ``flight`` study (``python evaluate.py
--config configs/flight.yaml --log LOG --map MAP``) run the same steps (`navigate_flight`,
then `write_flight`):

1. resolve the map (`neuralmap.nav.map_source.resolve_map`: trained map, DEM file or
   embedded tile) and its frame;
2. read the log into the map frame (`neuralmap.nav.flight_input.read_flight_input`),
   refusing bad logs before anything is written;
3. check the vertical datum (`neuralmap.nav.vertical_datum.check_datum`);
4. replay it through the `Navigator` (configured by the navigator YAML,
   ``configs/navigator.yaml`` by default);
5. write navigation.csv, navigation.geojson and, with a reference, the errors in the report
   format of the toolkit (report.md, results.json, figures, TensorBoard) through its one
   outputs writer.
"""

from __future__ import annotations

import dataclasses
import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from neuralmap.exceptions import NeuralMapError

__all__ = ["FLIGHT_TITLE", "FlightNavigation", "FlightOptions", "navigate_flight",
           "write_flight"]

#: The report title of a navigated flight.
FLIGHT_TITLE = "Navigation of a recorded flight"


@dataclass
class FlightOptions:
    """How to navigate one recorded flight (``neuralmap-navigate``, the ``flight`` study).

    Attributes:
        log: The flight log: map-frame or geographic CSV/NPZ, or a KF-GINS navigation
            result (then ``radar`` is required). See `neuralmap.nav.flight_input`.
        map: A DEM file, a trained map file or an embedded tile name
            (`neuralmap.nav.map_source`).
        navigator: Navigator YAML (None = the shipped ``configs/navigator.yaml``).
        navigator_options: Overrides on top of it, by section
            (``{sensor: {altimeter_sigma_m: 5}}``).
        format: ``auto``, ``map_frame``, ``geographic`` or ``kfgins``.
        radar: Radar log of a KF-GINS input (``time, radar``).
        reference: KF-GINS navigation file used as reference for a KF-GINS input.
        alt_datum: ``dem`` (altitude above the DEM's vertical datum) or ``ellipsoidal``
            (WGS-84); None = ``dem`` for CSV/NPZ logs, ``ellipsoidal`` for KF-GINS.
        geoid_undulation: Geoid undulation N (m) for ellipsoidal altitudes (``h − N``).
        dem_accuracy_m: The DEM's stated vertical accuracy (1σ, m); overrides the
            navigator config's ``map_error.dem_accuracy_m``.
        datum_check: Refuse a log whose altitude disagrees with map + clearance.
        datum_check_sigma: Threshold of that check, in σ of what the navigator allows.
        n_ellipses: σ ellipses drawn along the track.
        study: The study that reruns these options (``python evaluate.py --config`` the
            run's config.yaml): ``flight``.
        dtype: Filter precision, ``float64`` or ``float32``.
        progress: Progress bar (heartbeat lines off a terminal).
    """

    study: str = "flight"
    log: str | None = None
    map: str | None = None
    navigator: str | None = None
    navigator_options: dict[str, Any] = field(default_factory=dict)
    format: str = "auto"
    radar: str | None = None
    reference: str | None = None
    alt_datum: str | None = None
    geoid_undulation: float | None = None
    dem_accuracy_m: float | None = None
    datum_check: bool = True
    datum_check_sigma: float = 3.0
    n_ellipses: int = 20
    dtype: str = "float64"
    progress: bool = True

    @property
    def torch_dtype(self) -> torch.dtype:
        """The filter dtype as a torch dtype."""
        return torch.float32 if self.dtype == "float32" else torch.float64

    def validate(self) -> None:
        """Checks the options (not the files: those are read by `navigate_flight`).

        Raises:
            NeuralMapError: A missing ``log``/``map`` or a value out of range.
        """
        from neuralmap.nav.flight_input import FLIGHT_FORMATS
        from neuralmap.nav.vertical_datum import ALT_DATUMS

        if not self.log:
            raise NeuralMapError("--log LOG is required: the flight log to navigate (CSV/NPZ "
                                 "or a KF-GINS navigation result).")
        if not self.map:
            raise NeuralMapError("--map MAP is required: a DEM file, a trained map "
                                 "(neural_map.pt) or a tile name such as jacksboro.")
        if self.format not in FLIGHT_FORMATS:
            raise NeuralMapError(f"--format {self.format!r}: choose one of "
                                 f"{', '.join(FLIGHT_FORMATS)}.")
        if self.alt_datum is not None and self.alt_datum not in ALT_DATUMS:
            raise NeuralMapError(f"--alt_datum {self.alt_datum!r}: choose one of "
                                 f"{', '.join(ALT_DATUMS)}.")
        if self.geoid_undulation is not None and not math.isfinite(self.geoid_undulation):
            raise NeuralMapError("--geoid_undulation must be a finite number of metres.")
        if self.dem_accuracy_m is not None and not (
                math.isfinite(self.dem_accuracy_m) and self.dem_accuracy_m >= 0):
            raise NeuralMapError("--dem_accuracy_m must be a finite number >= 0 (m, 1σ).")
        if not self.datum_check_sigma > 0:
            raise NeuralMapError("--datum_check_sigma must be > 0.")
        if self.n_ellipses < 0:
            raise NeuralMapError("--n_ellipses must be >= 0.")
        if not isinstance(self.navigator_options, dict):
            raise NeuralMapError("--navigator_options must be a mapping of section: options.")
        if self.dtype not in ("float64", "float32"):
            raise NeuralMapError(f"--dtype must be float64 or float32, got {self.dtype!r}.")


@dataclass
class FlightNavigation:
    """A navigated flight, ready to be written.

    Attributes:
        config: The flight options.
        source: The resolved map (`MapSource`).
        flight: The flight input (`FlightInput`).
        navigator_config: The `NavigatorConfig` used.
        track: The `FixTrack`.
        datum: The datum check's summary.
        noise: The navigator's ``R`` parts (`MapNoise`).
        seconds: Wall time of the replay.
    """

    config: FlightOptions
    source: Any
    flight: Any
    navigator_config: Any
    track: Any
    datum: dict[str, Any]
    noise: Any
    seconds: float


def _navigator_config(config: FlightOptions) -> Any:
    from neuralmap.nav.config import NavigatorConfig, load_navigator_config

    nav_cfg = load_navigator_config(config.navigator)
    if config.navigator_options:
        nav_cfg = NavigatorConfig.from_dict(config.navigator_options,
                                            where="--navigator_options", base=nav_cfg)
    if config.dem_accuracy_m is not None:
        nav_cfg = dataclasses.replace(nav_cfg, map_error=dataclasses.replace(
            nav_cfg.map_error, dem_accuracy_m=float(config.dem_accuracy_m))).validate()
    return nav_cfg


def navigate_flight(config: FlightOptions) -> FlightNavigation:
    """Reads the map and the log, checks them, and replays the flight (writes nothing).

    Raises:
        NeuralMapError: A refused log or map (file, line and column named) or bad options.
    """
    from neuralmap.nav.flight_input import detect_format, read_flight_input
    from neuralmap.nav.map_noise import measurement_noise
    from neuralmap.nav.map_source import resolve_map
    from neuralmap.nav.navigator import Navigator
    from neuralmap.nav.vertical_datum import check_datum

    dtype = config.torch_dtype
    nav_cfg = _navigator_config(config)
    source = resolve_map(config.map, dtype=dtype,
                         dem_accuracy_m=nav_cfg.map_error.dem_accuracy_m)
    needs_frame = detect_format(config.log, config.format) != "map_frame"
    frame = None
    if source.has_frame or needs_frame:
        try:
            frame = source.frame  # raises when there is no georeference or pyproj is missing
        except NeuralMapError:
            if needs_frame:
                raise
    sensor = nav_cfg.sensor
    flight = read_flight_input(
        config.log, map_frame=frame, extent=source.extent, fmt=config.format,
        radar=config.radar, reference=config.reference, alt_datum=config.alt_datum,
        geoid_undulation=config.geoid_undulation,
        clearance_range=(sensor.clearance_min_m, sensor.clearance_max_m),
        period_s=sensor.dt_s, dtype=dtype)
    noise = measurement_noise(nav_cfg, source.terrain)
    datum: dict[str, Any] = {"alt_datum": flight.alt_datum,
                             "geoid_undulation_m": config.geoid_undulation, "checked": False}
    if config.datum_check:
        xy = flight.ins_position.reshape(-1, 2)
        xmin, xmax, ymin, ymax = source.extent
        on = ((xy[:, 0] >= xmin) & (xy[:, 0] <= xmax) & (xy[:, 1] >= ymin) & (xy[:, 1] <= ymax))
        heights = torch.full((xy.shape[0],), float("nan"), dtype=torch.float64)
        if on.any():
            with torch.no_grad():
                terrain_dtype = next((b.dtype for b in source.terrain.buffers()
                                      if b.is_floating_point()), dtype)
                heights[on] = source.terrain(xy[on].to(terrain_dtype)).double()
        sigma = math.sqrt(nav_cfg.initial.altitude_sigma_m ** 2 + noise.R)
        datum.update(check_datum(
            flight.ins_altitude.reshape(-1).double().numpy(), heights.numpy(),
            flight.clearance.reshape(-1).double().numpy(), sigma_m=sigma,
            n_sigma=config.datum_check_sigma, alt_datum=flight.alt_datum,
            where=f"{flight.source} against --map {config.map}"), checked=True)
    navigator = Navigator(source.terrain, nav_cfg, n_vehicles=flight.n_vehicles,
                          map_frame=frame, dtype=dtype, tile=source.tile)
    print(f"flight: {flight.n_vehicles} vehicle(s) x {flight.n_epochs} epochs "
          f"({float(flight.t[-1] - flight.t[0]):.1f} s) from {flight.source}, map "
          f"{source.name} ({source.kind}), method {nav_cfg.method}", flush=True)
    start = time.perf_counter()
    track = _replay(navigator, flight, progress=config.progress)
    seconds = time.perf_counter() - start
    return FlightNavigation(config=config, source=source, flight=flight,
                            navigator_config=nav_cfg, track=track, datum=datum, noise=noise,
                            seconds=seconds)


def _replay(navigator: Any, flight: Any, *, progress: bool) -> Any:
    """`Navigator.replay` of the flight with a progress bar (heartbeat lines off a
    terminal); the track is filled in place, epoch by epoch."""
    from neuralmap.progress import stage_progress

    with stage_progress("navigate", flight.n_epochs, "epochs", enabled=progress) as advance:
        return navigator.replay(flight.t, flight.ins_position, flight.ins_altitude,
                                flight.clearance, progress=advance)


def write_flight(nav: FlightNavigation, outputs: Any) -> None:
    """Writes a navigated flight into the outputs (CSV, GeoJSON, report, errors).

    Args:
        nav: `navigate_flight`'s result.
        outputs: The run's outputs writer (`neuralmap.outputs.StudyOutputs`).
    """
    from neuralmap.nav.outputs import (
        add_reference_errors,
        add_status,
        write_navigation_csv,
        write_navigation_geojson,
    )

    flight, track, source = nav.flight, nav.track, nav.source
    counts = {**{f"input_{k}": int(v) for k, v in flight.counts.items()},
              **{k: int(v) for k, v in track.counts.items()}}
    write_navigation_csv(outputs.dir / "navigation.csv", track, flight.reference_position)
    files = ["navigation.csv"]
    if track.lat is not None:
        write_navigation_geojson(outputs.dir / "navigation.geojson", track, counts=counts,
                                 properties={"map": source.name, "log": flight.source})
        files.append("navigation.geojson")
    outputs.results.update({
        "log": flight.describe(), "map": source.describe(),
        "navigator": nav.navigator_config.to_dict(), "noise": nav.noise.to_dict(),
        "vertical_datum": nav.datum, "counts": counts, "files": files,
        "replay_seconds": nav.seconds,
        "epochs_per_second": flight.n_epochs * flight.n_vehicles / max(nav.seconds, 1e-12),
    })
    assumed = ("above the DEM's vertical datum" if flight.alt_datum == "dem" else
               f"WGS-84 ellipsoidal, converted with geoid undulation "
               f"{nav.config.geoid_undulation} m")
    outputs.add_text(
        f"Log `{flight.source}` ({flight.kind}, {flight.n_vehicles} vehicle(s), "
        f"{flight.n_epochs} epochs, {float(flight.t[0]):.3f}–{float(flight.t[-1]):.3f} s) "
        f"navigated over `{source.source}` ({source.kind} '{source.name}') with method "
        f"`{nav.navigator_config.method}` in {nav.seconds:.2f} s. INS altitude assumed "
        f"{assumed}. Measurement noise R = {nav.noise.R:.4g} m² (altimeter "
        f"{nav.noise.altimeter_m2:.4g}, DEM {nav.noise.dem_m2:.4g}, map fit "
        f"{nav.noise.fit_m2:.4g} from {nav.noise.fit_source}). Written: "
        f"{', '.join(files)}" + ("" if track.lat is not None else
                                 " (no navigation.geojson: the map has no georeference)")
        + ".")
    outputs.add_table("Counted, not refused", ["what", "count"],
                      [[k, v] for k, v in counts.items()])
    add_status(outputs, track)
    if flight.reference_position is not None:
        add_reference_errors(outputs, track, flight.reference_position,
                             ins_xy=flight.ins_position, preview=source.preview_tile(),
                             n_ellipses=nav.config.n_ellipses,
                             reference_altitude=flight.reference_altitude,
                             ins_altitude=flight.ins_altitude)
    else:
        outputs.add_text("The log carries no reference position: no errors are reported.")
    final = track.fix(track.n_epochs - 1)
    sig = final.sigma_xy()
    outputs.results["final_fix"] = {
        "xy": final.xy.tolist(), "altitude": final.altitude.tolist(),
        "sigma_xy_m": sig.tolist(), "status": final.status_names(),
        "lat": None if final.lat is None else final.lat.tolist(),
        "lon": None if final.lon is None else final.lon.tolist()}
    if np.isfinite(outputs.results["epochs_per_second"]):
        outputs.log_scalar("replay/epochs_per_second", outputs.results["epochs_per_second"])
