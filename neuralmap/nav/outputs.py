"""What a navigated flight leaves behind: navigation.csv, navigation.geojson, and errors.

``navigation.csv`` — one row per vehicle and epoch::

    vehicle, time, lat, lon, x, y, altitude, sigma_major_m, sigma_minor_m,
    ellipse_azimuth_deg, sigma_altitude_m, hpl_m, vpl_m, status, nis, mean_nis
    [, ref_x, ref_y, horizontal_error_m]

``lat, lon`` WGS-84 degrees (empty when the map has no georeference), ``x, y`` the map
frame (m), ``altitude`` on the DEM's vertical datum. The 1σ horizontal ellipse comes from
the 2×2 position covariance ``P = [[p_xx, p_xy], [p_xy, p_yy]]``: semi-axes
``sqrt(λ±)`` with ``λ± = (p_xx + p_yy)/2 ± sqrt(((p_xx − p_yy)/2)² + p_xy²)`` and the
major axis at ``θ = ½·atan2(2 p_xy, p_xx − p_yy)`` from east, written as an azimuth
(degrees clockwise from north, in [0, 180)). Numbers are written in Python's shortest
round-trip form, so reading the CSV back gives the navigator's float64 values exactly.
``hpl_m``, ``vpl_m``: the horizontal and vertical protection levels at the navigator's
integrity risk (`neuralmap.nav.integrity`); ``nis`` this epoch's NIS, ``mean_nis`` the
lost-lock window's mean. Both files are streamed into their temporary name (a log of a
million epochs never holds its text in memory) and renamed when complete.

``navigation.geojson`` — RFC 7946 (lon/lat WGS-84): one ``LineString`` track per vehicle
(properties: vehicle, epochs, counts) and one ``Point`` per fix (properties: the CSV
columns). Written only for a georeferenced map.

With a reference, `add_reference_errors` puts into the study outputs the errors in
the study report format: a table and results.json entries (horizontal RMSE, final error,
the fraction inside the 3σ ellipse, NEES), the track over the hillshade with σ ellipses,
the east/north error against time inside ±3σ, the status timeline and TensorBoard curves.
"""

from __future__ import annotations

import csv
import io
import json
import math
from pathlib import Path
from typing import Any

import numpy as np
import torch

from neuralmap.filters.stats import symmetrize
from neuralmap.io import atomic_write
from neuralmap.nav.fix import STATUS, FixTrack

__all__ = ["CSV_COLUMNS", "add_reference_errors", "sigma_ellipse", "write_navigation_csv",
           "write_navigation_geojson"]

#: Columns of navigation.csv (reference columns follow when the log has a reference).
CSV_COLUMNS = ("vehicle", "time", "lat", "lon", "x", "y", "altitude", "sigma_major_m",
               "sigma_minor_m", "ellipse_azimuth_deg", "sigma_altitude_m", "hpl_m", "vpl_m",
               "status", "nis", "mean_nis")
REFERENCE_COLUMNS = ("ref_x", "ref_y", "horizontal_error_m")


