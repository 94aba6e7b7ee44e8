"""What a navigated flight leaves behind: navigation.csv, navigation.geojson, and errors.

``navigation.csv`` — one row per vehicle and epoch (the rows of vehicle 0, then vehicle 1,
...)::

    vehicle, time, lat, lon, x, y, altitude, sigma_major_m, sigma_minor_m,
    ellipse_azimuth_deg, sigma_altitude_m, hpl_m, vpl_m, status, nis, mean_nis
    [, ref_x, ref_y, horizontal_error_m]

``lat, lon`` WGS-84 degrees (empty when the map has no georeference), ``x, y`` the map
frame (m), ``altitude`` on the DEM's vertical datum. The 1σ horizontal ellipse comes from
the 2×2 position covariance (`neuralmap.flights.track_summary.sigma_ellipse`): semi-axes
``sqrt(λ±)`` of ``P = [[p_xx, p_xy], [p_xy, p_yy]]`` and the major axis written as an
azimuth (degrees clockwise from north, in [0, 180)). Numbers are written in Python's
shortest round-trip form, so reading the CSV back gives the navigator's float64 values
exactly. ``hpl_m``, ``vpl_m``: the horizontal and vertical protection levels at the
navigator's integrity risk (`neuralmap.nav.integrity`); ``nis`` this epoch's NIS,
``mean_nis`` the lost-lock window's mean.

``navigation.geojson`` — RFC 7946 (lon/lat WGS-84): one ``LineString`` track per vehicle
(properties: vehicle, epochs, counts) and one ``Point`` per fix (properties: the CSV
columns). Written only for a georeferenced map.

Both are written by `NavigationFiles` as the replay goes: each chunk of fixes is formatted
at once into anonymous spool files (in the run's folder; the system removes them when
they are closed, also after a crash), so a log of a million epochs never holds its fixes
or its text in memory; at the end each file is assembled in its final order into a
temporary name and renamed (`neuralmap.io.atomic_write`): a failure leaves no
half-written file. A whole `FixTrack` goes the same way: one `NavigationFiles.append`.

With a reference, `add_reference_errors` puts into the study outputs the errors in
the study report format: a table and results.json entries (horizontal RMSE, final error,
the fraction inside the 3σ ellipse, NEES), the track over the hillshade with σ ellipses,
the east/north error against time inside ±3σ, the status timeline and TensorBoard curves.
They read a `TrackSummary` (the compact record of the flight, filled chunk by chunk);
the figures and curves of a flight longer than `PLOT_POINTS` epochs draw every
``stride``-th epoch (their captions say so), the numbers use every epoch.
"""

from __future__ import annotations

import csv
import gc
import io
import json
import math
import tempfile
from collections import defaultdict
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import IO, Any

import numpy as np
import torch

from neuralmap.flights.track_summary import PLOT_POINTS, TrackSummary, sigma_ellipse
from neuralmap.io import atomic_write
from neuralmap.nav.fix import STATUS, FixTrack

__all__ = ["CSV_COLUMNS", "NavigationFiles", "REFERENCE_COLUMNS", "add_reference_errors",
           "add_status"]

#: Columns of navigation.csv (reference columns follow when the log has a reference).
CSV_COLUMNS = ("vehicle", "time", "lat", "lon", "x", "y", "altitude", "sigma_major_m",
               "sigma_minor_m", "ellipse_azimuth_deg", "sigma_altitude_m", "hpl_m", "vpl_m",
               "status", "nis", "mean_nis")
REFERENCE_COLUMNS = ("ref_x", "ref_y", "horizontal_error_m")

#: Epochs of one vehicle formatted into text at a time (bounds the text in memory).
_TEXT_BLOCK = 2048

#: Status changes the timeline draws exactly (as steps); a vehicle with more is drawn at
#: the summary's decimated epochs.
_STEP_POINTS = 4 * PLOT_POINTS


