"""Recorded flights into the navigator: map-frame logs, lat/lon logs, KF-GINS INS results.

Three inputs, one result (`FlightInput`, batch first like the Navigator):

(a) **Map-frame flight log** (CSV or NPZ), the format of
    `neuralmap.learning.flight_log`: ``time, ins_x, ins_y, ins_h, radar`` (optional
    ``flight``; rows of one flight contiguous, every flight on the same times → one vehicle
    each). Optional reference columns ``ref_x, ref_y, ref_h`` (map frame, m).
(b) **Geographic log** (CSV or NPZ): ``time, lat, lon, alt, radar``; ``lat, lon`` WGS-84
    degrees, ``alt`` the INS altitude (m, above the DEM's vertical datum unless declared
    ellipsoidal, `neuralmap.flights.vertical_datum`), ``radar`` the measured clearance (m).
    Optional reference ``ref_lat, ref_lon, ref_alt`` (same datum as ``alt``).
(c) **KF-GINS navigation result** (11 columns, what ``neuralmap-gins`` writes as
    ``KF_GINS_Navresult.nav``) as the INS, with a separate radar log (CSV/NPZ: ``time,
    radar``, optional ``ref_lat, ref_lon, ref_alt``) on the same time scale. The INS is
    interpolated linearly to the radar epochs; its heights are ellipsoidal (KF-GINS), so
    the geoid undulation must be given. A reference may also come as a KF-GINS navigation
    file (the truth file of ``neuralmap-gins --truthpath``).

Counted, not fatal (in `FlightInput.counts`): missing radar samples (empty / NaN /
inf), clearances outside the sensor's stated range, time gaps (a step longer than
``gap_factor`` × the median step), epochs off the map, radar epochs outside the INS record.
Refused with the file, line and column: time out of order, non-finite positions or
altitudes, a log of which no epoch lies on the map.
"""

from __future__ import annotations

import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.flights.vertical_datum import apply_datum
from neuralmap.nav.georef import MapFrame

__all__ = ["FLIGHT_FORMATS", "FlightInput", "detect_format", "read_flight_input"]

#: Log formats: map frame, geographic lat/lon, KF-GINS navigation result + radar log.
FLIGHT_FORMATS = ("auto", "map_frame", "geographic", "kfgins")
#: A time step longer than this many median steps is a gap.
GAP_FACTOR = 1.5
_MAP_COLUMNS = ("time", "ins_x", "ins_y", "ins_h", "radar")
_GEO_COLUMNS = ("time", "lat", "lon", "alt", "radar")


@dataclass
class FlightInput:
    """A recorded flight in the map frame, ready for `Navigator.replay`.

    Attributes:
        t: ``(K,)`` epoch times, s, strictly increasing.
        ins_position: ``(N, K, 2)`` INS east/north position in the map frame, m.
        ins_altitude: ``(N, K)`` INS altitude on the DEM's vertical datum, m.
        clearance: ``(N, K)`` measured radar clearance, m; NaN = no measurement.
        reference_position: ``(N, K, 2)`` reference (GNSS/RTK/truth) position, map frame,
            or None.
        reference_altitude: ``(N, K)`` reference altitude (DEM datum), or None.
        counts: What was counted, not refused: ``rows``, ``missing_radar``,
            ``out_of_range``, ``gaps``, ``off_map_epochs``, ``radar_outside_ins``.
        source: The log's path (and the radar log's for KF-GINS input).
        kind: ``"map_frame"``, ``"geographic"`` or ``"kfgins"``.
        alt_datum: The vertical datum the altitude was declared on (``"dem"`` or
            ``"ellipsoidal"``; the stored altitude is converted to the DEM's datum).
        lines: ``(K,)`` the source line (CSV; record for NPZ / KF-GINS) of each epoch,
            for messages.
    """

    t: torch.Tensor
    ins_position: torch.Tensor
    ins_altitude: torch.Tensor
    clearance: torch.Tensor
    reference_position: torch.Tensor | None = None
    reference_altitude: torch.Tensor | None = None
    counts: dict[str, int] = field(default_factory=dict)
    source: str = ""
    kind: str = "map_frame"
    alt_datum: str = "dem"
    lines: np.ndarray | None = None

    @property
    def n_vehicles(self) -> int:
        """N."""
        return int(self.ins_position.shape[0])

    @property
    def n_epochs(self) -> int:
        """K."""
        return int(self.t.shape[0])

    @property
    def has_reference(self) -> bool:
        """Whether a reference position came with the log."""
        return self.reference_position is not None

    def describe(self) -> dict[str, Any]:
        """JSON-serialisable summary (source, kind, sizes, datum, counts)."""
        return {"source": self.source, "kind": self.kind, "n_vehicles": self.n_vehicles,
                "n_epochs": self.n_epochs, "t0": float(self.t[0]), "t1": float(self.t[-1]),
                "alt_datum": self.alt_datum, "has_reference": self.has_reference,
                "counts": dict(self.counts)}


