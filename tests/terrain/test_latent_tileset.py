"""Latent tilesets: seams against a single-tile fit, C¹ across seams, slope = d height,
lazy bounded decode, save / load, per-tile GeoTIFF, train.py end to end, the navigator's map.

One synthetic 65 x 65 region (30 m) is written as 2 x 2 metric ESRI ASCII tiles of 33 x 33
nodes sharing their edge node lines (as SRTM tiles do); the tileset is fitted with a 4-node
overlap and compared with one latent map fitted to the whole region with the same settings.
"""

from __future__ import annotations

import dataclasses
import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from neuralmap.dem.synthetic import synthetic_tile
from neuralmap.exceptions import NeuralMapError
from neuralmap.terrain.latent.encode import fit_latent_map
from neuralmap.terrain.latent.quality import map_quality
from neuralmap.terrain.latent.tile_cache import DEFAULT_CACHE_BYTES, decoded_bytes
from neuralmap.terrain.latent.tileset import LatentTileset
from neuralmap.terrain.latent.tileset_index import INDEX_FILENAME
from neuralmap.terrain.latent.tileset_layout import TilesetLayout
from neuralmap.training.latent_tileset import fit_tileset, plan_tileset

CONFIGS = Path(__file__).resolve().parents[2] / "configs"
SIDE, HALF, CELL = 65, 32, 30.0
SEAM = HALF * CELL  # 960 m, both axes
OVERLAP = 4
BLEND = OVERLAP * CELL  # blend half-width, m
OPTIONS = {"rate_weight": 3.0, "levels": 3, "between_points": 512, "seed": 0}
STEPS = 40
E0, N0 = 500000.0, 4000000.0
UTM16N = ('PROJCS["WGS 84 / UTM zone 16N",GEOGCS["WGS 84",DATUM["WGS_1984",SPHEROID["WGS 84",'
          '6378137,298.257223563]],PRIMEM["Greenwich",0],UNIT["degree",0.0174532925199433]],'
          'PROJECTION["Transverse_Mercator"],PARAMETER["latitude_of_origin",0],'
          'PARAMETER["central_meridian",-87],PARAMETER["scale_factor",0.9996],'
          'PARAMETER["false_easting",500000],PARAMETER["false_northing",0],UNIT["metre",1]]')


def _write_asc(path: Path, heights: np.ndarray, x0: float, y0: float, cell: float = CELL) -> None:
    ny, nx = heights.shape
    header = f"ncols {nx}\nnrows {ny}\nxllcenter {x0}\nyllcenter {y0}\ncellsize {cell}\n"
    rows = "\n".join(" ".join(f"{v:.3f}" for v in row) for row in np.flipud(heights))
    path.write_text(header + rows + "\n")
    path.with_suffix(".prj").write_text(UTM16N)


def _write_tiles(folder: Path, heights: np.ndarray) -> None:
    folder.mkdir(parents=True, exist_ok=True)
    for i in range(2):
        for j in range(2):
            _write_asc(folder / f"t{i}{j}.asc",
                       heights[HALF * i:HALF * i + HALF + 1, HALF * j:HALF * j + HALF + 1],
                       E0 + HALF * CELL * j, N0 + HALF * CELL * i)


@pytest.fixture(scope="module")
def fitted(tmp_path_factory: pytest.TempPathFactory) -> dict:
    root = tmp_path_factory.mktemp("tileset")
    region = synthetic_tile((SIDE, SIDE), CELL, seed=3)
    _write_tiles(root / "tiles", region.heights)
    torch.manual_seed(0)
    plan = plan_tileset(str(root / "tiles" / "*.asc"), overlap_nodes=OVERLAP)
    index = fit_tileset(plan, root / "run", steps=STEPS, options=OPTIONS, progress=False)
    single, _ = fit_latent_map(plan.region, steps=STEPS, **OPTIONS)
    return {"root": root, "plan": plan, "index": index, "single": single,
            "single_rmse": map_quality(single, plan.region, n_between=256)["rmse_m"]}


