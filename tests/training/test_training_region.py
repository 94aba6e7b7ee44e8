"""Region training: memory-mapped batches, shard independence, seamless lazy sharded maps."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from neuralmap.dem.region import synthetic_region
from neuralmap.exceptions import NeuralMapError
from neuralmap.terrain import load_map
from neuralmap.terrain.sharded import ShardedTerrainMap
from neuralmap.training.region import (
    RegionBatches,
    RegionData,
    fit_region,
    plan_layout,
    splitmix64,
    train_shard,
)

SHAPE = (49, 73)  # 2 x 3 blocks of 24 node intervals


@pytest.fixture(scope="module")
def region_path(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("region") / "r.npy"
    synthetic_region(path, shape=SHAPE, spacing=100.0, seed=1)
    heights = np.load(path, mmap_mode="r+")
    heights[3, 4] = np.nan  # a void
    heights.flush()
    return path


def _grid_xy(data: RegionData) -> torch.Tensor:
    ny, nx = data.shape
    ii, jj = np.meshgrid(np.arange(ny), np.arange(nx), indexing="ij")
    return torch.tensor(np.stack([jj * 100.0, ii * 100.0], -1).reshape(-1, 2), dtype=torch.float32)


def test_splitmix64_reference_values() -> None:
    # reference outputs of splitmix64 seeded with 0 (Vigna's splitmix64.c: next() from x=0)
    out = splitmix64(np.array([0, 0x9E3779B97F4A7C15], dtype=np.uint64))
    assert out.tolist() == [0xE220A8397B1DCDAF, 0x6E789E6AA1B965F4]


def test_memmap_and_in_memory_batches_identical(region_path: Path) -> None:
    mapped = RegionData.open(region_path)
    loaded = RegionData.open(region_path, in_memory=True)
    assert isinstance(mapped.heights, np.memmap) and not isinstance(loaded.heights, np.memmap)
    layout = plan_layout(mapped, block_nodes=24)
    ids = np.arange(layout.count)
    windows = mapped.node_window(layout.block_bounds())
    a = RegionBatches(
        mapped.heights, (0, 0), mapped, windows, ids, points_per_block=50, steps=3, seed=4
    )
    b = RegionBatches(
        loaded.heights, (0, 0), loaded, windows, ids, points_per_block=50, steps=3, seed=4
    )
    for step in range(3):
        for x, y in zip(a[step], b[step], strict=True):
            assert torch.equal(x, y)
    xy, h, block = a[1]
    # every sample is a node of its block's extended domain, with the stored height
    bounds = torch.as_tensor(layout.block_bounds(), dtype=torch.float32)[block]
    assert bool(((xy[:, 0] >= bounds[:, 0] - 1e-3) & (xy[:, 0] <= bounds[:, 1] + 1e-3)).all())
    rows, cols = (xy[:, 1] / 100).round().long(), (xy[:, 0] / 100).round().long()
    assert torch.equal(h, torch.as_tensor(np.asarray(loaded.heights)[rows, cols]))
    assert bool(torch.isfinite(h).all())  # void nodes are dropped
    net_a, _ = train_shard(mapped, layout, (0, 3, 0, 2), steps=5, seed=2, points_per_block=32)
    net_b, _ = train_shard(loaded, layout, (0, 3, 0, 2), steps=5, seed=2, points_per_block=32)
    for key, value in net_a.state_dict().items():
        assert torch.equal(value, net_b.state_dict()[key]), key


def test_shard_layout_does_not_change_the_fit(region_path: Path, tmp_path: Path) -> None:
    data = RegionData.open(region_path)
    one = fit_region(
        data, tmp_path / "one", shard_blocks=(3, 2), steps=40, lr=1e-2, points_per_block=64
    )
    six = fit_region(
        data, tmp_path / "six", shard_blocks=(1, 1), steps=40, lr=1e-2, points_per_block=64
    )
    assert one["shards"] == 1 and six["shards"] == 6
    xy = _grid_xy(data)
    with torch.no_grad():
        h_one, h_six = load_map(one["index"])(xy), load_map(six["index"])(xy)
    np.testing.assert_allclose(h_six.numpy(), h_one.numpy(), atol=1e-3, rtol=0)


def test_sharded_map_is_seamless_and_lazy(region_path: Path, tmp_path: Path) -> None:
    data = RegionData.open(region_path)
    summary = fit_region(
        data, tmp_path / "m", shard_blocks=(1, 1), steps=100, lr=2e-2, points_per_block=64
    )
    model = load_map(tmp_path / "m")
    assert isinstance(model, ShardedTerrainMap) and model.loaded_shards == []
    with torch.no_grad():
        model(torch.tensor([[150.0, 150.0]]))
    assert model.loaded_shards == [0]  # only the south-west shard was read
    # a shard border at x = 2400 m: height and slope continuous (C2 blending, global weights)
    y = torch.linspace(200.0, 4600.0, 23)
    eps = 1e-2
    left = torch.stack([torch.full_like(y, 2400.0 - eps), y], -1).requires_grad_(True)
    right = torch.stack([torch.full_like(y, 2400.0 + eps), y], -1).requires_grad_(True)
    h_l, h_r = model(left), model(right)
    (g_l,) = torch.autograd.grad(h_l.sum(), left)
    (g_r,) = torch.autograd.grad(h_r.sum(), right)
    assert float((h_l - h_r).abs().max()) < 1e-2
    assert float((g_l - g_r).abs().max()) < 2e-3
    # the fit is a terrain map: RMSE well below the relief (std about 160 m)
    xy = _grid_xy(data)
    ref = torch.tensor(np.asarray(data.heights, dtype=np.float32)).reshape(-1)
    with torch.no_grad():
        pred = model(xy)
    ok = torch.isfinite(ref)
    rmse = float(((pred - ref)[ok] ** 2).mean().sqrt())
    assert rmse < 0.2 * float(ref[ok].std()), rmse
    assert summary["points"] > 0


def test_bad_region_input(tmp_path: Path) -> None:
    with pytest.raises(NeuralMapError, match="not found"):
        RegionData.open(tmp_path / "none.npy")
    np.save(tmp_path / "flat.npy", np.zeros((10, 10)))
    with pytest.raises(NeuralMapError, match="spacing"):
        RegionData.open(tmp_path / "flat.npy")
    data = RegionData.open(tmp_path / "flat.npy", spacing=30.0)
    with pytest.raises(NeuralMapError, match="devices"):
        fit_region(data, tmp_path / "o", devices=0)
    with pytest.raises(NeuralMapError, match="sharded"):
        (tmp_path / "bad.json").write_text("{}")
        load_map(tmp_path / "bad.json")


@pytest.mark.slow
def test_two_processes_equal_one(region_path: Path, tmp_path: Path) -> None:
    data = RegionData.open(region_path)
    one = fit_region(
        data, tmp_path / "p1", shard_blocks=(1, 1), steps=40, lr=1e-2, points_per_block=64
    )
    two = fit_region(
        data,
        tmp_path / "p2",
        shard_blocks=(1, 1),
        steps=40,
        lr=1e-2,
        devices=2,
        points_per_block=64,
    )
    assert two["world_size"] == 2 and [r["shards"] for r in two["per_rank"]] == [3, 3]
    xy = _grid_xy(data)
    with torch.no_grad():
        h1, h2 = load_map(one["index"])(xy), load_map(two["index"])(xy)
    np.testing.assert_allclose(h2.numpy(), h1.numpy(), atol=1e-4, rtol=0)


def _two_tiles(folder: Path, *, disagree: float = 0.0) -> np.ndarray:
    """Two adjacent 25 x 25 UTM .asc tiles of a plane (+ noise); returns the whole grid."""
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:25, 0:50]
    whole = 400 + 3.0 * xx + 2.0 * yy + rng.normal(0, 0.1, (25, 50))
    folder.mkdir(parents=True, exist_ok=True)
    # b starts one node early: its first column overlaps a's last one
    for name, part, x0 in (("a", whole[:, :25], 0.0),
                           ("b", whole[:, 24:49] + disagree, 24 * 30.0)):
        rows = "\n".join(" ".join(f"{v:.2f}" for v in r) for r in np.flipud(part))
        (folder / f"{name}.asc").write_text(
            f"ncols 25\nnrows 25\nxllcenter {500000 + x0}\nyllcenter 4000000\ncellsize 30\n"
            + rows + "\n")
        (folder / f"{name}.prj").write_text('PROJCS["WGS 84 / UTM zone 16N"]')
    return whole[:, :49]


FAST_REGION = ["--model.steps", "80", "--model.block_nodes", "12", "--model.overlap_nodes", "2",
               "--model.lr", "1e-2"]


def _region(args: list[str]) -> Path | None:
    from neuralmap.training.cli import main

    return main(["region", *args])


def _region_fails(args: list[str], capsys: pytest.CaptureFixture[str], code: int = 2) -> str:
    with pytest.raises(SystemExit) as info:
        _region(args)
    err = capsys.readouterr().err
    assert info.value.code == code, err[-2000:]
    assert "Traceback" not in err and err.count("error:") == 1, err
    return err


def test_cli_trains_a_two_tile_mosaic(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    whole = _two_tiles(tmp_path / "tiles")
    index = _region(["--data.path", str(tmp_path / "tiles" / "*.asc"),
                     "--out", str(tmp_path / "out"), *FAST_REGION])
    assert index == tmp_path / "out" / "map_index.json" and index.is_file()
    model = load_map(tmp_path / "out")
    assert model.info["region"]["path"] == str(tmp_path / "out" / "region.npy")
    stored = np.load(tmp_path / "out" / "region.npy")
    np.testing.assert_allclose(stored, np.round(whole, 2), atol=1e-4)
    xy = torch.tensor([[30.0 * 30, 10 * 30.0], [10 * 30.0, 20 * 30.0]])
    with torch.no_grad():
        h = model(xy)
    expected = torch.tensor([whole[10, 30], whole[20, 10]], dtype=torch.float32)
    assert float((h - expected).abs().max()) < 5.0  # a 3 m/node plane, fitted in 80 steps
    # nothing but the published folder is left beside it
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out", "tiles"]


@pytest.fixture(scope="module")
def published(tmp_path_factory: pytest.TempPathFactory, region_path: Path) -> Path:
    """A complete region output (2 x 3 shards of one block) to rerun into."""
    out = tmp_path_factory.mktemp("pub") / "out"
    _region(["--data.path", str(region_path), "--out", str(out), "--model.steps", "5",
             "--model.shard_blocks", "[1, 1]", "--model.points_per_block", "32"])
    return out


def _snapshot(out: Path) -> dict[str, bytes]:
    return {str(p.relative_to(out)): p.read_bytes() for p in sorted(out.rglob("*")) if p.is_file()}


@pytest.mark.parametrize("case", ["points_0", "points_neg", "all_nan", "spacing_0", "lr_nan",
                                  "threads_0", "strategy", "out_file", "sidecar_not_json",
                                  "sidecar_text_spacing", "text_npy", "mosaic_refused",
                                  "out_foreign", "no_spacing"])
def test_region_bad_input_exits_2_and_leaves_the_output_as_it_was(
    case: str, published: Path, region_path: Path, tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    before = _snapshot(published)
    source, out, extra = str(region_path), published, []
    if case in ("sidecar_not_json", "sidecar_text_spacing", "text_npy", "all_nan",
                "no_spacing"):
        source = str(tmp_path / "r.npy")
        if case == "text_npy":
            Path(source).write_text("not an array\n")
        elif case == "no_spacing":
            np.save(source, np.load(region_path))
        else:
            values = np.load(region_path)
            np.save(source, np.full_like(values, np.nan) if case == "all_nan" else values)
            sidecar = {"sidecar_not_json": "{spacing: [100, 100]",
                       "sidecar_text_spacing": '{"spacing": "100 m"}',
                       "all_nan": '{"spacing": [100, 100]}'}[case]
            Path(source + ".json").write_text(sidecar)
    if case == "mosaic_refused":
        _two_tiles(tmp_path / "tiles", disagree=50.0)  # the shared column disagrees by 50 m
        source = str(tmp_path / "tiles" / "*.asc")
    if case == "out_file":
        out = region_path
    if case == "out_foreign":
        out = tmp_path / "mine"
        out.mkdir()
        (out / "notes.txt").write_text("keep me")
    extra, expect = {
        "points_0": (["--model.points_per_block", "0"], "--model.points_per_block must be"),
        "points_neg": (["--model.points_per_block", "-5"], "--model.points_per_block must be"),
        "all_nan": ([], "holds no finite height"),
        "spacing_0": (["--data.spacing", "0"], "--data.spacing must be"),
        "lr_nan": (["--model.lr", "nan"], "model.lr"),
        "threads_0": (["--threads", "0"], "--threads must be"),
        "strategy": (["--trainer.strategy", "foo"], "--trainer.strategy must be one of"),
        "out_file": ([], "is a file"),
        "sidecar_not_json": ([], "is not JSON"),
        "sidecar_text_spacing": ([], "must be one number or [dx, dy]"),
        "text_npy": ([], "is not a NumPy .npy array"),
        "mosaic_refused": ([], "disagree"),
        "out_foreign": ([], "holding other files"),
        # the region trainer's own option (was: the Python keyword spacing=)
        "no_spacing": ([], "give it in metres (--data.spacing 100"),
    }[case]
    err = _region_fails(["--data.path", source, "--out", str(out), "--model.steps", "2",
                         *extra], capsys)
    assert expect in err, err
    assert _snapshot(published) == before  # the earlier output is untouched
    if case == "out_foreign":
        assert sorted(p.name for p in out.iterdir()) == ["notes.txt"]
    hidden = [p.name for p in published.parent.iterdir() if p.name.startswith(".")]
    assert hidden == []  # no staging folder or lock left


def test_region_rerun_that_fails_midway_keeps_the_old_output(
    published: Path, region_path: Path, monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    """A rerun failing (or Ctrl-C) after some shards were written leaves the old map whole."""
    import neuralmap.training.region as region

    before = _snapshot(published)
    original, calls = region.train_shard, []

    def fail_on_third(*args, **kwargs):  # noqa: ANN002, ANN003, ANN202
        calls.append(1)
        if len(calls) == 3:
            raise KeyboardInterrupt
        return original(*args, **kwargs)

    monkeypatch.setattr(region, "train_shard", fail_on_third)
    err = _region_fails(["--data.path", str(region_path), "--out", str(published),
                         "--model.steps", "5", "--model.shard_blocks", "[1, 1]",
                         "--model.points_per_block", "32", "--model.seed", "7"], capsys, code=1)
    assert "interrupted; nothing was published" in err
    assert _snapshot(published) == before
    assert not [p for p in published.parent.iterdir() if p.name.startswith(".")]


def test_region_rerun_killed_with_sigkill_keeps_the_old_output(
    published: Path, region_path: Path, tmp_path: Path,
) -> None:
    """kill -9 after two new shards: the old index and shards stay, whole and unmixed."""
    import os
    import shutil
    import subprocess
    import sys

    out = tmp_path / "out"
    shutil.copytree(published, out)
    before = _snapshot(out)
    script = (
        "import os, signal, sys\n"
        "import neuralmap.training.region as region\n"
        "original, calls = region.train_shard, []\n"
        "def kill_on_third(*a, **k):\n"
        "    calls.append(1)\n"
        "    if len(calls) == 3:\n"
        "        os.kill(os.getpid(), signal.SIGKILL)\n"
        "    return original(*a, **k)\n"
        "region.train_shard = kill_on_third\n"
        "from neuralmap.training.cli import main\n"
        "main(sys.argv[1:])\n")
    env = {**os.environ, "OMP_NUM_THREADS": "1",
           "PYTHONPATH": str(Path(__file__).resolve().parents[2])}
    proc = subprocess.run(
        [sys.executable, "-c", script, "region", "--data.path", str(region_path), "--out",
         str(out), "--model.steps", "5", "--model.shard_blocks", "[1, 1]",
         "--model.points_per_block", "32", "--model.seed", "7"],
        env=env, capture_output=True, text=True, timeout=300)
    assert proc.returncode == -9, proc.stderr[-2000:]
    assert _snapshot(out) == before
    # the next run cleans the killed run's hidden build and publishes whole
    _region(["--data.path", str(region_path), "--out", str(out), "--model.steps", "5",
             "--model.shard_blocks", "[1, 1]", "--model.points_per_block", "32"])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out"]
    assert _snapshot(out) == before  # same settings, same seed: the same map, bit for bit


def test_second_region_run_into_the_same_out_is_refused_while_one_runs(
    published: Path, region_path: Path, capsys: pytest.CaptureFixture[str],
) -> None:
    from neuralmap.io import replacing_dir

    before = _snapshot(published)
    with pytest.raises(RuntimeError, match="the other run fails"):
        with replacing_dir(published):  # another run holds the output, then fails
            err = _region_fails(["--data.path", str(region_path), "--out", str(published),
                                 "--model.steps", "2"], capsys)
            raise RuntimeError("the other run fails")
    assert "another run is writing this output now" in err
    assert _snapshot(published) == before


def test_train_py_map_mode_takes_a_glob_of_tiles(tmp_path: Path) -> None:
    """``train.py --data.path "tiles/*.asc"`` fits the stitched mosaic (was: file not found)."""
    import io
    from contextlib import redirect_stdout

    from neuralmap.training.cli import main

    whole = _two_tiles(tmp_path / "tiles")
    threads = torch.get_num_threads()
    try:
        with redirect_stdout(io.StringIO()):
            path = main(["--data.path", str(tmp_path / "tiles" / "*.asc"),
                         "--runs_dir", str(tmp_path / "runs"), "--experiment", "mosaic",
                         "--trainer.max_epochs", "2", "--model.block_nodes", "12",
                         "--model.hidden", "8", "--model.n_frequencies", "4",
                         "--data.batch_size", "512", "--data.refit_epochs", "0",
                         "--trainer.enable_progress_bar", "false"])
    finally:
        torch.set_num_threads(threads)
    model = load_map(path)
    assert model.tile_info["shape"] == [25, 49]
    assert model.tile_name.startswith("mosaic_a_2")
    assert whole.shape == (25, 49)


def test_void_shard_is_stored_as_void(tmp_path: Path) -> None:
    """A region with one all-NaN block (shards of one block): that shard is not trained and
    stored as void, queries over it return NaN (as a grid over voids), the other five are
    fitted, and the map loads through load_map."""
    from neuralmap.training.region import void_shards

    path = tmp_path / "r.npy"
    synthetic_region(path, shape=SHAPE, spacing=100.0, seed=1)
    heights = np.load(path, mmap_mode="r+")
    heights[24:, 48:] = np.nan  # the core of block (2, 1): x 4800-7200 m, y 2400-4800 m
    heights.flush()
    data = RegionData.open(path)
    layout = plan_layout(data, block_nodes=24)
    assert void_shards(data, layout, [(0, 3, 0, 2), (2, 3, 1, 2), (2, 3, 0, 1)]) == [1]
    summary = fit_region(data, tmp_path / "m", shard_blocks=(1, 1), steps=100, lr=2e-2,
                         points_per_block=64, block_nodes=24)
    assert summary["void_shards"] == [5] and summary["trained_shards"] == 5
    assert not (tmp_path / "m" / "shards" / "shard_00005.pt").exists()
    model = load_map(tmp_path / "m")
    assert isinstance(model, ShardedTerrainMap) and model.void_shards == [5]
    with torch.no_grad():
        void_h = model(torch.tensor([[6000.0, 3600.0], [7000.0, 4700.0], [5000.0, 2600.0]]))
        xy = _grid_xy(data)
        pred = model(xy)
    assert bool(torch.isnan(void_h).all())
    ref = torch.tensor(np.asarray(data.heights, dtype=np.float32)).reshape(-1)
    # away from the void block (and its blend band) the other blocks are fitted
    far = (xy[:, 0] < 4400.0) | (xy[:, 1] < 2000.0)
    assert bool(torch.isfinite(pred[far]).all())
    rmse = float(((pred - ref)[far] ** 2).mean().sqrt())
    assert rmse < 0.2 * float(ref[far].std()), rmse
    assert bool(torch.isnan(pred[(xy[:, 0] > 4800.0) & (xy[:, 1] > 2400.0)]).all())
    # gradients stay finite next to the void (no NaN leaks through the blend weights)
    probe = torch.tensor([[2000.0, 2000.0]], requires_grad=True)
    (grad,) = torch.autograd.grad(model(probe).sum(), probe)
    assert bool(torch.isfinite(grad).all())


@pytest.mark.slow
def test_torchrun_ranks_build_one_map_equal_to_one_process(region_path: Path,
                                                           tmp_path: Path) -> None:
    """``torchrun --nproc_per_node 2 train.py region --trainer.strategy ddp``: every rank
    starts at once, rank 0's build folder reaches the other by a broadcast, and the map
    published is the one-process map (the multi-node launch on one node)."""
    import json
    import os
    import subprocess
    import sys

    repo = Path(__file__).resolve().parents[2]
    args = ["--data.path", str(region_path), "--model.shard_blocks", "[1,1]",
            "--model.steps", "40", "--model.points_per_block", "64", "--model.lr", "1e-2"]
    env = {**os.environ, "OMP_NUM_THREADS": "1"}
    proc = subprocess.run(
        [sys.executable, "-m", "torch.distributed.run", "--nnodes", "1", "--nproc_per_node",
         "2", "--master_port", "29517", str(repo / "train.py"), "region", *args,
         "--out", str(tmp_path / "torchrun"), "--trainer.strategy", "ddp",
         "--trainer.devices", "2"],
        cwd=repo, env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    summary = json.loads(proc.stdout[proc.stdout.index("{"):])
    assert summary["world_size"] == 2 and [r["shards"] for r in summary["per_rank"]] == [3, 3]
    one = _region([*args, "--out", str(tmp_path / "one")])
    data = RegionData.open(region_path)
    xy = _grid_xy(data)
    with torch.no_grad():
        h1 = load_map(one)(xy)
        h2 = load_map(tmp_path / "torchrun" / "map_index.json")(xy)
    np.testing.assert_allclose(h2.numpy(), h1.numpy(), atol=1e-4, rtol=0)