def _num(value: float) -> str:
    """Shortest round-trip text of a float; empty for NaN."""
    return "" if not math.isfinite(value) else repr(float(value))


def _track_arrays(track: FixTrack) -> dict[str, np.ndarray]:
    """The CSV/GeoJSON quantities of a (chunk of a) track as float64 arrays."""
    def a(x: torch.Tensor | None) -> np.ndarray | None:
        return None if x is None else x.detach().cpu().double().numpy()

    major, minor, azimuth = sigma_ellipse(track.cov[..., :2, :2])
    return {"t": a(track.t), "xy": a(track.xy), "alt": a(track.altitude), "major": major,
            "minor": minor, "azimuth": azimuth,
            "sigma_h": np.sqrt(np.clip(a(track.cov[..., 2, 2]), 0.0, None)),
            "status": track.status.cpu().numpy(), "nis": a(track.nis),
            "mean_nis": a(track.mean_nis), "hpl": a(track.hpl), "vpl": a(track.vpl),
            "lat": a(track.lat), "lon": a(track.lon)}


class _Spool:
    """Text segments by key in one anonymous temporary file, copied out key by key.

    Args:
        folder: Where the file lives (None: the system's temporary folder).
    """

    def __init__(self, folder: str | Path | None) -> None:
        self._file: IO[bytes] = tempfile.TemporaryFile(dir=folder)
        self._size = 0
        self._segments: dict[Any, list[list[int]]] = defaultdict(list)

    def add(self, key: Any, data: bytes) -> None:
        """Appends ``data`` as the next segment of ``key``."""
        if not data:
            return
        self._file.seek(self._size)
        self._file.write(data)
        segments = self._segments[key]
        if segments and segments[-1][0] + segments[-1][1] == self._size:
            segments[-1][1] += len(data)  # contiguous with the key's last segment
        else:
            segments.append([self._size, len(data)])
        self._size += len(data)

    def copy(self, key: Any, handle: IO[bytes], block: int = 1 << 20) -> None:
        """Writes the segments of ``key``, in the order added, into ``handle``."""
        self._file.flush()
        for offset, length in self._segments.get(key, []):
            self._file.seek(offset)
            while length > 0:
                data = self._file.read(min(block, length))
                if not data:
                    raise OSError(f"spool file ended {length} bytes early")
                handle.write(data)
                length -= len(data)

    def close(self) -> None:
        """Closes (and so removes) the file."""
        self._file.close()


