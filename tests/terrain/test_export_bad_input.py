"""neuralmap-export on unusual input: a CRS rasterio reads back from every DEM kind, outputs
written all or nothing (full disk, Ctrl-C), an --out that cannot be made refused before any
work, a parse error or an interrupt in one line."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest
import rasterio
from rasterio.transform import from_origin

from neuralmap.dem import load_mosaic, load_tile
from neuralmap.dem.tile import DemTile, ProjectedReference
from neuralmap.exceptions import NeuralMapError
from neuralmap.terrain.blockwise import BlockwiseTerrainNet
from neuralmap.terrain.export import load_map, save_map
from neuralmap.terrain.export_cli import main
from neuralmap.terrain.geotiff import map_layers, rasterio_crs, write_map_geotiffs
from neuralmap.terrain.grid import GridTerrain
from neuralmap.terrain.latent.tileset_layout import window_tile

#: A .prj as GDAL and ESRI tools write it (no AUTHORITY node): UTM zone 16N on WGS 84.
ESRI_UTM16N = (Path(__file__).parents[1] / "data" / "esri_utm16n.prj").read_text().strip()
LAYERS = ("height", "residual", "slope")


def _plane(ny: int, nx: int, cell: float) -> np.ndarray:
    """A tilted plane with some relief (row 0 south)."""
    y, x = np.mgrid[0:ny, 0:nx] * cell
    return 200.0 + 0.03 * x - 0.02 * y + 5.0 * np.sin(x / 300.0) * np.cos(y / 250.0)


def _asc(path: Path, heights: np.ndarray, x0: float, y0: float, cell: float,
         prj: str | None = ESRI_UTM16N) -> Path:
    ny, nx = heights.shape
    header = f"ncols {nx}\nnrows {ny}\nxllcenter {x0}\nyllcenter {y0}\ncellsize {cell}\n"
    rows = "\n".join(" ".join(f"{v:.3f}" for v in row) for row in np.flipud(heights))
    path.write_text(header + rows + "\n")
    if prj is not None:
        path.with_suffix(".prj").write_text(prj)
    return path


def _relief(shape: tuple[int, int], seed: int) -> np.ndarray:
    """Smooth random relief around 300 m (row 0 north, as SRTM files store it)."""
    g = np.random.default_rng(seed)
    return 300.0 + np.cumsum(np.cumsum(g.normal(size=shape), axis=0), axis=1) * 0.01


def _hgt(path: Path, heights: np.ndarray) -> Path:
    """A 3-arc-second SRTM tile (1201 x 1201 big-endian int16, first row north)."""
    heights.astype(">i2").tofile(path)
    return path


def _geotiff(path: Path, heights: np.ndarray, *, crs: str, west: float, north: float,
             cell: float) -> Path:
    with rasterio.open(path, "w", driver="GTiff", height=heights.shape[0],
                       width=heights.shape[1], count=1, dtype="float32", crs=crs,
                       transform=from_origin(west, north, cell, cell), nodata=-32768.0) as dst:
        dst.write(np.flipud(heights).astype(np.float32), 1)
    return path


def _check_round_trip(paths: dict[str, Path], terrain: object, tile: DemTile,
                      epsg: int) -> None:
    """rasterio reads the CRS back, and every layer equals the plain export (`map_layers`)."""
    expected = map_layers(terrain, tile)
    for name, path in paths.items():
        with rasterio.open(path) as ds:
            assert ds.crs is not None and ds.crs.to_epsg() == epsg, (name, ds.crs)
            values = np.flipud(ds.read(1, masked=True).filled(np.nan)).astype(np.float64)
        np.testing.assert_array_equal(values, expected[name].astype(np.float32), err_msg=name)


def _no_hidden(folder: Path) -> None:
    assert not [p.name for p in folder.iterdir() if p.name.startswith(".")]


# --------------------------------------------------------------------------- CRS per DEM kind


def test_srtm_hgt_round_trip(tmp_path: Path) -> None:
    tile = load_tile(_hgt(tmp_path / "N36W085.hgt", _relief((1201, 1201), 0)))
    assert tile.meta["crs"] == "EPSG:4326"
    part = window_tile(tile, (100, 139, 200, 249), "part")  # the tileset export's path
    terrain = GridTerrain(part)
    _check_round_trip(write_map_geotiffs(terrain, part, tmp_path / "out"), terrain, part, 4326)


def test_srtm_mosaic_of_a_tileset_round_trip(tmp_path: Path) -> None:
    """An SRTM region (the source of an SRTM latent tileset) records EPSG:4326, not a
    name rasterio cannot parse; a tile's window of it exports with that CRS."""
    heights = _relief((1201, 2401), 1)  # two tiles sharing their seam column
    _hgt(tmp_path / "N36W085.hgt", heights[:, :1201])
    _hgt(tmp_path / "N36W084.hgt", heights[:, 1200:])
    region = load_mosaic(str(tmp_path / "N36W08*.hgt"))
    assert region.meta["crs"] == "EPSG:4326"
    part = window_tile(region, (600, 629, 1190, 1219), "seam")  # across the seam
    terrain = GridTerrain(part)
    _check_round_trip(write_map_geotiffs(terrain, part, tmp_path / "out"), terrain, part, 4326)


