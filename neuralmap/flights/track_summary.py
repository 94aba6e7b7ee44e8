"""The compact record of a navigated flight: what its report, figures and errors need,
filled chunk by chunk, without the whole `FixTrack`.

A `FixTrack` costs about 330 bytes per epoch and vehicle (its ``(5, 5)`` float64 covariance
alone 200), so a log of a million epochs would need a third of a gigabyte for the track
and as much again for the float64 copies of the writers. `neuralmap.flights.flight` replays a
long log in chunks of epochs (`Navigator.replay` with ``reset=False``) and hands each
chunk's `FixTrack` to `TrackSummary.add`, which keeps:

* per epoch and vehicle, the status code (1 byte: the status fractions and timeline);
* the sums behind every error number, accumulated chunk by chunk *exactly* (each float64
  term is an integer multiple of 2⁻¹⁰⁷⁴, added as a Python integer; `exact_sum`), so the
  numbers are the correctly rounded results over every epoch and do not depend on the
  chunk size: the horizontal error ``|xy − ref|`` (RMSE over all epochs and while
  tracking, its maximum, the last epoch's), the horizontal NEES ``eᵀ P_xy⁻¹ e`` (mean, the
  fraction ≤ 9: inside the 3σ ellipse), the vertical error, and the same for the INS;
* for the figures and curves, a decimated series: every `stride`-th epoch and the last (at
  most about ``plot_points`` epochs per vehicle; ``stride`` is 1 for a shorter flight, so a
  short flight is drawn whole) of the estimate, its east/north σ and 1σ major axis, its
  error, the reference and the INS, the vehicles' RMS error and mean major axis; the σ
  ellipses at the ``n_ellipses`` epochs the track figure draws; the extent of the estimate
  and the reference over every epoch;
* the last epoch as a `Fix`, and the navigator's counters.

That is 1 byte per epoch and vehicle, plus a fixed amount for the figures.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import fields, replace
from typing import Any

import numpy as np
import torch

from neuralmap.filters.stats import nees, symmetrize
from neuralmap.nav.fix import STATUS, STATUS_CODE, Fix, FixTrack

__all__ = ["PLOT_POINTS", "TrackSummary", "exact_sum", "sigma_ellipse"]

#: Epochs per vehicle the figures and curves of a long flight draw at most (a flight with
#: more is drawn every ``ceil(K / PLOT_POINTS)``-th epoch).
PLOT_POINTS = 10_000


def sigma_ellipse(cov_xy: torch.Tensor | np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """1σ ellipse of ``(..., 2, 2)`` position covariances, in closed form.

    With ``P = [[p_xx, p_xy], [p_xy, p_yy]]``: semi-axes ``sqrt(λ±)``, ``λ± = (p_xx + p_yy)/2
    ± sqrt(((p_xx − p_yy)/2)² + p_xy²)``; the major axis at ``θ = ½·atan2(2 p_xy, p_xx −
    p_yy)`` from east, returned as an azimuth (degrees clockwise from north).

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


def exact_sum(values: np.ndarray | torch.Tensor) -> int:
    """The exact sum of finite float64 values, in units of 2⁻¹⁰⁷⁴ (the smallest subnormal).

    Every float64 is an integer multiple of 2⁻¹⁰⁷⁴, so its sum is an integer in those units:
    the mantissas (53 bits, split in two halves so that numpy's int64 sums cannot overflow)
    are summed per binary exponent and shifted into one Python integer. Sums of parts add
    up to the sum of the whole, exactly: a mean over a flight does not depend on how it was
    split into chunks, and ``exact_sum(v) / 2**1074`` is the correctly rounded sum
    (`math.fsum`'s).

    Args:
        values: Finite values (any shape).

    Returns:
        ``Σ values · 2¹⁰⁷⁴`` as an integer.
    """
    v = np.asarray(values.detach().cpu().double() if isinstance(values, torch.Tensor)
                   else values, dtype=np.float64).reshape(-1)
    mantissa, exponent = np.frexp(v)  # v = m · 2^e, 0.5 <= |m| < 1 (m = 0 for 0)
    m = (mantissa * 2.0 ** 53).astype(np.int64)  # exact: |m| < 2^53
    total = 0
    for e in np.unique(exponent):
        sel = m[exponent == e]
        part = (int((sel >> 26).sum()) << 26) + int((sel & ((1 << 26) - 1)).sum())
        shift = int(e) - 53 + 1074  # v = m · 2^(e − 53) = m · 2^shift units
        total += part << shift if shift >= 0 else part >> -shift  # subnormals: exact too
    return total


