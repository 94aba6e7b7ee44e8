"""train.py on inputs that used to lose results, report in-sample numbers as held out, or
end in a raw traceback: each gives its own run folder, an honest metric or a clear error."""

from __future__ import annotations

import io
import json
import signal
from contextlib import redirect_stdout
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from neuralmap.dem import synthetic_tile
from neuralmap.training.cli import main
from neuralmap.training.datamodule import DemDataModule
from neuralmap.training.module import TerrainFitModule

SPACING = 30.0
FAST = ["--model.block_nodes", "16", "--model.hidden", "8", "--model.n_frequencies", "4",
        "--data.batch_size", "2048", "--data.val_fraction", "0.05",
        "--trainer.enable_progress_bar", "false", "--trainer.enable_model_summary", "false"]


@pytest.fixture(autouse=True, scope="module")
def _restore_threads() -> object:
    threads = torch.get_num_threads()
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def heights() -> np.ndarray:
    return synthetic_tile((32, 32), spacing=SPACING, seed=5).heights


@pytest.fixture(scope="module")
def tile_path(tmp_path_factory: pytest.TempPathFactory, heights: np.ndarray) -> Path:
    path = tmp_path_factory.mktemp("tile") / "small.npy"
    np.save(path, heights)
    return path


def _args(tile: Path, runs: Path, *extra: str, spacing: bool = True) -> list[str]:
    where = ["--data.path", str(tile)] + (["--data.spacing", str(SPACING)] if spacing else [])
    return [*where, "--runs_dir", str(runs), "--experiment", "small", *FAST, *extra]


def _run(args: list[str]) -> Path | None:
    with redirect_stdout(io.StringIO()):
        return main(args)


def _fails(args: list[str], capsys: pytest.CaptureFixture[str], code: int = 2) -> str:
    with pytest.raises(SystemExit) as info, redirect_stdout(io.StringIO()):
        main(args)
    err = capsys.readouterr().err
    assert info.value.code == code, err[-2000:]
    assert "Traceback" not in err
    return err


@pytest.fixture(scope="module")
def no_logger_runs(tmp_path_factory: pytest.TempPathFactory, tile_path: Path) -> Path:
    """Two runs with --trainer.logger false into the same experiment."""
    runs = tmp_path_factory.mktemp("runs")
    for seed in ("0", "1"):
        _run(_args(tile_path, runs, "--trainer.logger", "false", "--trainer.max_epochs", "2",
                   "--model.seed", seed))
    return runs


# --------------------------------------------------------------------------- results kept


def test_runs_without_logger_get_their_own_version_folders(no_logger_runs: Path) -> None:
    first, second = no_logger_runs / "small" / "version_0", no_logger_runs / "small" / "version_1"
    for run in (first, second):
        assert (run / "neural_map.pt").is_file() and (run / "metrics.json").is_file()
        assert (run / "config.yaml").is_file() and (run / "checkpoints" / "last.ckpt").is_file()
    assert not (no_logger_runs / "small" / "neural_map.pt").exists()  # was overwritten there
    seeds = [torch.load(r / "neural_map.pt", weights_only=True)["config"]["seed"]
             for r in (first, second)]
    assert seeds == [0, 1]


def test_refit_as_long_as_the_run_is_disabled_and_target_applied(
    tile_path: Path, tmp_path: Path
) -> None:
    # default refit_epochs 150 > 3 epochs: the validation nodes were trained on from epoch 0,
    # metrics.json still said val_rmse_m, and target_rmse was never applied. Also: a model
    # seed and a data seed (Lightning's hparams merge used to refuse the two `seed`s).
    with pytest.warns(UserWarning, match="refit disabled"):
        path = _run(_args(tile_path, tmp_path, "--trainer.max_epochs", "3",
                          "--model.target_rmse", "1.0e6", "--model.seed", "3",
                          "--data.seed", "4"))
    assert sorted(p.name for p in (tmp_path / "small").iterdir()) == ["version_0"]
    metrics = json.loads((path.parent / "metrics.json").read_text())
    assert metrics["refit_epochs_requested"] == 150 and metrics["refit_epochs"] == 0
    assert "refit disabled" in metrics["refit_note"]
    assert metrics["heldout_validation"] is True and metrics["val_epoch"] == 0
    assert metrics["target_reached_epoch"] == 0 and metrics["epochs"] == 1
    assert metrics["tile_units"] == "metres"


def test_plan_refit_rule() -> None:
    tile = synthetic_tile((8, 8), spacing=10.0)
    data = DemDataModule.from_tile(tile, refit_epochs=5)
    for max_epochs, effective, start in ((6, 5, 1), (5, 0, None), (3, 0, None), (-1, 0, None)):
        data.trainer = SimpleNamespace(max_epochs=max_epochs)  # type: ignore[assignment]
        if effective:
            data.plan_refit()
        else:
            with pytest.warns(UserWarning, match="refit disabled"):
                data.plan_refit()
        assert data.refit_epochs == effective and data.refit_start_epoch == start
        assert data.in_refit(max_epochs - 1) == (effective > 0)


