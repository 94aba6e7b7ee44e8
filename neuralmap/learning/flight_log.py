"""The flight-log format for learning from real flights: CSV or NPZ, one row per epoch.

Columns (names exact, any order; extra columns are ignored):

==========  =====================================================================
``flight``  optional flight id (integer or text); rows of one flight are contiguous
``time``    time of the epoch, s; strictly increasing within a flight, constant step
``ins_x``   INS east position in the map frame (metres east of the tile's south-west
            node, the frame of `DemTile` extents), m
``ins_y``   INS north position, m
``ins_h``   INS altitude (same datum as the map heights), m
``radar``   radar-altimeter clearance, m; empty / ``nan`` = no measurement (skipped and
            counted: `FlightBatch.n_missing`)
==========  =====================================================================

The first row of every flight is the filter's prior epoch (no update). A CSV has one header
line; an NPZ holds one 1-D array per column, all of the same length. Without a ``flight``
column the whole file is one flight. Flights of different lengths are padded and masked
(`FlightBatch`).
"""

from __future__ import annotations

import csv
import os
import zipfile
from pathlib import Path

import numpy as np
import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.learning.flights import FlightBatch

__all__ = ["LOG_COLUMNS", "read_flight_log", "write_flight_log"]

#: Required columns of a flight log.
LOG_COLUMNS = ("time", "ins_x", "ins_y", "ins_h", "radar")


def _read_npz(path: Path) -> dict[str, np.ndarray]:
    """The columns of an NPZ log: 1-D arrays of numbers (``flight`` may hold text)."""
    if not zipfile.is_zipfile(path):
        raise NeuralMapError(
            f"{path}: not a readable .npz flight log (not a zip archive); write it with "
            "numpy.savez or neuralmap.learning.flight_log.write_flight_log.")
    try:
        with np.load(path, allow_pickle=False) as data:
            columns = {k: np.asarray(data[k]) for k in data.files}
    except ValueError as exc:
        if "allow_pickle" in str(exc):
            raise NeuralMapError(
                f"{path}: a column holds Python objects (an object array); a flight log "
                "holds plain numbers. Save each column as a float array, e.g. "
                "np.savez(path, time=t.astype(float), ...).") from None
        raise NeuralMapError(f"{path}: not a readable .npz flight log ({exc}).") from None
    except Exception as exc:  # noqa: BLE001 - BadZipFile, EOFError, OSError: not an archive
        raise NeuralMapError(
            f"{path}: not a readable .npz flight log ({type(exc).__name__}: {exc}).") from None
    for name, values in columns.items():
        if name not in (*LOG_COLUMNS, "flight"):
            continue
        if values.ndim != 1:
            raise NeuralMapError(
                f"{path}: column {name!r} has shape {values.shape}; every column of a flight "
                "log is 1-D (one value per row).")
        if name != "flight" and not (np.issubdtype(values.dtype, np.number)
                                     or values.dtype == np.bool_):
            raise NeuralMapError(
                f"{path}: column {name!r} holds {values.dtype} values, not numbers.")
    return columns


def _read_csv(path: Path) -> dict[str, np.ndarray]:
    """The columns of a CSV log (UTF-8, with or without a byte-order mark)."""
    try:
        with path.open(newline="", encoding="utf-8-sig") as handle:
            reader = csv.DictReader(handle)
            if reader.fieldnames is None:
                raise NeuralMapError(f"{path}: empty flight log (no header line).")
            rows = list(reader)
            names = [n.strip() for n in reader.fieldnames]
    except UnicodeDecodeError as exc:
        raise NeuralMapError(
            f"{path}: not UTF-8 text (byte {exc.start} cannot be decoded: "
            f"{exc.object[exc.start:exc.start + 1]!r}); save the flight log as UTF-8 CSV."
        ) from None
    columns: dict[str, np.ndarray] = {}
    for raw, name in zip(reader.fieldnames, names, strict=True):
        values = [(r.get(raw) or "").strip() for r in rows]
        if name == "flight":
            columns[name] = np.asarray(values)
            continue
        try:
            columns[name] = np.asarray([float(v) if v else np.nan for v in values])
        except ValueError as exc:
            raise NeuralMapError(f"{path}: column {name!r} has a non-number ({exc}).") from None
    return columns


def _read_columns(path: Path) -> dict[str, np.ndarray]:
    if path.suffix.lower() == ".npz":
        return _read_npz(path)
    if path.suffix.lower() == ".csv":
        return _read_csv(path)
    raise NeuralMapError(f"{path}: a flight log must be a .csv or .npz file.")


