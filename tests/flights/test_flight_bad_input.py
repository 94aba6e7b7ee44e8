"""Bad input on the flight surfaces: every case gives the right result or one ``error:``
line (what, where, how to fix), exit 2, nothing written — logs, time bases, gaps, voids of
the map, the antimeridian, options, the output folder."""

from __future__ import annotations

import csv
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from neuralmap import Navigator
from neuralmap.exceptions import NeuralMapError
from neuralmap.flights.cli import main
from neuralmap.flights.flight_input import read_flight_input
from neuralmap.nav.fix import STATUS_CODE

COLUMNS = ["time", "ins_x", "ins_y", "ins_h", "radar"]


@pytest.fixture(scope="module")
def flight():  # noqa: ANN201
    """Two simulated vehicles of the tiny scenario over the embedded synthetic tile."""
    from neuralmap.lab.scenario import load_scenario
    from neuralmap.lab.simulator import simulate
    from neuralmap.nav.map_source import resolve_map

    source = resolve_map("synthetic")
    truth = simulate(load_scenario("tiny"), source.tile, n_runs=2, seed=4)
    return source, truth


def _rows(truth, n: int = 1, time_scale: float = 1.0, time_offset: float = 0.0):  # noqa: ANN001, ANN202
    for k in range(truth.t.shape[0]):
        yield [repr(float(truth.t[k]) * time_scale + time_offset)] + [
            repr(float(v)) for v in truth.ins_pos[n, k]] + [repr(float(truth.radar[n, k]))]


def _write(path: Path, header: list[str], rows) -> Path:  # noqa: ANN001
    with path.open("w", newline="") as handle:
        w = csv.writer(handle)
        w.writerow(header)
        w.writerows(rows)
    return path


def _navigate(capsys, log: Path, out: Path, *extra: str) -> tuple[int, str]:  # noqa: ANN001
    code = main([str(log), "--map", "synthetic", "--out", str(out), "--no_datum_check",
                 "--tensorboard", "false", "--progress", "false", *extra])
    return code, capsys.readouterr().err


def _one_error(code: int, err: str, *needles: str) -> None:
    assert code == 2, err
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and "error:" in lines[0], err
    for needle in needles:
        assert needle in lines[0], (needle, lines[0])


def test_a_column_given_twice_is_refused_with_its_name(flight, tmp_path, capsys) -> None:  # noqa: ANN001
    _, truth = flight
    log = _write(tmp_path / "dup.csv", [*COLUMNS, "ins_x"],
                 (r + [r[1]] for r in _rows(truth)))
    code, err = _navigate(capsys, log, tmp_path / "out")
    _one_error(code, err, "'ins_x' appears twice", "line 1")
    assert not (tmp_path / "out").exists() or not any((tmp_path / "out").iterdir())


def test_interleaved_flights_name_the_first_offending_line(flight, tmp_path, capsys) -> None:  # noqa: ANN001
    _, truth = flight
    a, b = list(_rows(truth, 0)), list(_rows(truth, 1))
    rows = [["A", *a[0]], ["B", *b[0]], ["A", *a[1]]] + [["B", *r] for r in b[1:]]
    log = _write(tmp_path / "mixed.csv", ["flight", *COLUMNS], rows)
    code, err = _navigate(capsys, log, tmp_path / "out")
    _one_error(code, err, "flight 'A' starts again", "line 4", "line 2", "sort the log")
    assert len(err) < 400


def test_a_2d_column_in_an_npz_is_refused(tmp_path, capsys) -> None:  # noqa: ANN001
    log = tmp_path / "geo.npz"
    np.savez(log, time=np.arange(5.0), lat=np.zeros((5, 2)), lon=np.zeros(5),
             alt=np.zeros(5), radar=np.ones(5))
    code, err = _navigate(capsys, log, tmp_path / "out")
    _one_error(code, err, "'lat' has shape (5, 2)", "1-D")


