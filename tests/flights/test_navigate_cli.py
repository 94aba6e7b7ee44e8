"""``neuralmap-navigate``: a study flight written as a log gives the Navigator's own fixes;
refused logs print one ``error:`` line, exit 2 and write nothing; the GNSS-outage example."""

from __future__ import annotations

import csv
import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from neuralmap.flights.cli import main
from neuralmap.nav.fix import STATUS

pytest.importorskip("pyproj")
rasterio = pytest.importorskip("rasterio")

NAV_CONFIG = {"sensor": {"altimeter_sigma_m": 3.0},
              "initial": {"position_sigma_m": 20.0, "altitude_sigma_m": 10.0,
                          "velocity_sigma_mps": 0.2},
              "process_noise": {"position_sigma_m": 1.0, "altitude_sigma_m": 1.0,
                                "velocity_sigma_mps": 0.05},
              "point_mass_tracker": {"cells": 16}}


def _write_geotiff(path: Path, tile, *, crs: str, west: float, north: float,  # noqa: ANN001
                   dx: float, dy: float) -> Path:
    from rasterio.transform import from_origin

    ny, nx = tile.shape
    with rasterio.open(path, "w", driver="GTiff", height=ny, width=nx, count=1,
                       dtype="float64", crs=crs, transform=from_origin(west, north, dx, dy)
                       ) as dst:
        dst.write(np.flipud(tile.heights), 1)
    return path


@pytest.fixture(scope="module")
def study_flight(tmp_path_factory):  # noqa: ANN201
    """The tiny scenario's flight (2 runs) over its tile written as a UTM GeoTIFF, the
    flight written as a map-frame log with the truth as reference, and a navigator YAML."""
    from neuralmap.lab.scenario import load_scenario, scenario_tile
    from neuralmap.lab.simulator import simulate

    folder = tmp_path_factory.mktemp("flight")
    scenario = load_scenario("tiny")
    tile = scenario_tile(scenario)
    truth = simulate(scenario, tile, n_runs=2, seed=1)
    dx, dy = tile.spacing
    tif = _write_geotiff(folder / "tiny_utm.tif", tile, crs="EPSG:32617",
                         west=600000.0 - dx / 2, north=4000000.0 + (tile.shape[0] - 0.5) * dy,
                         dx=dx, dy=dy)
    log = folder / "flight.csv"
    with log.open("w", newline="") as handle:
        w = csv.writer(handle)
        w.writerow(["flight", "time", "ins_x", "ins_y", "ins_h", "radar", "ref_x", "ref_y",
                    "ref_h"])
        for n in range(truth.ins_pos.shape[0]):
            for k in range(truth.t.shape[0]):
                w.writerow([n, repr(float(truth.t[k]))]
                           + [repr(float(v)) for v in truth.ins_pos[n, k]]
                           + [repr(float(truth.radar[n, k]))]
                           + [repr(float(v)) for v in truth.pos[n, k]])
    nav_yaml = folder / "nav.yaml"
    nav_yaml.write_text(yaml.safe_dump(NAV_CONFIG))
    return {"folder": folder, "tile": tile, "truth": truth, "tif": tif, "log": log,
            "nav": nav_yaml}


def _read_csv(path: Path) -> list[dict[str, str]]:
    with path.open(newline="") as handle:
        return list(csv.DictReader(handle))


def _only_version(out: Path) -> Path:
    versions = sorted(out.glob("version_*"))
    assert len(versions) == 1
    return versions[0]