_UNIT = 1 << 1074  # 2^1074: exact_sum's unit


class _Mean:
    """The exact mean of the finite values added (`exact_sum`); NaN once a non-finite
    value was added when ``strict``, else those are left out (and counted apart)."""

    def __init__(self, *, strict: bool = True) -> None:
        self.strict = strict
        self.total = 0
        self.count = 0
        self.nonfinite = 0

    def add(self, values: torch.Tensor | np.ndarray) -> None:
        v = np.asarray(values.detach().cpu().double() if isinstance(values, torch.Tensor)
                       else values, dtype=np.float64).reshape(-1)
        ok = np.isfinite(v)
        bad = int(v.size - ok.sum())
        self.nonfinite += bad
        self.total += exact_sum(v[ok] if bad else v)
        self.count += int(ok.sum())

    def value(self) -> float | None:
        """The mean (None when nothing finite was added; NaN for a strict mean that saw a
        non-finite value)."""
        if self.strict and self.nonfinite:
            return math.nan
        return self.total / (self.count * _UNIT) if self.count else None  # one rounding


def _clone(fix: Fix) -> Fix:
    """``fix`` with its own copies of every tensor (not views into a chunk's track)."""
    return replace(fix, **{f.name: getattr(fix, f.name).clone() for f in fields(fix)
                           if isinstance(getattr(fix, f.name), torch.Tensor)})


def _np(x: torch.Tensor) -> np.ndarray:
    return x.detach().cpu().double().numpy()


