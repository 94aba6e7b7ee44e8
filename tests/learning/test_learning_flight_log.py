"""The CSV/NPZ flight-log format: round trip, different lengths, bad files."""

from __future__ import annotations

from pathlib import Path

import numpy as np
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


def _good_csv() -> str:
    return "time,ins_x,ins_y,ins_h,radar\n0,1,2,3,4\n1,1,2,3,4\n2,1,2,3,4\n"


def test_csv_with_a_byte_order_mark_reads_like_without(tmp_path: Path) -> None:
    """Excel writes UTF-8 with a BOM; its first column is still 'time' (was: bad time step)."""
    plain, bom = tmp_path / "plain.csv", tmp_path / "bom.csv"
    plain.write_text(_good_csv(), encoding="utf-8")
    bom.write_text(_good_csv(), encoding="utf-8-sig")
    a, b = read_flight_log(plain), read_flight_log(bom)
    assert b.dt == a.dt == 1.0
    torch.testing.assert_close(b.ins_pos, a.ins_pos, rtol=0, atol=0)


def test_csv_that_is_not_utf8_is_a_clear_error(tmp_path: Path) -> None:
    path = tmp_path / "latin1.csv"
    path.write_bytes(_good_csv().replace("radar", "radar_\xe9").encode("latin-1"))
    with pytest.raises(NeuralMapError, match="not UTF-8 text.*save the flight log as UTF-8"):
        read_flight_log(path)


@pytest.mark.parametrize("case", ["object", "2d", "text", "not_a_zip"])
def test_npz_with_bad_columns_is_a_clear_error(tmp_path: Path, case: str) -> None:
    path = tmp_path / "log.npz"
    cols = {c: np.arange(4, dtype=float) for c in ("time", "ins_x", "ins_y", "ins_h", "radar")}
    expect = {"object": "Python objects", "2d": "has shape", "text": "not numbers",
              "not_a_zip": "not a readable .npz"}[case]
    if case == "object":
        cols["radar"] = np.array([1.0, None, 2.0, 3.0], dtype=object)
    elif case == "2d":
        cols["ins_x"] = np.zeros((4, 2))
    elif case == "text":
        cols["ins_h"] = np.array(["a", "b", "c", "d"])
    if case == "not_a_zip":
        path.write_text("time,ins_x\n")
    else:
        np.savez(path, **cols)
    with pytest.raises(NeuralMapError, match=expect):
        read_flight_log(path)