# --------------------------------------------------------------------------- columns


def _columns(path: Path) -> dict[str, np.ndarray]:
    """The columns of a CSV/NPZ log (`neuralmap.columns.read_columns`)."""
    from neuralmap.columns import read_columns

    return read_columns(path, what="flight log")


def _line(path: Path, row: int) -> str:
    """``line L`` of a CSV (header = line 1) or ``row R`` of an NPZ, for messages."""
    return f"line {row + 2}" if path.suffix.lower() == ".csv" else f"row {row + 1}"


def _where(path: Path, names: list[str], row: int, column: str) -> str:
    """``file, line L, column C ('name')`` for a CSV; ``file, row R, column 'name'`` NPZ."""
    if path.suffix.lower() == ".csv" and column in names:
        return f"{path}, {_line(path, row)}, column {names.index(column) + 1} ('{column}')"
    return f"{path}, {_line(path, row)}, column '{column}'"


def _require(path: Path, columns: dict[str, np.ndarray], required: tuple[str, ...],
             what: str) -> None:
    missing = [c for c in required if c not in columns]
    if missing:
        raise NeuralMapError(
            f"{path}: {what} lacks column(s) {missing}; it has {sorted(columns)}. Required: "
            f"{', '.join(required)}.")
    lengths = {c: len(columns[c]) for c in columns}
    if len(set(lengths.values())) != 1 or 0 in lengths.values():
        raise NeuralMapError(f"{path}: columns must be non-empty and of equal length, got "
                             f"{lengths}.")


def _check_finite(path: Path, names: list[str], columns: dict[str, np.ndarray],
                  which: tuple[str, ...], what: str) -> None:
    """Refuses the first non-finite value of the named columns (file, line, column)."""
    for name in which:
        values = np.asarray(columns[name], dtype=np.float64)
        bad = ~np.isfinite(values)
        if bad.any():
            row = int(np.argmax(bad))
            raise NeuralMapError(
                f"{_where(path, names, row, name)}: {what} {float(values[row])!r} is not finite "
                f"({int(bad.sum())} such value(s) in the column); every epoch needs a finite "
                "time, position and altitude (only 'radar' may be empty). Remove or repair "
                "the record.")


def _check_time(path: Path, names: list[str], time: np.ndarray, rows: np.ndarray) -> None:
    """Refuses time that does not strictly increase (file, line, column)."""
    bad = np.nonzero(np.diff(time) <= 0)[0]
    if bad.size:
        k = int(bad[0]) + 1
        raise NeuralMapError(
            f"{_where(path, names, int(rows[k]), 'time')}: time {float(time[k])!r} s is out of order "
            f"(the epoch before, {_line(path, int(rows[k - 1]))}, is at {float(time[k - 1])!r} s). "
            "Sort the log by time and remove repeated epochs.")


#: A log whose median time step is this many times the navigator's period (or its inverse)
#: is refused: its time is most likely not in seconds.
TIME_BASE_FACTOR = 20.0


