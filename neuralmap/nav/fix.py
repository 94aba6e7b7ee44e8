"""Navigation fixes: what `Navigator` returns per epoch.

A `Fix` is one epoch for N vehicles (batch first); a `FixTrack` is K epochs
(every field with a time axis after N) plus the counters of what the navigator skipped or
re-did. The state convention is the 5-state TAN error of SEEDS 004, ``δX = [δx, δy, δh,
δv_x, δv_y]`` = INS − truth; a fix is the corrected estimate ``INS − δX̂`` and ``cov`` is
the covariance of ``δX`` (the INS reading is known, so it is also the covariance of the
estimate ``[x, y, h, v_x, v_y]``).

Status codes (index into `STATUS`):

* ``acquiring`` — the posterior is still wide (the acquisition grid holds the vehicle, or
  the tracker's horizontal σ is above the navigator's ``acquired_sigma_m``);
* ``tracking`` — locked: small posterior, updated by the altimeter;
* ``lost`` — the windowed-NIS lost-lock test fired at this epoch (the next epochs
  re-acquire: ``lost → acquiring → tracking``);
* ``off_map`` — the estimated position lies off the map: predicted only;
* ``no_measurement`` — no usable clearance (NaN, or outside the sensor's stated range, or
  a spike refused by the gate): predicted only (after a time gap longer than
  ``max_gap_s`` every vehicle restarts from the prior instead, as at the first epoch);
* ``unavailable`` — locked, but the horizontal protection level exceeds the configured
  alert limit (`neuralmap.nav.integrity`);
* ``no_map`` — the estimate lies over a void of the map's DEM (a no-data cell filled from
  its neighbours, not a measured height): the clearance is not used, predicted only.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch

__all__ = ["FIX_FIELDS", "STATUS", "STATUS_CODE", "Fix", "FixTrack", "status_names"]

#: Status names; a status code is the index into this tuple.
STATUS: tuple[str, ...] = ("acquiring", "tracking", "lost", "off_map", "no_measurement",
                           "unavailable", "no_map")

#: Status name -> code.
STATUS_CODE: dict[str, int] = {name: code for code, name in enumerate(STATUS)}


def status_names(codes: torch.Tensor) -> list:
    """Status names of a code tensor, nested like ``codes`` (``(N,)`` -> list of str)."""
    values = codes.tolist()
    if isinstance(values, int):
        return STATUS[values]  # type: ignore[return-value]

    def name(v):
        return [name(u) for u in v] if isinstance(v, list) else STATUS[int(v)]

    return name(values)


@dataclass
class Fix:
    """One navigation epoch for N vehicles.

    Attributes:
        t: ``(N,)`` epoch time, s.
        xy: ``(N, 2)`` estimated position in the map frame (east, north), m.
        altitude: ``(N,)`` estimated altitude, m (the datum of the INS altitude input).
        velocity: ``(N, 2)`` estimated horizontal velocity, m/s: the INS velocity from
            successive INS positions minus ``δv̂`` (NaN at the first epoch).
        cov: ``(N, 5, 5)`` covariance of ``[x, y, h, v_x, v_y]``.
        status: ``(N,)`` int64 code, index into `STATUS`.
        hpl: ``(N,)`` horizontal protection level at the configured integrity risk, m.
        vpl: ``(N,)`` vertical protection level, m.
        nis: ``(N,)`` NIS of this epoch's update (NaN where none; a refused spike's
            predictive NIS).
        mean_nis: ``(N,)`` mean NIS over the navigator's lost-lock window (NaN until the
            first measurement update).
        innovation: ``(N,)`` this epoch's measurement residual, m (NaN where none).
        updated: ``(N,)`` bool, the altimeter updated the vehicle at this epoch.
        correction: ``(N, 5)`` the estimated INS error ``δX̂`` (INS − estimate): the
            correction applied to the INS.
        healthy: ``(N,)`` bool, the filter is numerically healthy.
        lat: ``(N,)`` WGS-84 latitude, deg, when the navigator has a map frame, else None.
        lon: ``(N,)`` longitude, deg, or None.
        hpl_extra: ``(N, R)`` horizontal protection levels at the config's
            ``integrity.report_risks``, or None when it names none.
        vpl_extra: ``(N, R)`` vertical ones, or None.
    """

    t: torch.Tensor
    xy: torch.Tensor
    altitude: torch.Tensor
    velocity: torch.Tensor
    cov: torch.Tensor
    status: torch.Tensor
    hpl: torch.Tensor
    vpl: torch.Tensor
    nis: torch.Tensor
    mean_nis: torch.Tensor
    innovation: torch.Tensor
    updated: torch.Tensor
    correction: torch.Tensor
    healthy: torch.Tensor
    lat: torch.Tensor | None = None
    lon: torch.Tensor | None = None
    hpl_extra: torch.Tensor | None = None
    vpl_extra: torch.Tensor | None = None

    @property
    def n_vehicles(self) -> int:
        """Number of vehicles N."""
        return int(self.xy.shape[0])

    def status_names(self) -> list[str]:
        """``N`` status names (`STATUS`)."""
        return status_names(self.status)

    def sigma_xy(self) -> torch.Tensor:
        """``(N, 2)`` horizontal standard deviations (east, north), m."""
        return torch.diagonal(self.cov[:, :2, :2], dim1=1, dim2=2).clamp_min(0.0).sqrt()


#: The per-epoch fields of a `Fix` (and of a `FixTrack`, with a time axis).
FIX_FIELDS: tuple[str, ...] = ("t", "xy", "altitude", "velocity", "cov", "status", "hpl", "vpl",
                               "nis", "mean_nis", "innovation", "updated", "correction",
                               "healthy", "lat", "lon", "hpl_extra", "vpl_extra")


@dataclass
class FixTrack:
    """K epochs of N vehicles (`Navigator.replay`).

    Attributes:
        t: ``(K,)`` epoch times, s.
        xy: ``(N, K, 2)``; altitude ``(N, K)``; velocity ``(N, K, 2)``; cov ``(N, K, 5, 5)``;
            status ``(N, K)`` int64; hpl, vpl, nis, mean_nis, innovation, updated, healthy
            ``(N, K)``; correction ``(N, K, 5)``; lat, lon ``(N, K)`` or None; hpl_extra,
            vpl_extra ``(N, K, R)`` or None — as `Fix`, with the time axis after N.
        counts: What the navigator counted over the replay (summed over vehicles):
            ``missing_radar`` (NaN clearances), ``out_of_range`` (clearances outside the
            sensor's range), ``spikes`` (clearances the tracker's spike gate left out), ``gaps`` (intervals longer than the nominal period, up to
            ``max_gap_s``, predicted across), ``long_gaps`` (intervals beyond
            ``max_gap_s``), ``off_map_epochs``, ``lost`` (lost-lock detections),
            ``reacquisitions`` (re-acquisitions from the open-loop prior), ``handoffs``
            (acquisition grid → tracking filter), ``updates``, ``cell_updates``.
        vehicle_counts: The per-vehicle counters ``(N,)`` behind ``counts``, and
            ``first_handoff`` (the epoch of each vehicle's first hand-off, −1 = none).
    """

    t: torch.Tensor
    xy: torch.Tensor
    altitude: torch.Tensor
    velocity: torch.Tensor
    cov: torch.Tensor
    status: torch.Tensor
    hpl: torch.Tensor
    vpl: torch.Tensor
    nis: torch.Tensor
    mean_nis: torch.Tensor
    innovation: torch.Tensor
    updated: torch.Tensor
    correction: torch.Tensor
    healthy: torch.Tensor
    lat: torch.Tensor | None = None
    lon: torch.Tensor | None = None
    hpl_extra: torch.Tensor | None = None
    vpl_extra: torch.Tensor | None = None
    counts: dict[str, int] = field(default_factory=dict)
    vehicle_counts: dict[str, torch.Tensor] = field(default_factory=dict)

    @property
    def n_epochs(self) -> int:
        """Number of epochs K."""
        return int(self.t.shape[0])

    def fix(self, k: int) -> Fix:
        """Epoch ``k`` as a `Fix` (views, no copies)."""
        n = self.xy.shape[0]
        per_epoch = {name: getattr(self, name)[:, k] for name in FIX_FIELDS
                     if name != "t" and getattr(self, name) is not None}
        return Fix(t=self.t[k].expand(n), **per_epoch)

    @classmethod
    def empty_like(cls, fix: Fix, k: int) -> FixTrack:
        """A track of ``k`` epochs with the shapes, dtypes and device of ``fix`` (to fill
        with `FixTrack.put`)."""
        fields_ = {name: torch.empty((value.shape[0], k, *value.shape[1:]), dtype=value.dtype,
                                     device=value.device)
                   for name in FIX_FIELDS if name != "t"
                   and (value := getattr(fix, name)) is not None}
        return cls(t=torch.empty(k, dtype=fix.t.dtype, device=fix.t.device), **fields_)

    def put(self, k: int, fix: Fix) -> None:
        """Writes ``fix`` as epoch ``k``."""
        self.t[k] = fix.t[0]
        for name in FIX_FIELDS:
            value = getattr(fix, name)
            if name != "t" and value is not None:
                getattr(self, name)[:, k] = value

    def status_names(self) -> list[list[str]]:
        """``N × K`` status names."""
        return status_names(self.status)
