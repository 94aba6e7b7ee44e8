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
  the vehicle is past a time gap longer than ``max_gap_s``): predicted only.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch

__all__ = ["STATUS", "STATUS_CODE", "Fix", "FixTrack", "status_names"]

#: Status names; a status code is the index into this tuple.
STATUS: tuple[str, ...] = ("acquiring", "tracking", "lost", "off_map", "no_measurement")

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
        nis: ``(N,)`` mean NIS over the navigator's lost-lock window (NaN until the first
            measurement update).
        lat: ``(N,)`` WGS-84 latitude, deg, when the navigator has a map frame, else None.
        lon: ``(N,)`` longitude, deg, or None.
    """

    t: torch.Tensor
    xy: torch.Tensor
    altitude: torch.Tensor
    velocity: torch.Tensor
    cov: torch.Tensor
    status: torch.Tensor
    nis: torch.Tensor
    lat: torch.Tensor | None = None
    lon: torch.Tensor | None = None

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


@dataclass
class FixTrack:
    """K epochs of N vehicles (`Navigator.replay`).

    Attributes:
        t: ``(K,)`` epoch times, s.
        xy: ``(N, K, 2)``; altitude ``(N, K)``; velocity ``(N, K, 2)``; cov ``(N, K, 5, 5)``;
            status ``(N, K)`` int64; nis ``(N, K)``; lat, lon ``(N, K)`` or None — as
            `Fix`, with the time axis after N.
        counts: What the navigator counted over the replay (summed over vehicles):
            ``missing_radar`` (NaN clearances), ``out_of_range`` (clearances outside the
            sensor's range), ``spikes`` (clearances the tracker's spike gate left out), ``gaps`` (intervals longer than the nominal period, up to
            ``max_gap_s``, predicted across), ``long_gaps`` (intervals beyond
            ``max_gap_s``), ``off_map_epochs``, ``lost`` (lost-lock detections),
            ``reacquisitions`` (re-acquisitions from the open-loop prior), ``handoffs``
            (acquisition grid → tracking filter).
    """

    t: torch.Tensor
    xy: torch.Tensor
    altitude: torch.Tensor
    velocity: torch.Tensor
    cov: torch.Tensor
    status: torch.Tensor
    nis: torch.Tensor
    lat: torch.Tensor | None = None
    lon: torch.Tensor | None = None
    counts: dict[str, int] = field(default_factory=dict)

    @property
    def n_epochs(self) -> int:
        """Number of epochs K."""
        return int(self.t.shape[0])

    def fix(self, k: int) -> Fix:
        """Epoch ``k`` as a `Fix` (views, no copies)."""
        n = self.xy.shape[0]
        return Fix(t=self.t[k].expand(n), xy=self.xy[:, k], altitude=self.altitude[:, k],
                   velocity=self.velocity[:, k], cov=self.cov[:, k], status=self.status[:, k],
                   nis=self.nis[:, k],
                   lat=None if self.lat is None else self.lat[:, k],
                   lon=None if self.lon is None else self.lon[:, k])

    def status_names(self) -> list[list[str]]:
        """``N × K`` status names."""
        return status_names(self.status)

    @staticmethod
    def stack(fixes: list[Fix], counts: dict[str, int] | None = None) -> FixTrack:
        """Stacks per-epoch fixes (all of the same N) along a new time axis."""
        if not fixes:
            raise ValueError("FixTrack.stack: no fixes.")
        has_geo = fixes[0].lat is not None

        def along(name: str) -> torch.Tensor:
            return torch.stack([getattr(f, name) for f in fixes], 1)

        return FixTrack(t=torch.stack([f.t[0] for f in fixes]), xy=along("xy"),
                        altitude=along("altitude"), velocity=along("velocity"),
                        cov=along("cov"), status=along("status"), nis=along("nis"),
                        lat=along("lat") if has_geo else None,
                        lon=along("lon") if has_geo else None, counts=dict(counts or {}))