def _check_clearances(where: str, values: np.ndarray, lo: float, hi: float) -> None:
    """Refuses a radar column with no usable clearance, saying what it looks like."""
    if values.size == 0:
        raise NeuralMapError(f"{where}: no radar clearance at all (every value empty or NaN); "
                             "terrain-aided navigation needs the radar altimeter's readings.")
    if (values == 0).all():
        raise NeuralMapError(f"{where}: every clearance is 0 m: the column holds no "
                             "readings (a placeholder?); give the radar altimeter's clearance "
                             "above ground, m.")
    if ((values >= lo) & (values <= hi)).any():
        return
    if (values <= 0).all():
        raise NeuralMapError(
            f"{where}: every clearance is <= 0 m (from {values.min():g} to {values.max():g}): "
            "a clearance is the height above ground, positive; is the column the terrain "
            "height or the altitude difference with the wrong sign?")
    if (values > hi).all():
        raise NeuralMapError(
            f"{where}: every clearance is above the sensor's stated range (max "
            f"sensor.clearance_max_m = {hi:g} m; the values run {values.min():g}-"
            f"{values.max():g}): is the column in feet (multiply by 0.3048) or the altitude "
            "above sea level instead of the clearance? If the sensor reads that high, raise "
            "sensor.clearance_max_m in the navigator config.")
    raise NeuralMapError(
        f"{where}: no clearance lies in the sensor's stated range [{lo:g}, {hi:g}] m (the "
        f"values run {values.min():g}-{values.max():g}); check the column's units, or set "
        "sensor.clearance_min_m / clearance_max_m in the navigator config.")


def check_time_base(where: str, t: np.ndarray, period_s: float) -> None:
    """Refuses a log whose median time step is far from the navigator's period: its time
    is most likely not in seconds (milliseconds, minutes, hours).

    Raises:
        NeuralMapError: The median step is more than `TIME_BASE_FACTOR` times the period,
            or less than its inverse (names the likely unit and the fix).
    """
    steps = np.diff(np.asarray(t, dtype=np.float64))
    if steps.size == 0 or not period_s > 0:
        return
    step = float(np.median(steps))
    ratio = step / period_s
    if 1.0 / TIME_BASE_FACTOR <= ratio <= TIME_BASE_FACTOR:
        return
    units = {"milliseconds": 1e-3, "minutes": 60.0, "hours": 3600.0, "microseconds": 1e-6}
    guess = min(units, key=lambda u: abs(math.log(ratio * units[u])))
    fix = (f"if the time is in {guess}, convert it to seconds (multiply by "
           f"{units[guess]:g}); if the epochs really are {step:g} s apart, set the navigator's "
           f"sensor.dt_s to the log's period")
    raise NeuralMapError(
        f"{where}: the median time step is {step:g}, {ratio:.3g}x the navigator's period "
        f"sensor.dt_s = {period_s:g} s: the time does not look like seconds; {fix}.")


def _names(path: Path) -> list[str]:
    """The CSV header names in file order (for column numbers); [] for NPZ."""
    if path.suffix.lower() != ".csv":
        return []
    with path.open(encoding="utf-8-sig", newline="") as handle:
        import csv

        header = next(csv.reader(handle), [])
    return [h.strip() for h in header]


def _column_names(path: Path) -> set[str]:
    """The column names of a CSV/NPZ log: a CSV's header line alone (a long log is not
    parsed twice); an NPZ's (or a CSV whose header cannot be read: the reader's refusal)
    from `_columns`."""
    if path.suffix.lower() == ".csv":
        try:
            names = [n for n in _names(path) if n]
        except UnicodeDecodeError:
            names = []
        if names:
            return set(names)
    return set(_columns(path))


