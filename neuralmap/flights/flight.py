"""Navigating one recorded flight: the implementation behind ``neuralmap-navigate``.

``neuralmap-navigate LOG --map MAP`` and the ``flight`` study (``python evaluate.py
--config configs/flight.yaml --log LOG --map MAP``) run the same steps (`navigate_flight`,
then `write_flight`):

1. resolve the map (`neuralmap.nav.map_source.resolve_map`: trained map, DEM file or
   embedded tile) and its frame;
2. read the log into the map frame (`neuralmap.flights.flight_input.read_flight_input`),
   refusing bad logs before anything is written;
3. check the vertical datum (`neuralmap.flights.vertical_datum.check_datum`);
4. replay it through the `Navigator` (configured by the navigator YAML,
   ``configs/navigator.yaml`` by default) in chunks of ``chunk_epochs`` epochs: one
   navigator carries on from chunk to chunk (`Navigator.replay` with ``reset=False``), so
   the fixes are those of one replay of the whole log, bit for bit; each chunk's fixes are
   formatted into the spool of navigation.csv / navigation.geojson
   (`neuralmap.flights.outputs.NavigationFiles`) and reduced to the compact record the report
   needs (`neuralmap.flights.track_summary.TrackSummary`), then dropped;
5. write navigation.csv, navigation.geojson (each assembled into a temporary name and
   renamed) and, with a reference, the errors in the report format of the toolkit
   (report.md, results.json, figures, TensorBoard) through its one outputs writer.

Memory: while the replay runs, the log's per-epoch arrays (about 40 bytes per epoch and
vehicle, 72 with a reference) live in a memory-mapped temporary file of which one chunk is
resident at a time (`neuralmap.flights.mapped_flight`); besides them one chunk of full fixes
(about 330 bytes per epoch and vehicle: 16 MB for the default 50 000 epochs of one
vehicle), the compact record (1 byte per epoch and vehicle) and the ≈ 300 MB of the
libraries themselves (torch, scipy, matplotlib). Reading the log holds its arrays in
memory once (about 100 MB at a million rows). ``benchmarks/bench_flight_log.py`` measures
a million-epoch log.
"""

from __future__ import annotations

import dataclasses
import functools
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
            result (then ``radar`` is required). See `neuralmap.flights.flight_input`.
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
        chunk_epochs: Epochs replayed per chunk (module docstring): the replay holds
            ``chunk_epochs × N`` full fixes (about 330 bytes each) at a time; the results
            do not depend on it.
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
    chunk_epochs: int = 50_000

    @property
    def torch_dtype(self) -> torch.dtype:
        """The filter dtype as a torch dtype."""
        return torch.float32 if self.dtype == "float32" else torch.float64

    def validate(self) -> None:
        """Checks the options (not the files: those are read by `navigate_flight`).

        Raises:
            NeuralMapError: A missing ``log``/``map`` or a value out of range.
        """
        from neuralmap.flights.flight_input import FLIGHT_FORMATS
        from neuralmap.flights.vertical_datum import ALT_DATUMS

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
        if (isinstance(self.chunk_epochs, bool) or not isinstance(self.chunk_epochs, int)
                or self.chunk_epochs < 1):
            raise NeuralMapError(f"--chunk_epochs must be an integer >= 1 (epochs replayed "
                                 f"at a time), got {self.chunk_epochs!r}.")


@dataclass
class FlightNavigation:
    """A navigated flight, ready to be written (once, by `write_flight`).

    The fixes themselves are not kept (a long log would not fit): ``summary`` holds what
    the report needs, the last fix and the counters; ``files`` the formatted rows of
    navigation.csv / navigation.geojson. For the fixes in memory, replay the flight with
    `Navigator.replay`.

    Attributes:
        config: The flight options.
        source: The resolved map (`MapSource`).
        flight: The flight input (`FlightInput`).
        navigator_config: The `NavigatorConfig` used.
        summary: The compact record of the fixes (`TrackSummary`: status, errors against
            the reference, decimated series for the figures, ``final`` fix, ``counts``).
        files: The spooled navigation.csv / navigation.geojson (`NavigationFiles`).
        datum: The datum check's summary.
        noise: The navigator's ``R`` parts (`MapNoise`).
        seconds: Wall time of the replay (the navigator's steps, summed over the chunks).
    """

    config: FlightOptions
    source: Any
    flight: Any
    navigator_config: Any
    summary: Any
    files: Any
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


