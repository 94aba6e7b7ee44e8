"""Long logs: the chunked replay is one replay bit for bit, the outputs do not depend on the
chunk size, a failure mid-flight writes nothing, the replay never holds more than a chunk
of full fixes, and the compact record's numbers against independent references."""

from __future__ import annotations

import csv
import json
import math
import re
from fractions import Fraction
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from neuralmap.flights.cli import main
from neuralmap.flights.track_summary import TrackSummary, exact_sum
from neuralmap.lab.scenario import load_scenario, scenario_tile
from neuralmap.lab.simulator import simulate
from neuralmap.nav.fix import FIX_FIELDS, STATUS, STATUS_CODE, FixTrack
from neuralmap.nav.navigator import Navigator
from neuralmap.terrain.grid import GridTerrain

TINY = {"sensor": {"dt_s": 1.0, "altimeter_sigma_m": 3.0},
        "initial": {"position_sigma_m": 20.0, "altitude_sigma_m": 10.0, "velocity_sigma_mps": 0.2},
        "process_noise": {"position_sigma_m": 1.0, "altitude_sigma_m": 1.0,
                          "velocity_sigma_mps": 0.05}}
K = 90  # epochs of the CLI log


@pytest.fixture(scope="module")
def tiny_flight():  # noqa: ANN201
    scenario = load_scenario("tiny")
    tile = scenario_tile(scenario)
    truth = simulate(scenario, tile, n_runs=3, seed=2)
    return tile, truth, GridTerrain(tile, method="bilinear")


def _equal(a: torch.Tensor | None, b: torch.Tensor | None) -> bool:
    if a is None or b is None:
        return a is None and b is None
    if a.is_floating_point():
        return torch.equal(a.nan_to_num(-1.0), b.nan_to_num(-1.0))
    return torch.equal(a, b)


@pytest.mark.parametrize("method", ["point_mass_tracker", "bilinear"])
def test_chunked_replay_is_one_replay_bit_for_bit(tiny_flight, method: str) -> None:  # noqa: ANN001
    """`Navigator.replay(..., reset=False)` over chunks of the flight gives the fixes and
    counters of one replay of the whole flight (missing radar, out of range, a gap and a
    restart after a long gap inside the chunks)."""
    _, truth, grid = tiny_flight
    radar = truth.radar.clone()
    radar[0, 5] = math.nan
    radar[1, 12] = 1e6
    t = truth.t.clone()
    t[15:] += 2.0   # a 3 s gap
    t[30:] += 10.0  # a long gap: every vehicle restarts from the prior
    pos, alt = truth.ins_pos[..., :2], truth.ins_pos[..., 2]
    nav = Navigator(grid, {**TINY, "method": method}, n_vehicles=3)
    whole = nav.replay(t, pos, alt, radar)
    bounds = [0, 1, 8, 15, 16, 31, t.shape[0]]
    parts = [nav.replay(t[a:b], pos[:, a:b], alt[:, a:b], radar[:, a:b], reset=a == 0)
             for a, b in zip(bounds[:-1], bounds[1:], strict=True)]
    for name in FIX_FIELDS:
        got = [getattr(p, name) for p in parts]
        if got[0] is None:
            assert getattr(whole, name) is None, name
            continue
        assert _equal(torch.cat(got, 0 if name == "t" else 1), getattr(whole, name)), name
    assert parts[-1].counts == whole.counts
    assert whole.counts["long_gaps"] == 3 and whole.counts["gaps"] == 3
    for key, value in whole.vehicle_counts.items():
        assert torch.equal(parts[-1].vehicle_counts[key], value), key
    with pytest.raises(Exception, match="time must increase"):  # a chunk cannot go back
        nav.replay(t[:5], pos[:, :5], alt[:, :5], radar[:, :5], reset=False)


# ---------------------------------------------------------------------------- the CLI