def _flights(path: Path, columns: dict[str, np.ndarray]) -> list[np.ndarray]:
    """Row indices of each flight (one for a log without a ``flight`` column)."""
    n = len(columns["time"])
    if "flight" not in columns:
        return [np.arange(n)]
    ids = np.asarray(columns["flight"]).astype(str)
    starts = [0, *(np.flatnonzero(ids[1:] != ids[:-1]) + 1).tolist(), n]
    first_row: dict[str, int] = {}
    for s in starts[:-1]:
        if ids[s] in first_row:
            raise NeuralMapError(
                f"{path}, {_line(path, s)}: flight {str(ids[s])!r} starts again after other "
                f"flights (its rows began at {_line(path, first_row[ids[s]])}); the rows of "
                "each flight must be contiguous: sort the log by flight, then time.")
        first_row[ids[s]] = s
    return [np.arange(a, b) for a, b in zip(starts[:-1], starts[1:], strict=True)]


# --------------------------------------------------------------------------- reading


def detect_format(path: str | os.PathLike[str], fmt: str = "auto") -> str:
    """The log's format: ``fmt`` itself, or for ``"auto"`` by extension and columns
    (``ins_x`` → map frame, ``lat``/``lon`` → geographic, not CSV/NPZ → KF-GINS).

    Raises:
        NeuralMapError: No such file, unknown ``fmt``, or a CSV/NPZ of neither kind.
    """
    path = Path(path)
    if not path.is_file():
        raise NeuralMapError(f"flight log {str(path)!r}: no such file.")
    if fmt not in FLIGHT_FORMATS:
        raise NeuralMapError(f"--format {fmt!r}: choose one of {', '.join(FLIGHT_FORMATS)}.")
    if fmt != "auto":
        return fmt
    if path.suffix.lower() not in (".csv", ".npz"):
        return "kfgins"
    columns = _column_names(path)
    if "ins_x" in columns or "ins_y" in columns:
        return "map_frame"
    if "lat" in columns or "lon" in columns:
        return "geographic"
    raise NeuralMapError(
        f"{path}: neither a map-frame log ({', '.join(_MAP_COLUMNS)}) nor a geographic one "
        f"({', '.join(_GEO_COLUMNS)}); it has columns {sorted(columns)}. A KF-GINS navigation "
        "result is a whitespace-separated .nav/.txt file.")


def _table_log(path: Path, kind: str, map_frame: MapFrame | None, alt_datum: str,
               geoid_undulation: float | None) -> dict[str, Any]:
    """Map-frame or geographic CSV/NPZ as arrays ``(N, K, ...)`` plus rows and names."""
    columns = _columns(path)
    required = _MAP_COLUMNS if kind == "map_frame" else _GEO_COLUMNS
    _require(path, columns, required, "a map-frame flight log" if kind == "map_frame"
             else "a geographic flight log")
    names = _names(path)
    pos_cols = ("ins_x", "ins_y", "ins_h") if kind == "map_frame" else ("lat", "lon", "alt")
    ref_cols = ("ref_x", "ref_y", "ref_h") if kind == "map_frame" else (
        "ref_lat", "ref_lon", "ref_alt")
    has_ref = any(c in columns for c in ref_cols)
    if has_ref:
        _require(path, columns, (*required, *ref_cols), "a log with a reference")
    _check_finite(path, names, columns, ("time", *pos_cols), "value")
    if has_ref:
        _check_finite(path, names, columns, ref_cols, "reference value")
    if kind == "geographic":
        for name, bound in (("lat", 90.0), ("lon", 360.0)):
            values = np.asarray(columns[name], dtype=np.float64)
            bad = np.abs(values) > bound
            if bad.any():
                row = int(np.argmax(bad))
                raise NeuralMapError(
                    f"{_where(path, names, row, name)}: {float(values[row])!r} is not a {name} in "
                    f"degrees (|{name}| <= {bound:g}); a geographic log holds WGS-84 degrees.")
    flights = _flights(path, columns)
    time = np.asarray(columns["time"], dtype=np.float64)
    for rows in flights:
        _check_time(path, names, time[rows], rows)
    if len(flights) > 1:
        lengths = {len(r) for r in flights}
        same = len(lengths) == 1 and all(
            np.array_equal(time[r], time[flights[0]]) for r in flights[1:])
        if not same:
            raise NeuralMapError(
                f"{path}: the log holds {len(flights)} flights on different times; the "
                "navigator carries several vehicles only on common epochs. Split the log "
                "into one file per flight (or resample them to the same times).")
    n_rows = len(time)
    # the flights are contiguous blocks of K rows each, in order: a column is an (N, K)
    # view of itself unless (blank rows aside) they do not cover it exactly
    k = len(flights[0])
    blocks = len(flights) * k == n_rows and all(
        int(r[0]) == i * k and int(r[-1]) == (i + 1) * k - 1 for i, r in enumerate(flights))
    index = None if blocks else np.stack(flights)  # (N, K) rows

    def take(name: str) -> np.ndarray:
        values = np.asarray(columns[name], dtype=np.float64)
        return values.reshape(len(flights), k) if index is None else values[index]

    t = time[flights[0]] if len(flights) > 1 or index is not None else time
    out: dict[str, Any] = {"t": t, "rows": flights[0], "names": names,
                           "radar": take("radar")}
    if kind == "map_frame":
        out["xy"] = np.stack([take("ins_x"), take("ins_y")], -1)
        out["alt"] = apply_datum(take("ins_h"), alt_datum, geoid_undulation,
                                 where=f"{path} column 'ins_h'")
        if has_ref:
            out["ref_xy"] = np.stack([take("ref_x"), take("ref_y")], -1)
            out["ref_alt"] = apply_datum(take("ref_h"), alt_datum, geoid_undulation,
                                         where=f"{path} column 'ref_h'")
        return out
    if map_frame is None:
        raise NeuralMapError(f"{path}: a lat/lon log needs a georeferenced map to convert "
                             "positions into its frame (pass --map with a georeferenced DEM).")
    x, y = map_frame.to_map(take("lat"), take("lon"))
    out["xy"] = np.stack([x, y], -1)
    out["alt"] = apply_datum(take("alt"), alt_datum, geoid_undulation,
                             where=f"{path} column 'alt'")
    if has_ref:
        rx, ry = map_frame.to_map(take("ref_lat"), take("ref_lon"))
        out["ref_xy"] = np.stack([rx, ry], -1)
        out["ref_alt"] = apply_datum(take("ref_alt"), alt_datum, geoid_undulation,
                                     where=f"{path} column 'ref_alt'")
    return out