def test_asc_with_prj_round_trip_through_the_cli(tmp_path: Path) -> None:
    """A neural map fitted to an .asc + .prj: the reader keeps the .prj's WKT, so the
    export writes that CRS (it failed with 'The WKT could not be parsed' on the name)."""
    dem = _asc(tmp_path / "utm.asc", _plane(30, 40, 30.0), 500000.0, 4000000.0, 30.0)
    tile = load_tile(dem)
    assert tile.projected.crs == ESRI_UTM16N
    net = BlockwiseTerrainNet.from_tile(tile, block_nodes=16, hidden=4, n_frequencies=2)
    map_path = save_map(net, tmp_path / "run" / "neural_map.pt")
    main([str(map_path)])
    out = tmp_path / "run" / "geotiff"
    _check_round_trip({n: out / f"neural_map_{n}.tif" for n in LAYERS}, load_map(map_path),
                      tile, 32616)
    _no_hidden(out)


def test_geotiff_round_trip(tmp_path: Path) -> None:
    dem = _geotiff(tmp_path / "utm.tif", _plane(30, 40, 30.0), crs="EPSG:32617",
                   west=600000.0, north=4001000.0, cell=30.0)
    tile = load_tile(dem)
    terrain = GridTerrain(tile, method="bicubic")
    _check_round_trip(write_map_geotiffs(terrain, tile, tmp_path / "out"), terrain, tile, 32617)


def test_a_crs_recorded_by_name_is_looked_up(tmp_path: Path, monkeypatch) -> None:  # noqa: ANN001
    """Maps and tilesets written before the readers kept the WKT record only a name:
    pyproj turns it into a CRS; without pyproj, or for a name it does not know, one clear
    error names the extra or the fix."""
    assert rasterio_crs("WGS 84 / UTM zone 16N").to_epsg() == 32616
    assert rasterio_crs("WGS 84 (SRTM)").to_epsg() == 4326
    assert rasterio_crs('PROJCS["WGS 84 / UTM zone 16N",GEOGCS["WGS 84"]]').to_epsg() == 32616
    tile = DemTile(heights=_plane(12, 14, 10.0), spacing=(10.0, 10.0), origin=(0.0, 0.0),
                   name="old", projected=ProjectedReference(500000.0, 4000000.0,
                                                            crs="WGS 84 / UTM zone 16N"))
    terrain = GridTerrain(tile)
    _check_round_trip(write_map_geotiffs(terrain, tile, tmp_path / "out"), terrain, tile, 32616)
    with pytest.raises(NeuralMapError, match="neither WKT, an EPSG code nor a CRS name"):
        rasterio_crs("My Local Grid")
    monkeypatch.setitem(sys.modules, "pyproj", None)  # import pyproj fails
    with pytest.raises(NeuralMapError,
                       match=r"by pyproj, which is not installed.*neuralmap\[nav\]"):
        rasterio_crs("WGS 84 / UTM zone 16N")
    assert not (tmp_path / "none").exists()


# --------------------------------------------------------------------------- all or nothing


@pytest.fixture
def exported(tmp_path: Path) -> tuple[Path, Path, dict[str, bytes]]:
    """A neural map of a small GeoTIFF, exported once: (map, out folder, file bytes)."""
    dem = _geotiff(tmp_path / "utm.tif", _plane(24, 30, 30.0), crs="EPSG:32633",
                   west=400000.0, north=5200000.0, cell=30.0)
    net = BlockwiseTerrainNet.from_tile(load_tile(dem), block_nodes=16, hidden=4,
                                        n_frequencies=2)
    map_path = save_map(net, tmp_path / "run" / "neural_map.pt")
    out = tmp_path / "run" / "geotiff"
    main([str(map_path), "--out", str(out)])
    return map_path, out, {p.name: p.read_bytes() for p in sorted(out.iterdir())}