class NavigationFiles:
    """navigation.csv and navigation.geojson of a flight, fed chunk by chunk.

    `append` formats each chunk's rows (and GeoJSON features) into anonymous spool files as
    the replay produces them; `write_csv` and `write_geojson` then assemble each file in its
    final order (vehicle by vehicle) into a temporary name and rename it
    (`neuralmap.io.atomic_write`). Memory: the text of `_TEXT_BLOCK` epochs of one vehicle
    at a time (a few MB), whatever the chunk.

    Args:
        folder: Where the spool files live: the run's folder (the files are renamed there
            later: the same disk), or None for the system's temporary folder.
        n_vehicles: N.
        reference: Whether the rows carry the reference columns (`append` then takes the
            reference positions).
        geojson: Whether to write navigation.geojson too (the chunks need lat/lon).

    Attributes:
        n_vehicles: N.
        n_epochs: Epochs appended so far.
        reference: As given.
        geojson: As given.
    """

    def __init__(self, folder: str | Path | None, *, n_vehicles: int, reference: bool = False,
                 geojson: bool = False) -> None:
        self.n_vehicles, self.reference, self.geojson = int(n_vehicles), reference, geojson
        self.n_epochs = 0
        self._csv: _Spool | None = _Spool(folder)
        self._geo: _Spool | None = _Spool(folder) if geojson else None

    def __enter__(self) -> NavigationFiles:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()

    @property
    def closed(self) -> bool:
        """Whether the spool files are closed (`close`)."""
        return self._csv is None

    def close(self) -> None:
        """Closes (removes) the spool files; nothing can be written after."""
        for spool in (self._csv, self._geo):
            if spool is not None:
                spool.close()
        self._csv = self._geo = None

    def _check_open(self) -> None:
        if self.closed:
            raise ValueError("NavigationFiles: already closed (the spooled rows are gone).")

    def append(self, track: FixTrack, reference_xy: torch.Tensor | None = None) -> None:
        """Formats the next chunk of the flight.

        Args:
            track: The chunk's fixes (``N`` vehicles, ``k`` epochs).
            reference_xy: ``(N, k, 2)`` the chunk's reference positions (with
                ``reference=True``).

        Raises:
            ValueError: Closed, another N, a missing reference, or a GeoJSON chunk
                without lat/lon (the map has no georeference).
        """
        self._check_open()
        d = _track_arrays(track)
        n_veh, n_ep = d["xy"].shape[:2]
        if n_veh != self.n_vehicles:
            raise ValueError(f"NavigationFiles.append: {n_veh} vehicles, expected "
                             f"{self.n_vehicles}.")
        if self.reference and reference_xy is None:
            raise ValueError("NavigationFiles.append: the rows carry the reference: give "
                             "reference_xy.")
        if self.geojson and (d["lat"] is None or d["lon"] is None):
            raise ValueError("NavigationFiles: navigation.geojson needs the track's lat/lon "
                             "(the map has no georeference).")
        ref = (None if not self.reference
               else reference_xy.detach().cpu().double().numpy())
        for n in range(n_veh):
            for a in range(0, n_ep, _TEXT_BLOCK):  # a few MB of text at a time
                b = min(a + _TEXT_BLOCK, n_ep)
                self._csv.add(n, self._csv_rows(d, ref, n, a, b))
                if self._geo is not None:
                    coords, points = self._features(d, n, a, b, self.n_epochs + a == 0)
                    self._geo.add(("line", n), coords)
                    self._geo.add(("points", n), points)
        self.n_epochs += n_ep

    @staticmethod
    def _csv_rows(d: dict[str, np.ndarray], ref: np.ndarray | None, n: int, a: int, b: int
                  ) -> bytes:
        """Vehicle ``n``'s rows of the chunk's epochs ``a .. b``."""
        text = io.StringIO()
        writer = csv.writer(text, lineterminator="\n")
        for k in range(a, b):
            row = [str(n), _num(d["t"][k]),
                   "" if d["lat"] is None else _num(d["lat"][n, k]),
                   "" if d["lon"] is None else _num(d["lon"][n, k]),
                   _num(d["xy"][n, k, 0]), _num(d["xy"][n, k, 1]), _num(d["alt"][n, k]),
                   _num(d["major"][n, k]), _num(d["minor"][n, k]),
                   _num(d["azimuth"][n, k]), _num(d["sigma_h"][n, k]),
                   _num(d["hpl"][n, k]), _num(d["vpl"][n, k]),
                   STATUS[int(d["status"][n, k])], _num(d["nis"][n, k]),
                   _num(d["mean_nis"][n, k])]
            if ref is not None:
                e = float(np.hypot(*(d["xy"][n, k] - ref[n, k])))
                row += [_num(ref[n, k, 0]), _num(ref[n, k, 1]), _num(e)]
            writer.writerow(row)
        return text.getvalue().encode("utf-8")

    @staticmethod
    def _features(d: dict[str, np.ndarray], n: int, a: int, b: int, first: bool
                  ) -> tuple[bytes, bytes]:
        """Vehicle ``n``'s LineString coordinates and Point features of the chunk's epochs
        ``a .. b``, each with its leading separator (``first``: the flight's first
        coordinate has none), in the text of ``json.dumps``."""
        def val(x: float) -> float | None:
            return float(x) if math.isfinite(x) else None

        coords, points = [], []
        for k in range(a, b):
            coord = [float(d["lon"][n, k]), float(d["lat"][n, k])]
            coords.append(json.dumps(coord, allow_nan=False))
            points.append(json.dumps({
                "type": "Feature",
                "geometry": {"type": "Point", "coordinates": coord},
                "properties": {"vehicle": n, "kind": "fix", "time": val(d["t"][k]),
                               "x": val(d["xy"][n, k, 0]), "y": val(d["xy"][n, k, 1]),
                               "altitude": val(d["alt"][n, k]),
                               "sigma_major_m": val(d["major"][n, k]),
                               "sigma_minor_m": val(d["minor"][n, k]),
                               "ellipse_azimuth_deg": val(d["azimuth"][n, k]),
                               "sigma_altitude_m": val(d["sigma_h"][n, k]),
                               "hpl_m": val(d["hpl"][n, k]), "vpl_m": val(d["vpl"][n, k]),
                               "status": STATUS[int(d["status"][n, k])],
                               "nis": val(d["nis"][n, k]),
                               "mean_nis": val(d["mean_nis"][n, k])}}, allow_nan=False))
        line = ("" if first else ", ") + ", ".join(coords)
        return line.encode("utf-8"), "".join(", " + p for p in points).encode("utf-8")

    def write_csv(self, path: str | Path) -> Path:
        """Writes navigation.csv atomically from the chunks appended (columns:
        `CSV_COLUMNS`, then `REFERENCE_COLUMNS` with a reference)."""
        self._check_open()
        header = ",".join(CSV_COLUMNS + (REFERENCE_COLUMNS if self.reference else ()))

        def write(handle: IO[bytes]) -> None:
            handle.write((header + "\n").encode("utf-8"))
            for n in range(self.n_vehicles):
                self._csv.copy(n, handle)

        return atomic_write(path, write)

    def write_geojson(self, path: str | Path, *, counts: dict[str, int] | None = None,
                      properties: dict[str, Any] | None = None) -> Path:
        """Writes navigation.geojson atomically from the chunks appended.

        Args:
            path: The file.
            counts: The navigator's counters (each track's ``counts`` property).
            properties: More properties of each track (map, log).

        Raises:
            ValueError: The files were made without ``geojson=True``.
        """
        self._check_open()
        if self._geo is None:
            raise ValueError("NavigationFiles.write_geojson: the files were made without "
                             "geojson=True.")

        def write(handle: IO[bytes]) -> None:  # streamed feature by feature
            handle.write(b'{"type": "FeatureCollection", "features": [')
            for n in range(self.n_vehicles):
                track_properties = {"vehicle": n, "kind": "track", "epochs": self.n_epochs,
                                    "counts": dict(counts or {}), **(properties or {})}
                handle.write((", " if n else "").encode() + b'{"type": "Feature", '
                             b'"geometry": {"type": "LineString", "coordinates": [')
                self._geo.copy(("line", n), handle)
                handle.write(b']}, "properties": ' + json.dumps(
                    track_properties, allow_nan=False).encode("utf-8") + b"}")
                self._geo.copy(("points", n), handle)
            handle.write(b"]}\n")

        return atomic_write(path, write)


