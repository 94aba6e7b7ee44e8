"""The CSV/NPZ flight-log format: round trip, different lengths, bad files."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.learning.flight_log import read_flight_log, write_flight_log
from neuralmap.learning.flights import FlightBatch


def _flights() -> FlightBatch:
    gen = torch.Generator().manual_seed(0)
    tracks = [torch.randn(n, 3, generator=gen, dtype=torch.float64) * 100 for n in (6, 4)]
    radar = [torch.randn(n, generator=gen, dtype=torch.float64) for n in (6, 4)]
    radar[0][2] = float("nan")
    return FlightBatch.from_sequences(0.5, tracks, radar)


@pytest.mark.parametrize("suffix", [".csv", ".npz"])
def test_round_trip_keeps_lengths_nan_and_values(tmp_path: Path, suffix: str) -> None:
    flights = _flights()
    back = read_flight_log(write_flight_log(tmp_path / f"log{suffix}", flights))
    assert back.dt == 0.5 and back.lengths.tolist() == [6, 4] and back.n_missing == 1
    torch.testing.assert_close(back.ins_pos[back.valid], flights.ins_pos[flights.valid])
    same = torch.isfinite(flights.radar) & flights.valid
    torch.testing.assert_close(back.radar[same], flights.radar[same])


def test_missing_columns_and_bad_rows_are_clear_errors(tmp_path: Path) -> None:
    path = tmp_path / "bad.csv"
    path.write_text("time,ins_x,ins_y,radar\n0,1,2,3\n1,1,2,3\n")
    with pytest.raises(NeuralMapError, match=r"lacks column\(s\) \['ins_h'\]"):
        read_flight_log(path)
    path.write_text("time,ins_x,ins_y,ins_h,radar\n0,1,2,3,4\n1,1,,3,4\n")
    with pytest.raises(NeuralMapError, match="'ins_y' has 1 NaN"):
        read_flight_log(path)
    path.write_text("time,ins_x,ins_y,ins_h,radar\n0,1,2,3,4\n1,1,2,3,4\n3,1,2,3,4\n")
    with pytest.raises(NeuralMapError, match="constant step"):
        read_flight_log(path)
    with pytest.raises(NeuralMapError, match="csv or .npz"):
        read_flight_log(tmp_path.joinpath("x.txt").resolve() if (tmp_path / "x.txt").write_text("a")
                        else path)
    with pytest.raises(NeuralMapError, match="no such file"):
        read_flight_log(tmp_path / "none.csv")