def _points(n: int, seed: int, x: tuple[float, float], y: tuple[float, float]) -> torch.Tensor:
    g = np.random.default_rng(seed)
    return torch.as_tensor(np.stack([g.uniform(*x, n), g.uniform(*y, n)], -1))


def test_plan_is_the_files_grid(fitted: dict) -> None:
    plan = fitted["plan"]
    assert plan.layout.grid == (2, 2) and plan.region.shape == (SIDE, SIDE)
    assert plan.layout.columns == ((0, HALF), (HALF, SIDE - 1))
    assert plan.layout.seams(0) == [SEAM] and plan.layout.seams(1) == [SEAM]
    assert plan.layout.window(0, 0) == (0, HALF + OVERLAP + 1, 0, HALF + OVERLAP + 1)
    assert plan.region.projected is not None and plan.region.projected.x_offset == E0
    assert Path(plan.sources[1]).name == "t01.asc"  # row 0 (south), column 1 (east)
    files = [str(fitted["root"] / "tiles" / f"t{k}.asc") for k in ("11", "00", "10", "01")]
    listed = plan_tileset(files, overlap_nodes=OVERLAP)  # a list, in any order
    assert listed.layout == plan.layout and listed.sources == plan.sources
    assert listed.region.fingerprint() == plan.region.fingerprint()


def test_seams_agree_with_a_single_tile_fit(fitted: dict) -> None:
    """On and near the seams, the tileset is as close to one map of the whole region as it
    is in the tile interiors, and both are within their fit error of the DEM."""
    ts, single = LatentTileset(fitted["index"]), fitted["single"]
    rmse = max(ts.metrics["rmse_m"], fitted["single_rmse"])
    near = torch.cat([_points(1500, 1, (SEAM - BLEND, SEAM + BLEND), (0, 1920)),
                      _points(1500, 2, (0, 1920), (SEAM - BLEND, SEAM + BLEND)),
                      torch.tensor([[SEAM, y] for y in np.linspace(0, 1920, 97)]),
                      torch.tensor([[x, SEAM] for x in np.linspace(0, 1920, 97)])])
    interior = torch.cat([_points(1500, 3, (60, SEAM - BLEND - 60), (60, SEAM - BLEND - 60)),
                          _points(1500, 4, (SEAM + BLEND + 60, 1860), (SEAM + BLEND + 60, 1860))])
    stats = {}
    for name, xy in (("near", near), ("interior", interior)):
        h, s = ts.height_and_slope(xy)
        hs, ss = single.height_and_slope(xy)
        stats[name] = ((h - hs).pow(2).mean().sqrt().item(),
                       (s - ss).pow(2).sum(-1).mean().sqrt().item())
    assert stats["near"][0] <= 2.0 * rmse  # independent fits: about sqrt(2) x RMSE apart
    assert stats["near"][0] <= 1.5 * stats["interior"][0] + 0.05 * rmse
    assert stats["near"][1] <= 1.5 * stats["interior"][1] + 1e-3
    # the seam nodes themselves: the tileset fits the DEM there as well as anywhere
    region = fitted["plan"].region
    nodes = torch.as_tensor(region.node_xy()[[HALF], :, :].reshape(-1, 2))
    seam_err = ts(nodes).numpy() - region.heights[HALF]
    assert np.sqrt(np.mean(seam_err**2)) <= 2.0 * ts.metrics["rmse_m"]