def test_nodata_and_units_options(tmp_path: Path, heights: np.ndarray,
                                  capsys: pytest.CaptureFixture[str]) -> None:
    grid = np.round(heights).astype(np.int16)
    grid[3, 4] = grid[10, 20] = -32768
    np.save(tmp_path / "srtm.npy", grid)
    err = _fails(_args(tmp_path / "srtm.npy", tmp_path, "--trainer.fast_dev_run", "true"),
                 capsys)
    assert "--data.nodata" in err and "2 of 1024" in err
    data = DemDataModule(str(tmp_path / "srtm.npy"), spacing=SPACING, nodata=-32768)
    assert data.n_void == 2 and data.n_valid == 1022
    # a 0.5 m grid at (0, 0) could be degrees: refused until --data.units says which
    asc = tmp_path / "lidar.asc"
    rows = "\n".join(" ".join(f"{v:.2f}" for v in row) for row in heights[::-1])
    asc.write_text(f"ncols 32\nnrows 32\nxllcorner 0\nyllcorner 0\ncellsize 0.5\n{rows}\n")
    err = _fails(_args(asc, tmp_path, "--trainer.fast_dev_run", "true", spacing=False), capsys)
    assert "--data.units metres|degrees" in err
    data = DemDataModule(str(asc), units="metres")
    assert data.tile.spacing == (0.5, 0.5) and "caller" in data.tile.meta["units_reason"]


def test_runs_started_at_once_with_the_default_logger_get_their_own_folders(
    tile_path: Path, tmp_path: Path
) -> None:
    """Two trainers set up before either fits (two processes started together) used to pick
    the same lazily chosen TensorBoard ``version_0``; the folder is now reserved at setup."""
    from neuralmap.training.cli import MapMode

    clis = []
    for _ in range(2):
        callbacks, _report = MapMode.callbacks()
        with redirect_stdout(io.StringIO()):
            clis.append(MapMode.build(_args(tile_path, tmp_path, "--trainer.max_epochs", "1"),
                                   {}, callbacks))
    dirs = [Path(cli.trainer.logger.log_dir) for cli in clis]
    assert dirs == [tmp_path / "small" / "version_0", tmp_path / "small" / "version_1"]
    assert all(d.is_dir() for d in dirs)


# --------------------------------------------------------------------------- clear errors


@pytest.mark.parametrize(
    "case",
    ["max_epochs_0", "experiment_up", "runs_dir_file", "gpu", "ckpt_truncated", "ckpt_map",
     "ckpt_epochs"],
)
def test_bad_input_exits_2_before_any_run_folder(
    case: str, no_logger_runs: Path, tile_path: Path, tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
) -> None:
    done = no_logger_runs / "small" / "version_0"
    runs = tmp_path / "runs"
    extra, expect = {
        "max_epochs_0": (["--trainer.max_epochs", "0"], "trains nothing"),
        "experiment_up": (["--experiment", "../.."], "plain folder name inside --runs_dir"),
        "runs_dir_file": (["--runs_dir", str(tile_path)], "is a file"),
        "gpu": (["--trainer.accelerator", "gpu"], "--trainer.accelerator cpu"),
        "ckpt_truncated": (["--ckpt_path", str(tmp_path / "cut.ckpt")], "truncated"),
        "ckpt_map": (["--ckpt_path", str(done / "neural_map.pt")], "exported neural map"),
        "ckpt_epochs": (["--ckpt_path", str(done / "checkpoints" / "last.ckpt"),
                         "--trainer.max_epochs", "2", "--model.seed", "0"],
                        "already trained 2 epoch(s)"),
    }[case]
    if case == "gpu" and torch.cuda.is_available():
        pytest.skip("a GPU is present")
    (tmp_path / "cut.ckpt").write_bytes((done / "checkpoints" / "last.ckpt").read_bytes()[:2000])
    err = _fails(_args(tile_path, runs, "--trainer.max_epochs", "1", *extra), capsys)
    assert "error:" in err and expect in err
    assert not list(runs.glob("*/version_*"))  # no orphan run folder


def test_ctrl_c_says_how_to_resume(
    tile_path: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    original = TerrainFitModule.on_train_epoch_end

    def interrupt_in_epoch_1(self: TerrainFitModule) -> None:
        original(self)
        if self.current_epoch == 1:
            raise KeyboardInterrupt

    monkeypatch.setattr(TerrainFitModule, "on_train_epoch_end", interrupt_in_epoch_1)
    handler = signal.getsignal(signal.SIGINT)
    try:
        err = _fails(_args(tile_path, tmp_path, "--trainer.max_epochs", "5"), capsys, code=1)
    finally:
        signal.signal(signal.SIGINT, handler)  # Lightning ignores further Ctrl-C on shutdown
    last = tmp_path / "small" / "version_0" / "checkpoints" / "last.ckpt"
    assert last.is_file()
    assert f"--ckpt_path {last}" in err and "python train.py --config" in err


def test_run_that_exports_nothing_exits_1(
    tile_path: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
    capsys: pytest.CaptureFixture[str],
) -> None:
    from neuralmap.training.callbacks.fit_report import FitReport

    monkeypatch.setattr(FitReport, "on_train_end", lambda self, trainer, module: None)
    err = _fails(_args(tile_path, tmp_path, "--trainer.fast_dev_run", "true"), capsys, code=1)
    assert "without exporting a map" in err


@pytest.mark.parametrize("which", ["max_epochs", "max_steps"])
def test_negative_run_length_names_the_option(which: str, tile_path: Path, tmp_path: Path,
                                              capsys: pytest.CaptureFixture[str]) -> None:
    """Lightning's own message pointed at the accelerator options; the refusal names the
    option and what it accepts, before any run folder is made."""
    err = _fails(_args(tile_path, tmp_path, f"--trainer.{which}", "-5"), capsys)
    assert f"error: --trainer.{which} -5: give a count >= 1, or -1 for no limit" in err
    assert "accelerator" not in err
    assert not (tmp_path / "small").exists()