@pytest.mark.parametrize("scale,unit", [(1000.0, "milliseconds"), (1.0 / 60.0, "minutes")])
def test_a_time_base_that_is_not_seconds_is_refused(flight, tmp_path, capsys, scale,  # noqa: ANN001
                                                    unit) -> None:
    _, truth = flight
    log = _write(tmp_path / "t.csv", COLUMNS, _rows(truth, time_scale=scale))
    code, err = _navigate(capsys, log, tmp_path / "out")
    _one_error(code, err, "column 'time'", unit, "sensor.dt_s")


def test_unix_time_navigates_in_float32(flight, tmp_path) -> None:  # noqa: ANN001
    source, truth = flight
    relative = _write(tmp_path / "rel.csv", COLUMNS, _rows(truth))
    unix = _write(tmp_path / "unix.csv", COLUMNS, _rows(truth, time_offset=1_700_001_024.0))
    a = read_flight_input(relative, extent=source.extent, dtype=torch.float32)
    b = read_flight_input(unix, extent=source.extent, dtype=torch.float32)
    assert b.t.dtype == torch.float64 and bool((b.t.diff() > 0).all())
    ta = Navigator(source.terrain, None, n_vehicles=1).replay(
        a.t, a.ins_position, a.ins_altitude, a.clearance)
    tb = Navigator(source.terrain, None, n_vehicles=1).replay(
        b.t, b.ins_position, b.ins_altitude, b.clearance)
    torch.testing.assert_close(ta.xy, tb.xy)


def test_a_long_gap_restarts_acquisition_from_the_ins_prior(flight) -> None:  # noqa: ANN001
    source, truth = flight
    t = truth.t.clone()
    t[20:] += 3600.0  # an hour without records
    nav = Navigator(source.terrain, {"integrity": {"spike_gate_prob": 0.0}}, n_vehicles=2)
    track = nav.replay(t, truth.ins_pos[..., :2], truth.ins_pos[..., 2], truth.radar)
    assert track.counts["long_gaps"] == 2
    # at the restart the fix is the INS and its covariance the prior: not kilometres off
    torch.testing.assert_close(track.xy[:, 20], truth.ins_pos[:, 20, :2])
    torch.testing.assert_close(track.cov[:, 20], nav.model.filter_prior().expand(2, 5, 5))
    err = (track.xy[:, -1] - truth.pos[:, -1, :2]).norm(dim=-1)
    ins_err = (truth.ins_pos[:, -1, :2] - truth.pos[:, -1, :2]).norm(dim=-1)
    assert bool((err < ins_err + 50.0).all()), (err, ins_err)


def test_an_estimate_over_a_void_of_the_map_is_not_updated(flight) -> None:  # noqa: ANN001
    from neuralmap.dem.tile import DemTile
    from neuralmap.terrain.grid import GridTerrain

    source, truth = flight
    heights = source.tile.heights.copy()
    i, j = (truth.pos[0, 10, 1] / 30.0).round().int(), (truth.pos[0, 10, 0] / 30.0).round().int()
    heights[i - 6:i + 7, j - 6:j + 7] = np.nan  # a hole under vehicle 0's track
    tile = DemTile(heights=heights, spacing=source.tile.spacing, origin=source.tile.origin,
                   name="holey")
    grid = GridTerrain(tile, method="bilinear")
    assert grid.n_filled > 0 and bool(grid.void_at(truth.pos[0, 10:11, :2]).all())
    nav = Navigator(grid, {"method": "bilinear", "integrity": {"spike_gate_prob": 0.0}},
                    n_vehicles=2)
    track = nav.replay(truth.t, truth.ins_pos[..., :2], truth.ins_pos[..., 2], truth.radar)
    no_map = track.status == STATUS_CODE["no_map"]
    assert bool(no_map[0].any())
    assert not bool(track.updated[no_map].any())
    assert track.counts["no_map_epochs"] == int(no_map.sum())
    # the whole map: the same flight has no void epoch
    full = Navigator(GridTerrain(source.tile, method="bilinear"), {"method": "bilinear"},
                     n_vehicles=2).replay(truth.t, truth.ins_pos[..., :2],
                                          truth.ins_pos[..., 2], truth.radar)
    assert not bool((full.status == STATUS_CODE["no_map"]).any())


