"""GNSS epochs on the IMU time line: the IMU interval split at the GNSS time (as KF-GINS).

A GNSS solution is valid at its own epoch ``t_g``, which a real log rarely puts on an IMU
record: at 200 Hz the nearest record is up to 2.5 ms away, 5 cm at 20 m/s. KF-GINS splits the
IMU interval ``(t_{k−1}, t_k]`` that holds ``t_g`` into ``(t_{k−1}, t_g]`` and
``(t_g, t_k]``, each with its share of the increments (``Δθ·f`` and ``Δθ·(1 − f)``,
``f = (t_g − t_{k−1}) / (t_k − t_{k−1})``: the same constant rate over both parts),
mechanises to ``t_g``, updates there and mechanises on to ``t_k``. `split_at_epochs`
builds that time line once for a whole log: the IMU records plus one inserted record per
GNSS epoch that is not on a record (within ``align_s``), every interval's increment shared
out by time. An interval without an epoch keeps its increment exactly (``f = 1``).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from neuralmap.exceptions import NeuralMapError

__all__ = ["ALIGN_S", "EpochTimeline", "split_at_epochs"]

#: A GNSS epoch this close to an IMU record (s) updates at the record (no split).
ALIGN_S = 1.0e-6


@dataclass(frozen=True)
class EpochTimeline:
    """IMU records with the GNSS epochs inserted.

    Attributes:
        time: ``(K',)`` record times (s): the K IMU records and the inserted epochs.
        dtheta, dvel: ``(K', 3)`` increments over each record's interval (shared out by
            time where an interval was split).
        real: ``(K',)`` bool, True at the K IMU records (False at inserted epochs).
        epoch_record: ``(M',)`` record index (into ``time``) of each used GNSS epoch.
        epoch_index: ``(M',)`` index of that epoch in the GNSS log.
        n_split: Epochs inserted between IMU records.
    """

    time: np.ndarray
    dtheta: np.ndarray
    dvel: np.ndarray
    real: np.ndarray
    epoch_record: np.ndarray
    epoch_index: np.ndarray
    n_split: int


def split_at_epochs(time: np.ndarray, dtheta: np.ndarray, dvel: np.ndarray,
                    epochs: np.ndarray, *, align_s: float = ALIGN_S) -> EpochTimeline:
    """Inserts the GNSS epochs into the IMU time line, splitting the intervals that hold them.

    Args:
        time: ``(K,)`` IMU record times (end of each increment interval), increasing.
        dtheta, dvel: ``(K, 3)`` increments (the first record's is kept as it is).
        epochs: ``(M,)`` GNSS epoch times, increasing.
        align_s: An epoch within this of a record updates at the record.

    Returns:
        `EpochTimeline`; epochs before the first or after the last record (beyond
        ``align_s``) are left out.

    Raises:
        NeuralMapError: Two GNSS epochs on one IMU record.
    """
    time = np.asarray(time, dtype=np.float64)
    epochs = np.asarray(epochs, dtype=np.float64)
    inside = (epochs >= time[0] - align_s) & (epochs <= time[-1] + align_s)
    index = np.nonzero(inside)[0]
    t_g = epochs[index]
    right = np.clip(np.searchsorted(time, t_g), 1, time.size - 1)
    near = np.where(np.abs(time[right] - t_g) < np.abs(t_g - time[right - 1]), right, right - 1)
    on_record = np.abs(time[near] - t_g) <= align_s
    hit = near[on_record]
    if np.unique(hit).size != hit.size:
        k = int(hit[np.nonzero(np.diff(hit) == 0)[0][0]])
        raise NeuralMapError(
            f"run_on_log: two GNSS epochs fall on the IMU record at {float(time[k]):.6f} s; "
            "the GNSS rate must be below the IMU rate (thin the GNSS file)."
        )
    n_imu = time.size
    inserted = t_g[~on_record]
    all_time = np.concatenate([time, inserted])
    order = np.argsort(all_time, kind="stable")
    new_time = all_time[order]
    real = order < n_imu
    # the IMU interval (t_{k−1}, t_k] of each record: k itself for an IMU record, the next
    # IMU record for an inserted epoch
    k = np.searchsorted(time, new_time, side="left")
    fraction = np.ones(new_time.size)
    fraction[1:] = np.diff(new_time) / (time[k[1:]] - time[k[1:] - 1])
    new_dtheta = np.asarray(dtheta, dtype=np.float64)[k] * fraction[:, None]
    new_dvel = np.asarray(dvel, dtype=np.float64)[k] * fraction[:, None]
    position = np.empty(all_time.size, dtype=np.int64)
    position[order] = np.arange(all_time.size)
    record = np.empty(t_g.size, dtype=np.int64)
    record[on_record] = position[near[on_record]]
    record[~on_record] = position[n_imu + np.arange(inserted.size)]
    return EpochTimeline(time=new_time, dtheta=new_dtheta, dvel=new_dvel, real=real,
                         epoch_record=record, epoch_index=index, n_split=int(inserted.size))
