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
from pathlib import Path

import numpy as np
import torch

from neuralmap.columns import read_columns
from neuralmap.exceptions import NeuralMapError
from neuralmap.learning.flights import FlightBatch

__all__ = ["LOG_COLUMNS", "read_flight_log", "write_flight_log"]

#: Required columns of a flight log.
LOG_COLUMNS = ("time", "ins_x", "ins_y", "ins_h", "radar")


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
    columns = read_columns(path, what="flight log")
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