# ---------------------------------------------------------------------------- the report


@contextmanager
def _bounded_drawing() -> Iterator[None]:
    """Matplotlib draws long paths in pieces of 2000 vertices (``agg.path.chunksize``):
    the Agg rasteriser's memory grows with the drawn length of a path, which for the
    decimated track of a long loiter (chords across the map) is a hundred megabytes. The
    figures drawn in the block are collected at its end (a figure is a cycle of
    references: it and its renderer's buffers would wait for the next collection)."""
    import matplotlib

    try:
        with matplotlib.rc_context({"agg.path.chunksize": 2000}):
            yield
    finally:
        gc.collect()


def _decimated(summary: TrackSummary) -> str:
    """The caption's note on a decimated series (empty when every epoch is drawn)."""
    if summary.stride == 1:
        return ""
    return (f" (drawn at every {summary.stride}th of the {summary.n_epochs} epochs; the "
            "numbers use every epoch)")


def _track_figure(preview: Any, summary: TrackSummary) -> Any:
    from matplotlib.patches import Ellipse

    from neuralmap.viz.navigation import plot_trajectories

    est = summary.plot["xy"]
    fig = plot_trajectories(preview, summary.plot["reference"],
                            {"TAN": est, "INS": summary.plot["ins"]},
                            title="Navigated track over the map (reference white, "
                                  "3σ ellipses)")
    ax = fig.axes[0]
    ell = summary.ellipses
    for j in range(summary.ellipse_index.size):
        for n in range(est.shape[0]):
            if not np.isfinite(ell["major"][n, j]):
                continue
            ax.add_patch(Ellipse((ell["xy"][n, j, 0], ell["xy"][n, j, 1]),
                                 6.0 * ell["major"][n, j], 6.0 * ell["minor"][n, j],
                                 angle=90.0 - ell["azimuth"][n, j], fill=False, color="C0",
                                 lw=0.8))
    # zoom to the flight with a margin (the ellipses and tracks, not the whole tile)
    lo, hi = summary.extent_lo, summary.extent_hi
    if np.isfinite(lo).all() and np.isfinite(hi).all():
        pad = max(float((hi - lo).max()) * 0.15, 200.0)
        ax.set_xlim(lo[0] - pad, hi[0] + pad)
        ax.set_ylim(lo[1] - pad, hi[1] + pad)
    return fig