def navigate_flight(config: FlightOptions, *, outputs: Any = None) -> FlightNavigation:
    """Reads the map and the log, checks them, and replays the flight in chunks.

    Every refusal happens before the replay starts. The replay then writes only anonymous
    temporary files (removed by the system when closed): the log's per-epoch arrays,
    memory-mapped (`neuralmap.flights.mapped_flight`), and the spooled rows of navigation.csv /
    navigation.geojson; in the outputs' folder when ``outputs`` is given (on the disk of
    the results), else in the system's temporary folder.

    Args:
        config: The flight options.
        outputs: The run's outputs writer (`neuralmap.outputs.StudyOutputs`) that
            `write_flight` will write into, or None.

    Raises:
        NeuralMapError: A refused log or map (file, line and column named) or bad options.
    """
    from neuralmap.flights.flight_input import detect_format, read_flight_input
    from neuralmap.flights.mapped_flight import map_flight
    from neuralmap.flights.outputs import NavigationFiles
    from neuralmap.flights.track_summary import TrackSummary
    from neuralmap.flights.vertical_datum import check_datum
    from neuralmap.nav.map_noise import measurement_noise
    from neuralmap.nav.map_source import resolve_map
    from neuralmap.nav.navigator import Navigator

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
        sigma = math.sqrt(nav_cfg.initial.altitude_sigma_m ** 2 + noise.R)
        datum.update(check_datum(
            flight.ins_altitude.reshape(-1).double().numpy(),
            _map_heights(source, flight.ins_position.reshape(-1, 2), dtype).numpy(),
            flight.clearance.reshape(-1).double().numpy(), sigma_m=sigma,
            n_sigma=config.datum_check_sigma, alt_datum=flight.alt_datum,
            where=f"{flight.source} against --map {config.map}"), checked=True)
    navigator = Navigator(source.terrain, nav_cfg, n_vehicles=flight.n_vehicles,
                          map_frame=frame, dtype=dtype, tile=source.tile)
    print(f"flight: {flight.n_vehicles} vehicle(s) x {flight.n_epochs} epochs "
          f"({float(flight.t[-1] - flight.t[0]):.1f} s) from {flight.source}, map "
          f"{source.name} ({source.kind}), method {nav_cfg.method}", flush=True)
    # every refusal is behind us: from here on the replay writes (into the outputs' folder)
    folder = None if outputs is None else outputs.dir
    flight, mapped = map_flight(flight, folder)  # the log's arrays, one chunk resident
    _release_heap()  # the arrays read from the log are gone: give their memory back
    summary = TrackSummary(flight.t, flight.n_vehicles, reference_xy=flight.reference_position,
                           reference_altitude=flight.reference_altitude,
                           ins_xy=flight.ins_position, ins_altitude=flight.ins_altitude,
                           n_ellipses=config.n_ellipses)
    files = NavigationFiles(folder, n_vehicles=flight.n_vehicles,
                            reference=flight.reference_position is not None,
                            geojson=frame is not None)
    try:
        seconds = _replay(navigator, flight, summary, files, mapped,
                          chunk=config.chunk_epochs, progress=config.progress)
    except BaseException:
        files.close()
        raise
    return FlightNavigation(config=config, source=source, flight=flight,
                            navigator_config=nav_cfg, summary=summary, files=files,
                            datum=datum, noise=noise, seconds=seconds)


#: Map heights evaluated per call of the datum check (bounds its memory on long logs).
_HEIGHT_BATCH = 65_536