class TrackSummary:
    """A navigated flight reduced to what its outputs need (module docstring).

    Fill it with the flight's `FixTrack` chunks in order (`add`), or at once
    (`from_track`).

    Args:
        t: ``(K,)`` the flight's epoch times, s.
        n_vehicles: N.
        reference_xy: ``(N, K, 2)`` reference positions (map frame), or None.
        reference_altitude: ``(N, K)`` reference altitude (the datum of the fixes), or None.
        ins_xy: ``(N, K, 2)`` the INS positions (the INS's errors and track beside the
            estimate's), or None.
        ins_altitude: ``(N, K)`` the INS altitude, or None.
        n_ellipses: σ ellipses the track figure draws (at least 2).
        plot_points: Epochs per vehicle the figures draw at most (`PLOT_POINTS`).

    Attributes:
        n_vehicles: N.
        n_epochs: K.
        t: ``(K,)`` float64 epoch times.
        stride: The figures' and curves' decimation: every ``stride``-th epoch.
        plot_index: ``(P,)`` the epochs the figures draw (every ``stride``-th and the last).
        curve_index: The epochs of the curves (every ``stride``-th).
        ellipse_index: ``(E,)`` the epochs of the track figure's σ ellipses.
        status: ``(N, K)`` int8 status codes (`STATUS`).
        plot: The decimated series at ``plot_index``: ``xy`` ``(N, P, 2)``, ``sigma_en``
            ``(N, P, 2)`` (east and north σ), ``major`` ``(N, P)``; with a reference
            ``error`` ``(N, P, 2)`` (estimate − reference) and ``reference`` ``(N, P,
            2)``; with the INS ``ins`` ``(N, P, 2)``.
        curves: At ``curve_index``: ``major_mean`` (the vehicles' mean 1σ major axis, m)
            and, with a reference, ``error_rms`` (the vehicles' RMS horizontal error, m).
        ellipses: At ``ellipse_index``: ``xy`` ``(N, E, 2)``, ``major``, ``minor``,
            ``azimuth`` ``(N, E)``.
        extent_lo, extent_hi: ``(2,)`` the smallest and largest finite east/north of the
            estimate and the reference over every epoch (NaN before any).
        final: The last epoch added, as a `Fix` (None before any).
        counts: The navigator's counters after the last chunk (the whole flight's).
        filled: Epochs added so far.
    """

    def __init__(self, t: torch.Tensor | np.ndarray, n_vehicles: int, *,
                 reference_xy: torch.Tensor | None = None,
                 reference_altitude: torch.Tensor | None = None,
                 ins_xy: torch.Tensor | None = None, ins_altitude: torch.Tensor | None = None,
                 n_ellipses: int = 20, plot_points: int = PLOT_POINTS) -> None:
        t_np = (_np(t) if isinstance(t, torch.Tensor) else np.asarray(t, dtype=np.float64))
        k, n = int(t_np.shape[0]), int(n_vehicles)
        if t_np.ndim != 1 or k < 1 or n < 1:
            raise ValueError(f"TrackSummary: t must be (K,) with K >= 1 and n_vehicles >= 1, "
                             f"got {t_np.shape} and {n_vehicles}.")
        if plot_points < 2:
            raise ValueError(f"TrackSummary: plot_points must be >= 2, got {plot_points}.")
        self.t, self.n_vehicles, self.n_epochs = t_np, n, k
        self.reference_xy, self.reference_altitude = reference_xy, reference_altitude
        self.ins_xy, self.ins_altitude = ins_xy, ins_altitude
        self.stride = max(1, math.ceil(k / plot_points))
        self.curve_index = np.arange(0, k, self.stride)
        self.plot_index = np.unique(np.r_[self.curve_index, k - 1])
        self.ellipse_index = np.unique(np.linspace(0, k - 1, max(2, n_ellipses)).astype(int))
        self.status = np.zeros((n, k), dtype=np.int8)
        p, e, c = self.plot_index.size, self.ellipse_index.size, self.curve_index.size
        self.plot: dict[str, np.ndarray] = {
            "xy": np.full((n, p, 2), np.nan), "sigma_en": np.full((n, p, 2), np.nan),
            "major": np.full((n, p), np.nan)}
        self.curves: dict[str, np.ndarray] = {"major_mean": np.full(c, np.nan)}
        if reference_xy is not None:
            self.plot["error"] = np.full((n, p, 2), np.nan)
            self.plot["reference"] = np.full((n, p, 2), np.nan)
            self.curves["error_rms"] = np.full(c, np.nan)
        if ins_xy is not None:
            self.plot["ins"] = np.full((n, p, 2), np.nan)
        self.ellipses: dict[str, np.ndarray] = {
            "xy": np.full((n, e, 2), np.nan), **{name: np.full((n, e), np.nan)
                                                 for name in ("major", "minor", "azimuth")}}
        self.extent_lo = np.full(2, np.nan)
        self.extent_hi = np.full(2, np.nan)
        # the exact sums of the error numbers (module docstring)
        self._h2, self._h2_tracking = _Mean(), _Mean()
        self._nees = _Mean(strict=False)
        self._inside = 0
        self._h_max = -math.inf
        self._v2, self._ins_h2, self._ins_v2 = _Mean(), _Mean(), _Mean()
        self._h_last: np.ndarray | None = None
        self._ins_h_last: np.ndarray | None = None
        self.final: Fix | None = None
        self.counts: dict[str, int] = {}
        self.filled = 0

    # ------------------------------------------------------------------ filling
    @classmethod
    def from_track(cls, track: FixTrack, *, reference_xy: torch.Tensor | None = None,
                   reference_altitude: torch.Tensor | None = None,
                   ins_xy: torch.Tensor | None = None, ins_altitude: torch.Tensor | None = None,
                   n_ellipses: int = 20, plot_points: int = PLOT_POINTS) -> TrackSummary:
        """The summary of a whole `FixTrack` (one chunk)."""
        summary = cls(track.t, int(track.xy.shape[0]), reference_xy=reference_xy,
                      reference_altitude=reference_altitude, ins_xy=ins_xy,
                      ins_altitude=ins_altitude, n_ellipses=n_ellipses,
                      plot_points=plot_points)
        summary.add(track)
        return summary

    def _extent(self, xy: np.ndarray) -> None:
        pts = xy.reshape(-1, 2)
        pts = pts[np.isfinite(pts).all(1)]
        if pts.size:
            self.extent_lo = np.fmin(self.extent_lo, pts.min(0))
            self.extent_hi = np.fmax(self.extent_hi, pts.max(0))

    def add(self, track: FixTrack) -> None:
        """Adds the next chunk of the flight (epochs ``filled .. filled + k``).

        Raises:
            ValueError: The chunk has another number of vehicles, or runs past the flight.
        """
        k, n, start = track.n_epochs, int(track.xy.shape[0]), self.filled
        if n != self.n_vehicles or start + k > self.n_epochs:
            raise ValueError(
                f"TrackSummary.add: a chunk of {n} vehicle(s) x {k} epochs after {start} "
                f"does not fit a flight of {self.n_vehicles} x {self.n_epochs}.")
        stop = start + k
        status = track.status.cpu().numpy()
        self.status[:, start:stop] = status
        cov_xy = track.cov[..., :2, :2].detach().cpu().double()
        major, minor, azimuth = sigma_ellipse(cov_xy)
        xy_t = track.xy.detach().cpu().double()
        xy = xy_t.numpy()
        self._extent(xy)
        # where the decimated series and the curves sample this chunk (local epochs)
        p_sel = (self.plot_index >= start) & (self.plot_index < stop)
        p_loc = self.plot_index[p_sel] - start
        c_sel = (self.curve_index >= start) & (self.curve_index < stop)
        c_loc = self.curve_index[c_sel] - start
        with warnings.catch_warnings():  # an epoch with no finite σ stays NaN
            warnings.simplefilter("ignore", RuntimeWarning)
            self.curves["major_mean"][c_sel] = np.nanmean(major[:, c_loc], 0)
        if self.reference_xy is not None:
            ref = self.reference_xy[:, start:stop].detach().cpu().double()
            self._extent(ref.numpy())
            err = xy_t - ref
            h = err.norm(dim=-1).numpy()  # (N, k)
            h2 = h * h
            self._h2.add(h2)
            self._h2_tracking.add(h2[status == STATUS_CODE["tracking"]])
            self._h_max = float(np.maximum(self._h_max, h.max()))
            nees_xy = nees(err, symmetrize(cov_xy)).numpy()
            self._nees.add(nees_xy)
            self._inside += int((nees_xy <= 9.0).sum())  # NaN compares False
            self._h_last = h[:, -1].copy()
            self.curves["error_rms"][c_sel] = np.sqrt(np.mean(h2[:, c_loc], 0))
            self.plot["error"][:, p_sel] = err.numpy()[:, p_loc]
            self.plot["reference"][:, p_sel] = ref.numpy()[:, p_loc]
            if self.ins_xy is not None:
                ins_h = (self.ins_xy[:, start:stop].detach().cpu().double() - ref).norm(dim=-1)
                self._ins_h2.add(ins_h * ins_h)
                self._ins_h_last = ins_h[:, -1].numpy().copy()
            if self.reference_altitude is not None:
                ref_h = self.reference_altitude[:, start:stop].detach().cpu().double()
                dv = track.altitude.detach().cpu().double() - ref_h
                self._v2.add(dv * dv)
                if self.ins_altitude is not None:
                    dv = self.ins_altitude[:, start:stop].detach().cpu().double() - ref_h
                    self._ins_v2.add(dv * dv)
        if self.ins_xy is not None:
            self.plot["ins"][:, p_sel] = _np(self.ins_xy[:, start:stop])[:, p_loc]
        var = np.diagonal(cov_xy.numpy(), axis1=-2, axis2=-1)  # (N, k, 2)
        self.plot["xy"][:, p_sel] = xy[:, p_loc]
        self.plot["sigma_en"][:, p_sel] = np.sqrt(np.clip(var[:, p_loc], 0.0, None))
        self.plot["major"][:, p_sel] = major[:, p_loc]
        e_sel = (self.ellipse_index >= start) & (self.ellipse_index < stop)
        e_loc = self.ellipse_index[e_sel] - start
        self.ellipses["xy"][:, e_sel] = xy[:, e_loc]
        for name, values in (("major", major), ("minor", minor), ("azimuth", azimuth)):
            self.ellipses[name][:, e_sel] = values[:, e_loc]
        self.final = _clone(track.fix(k - 1))
        self.counts = dict(track.counts)
        self.filled = stop

    # ------------------------------------------------------------------ reading
    @property
    def complete(self) -> bool:
        """Whether every epoch of the flight was added."""
        return self.filled == self.n_epochs

    @property
    def has_reference(self) -> bool:
        """Whether the errors against a reference are summed."""
        return self.reference_xy is not None

    @property
    def plot_t(self) -> np.ndarray:
        """``(P,)`` the times of `plot_index`."""
        return self.t[self.plot_index]

    def status_fractions(self) -> dict[str, float]:
        """Fraction of epochs (all vehicles) in each status."""
        counts = np.bincount(self.status.reshape(-1).astype(np.int64), minlength=len(STATUS))
        total = self.status.size
        return {name: float(counts[i]) / total for i, name in enumerate(STATUS)}

    def reference_errors(self) -> dict[str, Any]:
        """Errors against the reference, over every epoch.

        Returns:
            ``rmse_horizontal_m`` (all epochs), ``rmse_horizontal_tracking_m`` (epochs with
            status tracking; None without any), ``final_horizontal_error_m`` (per
            vehicle), ``max_horizontal_error_m``, ``inside_3sigma`` (the fraction of the
            epochs with a NEES whose error lies inside the 3σ ellipse: NEES_xy ≤ 9),
            ``mean_nees_xy`` (2 = consistent; the epochs whose ``P_xy`` is not positive
            definite have no NEES), the ``horizontal_error_curve`` (vehicle RMS at every
            ``horizontal_error_curve_stride``-th epoch: every epoch for a flight of at
            most ``plot_points`` epochs; navigation.csv holds each epoch's error).

        Raises:
            ValueError: The summary has no reference.
        """
        if self.reference_xy is None:
            raise ValueError("TrackSummary.reference_errors: the flight has no reference.")

        def root(mean: _Mean) -> float | None:
            value = mean.value()
            return None if value is None else math.sqrt(value)

        mean_nees = self._nees
        return {
            "rmse_horizontal_m": root(self._h2),
            "rmse_horizontal_tracking_m": root(self._h2_tracking),
            "final_horizontal_error_m": ([] if self._h_last is None
                                         else self._h_last.tolist()),
            "max_horizontal_error_m": self._h_max,
            "inside_3sigma": self._inside / mean_nees.count if mean_nees.count else None,
            "mean_nees_xy": mean_nees.value(),
            "horizontal_error_curve": self.curves["error_rms"].tolist(),
            "horizontal_error_curve_stride": self.stride,
        }

    def rmse_vertical(self) -> float | None:
        """RMS of altitude − reference altitude over every epoch (None without one)."""
        value = self._v2.value() if self.reference_altitude is not None else None
        return None if value is None else math.sqrt(value)

    def ins_errors(self) -> dict[str, Any]:
        """The INS's errors against the reference: ``rmse_horizontal_m``,
        ``final_horizontal_error_m`` (per vehicle), ``rmse_vertical_m`` (None without a
        reference altitude); every value None without the INS or a reference."""
        h2 = self._ins_h2.value() if self.ins_xy is not None else None
        v2 = (self._ins_v2.value() if self.ins_altitude is not None
              and self.reference_altitude is not None else None)
        return {"rmse_horizontal_m": None if h2 is None else math.sqrt(h2),
                "final_horizontal_error_m": (None if self._ins_h_last is None
                                             else self._ins_h_last.tolist()),
                "rmse_vertical_m": None if v2 is None else math.sqrt(v2)}