def sigma_ellipse(cov_xy: torch.Tensor | np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """1σ ellipse of ``(..., 2, 2)`` position covariances (closed form, see module docstring).

    Returns:
        ``(major, minor, azimuth_deg)``, each ``(...)``: semi-axes in m and the major axis
        azimuth in degrees clockwise from north, in ``[0, 180)``.
    """
    p = np.asarray(cov_xy.detach().cpu().double() if isinstance(cov_xy, torch.Tensor)
                   else cov_xy, dtype=np.float64)
    pxx, pyy, pxy = p[..., 0, 0], p[..., 1, 1], 0.5 * (p[..., 0, 1] + p[..., 1, 0])
    mean = 0.5 * (pxx + pyy)
    radius = np.hypot(0.5 * (pxx - pyy), pxy)
    major = np.sqrt(np.clip(mean + radius, 0.0, None))  # λ+ = mean + radius
    minor = np.sqrt(np.clip(mean - radius, 0.0, None))  # λ- = mean - radius
    theta = 0.5 * np.arctan2(2.0 * pxy, pxx - pyy)  # major axis angle from east
    azimuth = np.mod(90.0 - np.degrees(theta), 180.0)
    return major, minor, azimuth


def _num(value: float) -> str:
    """Shortest round-trip text of a float; empty for NaN."""
    return "" if not math.isfinite(value) else repr(float(value))


def _track_arrays(track: FixTrack) -> dict[str, np.ndarray]:
    def a(x: torch.Tensor | None) -> np.ndarray | None:
        return None if x is None else x.detach().cpu().double().numpy()

    major, minor, azimuth = sigma_ellipse(track.cov[..., :2, :2])
    return {"t": a(track.t), "xy": a(track.xy), "alt": a(track.altitude), "major": major,
            "minor": minor, "azimuth": azimuth,
            "sigma_h": np.sqrt(np.clip(a(track.cov[..., 2, 2]), 0.0, None)),
            "status": track.status.cpu().numpy(), "nis": a(track.nis),
            "mean_nis": a(track.mean_nis), "hpl": a(track.hpl), "vpl": a(track.vpl),
            "lat": a(track.lat), "lon": a(track.lon)}


def write_navigation_csv(path: str | Path, track: FixTrack,
                         reference_xy: torch.Tensor | None = None) -> Path:
    """Writes navigation.csv atomically (columns: `CSV_COLUMNS`, then the reference
    columns when ``reference_xy`` ``(N, K, 2)`` is given), streamed row by row into the
    temporary file (a long log never holds its text in memory)."""
    d = _track_arrays(track)
    ref = None if reference_xy is None else reference_xy.detach().cpu().double().numpy()
    n_veh, n_ep = d["xy"].shape[:2]

    def write(handle: Any) -> None:
        text = io.TextIOWrapper(handle, encoding="utf-8", newline="")
        writer = csv.writer(text, lineterminator="\n")
        writer.writerow(CSV_COLUMNS + (REFERENCE_COLUMNS if ref is not None else ()))
        for n in range(n_veh):
            for k in range(n_ep):
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
        text.flush()
        text.detach()  # leave the binary handle to the atomic writer

    return atomic_write(path, write)


def write_navigation_geojson(path: str | Path, track: FixTrack, *,
                             counts: dict[str, int] | None = None,
                             properties: dict[str, Any] | None = None) -> Path:
    """Writes navigation.geojson atomically (needs ``track.lat``/``lon``).

    Raises:
        ValueError: The track has no lat/lon (the map has no georeference).
    """
    if track.lat is None or track.lon is None:
        raise ValueError("write_navigation_geojson: the track has no lat/lon.")
    d = _track_arrays(track)
    n_veh, n_ep = d["xy"].shape[:2]

    def val(x: float) -> float | None:
        return float(x) if math.isfinite(x) else None

    def features() -> Any:
        for n in range(n_veh):
            coords = [[float(d["lon"][n, k]), float(d["lat"][n, k])] for k in range(n_ep)]
            yield {"type": "Feature",
                   "geometry": {"type": "LineString", "coordinates": coords},
                   "properties": {"vehicle": n, "kind": "track", "epochs": n_ep,
                                  "counts": dict(counts or {}), **(properties or {})}}
            for k in range(n_ep):
                yield {
                    "type": "Feature",
                    "geometry": {"type": "Point", "coordinates": coords[k]},
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
                                   "mean_nis": val(d["mean_nis"][n, k])}}

    def write(handle: Any) -> None:  # streamed feature by feature
        handle.write(b'{"type": "FeatureCollection", "features": [')
        for i, feature in enumerate(features()):
            handle.write((", " if i else "").encode() + json.dumps(
                feature, allow_nan=False).encode())
        handle.write(b"]}\n")

    return atomic_write(path, write)


def status_summary(track: FixTrack) -> dict[str, float]:
    """Fraction of epochs (all vehicles) in each status."""
    codes = track.status.cpu().numpy().reshape(-1)
    return {name: float(np.mean(codes == i)) for i, name in enumerate(STATUS)}