@pytest.fixture(scope="module")
def two_vehicle_log(tmp_path_factory):  # noqa: ANN201
    """Two vehicles over the georeferenced jacksboro tile (map-frame log with a reference,
    a missing radar sample), and a small navigator config."""
    from neuralmap.nav.map_source import resolve_map

    folder = tmp_path_factory.mktemp("chunks")
    terrain = resolve_map("jacksboro").terrain
    rng = np.random.default_rng(3)
    path = folder / "log.csv"
    with path.open("w", newline="") as handle:
        w = csv.writer(handle)
        w.writerow(["flight", "time", "ins_x", "ins_y", "ins_h", "radar", "ref_x", "ref_y",
                    "ref_h"])
        for n, (x0, y0, vx, vy) in enumerate([(9000.0, 12000.0, 60.0, 20.0),
                                              (20000.0, 9000.0, -15.0, 55.0)]):
            k = np.arange(K, dtype=np.float64)
            truth = np.stack([x0 + vx * k, y0 + vy * k], -1)
            with torch.no_grad():
                ground = terrain(torch.as_tensor(truth)).double().numpy()
            h = 1500.0 + 0.0 * k
            radar = h - ground + rng.normal(0.0, 3.0, K)
            radar[17 + n] = np.nan
            ins = truth + np.array([25.0, -15.0]) + 0.3 * k[:, None]
            for i in range(K):
                values = [k[i], ins[i, 0], ins[i, 1], h[i] + 2.0, radar[i], truth[i, 0],
                          truth[i, 1], h[i]]
                w.writerow([n] + ["" if np.isnan(v) else repr(float(v)) for v in values])
    nav = folder / "nav.yaml"
    nav.write_text(yaml.safe_dump({**TINY, "initial": {"position_sigma_m": 40.0},
                                   "point_mass_tracker": {"cells": 16}}))
    return path, nav


def _navigate(log: Path, nav: Path, out: Path, *extra: str) -> Path:
    code = main([str(log), "--map", "jacksboro", "--config", str(nav), "--out", str(out),
                 "--tensorboard", "false", "--progress", "false", *extra])
    assert code == 0
    versions = sorted(out.glob("version_*"))
    assert len(versions) == 1
    return versions[0]


def _results(folder: Path) -> dict:
    results = json.loads((folder / "results.json").read_text())
    for key in ("replay_seconds", "epochs_per_second", "config"):
        results.pop(key)
    return results


def test_outputs_do_not_depend_on_the_chunk_size(two_vehicle_log, tmp_path: Path) -> None:  # noqa: ANN001
    """navigation.csv and navigation.geojson byte for byte, results.json and report.md but
    for the timings, whatever the chunk size (one chunk, 7 epochs, 1 epoch); the rows go
    vehicle by vehicle, as the one-chunk writer puts them."""
    log, nav = two_vehicle_log
    one = _navigate(log, nav, tmp_path / "one")
    runs = [_navigate(log, nav, tmp_path / f"c{c}", "--chunk_epochs", str(c)) for c in (7, 1)]
    assert json.loads((one / "results.json").read_text())["config"]["chunk_epochs"] == 50_000

    def report(folder: Path) -> str:
        return re.sub(r"in [0-9.]+ s\.", "in _ s.", (folder / "report.md").read_text())

    for run in runs:
        for name in ("navigation.csv", "navigation.geojson"):
            assert (run / name).read_bytes() == (one / name).read_bytes(), name
        assert _results(run) == _results(one)
        assert report(run) == report(one)
    rows = list(csv.DictReader((one / "navigation.csv").open(newline="")))
    assert [int(r["vehicle"]) for r in rows] == [0] * K + [1] * K
    assert [float(r["time"]) for r in rows[:K]] == list(range(K))
    geo = json.loads((one / "navigation.geojson").read_text())
    kinds = [(f["properties"]["vehicle"], f["geometry"]["type"]) for f in geo["features"]]
    assert kinds == ([(0, "LineString")] + [(0, "Point")] * K + [(1, "LineString")]
                     + [(1, "Point")] * K)
    line = geo["features"][0]["geometry"]["coordinates"]
    assert line == [p["geometry"]["coordinates"] for p in geo["features"][1:K + 1]]
    results = json.loads((one / "results.json").read_text())
    assert results["errors"]["horizontal_error_curve_stride"] == 1
    assert len(results["errors"]["horizontal_error_curve"]) == K


def test_the_replay_holds_one_chunk_of_fixes(two_vehicle_log, monkeypatch) -> None:  # noqa: ANN001
    """The flight replays in chunks of at most ``chunk_epochs`` (the first one resets the
    navigator, the others carry on); what it keeps is the compact record (1 byte of status
    per epoch and vehicle, figures' series bounded by ``plot_points``), no `FixTrack`."""
    from dataclasses import fields

    from neuralmap.exceptions import NeuralMapError
    from neuralmap.flights.flight import FlightOptions, navigate_flight, write_flight

    log, nav = two_vehicle_log
    calls: list[tuple[int, bool]] = []
    real = Navigator.replay

    def spy(self, t, *args, reset: bool = True, **kwargs):  # noqa: ANN001, ANN202
        calls.append((int(t.shape[0]), reset))
        return real(self, t, *args, reset=reset, **kwargs)

    monkeypatch.setattr(Navigator, "replay", spy)
    result = navigate_flight(FlightOptions(log=str(log), map="jacksboro", navigator=str(nav),
                                           chunk_epochs=20, progress=False))
    assert calls == [(20, True), (20, False), (20, False), (20, False), (10, False)]
    assert not any(isinstance(getattr(result, f.name), FixTrack) for f in fields(result))
    summary = result.summary
    assert summary.complete and summary.status.dtype == np.int8
    assert summary.status.nbytes == 2 * K
    result.files.close()
    with pytest.raises(NeuralMapError, match="written already"):
        write_flight(result, None)  # its rows are gone: a navigated flight is written once
    small = TrackSummary(torch.arange(10_000.0), 2, plot_points=100)
    assert small.stride == 100 and small.plot["xy"].shape == (2, 101, 2)


