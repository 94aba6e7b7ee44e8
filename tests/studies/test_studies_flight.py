"""The ``flight`` study: ``evaluate.py --config configs/flight_tiny.yaml --log LOG`` runs the
same implementation as ``neuralmap-navigate`` (identical navigation.csv)."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from neuralmap.flights.cli import main as navigate_main
from neuralmap.resources import config_file
from neuralmap.studies.cli import main as evaluate_main

K = 25


@pytest.fixture(scope="module")
def small_log(tmp_path_factory):  # noqa: ANN201
    """A straight flight over the ``synthetic:64`` tile: INS 25 m off, radar = true
    clearance + 3 m noise, the truth as reference (map-frame CSV)."""
    from neuralmap.dem.load import load_tile
    from neuralmap.terrain.grid import GridTerrain

    folder = tmp_path_factory.mktemp("flight_study")
    tile = load_tile("synthetic:64")
    xmin, xmax, ymin, ymax = tile.extent
    s = np.linspace(0.25, 0.75, K)
    truth = np.stack([xmin + s * (xmax - xmin), ymin + s * (ymax - ymin)], -1)
    with torch.no_grad():
        ground = GridTerrain(tile, method="bicubic")(torch.as_tensor(truth)).numpy()
    rng = np.random.default_rng(4)
    h = ground.max() + 250.0
    radar = h - ground + rng.normal(0.0, 3.0, K)
    ins = truth + np.array([25.0, -15.0])
    path = folder / "log.csv"
    with path.open("w", newline="") as handle:
        w = csv.writer(handle)
        w.writerow(["time", "ins_x", "ins_y", "ins_h", "radar", "ref_x", "ref_y", "ref_h"])
        for k in range(K):
            w.writerow([float(k), *ins[k], h, radar[k], *truth[k], h])
    nav = folder / "nav.yaml"
    nav.write_text(yaml.safe_dump({"sensor": {"altimeter_sigma_m": 3.0},
                                   "initial": {"position_sigma_m": 40.0},
                                   "point_mass_tracker": {"cells": 16}}))
    return path, nav


def test_shipped_configs_parse() -> None:
    from neuralmap.studies.flight import FlightStudyConfig

    for name in ("flight.yaml", "flight_tiny.yaml"):
        data = yaml.safe_load(config_file(name).read_text())
        assert data["study"] == "flight" and "log" not in data
        FlightStudyConfig(**{**data, "log": "given.csv", "map": data.get("map", "x")}).validate()


def test_study_equals_cli(small_log, tmp_path: Path, capsys) -> None:  # noqa: ANN001
    log, nav = small_log
    code = evaluate_main(["--config", str(config_file("flight_tiny.yaml")), "--log", str(log),
                          "--navigator", str(nav), "--runs_dir", str(tmp_path / "runs")])
    assert code == 0, capsys.readouterr().err
    study = next((tmp_path / "runs" / "flight_tiny").glob("version_*"))
    code = navigate_main([str(log), "--map", "synthetic:64", "--config", str(nav), "--out",
                          str(tmp_path / "cli"), "--tensorboard", "false"])
    assert code == 0, capsys.readouterr().err
    cli = next((tmp_path / "cli").glob("version_*"))
    assert (study / "navigation.csv").read_text() == (cli / "navigation.csv").read_text()
    results = json.loads((study / "results.json").read_text())
    assert results["study"] == "flight" and results["map"]["kind"] == "sample"
    assert results["errors"]["rmse_horizontal_m"] < results["errors"]["ins_rmse_horizontal_m"]
    # the map has no georeference: no GeoJSON, and the report says so
    assert not (study / "navigation.geojson").exists()
    assert "no georeference" in (study / "report.md").read_text()


def test_study_without_log_is_refused(tmp_path: Path, capsys) -> None:  # noqa: ANN001
    code = evaluate_main(["--config", str(config_file("flight_tiny.yaml")), "--runs_dir",
                          str(tmp_path / "runs")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and "--log LOG is required" in err[0]
    assert not (tmp_path / "runs").exists()


def test_study_refuses_a_bad_log_with_one_line(small_log, tmp_path: Path, capsys) -> None:  # noqa: ANN001
    log, nav = small_log
    rows = log.read_text().splitlines()
    rows[3], rows[4] = rows[4], rows[3]  # time out of order at line 5
    bad = tmp_path / "bad.csv"
    bad.write_text("\n".join(rows) + "\n")
    code = evaluate_main(["--config", str(config_file("flight_tiny.yaml")), "--log", str(bad),
                          "--navigator", str(nav), "--runs_dir", str(tmp_path / "runs")])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1
    assert err[0].startswith("evaluate.py: error: ") and "line 5, column 1 ('time')" in err[0]
    assert not (tmp_path / "runs").exists()
