"""A flight input whose per-epoch arrays live in a memory-mapped temporary file.

A log of a million epochs holds about 72 MB of per-epoch arrays (time, INS position and
altitude, clearance, reference), which a navigated flight would keep resident from the
first epoch to the last figure. `map_flight` moves them into one anonymous temporary file
(in the run's folder, on disk; the system removes it when it is closed, also after a
crash) mapped into memory: the tensors read the same values as before (the file is written with
ordinary writes, so a full disk is an ``OSError`` there, and mapped copy-on-write: nothing
writes the arrays of a flight input), the replay pages in each chunk's epochs as it reads
them, and `MappedFlight.release` hands a replayed chunk's pages back to the system
(``madvise(MADV_DONTNEED)``: the file keeps the values, a later read pages them in
again). The process's resident memory then holds one chunk of
the log at a time instead of all of it; the pages may stay in the system's page cache,
which the kernel reclaims when memory is short.

Where the platform has no ``madvise`` (Windows), `release` does nothing: the values are
still read from the file, and stay resident once read.
"""

from __future__ import annotations

import dataclasses
import mmap
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
import torch

__all__ = ["MappedFlight", "map_flight"]

#: `FlightInput` fields with one entry per epoch (time axis after the vehicles, or first).
_PER_EPOCH = ("t", "ins_position", "ins_altitude", "clearance", "reference_position",
              "reference_altitude", "lines")


class MappedFlight:
    """The memory-mapped file behind a flight input's per-epoch arrays (`map_flight`).

    Args:
        folder: Where the temporary file lives (None: the system's temporary folder).
        arrays: Name → ``(K, ...)`` or ``(N, K, ...)`` array (tensor or numpy) to map.
        n_epochs: K.

    Attributes:
        arrays: Name → the mapped copy (a tensor for a tensor, a numpy array for one).
    """

    def __init__(self, folder: str | Path | None, arrays: dict[str, Any], n_epochs: int
                 ) -> None:
        self.n_epochs = int(n_epochs)
        layout, total = [], 0
        for name, value in arrays.items():
            a = value.detach().cpu().numpy() if isinstance(value, torch.Tensor) else value
            a = np.ascontiguousarray(a)
            total = -(-total // 64) * 64  # 64-byte aligned
            layout.append((name, a, total, isinstance(value, torch.Tensor)))
            total += a.nbytes
        # written through the file (a full disk is an OSError here, not a fault on a page
        # later), then mapped copy-on-write: reads come from the file; nothing writes them
        self._file = tempfile.TemporaryFile(dir=folder)
        for _, a, offset, _ in layout:
            self._file.seek(offset)
            self._file.write(memoryview(a).cast("B"))
        self._file.truncate(max(total, 1))
        self._file.flush()
        self._map = mmap.mmap(self._file.fileno(), max(total, 1), access=mmap.ACCESS_COPY)
        self.arrays: dict[str, Any] = {}
        self._spans: list[tuple[int, int, int]] = []  # (offset, vehicles, bytes per epoch)
        for name, a, offset, is_tensor in layout:
            mapped = np.ndarray(a.shape, dtype=a.dtype, buffer=self._map, offset=offset)
            self.arrays[name] = torch.from_numpy(mapped) if is_tensor else mapped
            vehicles = 1 if name in ("t", "lines") else a.shape[0]
            self._spans.append((offset, vehicles,
                                a.nbytes // max(vehicles * self.n_epochs, 1)))

    def _release(self, span: tuple[int, int, int], start: int, stop: int) -> None:
        advise = getattr(self._map, "madvise", None)
        dontneed = getattr(mmap, "MADV_DONTNEED", None)
        if advise is None or dontneed is None:
            return
        offset, vehicles, row = span
        page = mmap.PAGESIZE
        for n in range(vehicles):
            base = offset + n * self.n_epochs * row
            lo = -(-(base + start * row) // page) * page  # whole pages inside the range
            hi = (base + stop * row) // page * page
            if hi > lo:
                advise(dontneed, lo, hi - lo)

    def release(self, start: int = 0, stop: int | None = None) -> None:
        """Hands the resident pages of epochs ``start .. stop`` back to the system (their
        values stay in the file)."""
        stop = self.n_epochs if stop is None else stop
        for span in self._spans:
            self._release(span, start, stop)


def map_flight(flight: Any, folder: str | Path | None = None) -> tuple[Any, MappedFlight]:
    """A copy of ``flight`` (`FlightInput`) whose per-epoch arrays are memory-mapped
    (module docstring); the original's arrays can then be dropped.

    Args:
        flight: The flight input.
        folder: Where the temporary file lives (None: the system's temporary folder).

    Returns:
        ``(mapped flight, its MappedFlight)``: release a replayed chunk's pages with
        ``MappedFlight.release(start, stop)``.
    """
    arrays = {name: getattr(flight, name) for name in _PER_EPOCH
              if getattr(flight, name) is not None}
    mapped = MappedFlight(folder, arrays, flight.n_epochs)
    return dataclasses.replace(flight, **mapped.arrays), mapped
