"""GeoTIFF export of a map: read back with rasterio onto the source DEM's grid, CRS and
no-data; heights, residual and slope against the closed form of a plane."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
import rasterio
from rasterio.transform import from_origin

from neuralmap.dem import load_tile
from neuralmap.terrain.blockwise import BlockwiseTerrainNet
from neuralmap.terrain.export import load_map, save_map
from neuralmap.terrain.export_cli import main
from neuralmap.terrain.geotiff import map_layers, write_map_geotiffs
from neuralmap.terrain.grid import GridTerrain

NY, NX = 40, 50
GX, GY = 0.03, -0.04  # plane slope (per metre): |∇h| = 0.05


def _source(path: Path, *, crs: str, transform, cell_m: tuple[float, float]) -> np.ndarray:  # noqa: ANN001
    """A plane DEM (first row north) with a void block, written as a GeoTIFF; returns it."""
    col, row = np.meshgrid(np.arange(NX), np.arange(NY))
    x, y = col * cell_m[0], (NY - 1 - row) * cell_m[1]
    data = (300.0 + GX * x + GY * y).astype(np.float32)
    data[5:9, 10:14] = -32768.0
    with rasterio.open(path, "w", driver="GTiff", height=NY, width=NX, count=1, dtype="float32",
                       crs=crs, transform=transform, nodata=-32768.0) as dst:
        dst.write(data, 1)
    return data


def _check_layers(paths: dict[str, Path], src: Path, data: np.ndarray, *, atol_deg: float) -> None:
    with rasterio.open(src) as ref:
        ref_transform, ref_crs = ref.transform, ref.crs
    void = data == -32768.0
    # nodes whose 3 x 3 neighbourhood is valid (the grid model fills voids by nearest node)
    ring = np.zeros_like(void)
    for di in (-1, 0, 1):
        for dj in (-1, 0, 1):
            ring |= np.roll(np.roll(void, di, 0), dj, 1)
    ring[[0, -1], :] = ring[:, [0, -1]] = True  # the grid model's slope at the edge is one-sided
    for name, path in paths.items():
        with rasterio.open(path) as out:
            assert out.count == 1 and out.shape == (NY, NX) and out.crs == ref_crs
            np.testing.assert_allclose(tuple(out.transform)[:6], tuple(ref_transform)[:6],
                                       rtol=0, atol=atol_deg)
            band = out.read(1, masked=True)
            np.testing.assert_array_equal(np.ma.getmaskarray(band), void)  # no-data preserved
            values = band.filled(np.nan).astype(np.float64)
        if name == "height":
            np.testing.assert_allclose(values[~void], data[~void], atol=1e-3)
        elif name == "residual":
            assert np.nanmax(np.abs(values)) < 1e-3
        else:
            # float32 source heights (±3e-5 m) over one cell: slope to ~2e-6
            np.testing.assert_allclose(values[~ring], 0.05, atol=5e-6)


def test_projected_export_lands_on_the_source_grid(tmp_path: Path) -> None:
    src = tmp_path / "utm.tif"
    data = _source(src, crs="EPSG:32633", transform=from_origin(400000.0, 5200000.0, 30.0, 30.0),
                   cell_m=(30.0, 30.0))
    tile = load_tile(src)
    paths = write_map_geotiffs(GridTerrain(tile, method="bicubic"), tile, tmp_path / "out")
    assert sorted(paths) == ["height", "residual", "slope"]
    assert not [p for p in (tmp_path / "out").iterdir() if p.name.startswith(".")]
    _check_layers(paths, src, data, atol_deg=1e-6)
    back = load_tile(paths["height"])  # the toolkit's reader sees the source grid again
    assert back.projected == tile.projected and back.spacing == tile.spacing


def test_geographic_export_lands_on_the_source_grid(tmp_path: Path) -> None:
    src = tmp_path / "geo.tif"
    d = 1.0 / 3600.0  # 1 arc-second
    probe = tmp_path / "probe.tif"
    _source(probe, crs="EPSG:4326", transform=from_origin(7.0, 46.0, d, d), cell_m=(1.0, 1.0))
    tile = load_tile(probe)  # metric cell sizes of this grid, for the plane in metres
    data = _source(src, crs="EPSG:4326", transform=from_origin(7.0, 46.0, d, d),
                   cell_m=tile.spacing)
    tile = load_tile(src)
    paths = write_map_geotiffs(GridTerrain(tile, method="bicubic"), tile, tmp_path / "out")
    _check_layers(paths, src, data, atol_deg=1e-12)


def test_plain_grid_without_crs(tmp_path: Path) -> None:
    heights = 100.0 + np.arange(NY * NX, dtype=np.float64).reshape(NY, NX) * 0.1
    path = tmp_path / "grid.npy"
    np.save(path, heights)
    tile = load_tile(path, spacing=10.0)
    out = GridTerrain(tile).to_geotiff(tmp_path / "out", tile, layers=("height",))
    with rasterio.open(out["height"]) as ds:
        assert ds.crs is None and tuple(ds.transform)[:6] == (10.0, 0.0, -5.0, 0.0, -10.0, 395.0)
        np.testing.assert_allclose(np.flipud(ds.read(1)), heights, atol=1e-4)


def test_entry_point_exports_a_neural_map(tmp_path: Path, capsys, monkeypatch) -> None:  # noqa: ANN001
    src = tmp_path / "utm.tif"
    _source(src, crs="EPSG:32633", transform=from_origin(400000.0, 5200000.0, 30.0, 30.0),
            cell_m=(30.0, 30.0))
    tile = load_tile(src)
    net = BlockwiseTerrainNet.from_tile(tile, block_nodes=16, hidden=8, n_frequencies=4)
    map_path = save_map(net, tmp_path / "run" / "neural_map.pt")
    main([str(map_path)])  # the DEM comes from the map's record
    out = tmp_path / "run" / "geotiff"
    expected = map_layers(load_map(map_path), tile)
    for name in ("height", "residual", "slope"):
        with rasterio.open(out / f"neural_map_{name}.tif") as ds:
            values = np.flipud(ds.read(1, masked=True).filled(np.nan))
        np.testing.assert_allclose(values, expected[name].astype(np.float32), equal_nan=True)
    assert "neural_map_slope.tif" in capsys.readouterr().out
    # a map of another tile
    other = tmp_path / "other.tif"
    _source(other, crs="EPSG:32633", transform=from_origin(0.0, 5200000.0, 30.0, 30.0),
            cell_m=(30.0, 30.0))
    with pytest.raises(SystemExit) as info:
        main([str(map_path), "--dem", str(other), "--out", str(tmp_path / "x")])
    assert info.value.code == 2 and "fitted to tile" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()
    # a read-only output folder (root ignores permission bits: answer as for another user)
    locked = tmp_path / "locked"
    locked.mkdir()
    real_access = os.access
    monkeypatch.setattr(os, "access", lambda p, mode, **kw: False if Path(p) == locked
                        else real_access(p, mode, **kw))
    with pytest.raises(SystemExit) as info:
        main([str(map_path), "--out", str(locked / "tif")])
    err = capsys.readouterr().err
    assert info.value.code == 2 and err.count("\n") == 1 and "not writable" in err


def test_write_failure_leaves_nothing(tmp_path: Path, fail_write) -> None:  # noqa: ANN001
    heights = np.ones((8, 8))
    np.save(tmp_path / "g.npy", heights)
    tile = load_tile(tmp_path / "g.npy", spacing=1.0)
    fail_write(1)  # a full disk
    from neuralmap.exceptions import NeuralMapError

    with pytest.raises(NeuralMapError, match="cannot write .*No space left.*disk is full"):
        write_map_geotiffs(GridTerrain(tile), tile, tmp_path / "out", layers=("height",))
    assert not (tmp_path / "out").exists()  # the folder it made is gone again


def test_map_of_the_embedded_sample(tmp_path: Path) -> None:
    """A map of the jacksboro sample: the DEM is found from the map's record; the grid is the
    sample's 3-arc-second lon/lat grid (cell edges: its west and north bounds)."""
    import matplotlib.cbook as cbook

    tile = load_tile("jacksboro")
    net = BlockwiseTerrainNet.from_tile(tile, block_nodes=128, hidden=4, n_frequencies=2)
    map_path = save_map(net, tmp_path / "neural_map.pt")
    main([str(map_path), "--layers", "[residual]"])
    sample = cbook.get_sample_data("jacksboro_fault_dem.npz")  # an NpzFile
    with rasterio.open(tmp_path / "geotiff" / "neural_map_residual.tif") as ds:
        assert ds.crs == "EPSG:4326" and ds.shape == tile.shape
        np.testing.assert_allclose(
            tuple(ds.transform)[:6],
            (float(sample["dx"]), 0.0, float(sample["xmin"]), 0.0, -float(sample["dy"]),
             max(float(sample["ymin"]), float(sample["ymax"]))), rtol=0, atol=1e-9)