def _error_figure(summary: TrackSummary) -> Any:
    from matplotlib.figure import Figure

    t = summary.plot_t
    err, sigma = summary.plot["error"], summary.plot["sigma_en"]
    major = summary.plot["major"]
    fig = Figure(figsize=(8.0, 6.4))
    axes = fig.subplots(3, 1, sharex=True)
    for n in range(err.shape[0]):
        for i, (ax, name) in enumerate(zip(axes[:2], ("east", "north"), strict=True)):
            s3 = 3.0 * sigma[n, :, i]
            ax.fill_between(t, -s3, s3, color="C0", alpha=0.15,
                            label="±3σ" if n == 0 else None)
            ax.plot(t, err[n, :, i], color=f"C{(n + 1) % 10}", lw=1.0,
                    label=f"vehicle {n}" if err.shape[0] > 1 else "error")
            ax.set_ylabel(f"{name} error [m]")
        axes[2].plot(t, np.hypot(err[n, :, 0], err[n, :, 1]), color=f"C{(n + 1) % 10}", lw=1.0)
        axes[2].plot(t, 3.0 * major[n], color="C0", lw=0.8, ls="--",
                     label="3σ major axis" if n == 0 else None)
    axes[2].set_ylabel("horizontal error [m]")
    axes[2].set_xlabel("time [s]")
    for ax in axes:
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=8, loc="upper right")
    axes[0].set_title("Error against the reference with the ±3σ envelope")
    fig.tight_layout()
    return fig


def _status_figure(summary: TrackSummary) -> tuple[Any, bool]:
    """The status timeline: each vehicle's status as steps at its changes (exact), or at
    the decimated epochs when it changes more than `_STEP_POINTS` times. Returns the
    figure and whether any vehicle was decimated."""
    from matplotlib.figure import Figure

    t, codes = summary.t, summary.status
    fig = Figure(figsize=(8.0, 1.2 + 0.35 * codes.shape[0] + 1.5))
    ax = fig.add_subplot()
    decimated = False
    for n in range(codes.shape[0]):
        change = np.flatnonzero(np.diff(codes[n])) + 1
        if change.size <= _STEP_POINTS:  # the step plot of every epoch, drawn at its changes
            idx = np.unique(np.r_[0, change, codes.shape[1] - 1])
        else:
            idx, decimated = summary.plot_index, True
        ax.step(t[idx], codes[n, idx] + 0.08 * n, where="post", lw=1.2, label=f"vehicle {n}")
    ax.set_yticks(range(len(STATUS)), STATUS)
    ax.set_ylim(-0.5, len(STATUS) - 0.5)
    ax.set_xlabel("time [s]")
    ax.set_title("Navigator status")
    ax.grid(True, alpha=0.3)
    fig.tight_layout()
    return fig, decimated


