"""A batch of flights for learning: INS track and radar-altimeter clearance, padded and masked.

Flights of different lengths are padded to the longest one; `FlightBatch.valid`
marks the real samples. NaN altimeter samples (loss of lock, dropped records) are kept as
NaN in `radar` and counted (`FlightBatch.n_missing`); the learning filters skip
their update (predict only), exactly like a padded step, so they neither contribute to the
likelihood nor put NaN into a gradient.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import torch

from neuralmap.exceptions import NeuralMapError

__all__ = ["FlightBatch"]


@dataclass
class FlightBatch:
    """N flights of up to K + 1 samples (sample 0 = the prior, no update).

    Attributes:
        dt: Sample period T, s.
        ins_pos: ``(N, K+1, 3)`` INS ``x, y, h`` in the map frame, m (padding: last sample).
        radar: ``(N, K+1)`` radar-altimeter clearance, m (NaN = no measurement).
        valid: ``(N, K+1)`` bool, the sample exists (False = padding after the flight end).
        ins_error: ``(N, K+1, 5)`` the true INS error when known (simulation), else None.
        pos: ``(N, K+1, 3)`` the true position when known (simulation), else None.
    """

    dt: float
    ins_pos: torch.Tensor
    radar: torch.Tensor
    valid: torch.Tensor
    ins_error: torch.Tensor | None = None
    pos: torch.Tensor | None = None

    def __post_init__(self) -> None:
        n = self.ins_pos.shape[0] if self.ins_pos.ndim == 3 else -1
        if self.ins_pos.ndim != 3 or self.ins_pos.shape[2] != 3:
            raise NeuralMapError(
                f"FlightBatch: ins_pos must be (N, K+1, 3), got {tuple(self.ins_pos.shape)}.")
        k1 = self.ins_pos.shape[1]
        if self.radar.shape != (n, k1) or self.valid.shape != (n, k1):
            raise NeuralMapError(
                f"FlightBatch: radar and valid must be ({n}, {k1}) like ins_pos, got "
                f"{tuple(self.radar.shape)} and {tuple(self.valid.shape)}.")
        if not bool(torch.isfinite(self.ins_pos[self.valid]).all()):
            raise NeuralMapError(
                "FlightBatch: the INS track has NaN/inf entries inside a flight; the filter "
                "cannot predict without the INS. Cut the flight there (shorter length).")
        if not self.dt > 0:
            raise NeuralMapError(f"FlightBatch: dt must be > 0 s, got {self.dt!r}.")

    @property
    def n_flights(self) -> int:
        """Number of flights N."""
        return int(self.ins_pos.shape[0])

    @property
    def n_steps(self) -> int:
        """Longest flight's number of steps K."""
        return int(self.ins_pos.shape[1]) - 1

    @property
    def lengths(self) -> torch.Tensor:
        """``(N,)`` samples per flight."""
        return self.valid.sum(dim=1)

    @property
    def measured(self) -> torch.Tensor:
        """``(N, K+1)`` bool: a real sample with a finite altimeter reading."""
        return self.valid & torch.isfinite(self.radar)

    @property
    def n_missing(self) -> int:
        """Real samples (excluding sample 0) whose altimeter reading is NaN (skipped)."""
        return int((self.valid[:, 1:] & ~torch.isfinite(self.radar[:, 1:])).sum())

    @property
    def n_padded(self) -> int:
        """Padding samples (after the end of shorter flights)."""
        return int((~self.valid).sum())

    def to(self, dtype: torch.dtype | None = None, device: Any = None) -> FlightBatch:
        """A copy cast to ``dtype`` / moved to ``device``."""
        def cast(t: torch.Tensor | None) -> torch.Tensor | None:
            return None if t is None else t.to(device=device, dtype=dtype)

        return FlightBatch(self.dt, cast(self.ins_pos), cast(self.radar),  # type: ignore[arg-type]
                           self.valid.to(device), cast(self.ins_error), cast(self.pos))

    def subset(self, index: torch.Tensor | slice) -> FlightBatch:
        """The flights ``index`` (a slice or index tensor)."""
        def pick(t: torch.Tensor | None) -> torch.Tensor | None:
            return None if t is None else t[index]

        return FlightBatch(self.dt, self.ins_pos[index], self.radar[index], self.valid[index],
                           pick(self.ins_error), pick(self.pos))

    @classmethod
    def from_truth(cls, truth: Any) -> FlightBatch:
        """The flights of a simulated `Truth` (all full length)."""
        valid = torch.ones(truth.radar.shape, dtype=torch.bool, device=truth.radar.device)
        return cls(float(truth.scenario.dt), truth.ins_pos, truth.radar, valid,
                   truth.ins_error, truth.pos)

    @classmethod
    def from_sequences(cls, dt: float, ins_pos: Sequence[torch.Tensor],
                       radar: Sequence[torch.Tensor]) -> FlightBatch:
        """Pads flights of different lengths into one batch.

        Args:
            dt: Sample period, s.
            ins_pos: Per flight a ``(K_i + 1, 3)`` INS track.
            radar: Per flight a ``(K_i + 1,)`` clearance (NaN = missing).

        Raises:
            NeuralMapError: No flights, mismatched lengths, a flight with fewer than 2 samples.
        """
        if len(ins_pos) == 0 or len(ins_pos) != len(radar):
            raise NeuralMapError(
                f"FlightBatch.from_sequences: need as many INS tracks as radar series (>= 1), "
                f"got {len(ins_pos)} and {len(radar)}.")
        longest = 0
        for i, (p, r) in enumerate(zip(ins_pos, radar, strict=True)):
            if p.ndim != 2 or p.shape[1] != 3 or r.shape != (p.shape[0],) or p.shape[0] < 2:
                raise NeuralMapError(
                    f"FlightBatch.from_sequences: flight {i} must have an INS track (K+1, 3) "
                    f"and a radar series (K+1,) with K+1 >= 2, got {tuple(p.shape)} and "
                    f"{tuple(r.shape)}.")
            longest = max(longest, p.shape[0])
        n = len(ins_pos)
        dtype = ins_pos[0].dtype
        pos = torch.zeros(n, longest, 3, dtype=dtype)
        rad = torch.full((n, longest), float("nan"), dtype=dtype)
        valid = torch.zeros(n, longest, dtype=torch.bool)
        for i, (p, r) in enumerate(zip(ins_pos, radar, strict=True)):
            k = p.shape[0]
            pos[i, :k] = p
            pos[i, k:] = p[-1]  # padding: hold the last INS sample (never updated)
            rad[i, :k] = r
            valid[i, :k] = True
        return cls(float(dt), pos, rad, valid)