def read_flight_log(path: str | os.PathLike[str], *, dtype: torch.dtype = torch.float64
                    ) -> FlightBatch:
    """Reads a flight log (see the module docstring) into a `FlightBatch`.

    Raises:
        NeuralMapError: Missing file or columns (named, with the columns found), a CSV that
            is not UTF-8 (a byte-order mark is fine), NPZ columns that are objects or not
            1-D, columns of different lengths, non-numbers, NaN in the INS columns or time,
            a time step that is not constant, or flights with different time steps.
    """
    path = Path(path)
    if not path.is_file():
        raise NeuralMapError(f"read_flight_log: no such file {str(path)!r}.")
    columns = _read_columns(path)
    missing = [c for c in LOG_COLUMNS if c not in columns]
    if missing:
        raise NeuralMapError(
            f"{path}: the flight log lacks column(s) {missing}; it has {sorted(columns)}. "
            f"Required: {', '.join(LOG_COLUMNS)} (optional: flight); see "
            "neuralmap.learning.flight_log.")
    lengths = {c: len(columns[c]) for c in (*LOG_COLUMNS, *(["flight"] if "flight" in columns
                                                             else []))}
    if len(set(lengths.values())) != 1 or 0 in lengths.values():
        raise NeuralMapError(f"{path}: columns must be non-empty and of equal length, got {lengths}.")
    n_rows = next(iter(lengths.values()))
    for c in ("time", "ins_x", "ins_y", "ins_h"):
        bad = ~np.isfinite(columns[c].astype(np.float64))
        if bad.any():
            raise NeuralMapError(
                f"{path}: column {c!r} has {int(bad.sum())} NaN/empty value(s) (first at row "
                f"{int(np.argmax(bad)) + 1}); only 'radar' may be missing.")
    ids = columns.get("flight", np.zeros(n_rows, dtype=int))
    starts = [0] + [i for i in range(1, n_rows) if ids[i] != ids[i - 1]] + [n_rows]
    seen = [str(ids[s]) for s in starts[:-1]]
    if len(set(seen)) != len(seen):
        raise NeuralMapError(f"{path}: the rows of each flight must be contiguous; ids {seen}.")
    dts = []
    tracks, radars = [], []
    for first, last in zip(starts[:-1], starts[1:], strict=True):
        t = columns["time"][first:last].astype(np.float64)
        if last - first < 2:
            raise NeuralMapError(f"{path}: flight {ids[first]!r} has fewer than 2 rows.")
        step = np.diff(t)
        if not (step > 0).all() or np.ptp(step) > 1e-6 * max(abs(step.mean()), 1.0):
            raise NeuralMapError(
                f"{path}: flight {ids[first]!r}: time must increase by a constant step (the "
                f"filter period), got steps from {step.min():g} to {step.max():g} s. Resample "
                "the log to a constant rate (missing altimeter epochs: radar = nan).")
        dts.append(float(step.mean()))
        tracks.append(torch.tensor(np.stack([columns[c][first:last].astype(np.float64)
                                             for c in ("ins_x", "ins_y", "ins_h")], 1),
                                   dtype=dtype))
        radars.append(torch.tensor(columns["radar"][first:last].astype(np.float64), dtype=dtype))
    if max(dts) - min(dts) > 1e-6 * max(dts):
        raise NeuralMapError(f"{path}: flights have different time steps {sorted(set(dts))} s.")
    return FlightBatch.from_sequences(dts[0], tracks, radars)


def write_flight_log(path: str | os.PathLike[str], flights: FlightBatch) -> Path:
    """Writes flights as a CSV or NPZ flight log (padding dropped)."""
    path = Path(path)
    rows: dict[str, list] = {c: [] for c in ("flight", *LOG_COLUMNS)}
    for i in range(flights.n_flights):
        n = int(flights.lengths[i])
        pos = flights.ins_pos[i, :n].detach().cpu().double().numpy()
        rows["flight"] += [i] * n
        rows["time"] += (np.arange(n) * flights.dt).tolist()
        for j, c in enumerate(("ins_x", "ins_y", "ins_h")):
            rows[c] += pos[:, j].tolist()
        rows["radar"] += flights.radar[i, :n].detach().cpu().double().tolist()
    if path.suffix.lower() == ".npz":
        np.savez(path, **{k: np.asarray(v) for k, v in rows.items()})
    else:
        with path.open("w", newline="", encoding="utf-8") as handle:
            writer = csv.writer(handle)
            writer.writerow(rows)
            writer.writerows(zip(*rows.values(), strict=True))
    return path