@pytest.mark.parametrize("axis", [0, 1])
def test_height_and_slope_are_continuous_across_seams(fitted: dict, axis: int) -> None:
    """Left and right limits agree at the seam and at both ends of its blend zone, although
    the two tiles themselves disagree there by far more (a hard switch would jump)."""
    ts = LatentTileset(fitted["index"])
    along = torch.linspace(15.0, 1905.0, 64, dtype=torch.float64)
    eps = 1e-6
    for where in (SEAM - BLEND, SEAM, SEAM + BLEND):
        cross = torch.full_like(along, where)
        lo = torch.stack([cross - eps, along] if axis == 0 else [along, cross - eps], -1)
        hi = torch.stack([cross + eps, along] if axis == 0 else [along, cross + eps], -1)
        (h0, s0), (h1, s1) = ts.height_and_slope(lo), ts.height_and_slope(hi)
        assert (h1 - h0).abs().max() < 1e-4  # float32 tables: 1e-5 m jumps at cell borders
        assert (s1 - s0).abs().max() < 1e-4
    at = torch.stack([torch.full_like(along, SEAM), along] if axis == 0
                     else [along, torch.full_like(along, SEAM)], -1)
    low_tile = ts.tile(0)  # tile (0, 0): south-west, on the low side of both seams
    high_tile = ts.tile(1 if axis == 0 else 2)
    inside = along < SEAM - BLEND  # where tile (0, 0) is one of the two
    gap = (low_tile(at) - high_tile(at))[inside].abs().max()
    assert gap > 1e-2  # the independent fits differ by centimetres at the seam


def test_slope_is_the_derivative_of_height_everywhere(fitted: dict) -> None:
    """Analytic slope (sum phi grad h + sum h grad phi) = central differences and autograd,
    blend zones and the four-tile corner included."""
    ts = LatentTileset(fitted["index"])
    xy = torch.cat([_points(800, 5, (0, 1920), (0, 1920)),
                    _points(800, 6, (SEAM - BLEND, SEAM + BLEND), (SEAM - BLEND, SEAM + BLEND)),
                    _points(800, 7, (SEAM - BLEND, SEAM + BLEND), (0, 1920))])
    cell = xy / CELL
    frac = cell - cell.floor()
    xy = xy[((frac > 0.05) & (frac < 0.95)).all(-1)]  # away from the float32 cell borders
    _, slope = ts.height_and_slope(xy)
    eps = 1e-3
    for k in range(2):
        step = torch.zeros(2, dtype=torch.float64)
        step[k] = eps
        fd = (ts(xy + step) - ts(xy - step)) / (2 * eps)
        torch.testing.assert_close(slope[:, k], fd, rtol=0, atol=1e-6)
    probe = xy.clone().requires_grad_(True)
    ts(probe).sum().backward()
    torch.testing.assert_close(probe.grad, slope, rtol=0, atol=1e-9)
    blend = (xy[:, 0] - SEAM).abs() < BLEND
    assert blend.sum() > 300  # the blend zones are well sampled


def test_off_region_empty_and_non_finite_points(fitted: dict) -> None:
    """Off the region the border tile answers alone (clamped like one latent map); NaN
    points give NaN without spoiling the others; an empty batch is empty."""
    ts = LatentTileset(fitted["index"])
    off = torch.tensor([[-100.0, 300.0], [300.0, 2100.0], [2100.0, 2100.0]],
                       dtype=torch.float64)
    h, s = ts.height_and_slope(off)
    for k, tile in enumerate((0, 2, 3)):
        h_k, s_k = ts.tile(tile).height_and_slope(off[k:k + 1])
        assert h[k] == h_k[0] and torch.equal(s[k], s_k[0])
    mixed = torch.tensor([[float("nan"), 300.0], [300.0, 300.0]], dtype=torch.float64)
    h, s = ts.height_and_slope(mixed)
    assert torch.isnan(h[0]) and torch.isnan(s[0]).all() and torch.isfinite(h[1])
    assert h[1] == ts.tile(0)(mixed[1:])[0]
    h, s = ts.height_and_slope(torch.zeros(0, 2, dtype=torch.float64))
    assert h.shape == (0,) and s.shape == (0, 2)


