"""Inputs that used to give a silently wrong tile: units, no-data, sentinels, frames, links."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from neuralmap.dem import DemTile, load_tile
from neuralmap.dem.geo import crs_name, metres_per_degree
from neuralmap.exceptions import NeuralMapError


def _asc(path: Path, corner: tuple[float, float], cell: float, rows: list[list[float]],
         nodata: str | None = None) -> Path:
    lines = [f"ncols {len(rows[0])}", f"nrows {len(rows)}", f"xllcorner {corner[0]!r}",
             f"yllcorner {corner[1]!r}", f"cellsize {cell!r}"]
    if nodata is not None:
        lines.append(f"NODATA_value {nodata}")
    lines += [" ".join(str(v) for v in row) for row in rows]
    path.write_text("\n".join(lines) + "\n")
    return path


# --------------------------------------------------------------------------- units


def test_small_metric_cells_at_origin_are_ambiguous_and_settled_by_units(tmp_path: Path) -> None:
    # 0.1 m lidar at (0, 0): was silently read as 0.1 degree (11 km) cells.
    path = _asc(tmp_path / "lidar.asc", (0.0, 0.0), 0.1, [[1, 2, 3], [4, 5, 6], [7, 8, 9]])
    with pytest.raises(NeuralMapError, match="metres or degrees") as info:
        load_tile(path)
    assert "--data.units metres|degrees" in str(info.value)
    assert "units='metres'" in str(info.value)
    tile = load_tile(path, units="metres")
    assert tile.spacing == (0.1, 0.1) and tile.geo is None
    assert tile.meta["units"] == "metres" and "caller" in tile.meta["units_reason"]


def test_quarter_degree_grid_is_ambiguous_and_settled_by_units(tmp_path: Path) -> None:
    # 0.25° geographic grid: was silently read as 0.25 m cells.
    path = _asc(tmp_path / "coarse.asc", (-85.0, 36.0), 0.25, [[1, 2, 3], [4, 5, 6]])
    with pytest.raises(NeuralMapError, match="cannot tell"):
        load_tile(path)
    tile = load_tile(path, units="degrees")
    m_lon, m_lat = metres_per_degree(36.25)  # centre latitude of the node rows
    np.testing.assert_allclose(tile.spacing, (0.25 * m_lon, 0.25 * m_lat), rtol=1e-12)
    # a .prj sidecar settles it too, and the reason names it
    path.with_suffix(".prj").write_text('GEOGCS["WGS 84",DATUM["WGS_1984"]]')
    tile = load_tile(path)
    assert tile.meta["units"] == "degrees" and ".prj" in tile.meta["units_reason"]


@pytest.mark.parametrize(
    ("corner", "cell", "units", "reason"),
    [
        ((500000.0, 4000000.0), 30.0, "metres", "no longitude"),
        ((0.0, 0.0), 2.0, "metres", "over 1 degree"),
        ((-85.0, 36.0), 1.0 / 3600.0, "degrees", "sub-centimetre"),
    ],
)
def test_units_decided_from_ranges_with_reason(
    tmp_path: Path, corner: tuple[float, float], cell: float, units: str, reason: str
) -> None:
    tile = load_tile(_asc(tmp_path / "g.asc", corner, cell, [[1, 2], [3, 4]]))
    assert tile.meta["units"] == units and reason in tile.meta["units_reason"]
    assert tile.describe()["units_reason"] == tile.meta["units_reason"]


def test_units_option_is_checked(tmp_path: Path) -> None:
    path = _asc(tmp_path / "g.asc", (500000.0, 4000000.0), 30.0, [[1, 2], [3, 4]])
    with pytest.raises(NeuralMapError, match="'metres' or 'degrees'"):
        load_tile(path, units="feet")
    with pytest.raises(NeuralMapError, match="disagree"):
        load_tile(path, units="metres", geographic=True)
    with pytest.raises(NeuralMapError, match="units apply to"):
        load_tile("jacksboro", units="degrees")


# --------------------------------------------------------------------------- no-data


def test_gdal_float32_nodata_written_with_more_digits(tmp_path: Path) -> None:
    # GDAL: header -3.4028234663852886e+38, cells -3.4028235e+38 (the same float32).
    path = _asc(tmp_path / "gdal.asc", (500000.0, 4000000.0), 30.0,
                [[1.5, -3.4028235e38], [3.25, 4.0]], nodata="-3.4028234663852886e+38")
    tile = load_tile(path)
    assert tile.n_void == 1 and np.isnan(tile.heights[1, 1])
    assert tile.meta["n_nodata"] == 1


def test_int16_npy_srtm_voids_with_nodata_option(tmp_path: Path) -> None:
    grid = np.array([[100, 101, -32768], [102, 103, 104]], dtype=np.int16)
    np.save(tmp_path / "srtm.npy", grid)
    with pytest.raises(NeuralMapError, match="outside") as info:
        load_tile(tmp_path / "srtm.npy", spacing=30.0)  # -32768 is not a height
    assert "nodata" in str(info.value) and "1 of 6" in str(info.value)
    tile = load_tile(tmp_path / "srtm.npy", spacing=30.0, nodata=-32768)
    assert tile.n_void == 1 and tile.meta["n_nodata_option"] == 1
    np.testing.assert_array_equal(tile.valid_mask, grid != -32768)


def test_single_sentinel_refused_or_voided_with_count(tmp_path: Path) -> None:
    grid = np.full((4, 4), 250.0)
    grid[2, 1] = 1e30
    np.save(tmp_path / "s.npy", grid)
    with pytest.raises(NeuralMapError, match="1 of 16 heights lie outside -12000 … 9000 m"):
        load_tile(tmp_path / "s.npy", spacing=10.0)
    tile = load_tile(tmp_path / "s.npy", spacing=10.0, height_check="void")
    assert tile.n_void == 1 and tile.meta["n_implausible"] == 1
    assert "voided" in tile.meta["implausible_note"]
    kept = load_tile(tmp_path / "s.npy", spacing=10.0, height_check="off")
    assert kept.n_void == 0 and kept.heights[2, 1] == 1e30


def test_tile_of_sentinels_and_infinities(tmp_path: Path) -> None:
    np.save(tmp_path / "all.npy", np.full((3, 3), 9.99e29))
    with pytest.raises(NeuralMapError, match="9 of 9"):
        load_tile(tmp_path / "all.npy", spacing=10.0)
    with pytest.raises(NeuralMapError, match="every node is void"):
        load_tile(tmp_path / "all.npy", spacing=10.0, height_check="void")
    grid = np.full((3, 3), 10.0)
    grid[0, 0] = np.inf  # was silently turned into a void
    np.save(tmp_path / "inf.npy", grid)
    with pytest.raises(NeuralMapError, match="1 of 9"):
        load_tile(tmp_path / "inf.npy", spacing=10.0)


def test_nodata_option_for_asc_and_bad_values(tmp_path: Path) -> None:
    path = _asc(tmp_path / "a.asc", (500000.0, 4000000.0), 30.0, [[1, -9999], [3, 4]])
    assert load_tile(path, nodata=[-9999, -1]).n_void == 1
    with pytest.raises(NeuralMapError, match="nodata"):
        load_tile(path, nodata="none")
    with pytest.raises(NeuralMapError, match="height_check"):
        load_tile(path, height_check="maybe")


# --------------------------------------------------------------------------- frames


def test_utm_asc_gets_a_tile_local_frame(tmp_path: Path) -> None:
    path = _asc(tmp_path / "utm.asc", (500000.0, 4000000.0), 1.0,
                [[10, 11, 12], [13, 14, 15]])
    path.with_suffix(".prj").write_text('PROJCS["WGS 84 / UTM zone 16N",GEOGCS["WGS 84"]]')
    tile = load_tile(path)
    xy = tile.node_xy()
    assert tile.origin == (0.0, 0.0)
    np.testing.assert_array_equal(xy[0, 0], [0.0, 0.0])
    np.testing.assert_array_equal(xy[-1, -1], [2.0, 1.0])
    # float32 keeps the 1 m steps exactly (at 4e6 m they would round to 0.25-0.5 m)
    np.testing.assert_array_equal(xy.astype(np.float32), xy)
    ref = tile.georeference
    assert ref is tile.projected and crs_name(ref.crs) == "WGS 84 / UTM zone 16N"
    assert ref.to_projected(0.0, 0.0) == (500000.5, 4000000.5)  # SW cell centre
    assert ref.to_tile(500002.5, 4000001.5) == (2.0, 1.0)
    # same heights elsewhere on Earth are another tile
    other = _asc(tmp_path / "other.asc", (600000.0, 4000000.0), 1.0,
                 [[10, 11, 12], [13, 14, 15]])
    assert load_tile(other, units="metres").fingerprint() != load_tile(
        path.with_name("utm.asc")).fingerprint()


# --------------------------------------------------------------------------- messages


def test_asc_header_with_non_utf8_byte_and_float_counts(tmp_path: Path) -> None:
    path = tmp_path / "bin.asc"
    path.write_bytes(b"ncols 2\nnrows 2\nxllcorner 0\xff\n")
    with pytest.raises(NeuralMapError, match=r"byte 0xff at line 3") as info:
        load_tile(path)
    assert "codec" not in str(info.value)
    good = _asc(tmp_path / "f.asc", (500000.0, 4000000.0), 30.0, [[1, 2], [3, 4]])
    good.write_text(good.read_text().replace("ncols 2", "ncols 2.0"))
    assert load_tile(good).shape == (2, 2)
    good.write_text(good.read_text().replace("ncols 2.0", "ncols 2.5"))
    with pytest.raises(NeuralMapError, match="whole number"):
        load_tile(good)


def test_symlink_loop_and_dangling_link_are_named(tmp_path: Path) -> None:
    loop = tmp_path / "loop.asc"
    os.symlink(loop, loop)
    with pytest.raises(NeuralMapError, match="symbolic link loop"):
        load_tile(loop)
    dangling = tmp_path / "gone.npy"
    os.symlink(tmp_path / "missing.npy", dangling)
    with pytest.raises(NeuralMapError, match="dangling symbolic link"):
        load_tile(dangling, spacing=1.0)


def test_spacing_hint_names_every_place_to_set_it(tmp_path: Path) -> None:
    np.save(tmp_path / "g.npy", np.zeros((3, 3)))
    with pytest.raises(NeuralMapError) as info:
        load_tile(tmp_path / "g.npy")
    assert "tile_options: {spacing: 30}" in str(info.value)
    assert "load_tile(path, spacing=30)" in str(info.value)


def test_load_tile_of_none() -> None:
    with pytest.raises(NeuralMapError, match="NoneType"):
        load_tile(None)  # type: ignore[arg-type]


# --------------------------------------------------------------------------- voids


@pytest.mark.parametrize("halo", [0, 1])
def test_void_under_matches_a_plain_loop(halo: int) -> None:
    rng = np.random.default_rng(3)
    heights = rng.normal(size=(9, 11))
    heights[rng.random(heights.shape) < 0.08] = np.nan
    tile = DemTile(heights, spacing=(2.0, 3.0), origin=(10.0, -5.0))
    xy = np.stack([rng.uniform(5.0, 35.0, 400), rng.uniform(-10.0, 30.0, 400)], -1)
    xy[0] = [np.nan, 0.0]
    got = tile.void_under(xy.reshape(20, 20, 2), halo=halo).reshape(-1)
    ny, nx = heights.shape
    for k, (x, y) in enumerate(xy):
        u, v = (x - 10.0) / 2.0, (y + 5.0) / 3.0
        if not (np.isfinite(u) and 0 <= u <= nx - 1 and 0 <= v <= ny - 1):
            assert not got[k]
            continue
        j, i = min(int(u), nx - 2), min(int(v), ny - 2)
        block = heights[max(i - halo, 0): i + 2 + halo, max(j - halo, 0): j + 2 + halo]
        assert got[k] == bool(np.isnan(block).any()), (k, x, y)


# --------------------------------------------------------------------------- CRS and formats

#: A .prj as GDAL and ESRI tools write it: UTM zone 16N on WGS 84 (no AUTHORITY node).
ESRI_UTM16N = (Path(__file__).parents[1] / "data" / "esri_utm16n.prj").read_text().strip()


def test_readers_keep_a_crs_that_reads_back(tmp_path: Path) -> None:
    """The .prj's WKT (not just its name) and SRTM's EPSG:4326 are kept, so the CRS can be
    turned back into a real one (rasterio, pyproj)."""
    rasterio_crs = pytest.importorskip("rasterio.crs")
    path = _asc(tmp_path / "utm.asc", (500000.0, 4000000.0), 30.0, [[1, 2, 3], [4, 5, 6]])
    path.with_suffix(".prj").write_text(ESRI_UTM16N + "\n")
    tile = load_tile(path)
    assert tile.projected.crs == ESRI_UTM16N and tile.meta["crs"] == ESRI_UTM16N
    assert crs_name(tile.projected.crs) == "WGS_1984_UTM_Zone_16N"
    assert "WGS_1984_UTM_Zone_16N" in tile.meta["units_reason"]  # messages use the name
    assert rasterio_crs.CRS.from_user_input(tile.projected.crs).to_epsg() == 32616
    assert tile.describe()["projected"]["crs"] == ESRI_UTM16N
    # a geographic .asc keeps its GEOGCS too; units forced against the .prj drop it
    geo = _asc(tmp_path / "geo.asc", (-85.0, 36.0), 0.001, [[1, 2, 3], [4, 5, 6]])
    geo.with_suffix(".prj").write_text('GEOGCS["GCS_North_American_1983",DATUM['
                                       '"D_North_American_1983",SPHEROID["GRS_1980",6378137.0,'
                                       '298.257222101]],PRIMEM["Greenwich",0.0],UNIT["Degree",'
                                       '0.0174532925199433]]')
    tile = load_tile(geo)
    assert rasterio_crs.CRS.from_user_input(tile.meta["crs"]).to_epsg() == 4269
    assert load_tile(geo, units="metres").projected.crs is None
    hgt = tmp_path / "N36W085.hgt"
    np.full((1201, 1201), 100, dtype=">i2").tofile(hgt)
    assert load_tile(hgt).meta["crs"] == "EPSG:4326"


@pytest.mark.filterwarnings("ignore:Dataset has no geotransform")
def test_a_png_renamed_tif_is_named_as_such(tmp_path: Path) -> None:
    """A PNG renamed .tif was read as a 4-band raster with a gdal_translate -b 1 hint."""
    rasterio = pytest.importorskip("rasterio")
    png = tmp_path / "dem.png"
    with rasterio.open(png, "w", driver="PNG", height=8, width=8, count=4,
                       dtype="uint8") as dst:
        dst.write(np.zeros((4, 8, 8), dtype=np.uint8))
    renamed = tmp_path / "dem.tif"
    renamed.write_bytes(png.read_bytes())
    with pytest.raises(NeuralMapError) as info:
        load_tile(renamed)
    message = str(info.value)
    assert "'" + str(renamed) + "' is not a GeoTIFF" in message and "a PNG image" in message
    assert "bands" not in message and "-b 1" not in message
    assert "gdal_translate -of GTiff" in message
    for name, data, what in (("text.tif", b"ncols 3\nnrows 2\n", "a text file"),
                             ("empty.tif", b"", "an empty file"),
                             ("jpeg.tiff", b"\xff\xd8\xff\xe0" + bytes(12), "a JPEG image")):
        (tmp_path / name).write_bytes(data)
        with pytest.raises(NeuralMapError, match=f"is not a GeoTIFF: .*{what}"):
            load_tile(tmp_path / name)