def _map_heights(source: Any, xy: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    """``(M,)`` float64 map heights under ``xy`` ``(M, 2)`` (NaN off the map), evaluated in
    batches of `_HEIGHT_BATCH` points."""
    from neuralmap.terrain.base import inside_extent

    heights = torch.full((xy.shape[0],), float("nan"), dtype=torch.float64)
    terrain_dtype = next((b.dtype for b in source.terrain.buffers() if b.is_floating_point()),
                         dtype)
    with torch.no_grad():
        for a in range(0, xy.shape[0], _HEIGHT_BATCH):
            part = xy[a:a + _HEIGHT_BATCH]
            on = inside_extent(part, source.extent)
            if on.any():
                heights[a:a + part.shape[0]][on] = source.terrain(
                    part[on].to(terrain_dtype)).double()
    return heights


def _release_heap() -> None:
    """Collects garbage and hands the C heap's free pages back to the system (glibc's
    ``malloc_trim``; nothing elsewhere): the chunks' temporaries would otherwise stay in
    the process's resident memory after they are freed."""
    import gc

    gc.collect()
    trim = _malloc_trim()
    if trim is not None:
        trim(0)


@functools.lru_cache(maxsize=1)
def _malloc_trim() -> Any:
    """glibc's ``malloc_trim``, or None (another C library)."""
    import ctypes

    try:
        return ctypes.CDLL("libc.so.6").malloc_trim
    except (OSError, AttributeError):
        return None


def _replay(navigator: Any, flight: Any, summary: Any, files: Any, mapped: Any, *,
            chunk: int, progress: bool) -> float:
    """`Navigator.replay` of the flight, ``chunk`` epochs at a time (the first chunk resets
    the navigator, the others carry on), each chunk into ``summary`` and ``files``, its
    pages of the log then handed back (``mapped``: `MappedFlight`), with a progress bar
    (heartbeat lines off a terminal). Returns the seconds spent in the navigator."""
    from neuralmap.progress import stage_progress

    k_all = flight.n_epochs
    ref = flight.reference_position
    seconds = 0.0
    with stage_progress("navigate", k_all, "epochs", enabled=progress) as advance:
        for a in range(0, k_all, chunk):
            b = min(a + chunk, k_all)
            share = (b - a) / k_all

            def part(fraction: float, share: float = share) -> None:
                advance(fraction * share)

            start = time.perf_counter()
            track = navigator.replay(flight.t[a:b], flight.ins_position[:, a:b],
                                     flight.ins_altitude[:, a:b], flight.clearance[:, a:b],
                                     progress=None if advance is None else part,
                                     reset=a == 0)
            seconds += time.perf_counter() - start
            summary.add(track)
            files.append(track, None if ref is None else ref[:, a:b])
            del track
            mapped.release(a, b)
            _release_heap()
    return seconds


def write_flight(nav: FlightNavigation, outputs: Any) -> None:
    """Writes a navigated flight into the outputs (CSV, GeoJSON, report, errors).

    The spooled rows go into navigation.csv / navigation.geojson and are then released:
    a `FlightNavigation` is written once.

    Args:
        nav: `navigate_flight`'s result.
        outputs: The run's outputs writer (`neuralmap.outputs.StudyOutputs`).

    Raises:
        NeuralMapError: ``nav`` was written already.
    """
    from neuralmap.flights.outputs import add_reference_errors, add_status

    flight, summary, source, nav_files = nav.flight, nav.summary, nav.source, nav.files
    if nav_files.closed:
        raise NeuralMapError("write_flight: this navigated flight was written already (its "
                             "rows are released after writing); navigate it again.")
    counts = {**{f"input_{k}": int(v) for k, v in flight.counts.items()},
              **{k: int(v) for k, v in summary.counts.items()}}
    try:
        nav_files.write_csv(outputs.dir / "navigation.csv")
        files = ["navigation.csv"]
        if nav_files.geojson:
            nav_files.write_geojson(outputs.dir / "navigation.geojson", counts=counts,
                                    properties={"map": source.name, "log": flight.source})
            files.append("navigation.geojson")
    finally:
        nav_files.close()
    _release_heap()
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
        f"{', '.join(files)}" + ("" if nav_files.geojson else
                                 " (no navigation.geojson: the map has no georeference)")
        + ".")
    outputs.add_table("Counted, not refused", ["what", "count"],
                      [[k, v] for k, v in counts.items()])
    add_status(outputs, summary)
    if summary.has_reference:
        add_reference_errors(outputs, summary, preview=source.preview_tile())
    else:
        outputs.add_text("The log carries no reference position: no errors are reported.")
    final = summary.final
    sig = final.sigma_xy()
    outputs.results["final_fix"] = {
        "xy": final.xy.tolist(), "altitude": final.altitude.tolist(),
        "sigma_xy_m": sig.tolist(), "status": final.status_names(),
        "lat": None if final.lat is None else final.lat.tolist(),
        "lon": None if final.lon is None else final.lon.tolist()}
    if np.isfinite(outputs.results["epochs_per_second"]):
        outputs.log_scalar("replay/epochs_per_second", outputs.results["epochs_per_second"])