def test_tiles_decode_lazily_within_the_cache_bound(fitted: dict) -> None:
    ts = LatentTileset(fitted["index"], cache_tiles=2)
    assert ts.cache.decodes == 0 and len(ts.cache) == 0  # the index only
    ts(torch.tensor([[300.0, 300.0]], dtype=torch.float64))
    assert ts.cache.decodes == 1 and ts.cache.keys == [0]
    everywhere = _points(4000, 8, (0, 1920), (0, 1920))
    for lo in range(0, 4000, 250):
        ts.height_and_slope(everywhere[lo:lo + 250])
        assert len(ts.cache) <= 2
    assert ts.cache.peak_tiles == 2 and ts.cache.decodes > 4
    one = decoded_bytes(ts.tile(3))
    ny, nx = (b - a + 1 for a, b in zip(ts.tiles[3].window[::2], ts.tiles[3].window[1::2],
                                       strict=True))
    assert one >= 16 * 4 * (ny - 1) * (nx - 1)  # 16 float32 per cell: the polynomial table
    by_bytes = LatentTileset(fitted["index"], cache_bytes=int(1.5 * one))
    full = by_bytes.height_and_slope(everywhere)
    assert by_bytes.cache.peak_tiles == 1 and by_bytes.cache.peak_bytes <= 1.5 * one
    unbounded = LatentTileset(fitted["index"])  # the default budget holds all four
    assert unbounded.cache.max_bytes == DEFAULT_CACHE_BYTES
    same = unbounded.height_and_slope(everywhere)
    assert torch.equal(full[0], same[0]) and torch.equal(full[1], same[1])
    with pytest.raises(NeuralMapError, match="cache_tiles must be a whole number >= 1"):
        LatentTileset(fitted["index"], cache_tiles=0)


def test_save_load_round_trip_is_bit_identical(fitted: dict, tmp_path: Path) -> None:
    from neuralmap.terrain.export import load_map

    copy = tmp_path / "copied"
    shutil.copytree(fitted["index"].parent, copy)
    xy = _points(3000, 9, (-50, 1970), (-50, 1970))
    first = LatentTileset(fitted["index"]).height_and_slope(xy)
    for again in (load_map(copy / INDEX_FILENAME), load_map(copy)):
        assert isinstance(again, LatentTileset)
        second = again.height_and_slope(xy)
        assert torch.equal(first[0], second[0]) and torch.equal(first[1], second[1])
    assert not list(copy.glob(".*partial*"))  # no leftovers of the atomic writes