def test_study_flight_through_the_cli_equals_the_navigator(study_flight, tmp_path: Path,
                                                           capsys) -> None:  # noqa: ANN001
    from neuralmap.dem.load import load_tile
    from neuralmap.nav.georef import MapFrame
    from neuralmap.nav.navigator import Navigator
    from neuralmap.terrain.grid import GridTerrain

    s = study_flight
    out = tmp_path / "out"
    code = main([str(s["log"]), "--map", str(s["tif"]), "--config", str(s["nav"]), "--out",
                 str(out), "--tensorboard", "false"])
    assert code == 0, capsys.readouterr().err
    folder = _only_version(out)
    rows = _read_csv(folder / "navigation.csv")
    truth = s["truth"]
    n, k = truth.ins_pos.shape[:2]
    assert len(rows) == n * k
    # the same flight straight into the Navigator (same map file, same config)
    tile = load_tile(s["tif"])
    nav = Navigator(GridTerrain(tile, method="bicubic"), str(s["nav"]), n_vehicles=n,
                    map_frame=MapFrame.from_tile(tile), tile=tile)
    track = nav.replay(truth.t, truth.ins_pos[..., :2], truth.ins_pos[..., 2], truth.radar)
    got = np.array([[float(r["x"]), float(r["y"]), float(r["altitude"]), float(r["lat"]),
                     float(r["lon"])] for r in rows]).reshape(n, k, 5)
    want = torch.cat([track.xy, track.altitude[..., None], track.lat[..., None],
                      track.lon[..., None]], -1).numpy()
    np.testing.assert_array_equal(got, want)  # shortest round-trip text: bit for bit
    assert [r["status"] for r in rows] == [STATUS[c] for c in track.status.reshape(-1)]
    # the 1σ ellipse against an independent eigen-decomposition of the covariance
    lam, vec = np.linalg.eigh(track.cov[..., :2, :2].numpy())
    major = np.array([float(r["sigma_major_m"]) for r in rows]).reshape(n, k)
    minor = np.array([float(r["sigma_minor_m"]) for r in rows]).reshape(n, k)
    np.testing.assert_allclose(major, np.sqrt(lam[..., 1]), rtol=1e-10)
    np.testing.assert_allclose(minor, np.sqrt(lam[..., 0]), rtol=1e-10)
    azimuth = np.array([float(r["ellipse_azimuth_deg"]) for r in rows]).reshape(n, k)
    v = vec[..., :, 1]  # the major axis (east, north)
    ref_az = np.mod(np.degrees(np.arctan2(v[..., 0], v[..., 1])), 180.0)
    dif = np.abs(np.mod(azimuth - ref_az + 90.0, 180.0) - 90.0)
    round_ = np.isclose(lam[..., 1], lam[..., 0], rtol=1e-9)  # a circle has no axis
    assert (dif[~round_] < 1e-6).all()
    # errors against the reference in the study report format
    results = json.loads((folder / "results.json").read_text())
    err = np.hypot(*(track.xy - truth.pos[..., :2]).unbind(-1))
    assert results["errors"]["rmse_horizontal_m"] == pytest.approx(
        float(err.pow(2).mean().sqrt()), rel=1e-12)
    dh = track.altitude - truth.pos[..., 2]
    assert results["errors"]["rmse_vertical_m"] == pytest.approx(
        float(dh.pow(2).mean().sqrt()), rel=1e-12)
    assert results["log"]["kind"] == "map_frame"
    for name in ("report.md", "track.png", "error_vs_time.png", "status_timeline.png",
                 "navigation.geojson", "config.yaml"):
        assert (folder / name).is_file(), name
    geo = json.loads((folder / "navigation.geojson").read_text())
    lines = [f for f in geo["features"] if f["geometry"]["type"] == "LineString"]
    points = [f for f in geo["features"] if f["geometry"]["type"] == "Point"]
    assert len(lines) == n and len(points) == n * k
    assert lines[0]["geometry"]["coordinates"][3] == [float(track.lon[0, 3]),
                                                      float(track.lat[0, 3])]
    assert {p["properties"]["status"] for p in points} <= set(STATUS)


def test_cli_results_name_the_flight_study(study_flight, tmp_path: Path) -> None:  # noqa: ANN001
    """results.json of ``neuralmap-navigate`` says which implementation wrote it: the
    ``flight`` study's (as before the restructuring)."""
    s = study_flight
    out = tmp_path / "out"
    assert main([str(s["log"]), "--map", str(s["tif"]), "--config", str(s["nav"]), "--out",
                 str(out), "--tensorboard", "false", "--progress", "false"]) == 0
    results = json.loads((_only_version(out) / "results.json").read_text())
    assert results["study"] == "flight"


def _edit_log(src: Path, dst: Path, edit) -> Path:  # noqa: ANN001
    rows = list(csv.reader(src.open(newline="")))
    edit(rows)
    with dst.open("w", newline="") as handle:
        csv.writer(handle).writerows(rows)
    return dst


def _swap_times(rows: list[list[str]]) -> None:
    rows[5][1], rows[6][1] = rows[6][1], rows[5][1]