def test_a_failure_mid_flight_writes_nothing(two_vehicle_log, tmp_path: Path, capsys,  # noqa: ANN001
                                             monkeypatch) -> None:
    """A full disk in the third chunk of the replay: one error line, exit 2, no run folder,
    no temporary file left."""
    import errno

    log, nav = two_vehicle_log
    real = Navigator.replay
    calls = []

    def failing(self, *args, **kwargs):  # noqa: ANN001, ANN202
        calls.append(1)
        if len(calls) == 3:
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(self, *args, **kwargs)

    monkeypatch.setattr(Navigator, "replay", failing)
    out = tmp_path / "out"
    code = main([str(log), "--map", "jacksboro", "--config", str(nav), "--out", str(out),
                 "--tensorboard", "false", "--progress", "false", "--chunk_epochs", "10"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "free space" in err[0]
    assert not out.exists() or not list(out.rglob("*"))


def test_a_full_disk_while_writing_navigation_csv_writes_nothing(two_vehicle_log,  # noqa: ANN001
                                                                 tmp_path: Path, capsys,
                                                                 fail_write) -> None:
    """The chunked rows go into navigation.csv through one temporary file renamed at the
    end: a full disk part-way through it leaves no navigation.csv, no run folder."""
    log, nav = two_vehicle_log
    out = tmp_path / "out"
    fail_write(1)  # navigation.csv is the first file written
    code = main([str(log), "--map", "jacksboro", "--config", str(nav), "--out", str(out),
                 "--tensorboard", "false", "--progress", "false", "--chunk_epochs", "10"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "free space" in err[0]
    assert not out.exists() or not list(out.rglob("*"))


def test_chunk_epochs_must_be_positive(two_vehicle_log, tmp_path: Path, capsys) -> None:  # noqa: ANN001
    from neuralmap.exceptions import NeuralMapError
    from neuralmap.flights.flight import FlightOptions

    log, nav = two_vehicle_log
    with pytest.raises(NeuralMapError, match="--chunk_epochs must be an integer >= 1"):
        FlightOptions(log="x.csv", map="jacksboro", chunk_epochs=0).validate()
    code = main([str(log), "--map", "jacksboro", "--out", str(tmp_path / "out"),
                 "--chunk_epochs", "0"])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "--chunk_epochs" in err[0]
    assert not (tmp_path / "out").exists()


# ---------------------------------------------------------------------------- the record


def test_exact_sum_is_exact_and_free_of_the_split() -> None:
    rng = np.random.default_rng(5)
    v = rng.standard_normal(20_000) * 10.0 ** rng.uniform(-8, 8, 20_000)
    v = np.r_[v, 0.0, 5e-324, -3e-310, 1e300, -1e300]
    total = exact_sum(v)
    assert Fraction(total, 1 << 1074) == sum(Fraction(float(x)) for x in v)
    assert sum(exact_sum(part) for part in np.array_split(v, 13)) == total
    assert total / (1 << 1074) == math.fsum(v.tolist())


def test_summary_against_numpy_whatever_the_chunks(tiny_flight) -> None:  # noqa: ANN001
    """The error numbers of `TrackSummary` against NumPy on the whole track (NEES by
    ``np.linalg.solve``, not the Cholesky factor), and the same numbers bit for bit when
    the track comes in chunks of any size."""
    _, truth, grid = tiny_flight
    nav = Navigator(grid, TINY, n_vehicles=3)
    pos, alt = truth.ins_pos[..., :2], truth.ins_pos[..., 2]
    track = nav.replay(truth.t, pos, alt, truth.radar)
    ref_xy, ref_h = truth.pos[..., :2], truth.pos[..., 2]
    kwargs = {"reference_xy": ref_xy, "reference_altitude": ref_h, "ins_xy": pos,
              "ins_altitude": alt}
    whole = TrackSummary.from_track(track, plot_points=7, **kwargs)
    chunked = TrackSummary(track.t, 3, plot_points=7, **kwargs)
    k = track.n_epochs
    for a, b in zip([0, 3, 4, 17], [3, 4, 17, k], strict=True):
        part = FixTrack(**{name: (getattr(track, name)[a:b] if name == "t" else
                                  None if getattr(track, name) is None else
                                  getattr(track, name)[:, a:b]) for name in FIX_FIELDS},
                        counts=track.counts, vehicle_counts=track.vehicle_counts)
        chunked.add(part)
    assert chunked.complete
    assert chunked.reference_errors() == whole.reference_errors()
    assert chunked.ins_errors() == whole.ins_errors()
    assert chunked.rmse_vertical() == whole.rmse_vertical()
    assert chunked.status_fractions() == whole.status_fractions()
    for name in whole.plot:
        np.testing.assert_array_equal(chunked.plot[name], whole.plot[name])
    for name in whole.curves:
        np.testing.assert_array_equal(chunked.curves[name], whole.curves[name])
    # independent references (NumPy, float64)
    xy, ref = track.xy.numpy(), ref_xy.numpy()
    err = xy - ref
    h = np.hypot(err[..., 0], err[..., 1])
    cov = track.cov[..., :2, :2].numpy()
    nees = np.einsum("nki,nki->nk", err, np.linalg.solve(cov, err[..., None])[..., 0])
    tracking = track.status.numpy() == STATUS_CODE["tracking"]
    e = whole.reference_errors()
    assert e["rmse_horizontal_m"] == pytest.approx(np.sqrt(np.mean(h ** 2)), rel=1e-13)
    assert e["rmse_horizontal_tracking_m"] == pytest.approx(
        np.sqrt(np.mean(h[tracking] ** 2)), rel=1e-13)
    assert e["max_horizontal_error_m"] == h.max()
    assert e["final_horizontal_error_m"] == pytest.approx(h[:, -1].tolist(), rel=1e-15)
    assert e["mean_nees_xy"] == pytest.approx(nees.mean(), rel=1e-9)
    assert e["inside_3sigma"] == np.mean(nees <= 9.0)
    assert e["horizontal_error_curve_stride"] == whole.stride == math.ceil(k / 7)
    np.testing.assert_allclose(e["horizontal_error_curve"],
                               np.sqrt(np.mean(h ** 2, 0))[::whole.stride], rtol=1e-13)
    dh = track.altitude.numpy() - ref_h.numpy()
    assert whole.rmse_vertical() == pytest.approx(np.sqrt(np.mean(dh ** 2)), rel=1e-13)
    ins = whole.ins_errors()
    ins_h = np.hypot(*(pos.numpy() - ref).transpose(2, 0, 1))
    assert ins["rmse_horizontal_m"] == pytest.approx(np.sqrt(np.mean(ins_h ** 2)), rel=1e-13)
    assert ins["rmse_vertical_m"] == pytest.approx(
        np.sqrt(np.mean((alt.numpy() - ref_h.numpy()) ** 2)), rel=1e-13)
    codes = track.status.numpy().reshape(-1)
    assert whole.status_fractions() == {s: float(np.mean(codes == i))
                                        for i, s in enumerate(STATUS)}
    np.testing.assert_array_equal(whole.plot["xy"], xy[:, whole.plot_index])
    assert whole.plot_index[-1] == k - 1


def test_mapped_flight_reads_the_same_values(tiny_flight, tmp_path: Path) -> None:  # noqa: ANN001
    """The memory-mapped flight input holds the log's values, also after its pages were
    handed back."""
    from neuralmap.flights.flight_input import FlightInput
    from neuralmap.flights.mapped_flight import map_flight

    _, truth, _ = tiny_flight
    flight = FlightInput(t=truth.t.clone(), ins_position=truth.ins_pos[..., :2].clone(),
                         ins_altitude=truth.ins_pos[..., 2].clone(),
                         clearance=truth.radar.clone(),
                         reference_position=truth.pos[..., :2].clone(),
                         lines=np.arange(truth.t.shape[0]) + 2)
    mapped, spill = map_flight(flight, tmp_path)
    assert not list(tmp_path.iterdir())  # an anonymous file
    spill.release(3, 11)
    spill.release()
    for name in ("t", "ins_position", "ins_altitude", "clearance", "reference_position"):
        assert torch.equal(getattr(mapped, name), getattr(flight, name)), name
    np.testing.assert_array_equal(mapped.lines, flight.lines)
    assert mapped.reference_altitude is None


def test_the_format_is_told_from_the_header_alone(tmp_path: Path) -> None:
    """Detecting a CSV log's format reads its header line only (a long log is parsed
    once); the bad value is refused when the log is read, with its line and column."""
    from neuralmap.exceptions import NeuralMapError
    from neuralmap.flights.flight_input import detect_format, read_flight_input

    path = tmp_path / "log.csv"
    path.write_text("time,ins_x,ins_y,ins_h,radar\n0,1,2,3,4\n1,abc,2,3,4\n")
    assert detect_format(path) == "map_frame"
    with pytest.raises(NeuralMapError, match="line 3, column 'ins_x'"):
        read_flight_input(path)