def add_reference_errors(outputs: Any, summary: TrackSummary, *, preview: Any) -> dict:
    """Errors against the reference into a `StudyOutputs`
    (table, results.json ``errors``, two figures, TensorBoard curves).

    Args:
        outputs: The study outputs writer.
        summary: The navigated flight's `TrackSummary`, made with the reference, the INS
            and their altitudes (`TrackSummary.from_track` for a whole `FixTrack`).
        preview: A `DemTile` drawn as hillshade.

    Returns:
        The error summary (`TrackSummary.reference_errors`, with the INS's and the
        vertical RMSE).

    Raises:
        ValueError: The summary has no reference or no INS positions.
    """
    if summary.ins_xy is None or not summary.has_reference:
        raise ValueError("add_reference_errors: the summary needs the reference and the INS "
                         "positions (TrackSummary(..., reference_xy=, ins_xy=)).")
    errors = summary.reference_errors()
    ins = summary.ins_errors()
    errors["ins_rmse_horizontal_m"] = ins["rmse_horizontal_m"]
    errors["rmse_vertical_m"] = summary.rmse_vertical()
    errors["ins_rmse_vertical_m"] = ins["rmse_vertical_m"]
    outputs.results["errors"] = errors
    outputs.add_table(
        "Errors against the reference",
        ["estimate", "horizontal RMSE [m]", "RMSE while tracking [m]", "final error [m]",
         "inside 3σ ellipse", "mean NEES (xy, 2 = consistent)", "vertical RMSE [m]"],
        [["TAN", errors["rmse_horizontal_m"], errors["rmse_horizontal_tracking_m"],
          float(np.mean(errors["final_horizontal_error_m"])), errors["inside_3sigma"],
          errors["mean_nees_xy"], errors["rmse_vertical_m"]],
         ["INS alone", errors["ins_rmse_horizontal_m"], None,
          float(np.mean(ins["final_horizontal_error_m"])), None, None,
          errors["ins_rmse_vertical_m"]]],
        note="Final error: mean over vehicles. Inside 3σ: fraction of epochs whose error "
             "lies inside the 3σ ellipse of the reported covariance (98.9 % for a "
             "consistent Gaussian).")
    note = _decimated(summary)
    with _bounded_drawing():
        outputs.add_figure("track", _track_figure(preview, summary),
                           "Navigated track (TAN) and INS over the hillshade; reference in "
                           "white; 3σ ellipses along the track" + note)
        outputs.add_figure("error_vs_time", _error_figure(summary),
                           "East, north and horizontal error against the reference with ±3σ"
                           + note)
    s = summary.stride
    outputs.log_curve("error/horizontal_rms_m", errors["horizontal_error_curve"],
                      step_scale=s)
    outputs.log_curve("sigma/major_axis_mean_m", summary.curves["major_mean"].tolist(),
                      step_scale=s)
    return errors


def add_status(outputs: Any, summary: TrackSummary) -> dict[str, float]:
    """The status timeline figure, the status fractions table and TensorBoard curve."""
    fractions = summary.status_fractions()
    outputs.results["status_fraction"] = fractions
    outputs.add_table("Status", ["status", "fraction of epochs"],
                      [[name, value] for name, value in fractions.items()])
    fig, decimated = _status_figure(summary)
    with _bounded_drawing():
        outputs.add_figure("status_timeline", fig,
                           "Status against time (acquiring, tracking, lost, off map, "
                           "no measurement)" + (_decimated(summary) if decimated else ""))
    s = summary.stride
    outputs.log_curve("status/code_vehicle0", summary.status[0, ::s].astype(float).tolist(),
                      step_scale=s)
    return fractions