def _nan_position(rows: list[list[str]]) -> None:
    rows[9][3] = "nan"


def _off_map(rows: list[list[str]]) -> None:
    for r in rows[1:]:
        r[2] = repr(float(r[2]) + 1e5)


def _altitude_offset(rows: list[list[str]]) -> None:
    for r in rows[1:]:
        r[4] = repr(float(r[4]) + 400.0)


@pytest.mark.parametrize("case, edit, extra, match", [
    ("order", _swap_times, [], "line 7, column 2 ('time')"),
    ("nonfinite", _nan_position, [], "line 10, column 4 ('ins_y')"),
    ("offmap", _off_map, [], "lies off the map"),
    ("datum", _altitude_offset, [], "vertical datum mismatch"),
    ("undulation", None, ["--alt_datum", "ellipsoidal"], "--geoid_undulation"),
    ("nomap", None, ["--map", "no_such_map.tif"], "no such file and not an embedded tile"),
])
def test_refused_log_one_error_line_exit_2_nothing_written(
        study_flight, tmp_path: Path, capsys, case: str, edit, extra: list,  # noqa: ANN001
        match: str
) -> None:
    s = study_flight
    log = s["log"] if edit is None else _edit_log(s["log"], tmp_path / f"{case}.csv", edit)
    out = tmp_path / "out"
    args = [str(log), "--map", str(s["tif"]), "--config", str(s["nav"]), "--out", str(out),
            "--tensorboard", "false"]
    code = main(args + extra)
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2
    assert len(err) == 1 and err[0].startswith("neuralmap-navigate: error: "), err
    assert match in err[0]
    assert not out.exists()


def test_counted_cases_reach_the_report(study_flight, tmp_path: Path,  # noqa: ANN001
                                        capsys) -> None:  # noqa: ANN001
    """Missing radar, a clearance outside the sensor's range and a time gap are counted (by
    the reader and by the navigator), not refused."""
    def edit(rows: list[list[str]]) -> None:
        rows[4][5] = ""            # missing radar
        rows[8][5] = "nan"         # missing radar
        rows[12][5] = "-5.0"       # below clearance_min_m
        del rows[20:22]            # a 3 s step: one gap (flight 0)

    log = _edit_log(study_flight["log"], tmp_path / "counted.csv", edit)
    # a 2-flight log needs both flights on the same times: keep flight 0 only
    rows = [r for r in csv.reader(log.open(newline="")) if r[0] in ("flight", "0")]
    with log.open("w", newline="") as handle:
        csv.writer(handle).writerows(rows)
    out = tmp_path / "out"
    code = main([str(log), "--map", str(study_flight["tif"]), "--config",
                 str(study_flight["nav"]), "--out", str(out), "--tensorboard", "false"])
    assert code == 0, capsys.readouterr().err
    counts = json.loads((_only_version(out) / "results.json").read_text())["counts"]
    assert counts["input_missing_radar"] == 2 and counts["missing_radar"] == 2
    assert counts["input_out_of_range"] == 1 and counts["out_of_range"] == 1
    assert counts["input_gaps"] == 1 and counts["gaps"] == 1
    status = [r["status"] for r in _read_csv(_only_version(out) / "navigation.csv")]
    assert status.count("no_measurement") == 3


def test_gnss_outage_example_tiny(tmp_path: Path) -> None:
    """The worked GNSS/INS -> TAN hand-over at its tiny size: the KF-GINS result and radar
    log go through neuralmap-navigate, the navigator tracks the whole outage and its error
    at the end lies inside its reported 3σ."""
    from neuralmap.examples.gnss_outage import run_example

    summary = run_example(tmp_path / "example", size="tiny")
    results = summary["results"]
    assert results["log"]["kind"] == "kfgins" and results["log"]["alt_datum"] == "ellipsoidal"
    assert results["counts"]["off_map_epochs"] == 0
    assert results["status_fraction"]["tracking"] == 1.0
    assert math.isfinite(summary["tan_error_m"])
    assert summary["tan_error_m"] < 3.0 * summary["tan_sigma_m"]
    assert results["errors"]["inside_3sigma"] >= 0.9
    assert summary["gins_error_m"] > 1.0  # the coasting GNSS/INS did drift
    assert (summary["navigation"] / "navigation.geojson").is_file()