def _kfgins_log(path: Path, radar_path: Path | None, reference: Path | None,
                map_frame: MapFrame | None, alt_datum: str, geoid_undulation: float | None,
                counts: dict[str, int]) -> dict[str, Any]:
    """KF-GINS navigation result interpolated to the radar log's epochs."""
    from neuralmap.ins.kfgins import read_nav

    if radar_path is None:
        raise NeuralMapError(
            f"{path}: a KF-GINS navigation result carries no radar clearance; give the radar "
            "log with --radar RADAR.csv (columns time, radar; optional ref_lat, ref_lon, "
            "ref_alt), on the navigation result's time scale.")
    if map_frame is None:
        raise NeuralMapError(f"{path}: a KF-GINS navigation result is in lat/lon; it needs a "
                             "georeferenced map (--map with a georeferenced DEM).")
    nav = read_nav(path)  # refuses wrong columns, non-numbers, non-finite, time not increasing
    radar_path = Path(radar_path)
    if not radar_path.is_file():
        raise NeuralMapError(f"--radar {radar_path}: no such file.")
    columns = _columns(radar_path)
    _require(radar_path, columns, ("time", "radar"), "a radar log")
    names = _names(radar_path)
    _check_finite(radar_path, names, columns, ("time",), "time")
    rows = np.arange(len(columns["time"]))
    t_radar = np.asarray(columns["time"], dtype=np.float64)
    _check_time(radar_path, names, t_radar, rows)
    inside = (t_radar >= nav.time[0]) & (t_radar <= nav.time[-1])
    counts["radar_outside_ins"] = int((~inside).sum())
    if not inside.any():
        raise NeuralMapError(
            f"{radar_path}, line 2, column 1 ('time'): no radar epoch lies within the INS "
            f"record {path} ({nav.time[0]:.3f}-{nav.time[-1]:.3f} s; the radar log spans "
            f"{t_radar[0]:.3f}-{t_radar[-1]:.3f} s). Both must be on the same time scale "
            "(KF-GINS: GNSS seconds of week).")
    rows, t = rows[inside], t_radar[inside]

    def interp(table: np.ndarray, time: np.ndarray) -> list[np.ndarray]:
        return [np.interp(t, time, table[:, j]) for j in range(table.shape[1])]

    lat, lon, h = interp(nav.position, nav.time)
    x, y = map_frame.to_map(lat, lon)
    out: dict[str, Any] = {
        "t": t, "rows": rows, "names": names,
        "radar": np.asarray(columns["radar"], dtype=np.float64)[rows][None],
        "xy": np.stack([x, y], -1)[None],
        "alt": apply_datum(h, alt_datum, geoid_undulation, where=f"{path} (heights)")[None],
    }
    ref_cols = ("ref_lat", "ref_lon", "ref_alt")
    if reference is not None:
        ref = read_nav(reference)
        if t[0] < ref.time[0] or t[-1] > ref.time[-1]:
            raise NeuralMapError(
                f"--reference {reference}: covers {ref.time[0]:.3f}-{ref.time[-1]:.3f} s, "
                f"not the radar epochs {t[0]:.3f}-{t[-1]:.3f} s; give a reference over the "
                "whole flight.")
        r_lat, r_lon, r_h = interp(ref.position, ref.time)
    elif all(c in columns for c in ref_cols):
        _check_finite(radar_path, names, {c: columns[c][rows] for c in ref_cols}, ref_cols,
                      "reference value")
        r_lat, r_lon, r_h = (np.asarray(columns[c], dtype=np.float64)[rows] for c in ref_cols)
    else:
        return out
    rx, ry = map_frame.to_map(r_lat, r_lon)
    out["ref_xy"] = np.stack([rx, ry], -1)[None]
    out["ref_alt"] = apply_datum(r_h, alt_datum, geoid_undulation,
                                 where=f"{reference or radar_path} (reference heights)")[None]
    return out