def reference_errors(track: FixTrack, reference_xy: torch.Tensor) -> dict[str, Any]:
    """Errors of a track against a reference ``(N, K, 2)``.

    Returns:
        ``rmse_horizontal_m`` (all epochs), ``rmse_horizontal_tracking_m`` (epochs with
        status tracking), ``final_horizontal_error_m`` (per vehicle), ``inside_3sigma`` (the
        fraction of epochs whose error lies inside the 3σ ellipse: NEES_xy ≤ 9),
        ``mean_nees_xy`` (2 = consistent), and the ``horizontal_error_curve`` (vehicle
        RMS per epoch).
    """
    xy = track.xy.detach().cpu().double()
    err = xy - reference_xy.detach().cpu().double()  # (N, K, 2)
    cov = track.cov[..., :2, :2].detach().cpu().double()
    cov = symmetrize(cov)
    chol, info = torch.linalg.cholesky_ex(cov)
    ok = info == 0
    nees = torch.full(err.shape[:2], float("nan"), dtype=torch.float64)
    if ok.any():
        z = torch.linalg.solve_triangular(chol[ok], err[ok].unsqueeze(-1), upper=False)
        nees[ok] = (z.squeeze(-1) ** 2).sum(-1)  # NEES = eᵀ P⁻¹ e via the Cholesky factor
    h = err.norm(dim=-1)
    tracking = track.status.cpu() == STATUS.index("tracking")
    finite = torch.isfinite(nees)
    return {
        "rmse_horizontal_m": float(h.pow(2).mean().sqrt()),
        "rmse_horizontal_tracking_m": (float(h[tracking].pow(2).mean().sqrt())
                                       if tracking.any() else None),
        "final_horizontal_error_m": h[:, -1].tolist(),
        "max_horizontal_error_m": float(h.max()),
        "inside_3sigma": float((nees[finite] <= 9.0).double().mean()) if finite.any() else None,
        "mean_nees_xy": float(nees[finite].mean()) if finite.any() else None,
        "horizontal_error_curve": h.pow(2).mean(0).sqrt().tolist(),
    }


def _track_figure(preview: Any, track: FixTrack, reference_xy: torch.Tensor,
                  ins_xy: torch.Tensor, n_ellipses: int) -> Any:
    from matplotlib.patches import Ellipse

    from neuralmap.viz.navigation import plot_trajectories

    ref = reference_xy.detach().cpu().double().numpy()
    est = track.xy.detach().cpu().double().numpy()
    fig = plot_trajectories(preview, ref, {"TAN": est, "INS": ins_xy.cpu().double().numpy()},
                            title="Navigated track over the map (reference white, "
                                  "3σ ellipses)")
    ax = fig.axes[0]
    major, minor, azimuth = sigma_ellipse(track.cov[..., :2, :2])
    n_ep = est.shape[1]
    for k in np.unique(np.linspace(0, n_ep - 1, max(2, n_ellipses)).astype(int)):
        for n in range(est.shape[0]):
            if not np.isfinite(major[n, k]):
                continue
            ax.add_patch(Ellipse((est[n, k, 0], est[n, k, 1]), 6.0 * major[n, k],
                                 6.0 * minor[n, k], angle=90.0 - azimuth[n, k], fill=False,
                                 color="C0", lw=0.8))
    # zoom to the flight with a margin (the ellipses and tracks, not the whole tile)
    pts = np.concatenate([ref.reshape(-1, 2), est.reshape(-1, 2)])
    pts = pts[np.isfinite(pts).all(1)]
    if pts.size:
        lo, hi = pts.min(0), pts.max(0)
        pad = max(float((hi - lo).max()) * 0.15, 200.0)
        ax.set_xlim(lo[0] - pad, hi[0] + pad)
        ax.set_ylim(lo[1] - pad, hi[1] + pad)
    return fig


def _error_figure(track: FixTrack, reference_xy: torch.Tensor) -> Any:
    from matplotlib.figure import Figure

    t = track.t.detach().cpu().double().numpy()
    err = (track.xy - reference_xy).detach().cpu().double().numpy()
    cov = track.cov.detach().cpu().double().numpy()
    fig = Figure(figsize=(8.0, 6.4))
    axes = fig.subplots(3, 1, sharex=True)
    major = sigma_ellipse(cov[..., :2, :2])[0]
    for n in range(err.shape[0]):
        for i, (ax, name) in enumerate(zip(axes[:2], ("east", "north"), strict=True)):
            s3 = 3.0 * np.sqrt(np.clip(cov[n, :, i, i], 0.0, None))
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


def _status_figure(track: FixTrack) -> Any:
    from matplotlib.figure import Figure

    t = track.t.detach().cpu().double().numpy()
    codes = track.status.cpu().numpy()
    fig = Figure(figsize=(8.0, 1.2 + 0.35 * codes.shape[0] + 1.5))
    ax = fig.add_subplot()
    for n in range(codes.shape[0]):
        ax.step(t, codes[n] + 0.08 * n, where="post", lw=1.2, label=f"vehicle {n}")
    ax.set_yticks(range(len(STATUS)), STATUS)
    ax.set_ylim(-0.5, len(STATUS) - 0.5)
    ax.set_xlabel("time [s]")
    ax.set_title("Navigator status")
    ax.grid(True, alpha=0.3)
    fig.tight_layout()
    return fig