def test_full_disk_keeps_the_previous_export(exported, capsys, fail_write) -> None:  # noqa: ANN001
    map_path, out, before = exported
    capsys.readouterr()
    fail_write(2)  # the first layer is written, the second fills the disk
    with pytest.raises(SystemExit) as info:
        main([str(map_path), "--out", str(out)])
    err = capsys.readouterr().err
    assert info.value.code == 2 and err.count("\n") == 1 and "error:" in err, err
    assert "No space left on device" in err and "disk is full" in err
    assert {p.name: p.read_bytes() for p in sorted(out.iterdir())} == before  # byte for byte
    # a first export into a new folder leaves no folder behind
    fresh = out.parent / "new" / "tif"
    with pytest.raises(SystemExit):
        main([str(map_path), "--out", str(fresh)])
    assert not (out.parent / "new").exists()


def test_interrupt_while_writing_keeps_the_previous_export(exported, capsys,  # noqa: ANN001
                                                           fail_write) -> None:  # noqa: ANN001
    map_path, out, before = exported
    fail_write(3, KeyboardInterrupt())
    capsys.readouterr()
    with pytest.raises(SystemExit) as info:
        main([str(map_path), "--out", str(out)])
    err = capsys.readouterr().err
    assert info.value.code == 130 and err.strip().splitlines() == [
        "neuralmap-export: interrupted; nothing was written (earlier outputs are unchanged)."]
    assert {p.name: p.read_bytes() for p in sorted(out.iterdir())} == before


def test_out_that_cannot_be_made_is_refused_before_any_work(tmp_path: Path, capsys,  # noqa: ANN001
                                                            monkeypatch) -> None:  # noqa: ANN001
    blocker = tmp_path / "a_file"
    blocker.write_text("not a folder")

    def no_work(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        raise AssertionError("the map was loaded before --out was checked")

    monkeypatch.setattr("neuralmap.terrain.export.load_map", no_work)
    with pytest.raises(SystemExit) as info:
        main([str(tmp_path / "missing.pt"), "--out", str(blocker / "geotiff")])
    err = capsys.readouterr().err
    assert info.value.code == 2 and err.count("\n") == 1, err
    assert err.startswith("neuralmap-export: error: --out") and "is a file, not a folder" in err
    assert blocker.read_text() == "not a folder"


def test_interrupt_at_start_up_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                           monkeypatch: pytest.MonkeyPatch) -> None:
    from neuralmap import entry

    def interrupted(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        raise KeyboardInterrupt

    monkeypatch.setattr("neuralmap.terrain.export.load_map", interrupted)
    with pytest.raises(SystemExit) as info:
        main([str(tmp_path / "neural_map.pt")])
    assert info.value.code == 130
    assert capsys.readouterr().err.strip().splitlines() == [
        "neuralmap-export: interrupted; nothing was written (earlier outputs are unchanged)."]
    assert not (tmp_path / "geotiff").exists()
    # Ctrl-C while the console script still imports the package (torch)
    monkeypatch.setattr(entry.importlib, "import_module", interrupted)
    assert entry.export([str(tmp_path / "neural_map.pt")]) == 130
    assert capsys.readouterr().err.strip().splitlines() == [
        "neuralmap-export: interrupted; nothing was written (earlier outputs are unchanged)."]


@pytest.mark.parametrize(("extra", "expected"), [
    (["--spacing", "abc"], "--spacing: 'abc' is not valid; expected a grid spacing > 0"),
    (["--cog", "maybe"], "--cog: 'maybe' is not valid; expected true or false"),
    (["--bogus", "1"], "unrecognized arguments: --bogus 1"),
])
def test_parse_errors_are_one_line(tmp_path: Path, capsys, extra: list[str],  # noqa: ANN001
                                   expected: str) -> None:
    with pytest.raises(SystemExit) as info:
        main([str(tmp_path / "neural_map.pt"), *extra])
    err = capsys.readouterr().err
    assert info.value.code == 2 and err.count("\n") == 1, err
    assert err.startswith("neuralmap-export: error: ") and expected in err, err
    assert "usage:" not in err and "--help" in err
