"""Trajectory export: tile frame to the source DEM's frame (CSV) and WGS-84 (GeoJSON)."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np
import pytest

from neuralmap.dem import DemTile
from neuralmap.dem.geo import geographic_grid
from neuralmap.dem.tile import ProjectedReference
from neuralmap.studies.trajectories import write_trajectories


def _tracks() -> tuple[np.ndarray, dict[str, np.ndarray]]:
    t = np.arange(3) * 0.5
    truth = np.zeros((2, 3, 3))
    truth[..., 0] = np.arange(3) * 10.0
    truth[1, :, 1] = 5.0
    truth[..., 2] = 300.0
    return t, {"truth": truth, "est": truth + np.array([1.0, -1.0, 0.0])}


def test_projected_tile_csv_and_geojson(tmp_path: Path) -> None:
    tile = DemTile(np.zeros((4, 4)), spacing=(30.0, 30.0),
                   projected=ProjectedReference(500000.0, 0.0, "EPSG:32633"))
    t, tracks = _tracks()
    paths = write_trajectories(tmp_path, tile, t, tracks)
    rows = list(csv.DictReader(paths["csv"].open()))
    assert len(rows) == 2 * 2 * 3
    row = rows[4]  # truth, run 1, step 1
    assert (row["track"], row["run"], row["step"]) == ("truth", "1", "1")
    assert float(row["easting"]) == 500010.0 and float(row["northing"]) == 5.0
    features = json.loads(paths["geojson"].read_text())["features"]
    assert [f["properties"] for f in features][:2] == [{"track": "truth", "run": 0},
                                                      {"track": "truth", "run": 1}]
    # UTM 33N: easting 500 000 m, northing 0 is the central meridian 15° E on the equator
    assert features[0]["geometry"]["coordinates"][0] == pytest.approx([15.0, 0.0], abs=1e-9)
    lon, lat = features[0]["geometry"]["coordinates"][1]
    assert lat == pytest.approx(0.0, abs=1e-9) and 15.0 < lon < 15.0001


def test_geographic_tile_uses_lon_lat(tmp_path: Path) -> None:
    spacing, origin, geo = geographic_grid(7.0, 46.0, 0.001, 0.001, (4, 4), origin=None,
                                           where="test")
    tile = DemTile(np.zeros((4, 4)), spacing=spacing, origin=origin, geo=geo)
    t, tracks = _tracks()
    paths = write_trajectories(tmp_path, tile, t, tracks)
    header = paths["csv"].read_text().splitlines()[0]
    assert header.endswith("lon,lat")
    first = json.loads(paths["geojson"].read_text())["features"][0]["geometry"]["coordinates"]
    np.testing.assert_allclose(first[0], geo.to_geographic(0.0, 0.0), rtol=0, atol=1e-12)


def test_local_tile_writes_csv_only(tmp_path: Path) -> None:
    tile = DemTile(np.zeros((4, 4)), spacing=(1.0, 1.0))
    t, tracks = _tracks()
    paths = write_trajectories(tmp_path, tile, t, tracks)
    assert set(paths) == {"csv"}
    assert paths["csv"].read_text().splitlines()[0] == "track,run,step,t_s,x_m,y_m,h_m"