def add_reference_errors(outputs: Any, track: FixTrack, reference_xy: torch.Tensor, *,
                         ins_xy: torch.Tensor, preview: Any, n_ellipses: int = 20,
                         reference_altitude: torch.Tensor | None = None,
                         ins_altitude: torch.Tensor | None = None) -> dict:
    """Errors against the reference into a `StudyOutputs`
    (table, results.json ``errors``, three figures, TensorBoard curves).

    Args:
        outputs: The study outputs writer.
        track: The navigated track.
        reference_xy: ``(N, K, 2)`` reference positions, map frame.
        ins_xy: ``(N, K, 2)`` INS positions (drawn beside the estimate).
        preview: A `DemTile` drawn as hillshade.
        n_ellipses: σ ellipses drawn along the track.
        reference_altitude: ``(N, K)`` reference altitude (same datum), optional: adds the
            vertical RMSE of TAN and of the INS.
        ins_altitude: ``(N, K)`` INS altitude, with ``reference_altitude``.

    Returns:
        The error summary (`reference_errors`).
    """
    errors = reference_errors(track, reference_xy)
    ins_err = (ins_xy.double() - reference_xy.double()).norm(dim=-1)
    errors["ins_rmse_horizontal_m"] = float(ins_err.pow(2).mean().sqrt())
    errors["rmse_vertical_m"] = errors["ins_rmse_vertical_m"] = None
    if reference_altitude is not None:
        ref_h = reference_altitude.detach().cpu().double()
        dh = track.altitude.detach().cpu().double() - ref_h
        errors["rmse_vertical_m"] = float(dh.pow(2).mean().sqrt())
        if ins_altitude is not None:
            errors["ins_rmse_vertical_m"] = float(
                (ins_altitude.detach().cpu().double() - ref_h).pow(2).mean().sqrt())
    outputs.results["errors"] = errors
    outputs.add_table(
        "Errors against the reference",
        ["estimate", "horizontal RMSE [m]", "RMSE while tracking [m]", "final error [m]",
         "inside 3σ ellipse", "mean NEES (xy, 2 = consistent)", "vertical RMSE [m]"],
        [["TAN", errors["rmse_horizontal_m"], errors["rmse_horizontal_tracking_m"],
          float(np.mean(errors["final_horizontal_error_m"])), errors["inside_3sigma"],
          errors["mean_nees_xy"], errors["rmse_vertical_m"]],
         ["INS alone", errors["ins_rmse_horizontal_m"], None, float(ins_err[:, -1].mean()),
          None, None, errors["ins_rmse_vertical_m"]]],
        note="Final error: mean over vehicles. Inside 3σ: fraction of epochs whose error "
             "lies inside the 3σ ellipse of the reported covariance (98.9 % for a "
             "consistent Gaussian).")
    outputs.add_figure("track", _track_figure(preview, track, reference_xy, ins_xy,
                                              n_ellipses),
                       "Navigated track (TAN) and INS over the hillshade; reference in white; "
                       "3σ ellipses along the track")
    outputs.add_figure("error_vs_time", _error_figure(track, reference_xy),
                       "East, north and horizontal error against the reference with ±3σ")
    outputs.log_curve("error/horizontal_rms_m", errors["horizontal_error_curve"])
    major = sigma_ellipse(track.cov[..., :2, :2])[0]
    outputs.log_curve("sigma/major_axis_mean_m", np.nanmean(major, 0).tolist())
    return errors


def add_status(outputs: Any, track: FixTrack) -> dict[str, float]:
    """The status timeline figure, the status fractions table and TensorBoard curve."""
    fractions = status_summary(track)
    outputs.results["status_fraction"] = fractions
    outputs.add_table("Status", ["status", "fraction of epochs"],
                      [[name, value] for name, value in fractions.items()])
    outputs.add_figure("status_timeline", _status_figure(track),
                       "Status against time (acquiring, tracking, lost, off map, "
                       "no measurement)")
    outputs.log_curve("status/code_vehicle0", track.status[0].cpu().double().tolist())
    return fractions