def test_damaged_or_missing_tile_is_named(fitted: dict, tmp_path: Path) -> None:
    copy = tmp_path / "broken"
    shutil.copytree(fitted["index"].parent, copy)
    victim = copy / "tiles" / "r000_c001.nlat"
    data = bytearray(victim.read_bytes())
    data[len(data) // 2] ^= 0xFF
    victim.write_bytes(bytes(data))
    ts = LatentTileset(copy)
    ts(torch.tensor([[300.0, 300.0]], dtype=torch.float64))  # tile (0, 0) is fine
    with pytest.raises(NeuralMapError, match=r"r000_c001\.nlat' is damaged \(sha256"):
        ts(torch.tensor([[1500.0, 300.0]], dtype=torch.float64))
    with pytest.raises(NeuralMapError, match="r000_c001.nlat"):
        ts.verify()
    victim.unlink()
    with pytest.raises(NeuralMapError, match=r"tile file\(s\) \['tiles/r000_c001.nlat'\] are missing"):
        LatentTileset(copy)


def test_export_per_tile_geotiff(fitted: dict, tmp_path: Path) -> None:
    rasterio = pytest.importorskip("rasterio")
    from neuralmap.terrain.latent.tileset_geotiff import export_tileset_geotiffs

    ts = LatentTileset(fitted["index"])
    region = fitted["plan"].region  # its CRS: the tiles' .prj WKT, as the reader kept it
    assert region.projected.crs == UTM16N and ts.tile_info["projected"]["crs"] == UTM16N
    written = export_tileset_geotiffs(ts, tmp_path, region=region)
    assert sorted(written) == [(0, 0), (0, 1), (1, 0), (1, 1)]
    assert all(sorted(layers) == ["height", "residual", "slope"] for layers in written.values())
    with rasterio.open(written[(0, 0)]["height"]) as west, \
            rasterio.open(written[(0, 1)]["height"]) as east:
        a, b = west.read(1), east.read(1)
        assert a.shape == (HALF + 1, HALF + 1) and west.crs.to_epsg() == 32616
        assert west.transform.c == pytest.approx(E0 - CELL / 2)
        assert east.transform.c == pytest.approx(E0 + HALF * CELL - CELL / 2)
        np.testing.assert_array_equal(a[:, -1], b[:, 0])  # the shared seam column
    nodes = torch.as_tensor(region.node_xy()[:HALF + 1, :HALF + 1].reshape(-1, 2))
    expect = ts(nodes).numpy().reshape(HALF + 1, HALF + 1)
    np.testing.assert_allclose(np.flipud(a), expect, rtol=0, atol=1e-3)  # float32 file
    with rasterio.open(written[(0, 0)]["residual"]) as res:
        np.testing.assert_allclose(np.flipud(res.read(1)),
                                   expect - region.heights[:HALF + 1, :HALF + 1], atol=1e-3)
    without = export_tileset_geotiffs(ts, tmp_path / "nodem")  # height and slope only
    assert sorted(without[(1, 1)]) == ["height", "slope"]
    # a tileset written when the index kept only the CRS name: pyproj looks it up
    ts.tile_info["projected"]["crs"] = "WGS 84 / UTM zone 16N"
    by_name = export_tileset_geotiffs(ts, tmp_path / "byname")
    with rasterio.open(by_name[(0, 0)]["height"]) as src:
        assert src.crs.to_epsg() == 32616
        np.testing.assert_array_equal(src.read(1), a)
    with pytest.raises(NeuralMapError, match="residual layer needs the DEM"):
        export_tileset_geotiffs(ts, tmp_path / "x", layers=("residual",))
    # Cloud Optimized GeoTIFF: GDAL's COG layout, the same values as the plain file
    cog = export_tileset_geotiffs(ts, tmp_path / "cog", region=region, cog=True)
    with rasterio.open(cog[(0, 0)]["height"]) as src:
        assert src.tags(ns="IMAGE_STRUCTURE").get("LAYOUT") == "COG"
        np.testing.assert_array_equal(src.read(1), a)
    assert not list((tmp_path / "cog").glob(".*"))  # no temporary file left behind


def test_navigator_map_source_resolves_the_index(fitted: dict) -> None:
    from neuralmap.dem.tile import ProjectedReference
    from neuralmap.nav.map_source import resolve_map

    for text in (str(fitted["index"]), str(fitted["index"].parent)):
        source = resolve_map(text)
        assert source.kind == "trained_map" and isinstance(source.terrain, LatentTileset)
        assert source.extent == (0.0, 1920.0, 0.0, 1920.0)
        assert isinstance(source.reference, ProjectedReference)
        assert source.reference.x_offset == E0 and source.reference.y_offset == N0
        assert source.fit_rmse_m == pytest.approx(source.terrain.metrics["rmse_m"])
        preview = source.preview_tile()
        assert np.isfinite(preview.heights).all()


def test_layout_is_a_partition_of_unity_and_refuses_close_seams() -> None:
    layout = TilesetLayout(shape=(2, 101), spacing=(10.0, 10.0), origin=(0.0, 0.0),
                           columns=((0, 30), (30, 60), (61, 100)), rows=((0, 1),),
                           overlap_nodes=5)
    assert layout.seams(0) == [300.0, 605.0]
    u = torch.linspace(-20.0, 1020.0, 5001, dtype=torch.float64, requires_grad=True)
    w = layout.axis_weights(u, 0)
    assert set(w.lower.tolist()) == {0, 1}
    weight, slope = w.weight()
    (grad,) = torch.autograd.grad(weight.sum(), u)
    torch.testing.assert_close(grad, slope, rtol=0, atol=1e-12)
    mixed = (weight > 0) & (weight < 1)
    assert (mixed == ((u - 300).abs() < 50) | ((u - 605).abs() < 50)).all()
    assert (mixed == w.blending).all()
    # the tile whose core holds u carries all the weight outside the blend zones
    core = torch.searchsorted(torch.tensor([300.0, 605.0], dtype=torch.float64), u.detach(),
                              right=True)
    assert (w.own == core).all()
    assert ((weight == 1) == (~w.blending & (w.offset > 0))).all()
    with pytest.raises(NeuralMapError, match="blend half-width of 20"):
        TilesetLayout(shape=(2, 101), spacing=(10.0, 10.0), origin=(0.0, 0.0),
                      columns=((0, 30), (30, 60), (60, 100)), rows=((0, 1),), overlap_nodes=20)
    with pytest.raises(NeuralMapError, match="neither touch nor share"):
        TilesetLayout(shape=(2, 101), spacing=(10.0, 10.0), origin=(0.0, 0.0),
                      columns=((0, 30), (40, 100)), rows=((0, 1),), overlap_nodes=2)


def test_bad_tilesets_are_refused(tmp_path: Path) -> None:
    heights = synthetic_tile((SIDE, SIDE), CELL, seed=4).heights
    with pytest.raises(NeuralMapError, match="matches no file"):
        plan_tileset(str(tmp_path / "none" / "*.hgt"))
    _write_tiles(tmp_path / "three", heights)
    (tmp_path / "three" / "t11.asc").unlink()
    with pytest.raises(NeuralMapError, match=r"do not fill a rectangle of 2 x 2 tiles"):
        plan_tileset(str(tmp_path / "three" / "*.asc"))
    _write_tiles(tmp_path / "spacing", heights)
    _write_asc(tmp_path / "spacing" / "t11.asc", heights[:33, :33], E0 + 960, N0 + 960, 10.0)
    with pytest.raises(NeuralMapError, match="share the spacing"):
        plan_tileset(str(tmp_path / "spacing" / "*.asc"))
    _write_tiles(tmp_path / "crs", heights)
    (tmp_path / "crs" / "t11.prj").write_text('PROJCS["NAD27 / UTM zone 16N"]')
    with pytest.raises(NeuralMapError, match="datum/CRS"):
        plan_tileset(str(tmp_path / "crs" / "*.asc"))
    with pytest.raises(NeuralMapError, match="one DEM: a tileset needs a glob"):
        plan_tileset("synthetic:65x65")


def test_train_py_latent_fits_a_tileset_from_a_glob(tmp_path: Path, capsys) -> None:  # noqa: ANN001
    from neuralmap.terrain.export import load_map
    from neuralmap.training.cli import main

    _write_tiles(tmp_path / "tiles", synthetic_tile((SIDE, SIDE), CELL, seed=5).heights)
    base = ["latent", "--config", str(CONFIGS / "latent_map.yaml"),
            "--config", str(CONFIGS / "latent_tileset_tiny.yaml"), "--runs_dir", str(tmp_path)]
    path = main([*base, "--data.path", str(tmp_path / "tiles" / "*.asc"),
                 "--data.tile_nodes", "null"])
    captured = capsys.readouterr()
    assert path is not None and captured.out.strip().splitlines()[-1] == str(path)
    assert path.name == INDEX_FILENAME and "latent tileset: tile r1 c1 (4/4)" in captured.out
    assert (path.parent / "config.yaml").is_file() and (path.parent / "metrics.json").is_file()
    ts = load_map(path)
    assert isinstance(ts, LatentTileset) and ts.layout.grid == (2, 2)
    assert sorted(p.name for p in (path.parent / "tiles").iterdir()) == [
        "r000_c000.nlat", "r000_c001.nlat", "r001_c000.nlat", "r001_c001.nlat"]
    assert 0 < ts.metrics["rmse_m"] < 50  # ten steps per tile: a rough but real fit
    h, s = ts.height_and_slope(torch.tensor([[SEAM, SEAM]], dtype=torch.float64))
    assert torch.isfinite(h).all() and torch.isfinite(s).all()
    with pytest.raises(SystemExit) as exc:
        main([*base, "--data.path", str(tmp_path / "nothing" / "*.hgt"), "--data.tile_nodes",
              "null"])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("error: --data.path") and "matches no file" in err[-1]


def test_geotiff_tiles_train_and_export_through_the_clis(tmp_path: Path, capsys) -> None:  # noqa: ANN001
    """GeoTIFF tiles -> train.py latent -> neuralmap-export of the tileset folder: per-tile
    GeoTIFFs in the tiles' CRS, the residual against the recorded source files."""
    rasterio = pytest.importorskip("rasterio")
    from rasterio.transform import from_origin

    from neuralmap.terrain.export_cli import main as export_main
    from neuralmap.training.cli import main

    heights = synthetic_tile((SIDE, SIDE), CELL, seed=6).heights
    (tmp_path / "tif").mkdir()
    for i in range(2):
        for j in range(2):
            part = heights[HALF * i:HALF * i + HALF + 1, HALF * j:HALF * j + HALF + 1]
            west = E0 + HALF * CELL * j - CELL / 2
            north = N0 + HALF * CELL * i + HALF * CELL + CELL / 2
            with rasterio.open(tmp_path / "tif" / f"t{i}{j}.tif", "w", driver="GTiff",
                               height=HALF + 1, width=HALF + 1, count=1, dtype="float32",
                               crs="EPSG:32616", transform=from_origin(west, north, CELL, CELL),
                               nodata=-32768.0) as dst:
                dst.write(np.flipud(part).astype(np.float32), 1)
    index = main(["latent", "--config", str(CONFIGS / "latent_map.yaml"), "--config",
                  str(CONFIGS / "latent_tileset_tiny.yaml"), "--runs_dir", str(tmp_path / "runs"),
                  "--data.path", str(tmp_path / "tif" / "*.tif"), "--data.tile_nodes", "null"])
    assert index is not None
    export_main([str(index.parent)])
    out = capsys.readouterr().out
    assert "tile r1 c1 residual ->" in out
    files = sorted((index.parent / "geotiff").glob("*.tif"))
    assert len(files) == 12
    with rasterio.open(index.parent / "geotiff" / "latent_tileset_r001_c001_residual.tif") as res:
        assert res.crs.to_epsg() == 32616 and res.shape == (HALF + 1, HALF + 1)
        residual = res.read(1)
    ts = LatentTileset(index)
    assert np.sqrt(np.mean(residual.astype(np.float64) ** 2)) <= 3.0 * ts.metrics["rmse_m"]


def test_the_navigator_flies_across_the_seams_as_on_the_single_tile_fit(fitted: dict) -> None:
    # a flight over the four tiles' seams (960 m on both axes): the Navigator on the tileset
    # gives the fixes it gives on the single latent map of the whole region, within a
    # fraction of their σ (the two maps differ by their fit error, not by the seams)
    from neuralmap.lab.scenario import load_scenario
    from neuralmap.lab.simulator import simulate
    from neuralmap.nav.fix import STATUS_CODE
    from neuralmap.nav.navigator import Navigator
    from neuralmap.terrain.export import load_map

    scenario = dataclasses.replace(load_scenario("tiny"), start_xy=[400.0, 400.0],
                                   duration_s=24.0).validate()
    truth = simulate(scenario, fitted["plan"].region, n_runs=4, seed=0)
    assert bool((truth.pos[:, 0, :2] < SEAM).all() and (truth.pos[:, -1, :2] > SEAM).all())
    config = {"sensor": {"dt_s": 1.0, "altimeter_sigma_m": 3.0},
              "initial": {"position_sigma_m": 20.0, "altitude_sigma_m": 10.0,
                          "velocity_sigma_mps": 0.2},
              "process_noise": {"position_sigma_m": 1.0, "altitude_sigma_m": 1.0,
                                "velocity_sigma_mps": 0.05}}

    def fly(terrain: object):  # noqa: ANN202 - FixTrack
        nav = Navigator(terrain, config, n_vehicles=truth.n_runs)
        return nav.replay(truth.t, truth.ins_pos[..., :2], truth.ins_pos[..., 2], truth.radar)

    tiles, single = fly(load_map(fitted["index"])), fly(fitted["single"])
    sigma = tiles.cov[..., 0, 0].sqrt()
    assert torch.isfinite(tiles.xy).all()
    assert float(((tiles.xy - single.xy).norm(dim=-1) / sigma).max()) < 1.0
    assert bool((tiles.status[:, -1] == STATUS_CODE["tracking"]).all())