def test_a_map_across_the_antimeridian_takes_wrapped_longitudes() -> None:
    from neuralmap.dem.geo import geographic_reference
    from neuralmap.nav.georef import MapFrame

    frame = MapFrame(geographic_reference(180.0, -17.0), name="fiji")
    lat = np.array([-17.0, -17.0])
    x_wrapped, _ = frame.to_map(lat, np.array([-179.9, 179.9]))
    x_unwrapped, _ = frame.to_map(lat, np.array([180.1, 179.9]))
    np.testing.assert_allclose(x_wrapped, x_unwrapped)
    assert abs(x_wrapped[0]) < 20_000.0  # 0.1° of longitude, not the globe's width
    _, lon = frame.to_geo(x_wrapped, np.zeros(2))
    np.testing.assert_allclose(lon, [-179.9, 179.9], atol=1e-9)


def test_policy_args_that_are_not_a_mapping_are_refused() -> None:
    from neuralmap.nav.config import load_navigator_config

    with pytest.raises(NeuralMapError, match="policy_args must be a mapping"):
        load_navigator_config({"method": "bilinear", "ekf": {"policy": "raf",
                                                             "policy_args": [1, 2]}})


@pytest.mark.parametrize("value", ["nan", "abc", "inf", "-1"])
def test_a_bad_max_gap_is_one_line(flight, tmp_path, capsys, value) -> None:  # noqa: ANN001
    _, truth = flight
    log = _write(tmp_path / "f.csv", COLUMNS, _rows(truth))
    code, err = _navigate(capsys, log, tmp_path / "out", "--max_gap", value)
    _one_error(code, err, "--max_gap")


def test_an_out_folder_that_cannot_be_made_is_refused_first(flight, tmp_path, capsys,  # noqa: ANN001
                                                            monkeypatch) -> None:
    import neuralmap.flights.flight as flight_module

    _, truth = flight
    log = _write(tmp_path / "f.csv", COLUMNS, _rows(truth))
    blocker = tmp_path / "a_file"
    blocker.write_text("not a folder")
    called = []
    monkeypatch.setattr(flight_module, "navigate_flight", lambda *a: called.append(a))
    code, err = _navigate(capsys, log, blocker / "out")
    _one_error(code, err, "--out")
    assert not called  # refused before any navigation


def test_a_full_disk_is_an_error_line_and_writes_nothing(flight, tmp_path, capsys,  # noqa: ANN001
                                                         fail_write) -> None:
    _, truth = flight
    log = _write(tmp_path / "f.csv", COLUMNS, _rows(truth))
    out = tmp_path / "out"
    fail_write(1)  # ENOSPC at the first file written
    code, err = _navigate(capsys, log, out)
    _one_error(code, err, "--out", "free space")
    assert not list(out.glob("version_*"))


@pytest.mark.parametrize("radar,needle", [(0.0, "every clearance is 0 m"),
                                          (-5.0, "<= 0 m"),
                                          (2.0e4, "feet")])
def test_a_radar_column_that_cannot_be_clearances_says_why(flight, tmp_path, capsys,  # noqa: ANN001
                                                           radar, needle) -> None:
    _, truth = flight
    rows = [r[:-1] + [repr(radar)] for r in _rows(truth)]
    log = _write(tmp_path / "r.csv", COLUMNS, rows)
    code, err = _navigate(capsys, log, tmp_path / "out")
    _one_error(code, err, "column 'radar'", needle)


def test_interrupt_at_start_up_is_one_line(tmp_path, monkeypatch, capsys) -> None:  # noqa: ANN001
    import importlib

    from neuralmap import entry

    def interrupted(name: str):  # noqa: ANN202
        raise KeyboardInterrupt

    monkeypatch.setattr(importlib, "import_module", interrupted)
    assert entry.navigate(["x.csv", "--map", "synthetic"]) == 130
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "neuralmap-navigate: interrupted" in err[0]
    assert math.isfinite(130.0)
