"""Reading recorded flights: map-frame, lat/lon and KF-GINS logs; what is counted, what is
refused (with file, line and column)."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest

from neuralmap.exceptions import NeuralMapError
from neuralmap.flights.flight_input import read_flight_input
from neuralmap.nav.map_source import resolve_map

pytest.importorskip("pyproj")
rasterio = pytest.importorskip("rasterio")

K = 30


def _write_geotiff(path: Path, *, crs: str, west: float, north: float, d: float) -> Path:
    from rasterio.transform import from_origin

    y, x = np.mgrid[0:48, 0:48].astype(float)
    heights = 300.0 + 20.0 * np.sin(x / 5.0) + 15.0 * np.cos(y / 7.0)
    with rasterio.open(path, "w", driver="GTiff", height=48, width=48, count=1,
                       dtype="float64", crs=crs, transform=from_origin(west, north, d, d)
                       ) as dst:
        dst.write(np.flipud(heights), 1)
    return path


@pytest.fixture(scope="module", params=["projected", "geographic"])
def source(request, tmp_path_factory):  # noqa: ANN001, ANN201
    """A map on a projected (UTM) and on a geographic GeoTIFF."""
    folder = tmp_path_factory.mktemp(request.param)
    if request.param == "projected":
        path = _write_geotiff(folder / "utm.tif", crs="EPSG:32617", west=600000.0,
                              north=4050000.0, d=30.0)
    else:
        path = _write_geotiff(folder / "geo.tif", crs="EPSG:4326", west=-84.0, north=36.5,
                              d=1.0 / 2400.0)
    return resolve_map(str(path))


def _flight(source) -> dict[str, np.ndarray]:  # noqa: ANN001
    xmin, xmax, ymin, ymax = source.extent
    s = np.linspace(0.2, 0.8, K)
    x, y = xmin + s * (xmax - xmin), ymin + (1.0 - s) * (ymax - ymin)
    rng = np.random.default_rng(1)
    return {"time": 100.0 + np.arange(K, dtype=float), "x": x, "y": y,
            "alt": 900.0 + rng.normal(0, 1, K), "radar": 550.0 + rng.normal(0, 3, K),
            "ref_x": x + 5.0, "ref_y": y - 3.0, "ref_alt": np.full(K, 901.0)}


def _write_csv(path: Path, columns: dict[str, list]) -> Path:
    with path.open("w", newline="") as handle:
        w = csv.writer(handle)
        w.writerow(columns)
        w.writerows(zip(*columns.values(), strict=True))
    return path


def _geo_columns(source, f) -> dict[str, list]:  # noqa: ANN001
    lat, lon = source.frame.to_geo(f["x"], f["y"])
    rlat, rlon = source.frame.to_geo(f["ref_x"], f["ref_y"])
    return {"time": list(f["time"]), "lat": [repr(float(v)) for v in lat], "lon": [repr(float(v)) for v in lon],
            "alt": list(f["alt"]), "radar": list(f["radar"]), "ref_lat": list(rlat),
            "ref_lon": list(rlon), "ref_alt": list(f["ref_alt"])}


def test_latlon_log_round_trips(source, tmp_path: Path) -> None:  # noqa: ANN001
    f = _flight(source)
    path = _write_csv(tmp_path / "geo.csv", _geo_columns(source, f))
    got = read_flight_input(path, map_frame=source.frame, extent=source.extent)
    assert got.kind == "geographic" and got.alt_datum == "dem" and got.n_vehicles == 1
    np.testing.assert_allclose(got.ins_position[0].numpy(), np.stack([f["x"], f["y"]], -1),
                               rtol=0, atol=1e-6)
    np.testing.assert_allclose(got.reference_position[0].numpy(),
                               np.stack([f["ref_x"], f["ref_y"]], -1), rtol=0, atol=1e-6)
    np.testing.assert_array_equal(got.ins_altitude[0].numpy(), f["alt"])
    np.testing.assert_array_equal(got.clearance[0].numpy(), f["radar"])
    assert got.counts == {"rows": K, "missing_radar": 0, "gaps": 0, "off_map_epochs": 0}
    # back to lat/lon: the frame's inverse gives the log's degrees
    lat, lon = source.frame.to_geo(got.ins_position[0, :, 0], got.ins_position[0, :, 1])
    cols = _geo_columns(source, f)
    np.testing.assert_allclose(lat.numpy(), np.array(cols["lat"], float), rtol=0, atol=1e-10)
    np.testing.assert_allclose(lon.numpy(), np.array(cols["lon"], float), rtol=0, atol=1e-10)
    # ellipsoidal altitude with an undulation: h - N
    e = read_flight_input(path, map_frame=source.frame, alt_datum="ellipsoidal",
                          geoid_undulation=-30.0)
    np.testing.assert_allclose(e.ins_altitude[0].numpy(), f["alt"] + 30.0, rtol=0, atol=1e-12)
    with pytest.raises(NeuralMapError, match="geoid_undulation"):
        read_flight_input(path, map_frame=source.frame, alt_datum="ellipsoidal")


def test_map_frame_csv_and_npz_agree(source, tmp_path: Path) -> None:  # noqa: ANN001
    f = _flight(source)
    cols = {"flight": [0] * K + [1] * K, "time": list(f["time"]) * 2,
            "ins_x": list(f["x"]) + list(f["x"] + 1), "ins_y": list(f["y"]) * 2,
            "ins_h": list(f["alt"]) * 2, "radar": list(f["radar"]) * 2}
    a = read_flight_input(_write_csv(tmp_path / "m.csv", cols), extent=source.extent)
    np.savez(tmp_path / "m.npz", **{k: np.asarray(v) for k, v in cols.items()})
    b = read_flight_input(tmp_path / "m.npz", extent=source.extent)
    assert a.kind == b.kind == "map_frame" and a.n_vehicles == 2 and a.reference_position is None
    for name in ("t", "ins_position", "ins_altitude", "clearance"):
        np.testing.assert_array_equal(getattr(a, name).numpy(), getattr(b, name).numpy())
    np.testing.assert_array_equal(a.ins_position[1, :, 0].numpy(), f["x"] + 1)


def test_counted_not_refused(source, tmp_path: Path) -> None:  # noqa: ANN001
    f = _flight(source)
    cols = _geo_columns(source, f)
    cols["radar"][3] = ""          # missing
    cols["radar"][4] = "nan"       # missing
    cols["radar"][5] = "-2.0"      # below the sensor's range
    cols["radar"][6] = "9000"      # above it
    xmin, xmax, ymin, ymax = source.extent
    lat, lon = source.frame.to_geo(np.array([xmax + 500.0]), np.array([ymin - 100.0]))
    cols["lat"][7], cols["lon"][7] = repr(float(lat[0])), repr(float(lon[0]))  # off the map
    keep = [i for i in range(K) if i not in (10, 11, 20)]  # two gaps
    cols = {k: [v[i] for i in keep] for k, v in cols.items()}
    got = read_flight_input(_write_csv(tmp_path / "c.csv", cols), map_frame=source.frame,
                            extent=source.extent, clearance_range=(0.0, 8000.0))
    assert got.counts == {"rows": K - 3, "missing_radar": 2, "out_of_range": 2, "gaps": 2,
                          "off_map_epochs": 1}
    assert np.isnan(got.clearance[0, 3]) and np.isnan(got.clearance[0, 4])


@pytest.mark.parametrize("case, match", [
    ("order", r"line 7, column 1 \('time'\): time 104.0 s is out of order"),
    ("nonfinite", r"line 9, column 3 \('lon'\): value nan is not finite"),
    ("offmap", r"line 2, column 2 \('lat'\): the log lies off the map"),
    ("latrange", r"line 4, column 2 \('lat'\): 123.0 is not a lat"),
])
def test_refused_with_line_and_column(source, tmp_path: Path, case: str, match: str
                                      ) -> None:  # noqa: ANN001
    cols = _geo_columns(source, _flight(source))
    if case == "order":
        cols["time"][5] = 104.0  # the epoch before is 104.0
    elif case == "nonfinite":
        cols["lon"][7] = "nan"
    elif case == "offmap":
        lat, lon = source.frame.to_geo(np.full(K, -5e4), np.full(K, -5e4))
        cols["lat"], cols["lon"] = list(lat), list(lon)
    else:
        cols["lat"][2] = 123.0
    path = _write_csv(tmp_path / f"{case}.csv", cols)
    with pytest.raises(NeuralMapError, match=match) as info:
        read_flight_input(path, map_frame=source.frame, extent=source.extent)
    assert str(path) in str(info.value)


def test_kfgins_result_with_radar_log(source, tmp_path: Path) -> None:  # noqa: ANN001
    from neuralmap.ins.kfgins import NavLog, write_nav

    f = _flight(source)
    # the INS at 10 Hz (the radar at 1 Hz falls between records only at its ends)
    t_ins = np.arange(99.0, 100.0 + K + 0.001, 0.1)
    x = np.interp(t_ins, f["time"], f["x"])
    y = np.interp(t_ins, f["time"], f["y"])
    lat, lon = source.frame.to_geo(x, y)
    h = np.interp(t_ins, f["time"], f["alt"]) - 25.0  # ellipsoidal: N = -25 m
    n = t_ins.size
    nav = NavLog(week=np.zeros(n), time=t_ins, position=np.column_stack([lat, lon, h]),
                 velocity=np.zeros((n, 3)), euler=np.zeros((n, 3)))
    nav_path = write_nav(tmp_path / "KF_GINS_Navresult.nav", nav)
    radar = {"time": list(np.r_[90.0, f["time"]]), "radar": list(np.r_[1.0, f["radar"]])}
    radar_path = _write_csv(tmp_path / "radar.csv", radar)
    with pytest.raises(NeuralMapError, match="geoid undulation"):
        read_flight_input(nav_path, map_frame=source.frame, radar=radar_path)
    with pytest.raises(NeuralMapError, match="--radar"):
        read_flight_input(nav_path, map_frame=source.frame, geoid_undulation=-25.0)
    got = read_flight_input(nav_path, map_frame=source.frame, radar=radar_path,
                            geoid_undulation=-25.0, extent=source.extent)
    assert got.kind == "kfgins" and got.alt_datum == "ellipsoidal"
    assert got.counts["radar_outside_ins"] == 1 and got.n_epochs == K
    np.testing.assert_array_equal(got.t.numpy(), f["time"])
    # linear interpolation of lat/lon between records: the map-frame track is reproduced
    # to the equirectangular/UTM curvature of a 0.1 s step (sub-millimetre)
    np.testing.assert_allclose(got.ins_position[0].numpy(), np.stack([f["x"], f["y"]], -1),
                               rtol=0, atol=1e-3)
    np.testing.assert_allclose(got.ins_altitude[0].numpy(), f["alt"], rtol=0, atol=1e-9)
    np.testing.assert_array_equal(got.clearance[0].numpy(), f["radar"])