def read_flight_input(
    path: str | os.PathLike[str],
    *,
    map_frame: MapFrame | None = None,
    extent: tuple[float, float, float, float] | None = None,
    fmt: str = "auto",
    radar: str | os.PathLike[str] | None = None,
    reference: str | os.PathLike[str] | None = None,
    alt_datum: str | None = None,
    geoid_undulation: float | None = None,
    clearance_range: tuple[float, float] | None = None,
    gap_factor: float = GAP_FACTOR,
    period_s: float | None = None,
    dtype: torch.dtype = torch.float64,
) -> FlightInput:
    """Reads a recorded flight (see the module docstring) into the map frame.

    Args:
        path: The log: map-frame or geographic CSV/NPZ, or a KF-GINS navigation result.
        map_frame: The map's frame (needed for lat/lon and KF-GINS input).
        extent: ``(xmin, xmax, ymin, ymax)`` of the map, m; epochs outside are counted and
            a log with no epoch inside is refused. None = not checked.
        fmt: One of `FLIGHT_FORMATS` (``"auto"``: by extension and columns).
        radar: The radar log of a KF-GINS input.
        reference: A KF-GINS navigation file as the reference of a KF-GINS input.
        alt_datum: ``"dem"`` or ``"ellipsoidal"``; None = ``"dem"`` for CSV/NPZ logs and
            ``"ellipsoidal"`` for KF-GINS results (their heights are ellipsoidal).
        geoid_undulation: Geoid undulation N (m) for ellipsoidal altitudes.
        clearance_range: ``(min, max)`` valid clearance of the sensor, m; samples outside
            are counted (the navigator skips them). None = not counted.
        gap_factor: A step longer than this many median steps counts as a gap.
        period_s: The navigator's nominal period (``sensor.dt_s``): a log whose time steps
            are far from it is refused (`check_time_base`); None = not checked.
        dtype: Tensor dtype of the positions and clearances (time is always float64).

    Returns:
        The `FlightInput`.

    Raises:
        NeuralMapError: A refused log (file, line and column named), see the module
            docstring, or bad options.
    """
    path = Path(path)
    if not path.is_file():
        raise NeuralMapError(f"flight log {str(path)!r}: no such file.")
    kind = detect_format(path, fmt)
    if alt_datum is None:
        alt_datum = "ellipsoidal" if kind == "kfgins" else "dem"
    counts: dict[str, int] = {}
    if kind == "kfgins":
        data = _kfgins_log(path, None if radar is None else Path(radar),
                           None if reference is None else Path(reference), map_frame,
                           alt_datum, geoid_undulation, counts)
        source = f"{path} + {radar}"
        line_path = Path(radar)  # type: ignore[arg-type]
    else:
        if radar is not None or reference is not None:
            raise NeuralMapError(
                f"{path}: --radar and --reference apply to KF-GINS navigation results only; "
                "a CSV/NPZ log carries its radar and reference columns itself.")
        data = _table_log(path, kind, map_frame, alt_datum, geoid_undulation)
        source = str(path)
        line_path = path
    t = data["t"]
    if period_s is not None:
        check_time_base(f"{path} column 'time'" if kind != "kfgins" else f"{radar}",
                        t, period_s)
    radar_values = np.where(np.isfinite(data["radar"]), data["radar"], np.nan)
    counts["rows"] = int(t.size)
    counts["missing_radar"] = int(np.isnan(radar_values).sum())
    if clearance_range is not None:
        lo, hi = clearance_range
        ok = np.isfinite(radar_values)
        counts["out_of_range"] = int((ok & ((radar_values < lo) | (radar_values > hi))).sum())
        _check_clearances(f"{line_path} column 'radar'", radar_values[ok], lo, hi)
    steps = np.diff(t)
    counts["gaps"] = int((steps > gap_factor * np.median(steps)).sum()) if steps.size else 0
    xy = data["xy"]
    if extent is not None:
        xmin, xmax, ymin, ymax = extent
        on = ((xy[..., 0] >= xmin) & (xy[..., 0] <= xmax) & (xy[..., 1] >= ymin)
              & (xy[..., 1] <= ymax))
        counts["off_map_epochs"] = int((~on).sum())
        for n in range(on.shape[0]):
            if not on[n].any():
                row = int(data["rows"][0])
                x0, y0 = xy[n, 0]
                cx, cy = np.clip(x0, xmin, xmax), np.clip(y0, ymin, ymax)
                col = {"map_frame": "ins_x", "geographic": "lat"}.get(kind, "time")
                names = data["names"]
                where = (_where(line_path, names, row, col) if kind != "kfgins"
                         else f"{path} (INS at {line_path}, {_line(line_path, row)})")
                raise NeuralMapError(
                    f"{where}: the log lies off the map: no epoch"
                    + (f" of flight {n}" if on.shape[0] > 1 else "")
                    + f" is inside the map extent x {xmin:.1f}..{xmax:.1f}, y {ymin:.1f}.."
                    f"{ymax:.1f} m; the first epoch is at map ({x0:.1f}, {y0:.1f}) m, "
                    f"{float(np.hypot(x0 - cx, y0 - cy)) / 1000.0:.2f} km outside. Check that "
                    "the log and --map cover the same area (and the log's coordinate columns).")

    def tensor(a: np.ndarray) -> torch.Tensor:
        return torch.as_tensor(np.ascontiguousarray(a), dtype=dtype)

    return FlightInput(
        t=torch.as_tensor(t, dtype=torch.float64),  # time stays float64 (Unix seconds too)
        ins_position=tensor(xy), ins_altitude=tensor(data["alt"]),
        clearance=tensor(radar_values),
        reference_position=tensor(data["ref_xy"]) if "ref_xy" in data else None,
        reference_altitude=tensor(data["ref_alt"]) if "ref_alt" in data else None,
        counts=counts, source=source, kind=kind, alt_datum=alt_datum,
        lines=np.asarray(data["rows"], dtype=np.int64)
        + (2 if line_path.suffix.lower() == ".csv" else 1),
    )
