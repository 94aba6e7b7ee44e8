"""train.py end to end through ``main(args)`` on a tiny synthetic tile written as .npy."""

from __future__ import annotations

import io
import json
import sys
from contextlib import redirect_stdout
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
from tensorboard.plugins.custom_scalar import layout_pb2
from tensorboard.plugins.hparams import plugin_data_pb2

from neuralmap.dem import load_tile, synthetic_tile
from neuralmap.terrain.export import load_map
from neuralmap.training.callbacks.dashboard import SCALAR_LAYOUT
from neuralmap.training.callbacks.fit_report import HISTOGRAM_TAG, IMAGE_TAGS
from neuralmap.training.cli import default_config_path, main
from neuralmap.training.evaluation import evaluate_fit

REPO = Path(__file__).resolve().parents[2]
SPACING = 30.0
#: Small, fast model for the tiny tile (4 x 4 blocks on 64 x 64 nodes).
MODEL_ARGS = [
    "--model.block_nodes", "16", "--model.hidden", "16", "--model.n_frequencies", "8",
    "--data.batch_size", "1024", "--data.val_fraction", "0.05",
    "--trainer.log_every_n_steps", "1",
]


@pytest.fixture(autouse=True, scope="module")
def _restore_threads() -> object:
    """main() applies the config's `threads: 1`; give other test modules their setting back."""
    threads = torch.get_num_threads()
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="module")
def tile_path(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("tile") / "tiny.npy"
    np.save(path, synthetic_tile((64, 64), spacing=SPACING, seed=4).heights)
    return path


def _args(tile_path: Path, runs: Path, *extra: str) -> list[str]:
    return ["--data.path", str(tile_path), "--data.spacing", str(SPACING),
            "--runs_dir", str(runs), "--experiment", "tiny", *MODEL_ARGS, *extra]


def _run(args: list[str]) -> tuple[Path | None, str]:
    out = io.StringIO()
    with redirect_stdout(out):
        path = main(args)
    return path, out.getvalue()


@pytest.fixture(scope="module")
def trained(tmp_path_factory: pytest.TempPathFactory, tile_path: Path) -> tuple[Path, str, Path]:
    runs = tmp_path_factory.mktemp("runs")
    path, stdout = _run(_args(tile_path, runs, "--trainer.max_epochs", "3"))
    assert path is not None
    return path, stdout, runs


def test_last_stdout_line_is_the_map_path(trained: tuple[Path, str, Path]) -> None:
    path, stdout, runs = trained
    assert stdout.strip().splitlines()[-1] == str(path)
    assert path == runs / "tiny" / "version_0" / "neural_map.pt"
    assert path.is_file()


def test_run_folder_holds_config_metrics_figures_checkpoints(
    trained: tuple[Path, str, Path], tile_path: Path
) -> None:
    path, _, _ = trained
    run = path.parent
    config = yaml.safe_load((run / "config.yaml").read_text())
    assert config["data"]["path"] == str(tile_path)
    assert config["model"]["block_nodes"] == 16 and config["trainer"]["max_epochs"] == 3
    metrics = json.loads((run / "metrics.json").read_text())
    assert metrics["n_nodes"] == 64 * 64 and metrics["n_void"] == 0
    assert metrics["epochs"] == 3 and metrics["train_points"] > 0
    for key in ("rmse_m", "max_abs_m", "mean_m", "slope_rmse", "points_per_s", "num_parameters"):
        assert np.isfinite(metrics[key]), key
    for png in IMAGE_TAGS.values():
        assert (run / png).stat().st_size > 1000
    assert (run / "checkpoints" / "last.ckpt").is_file()
    assert list((run / "checkpoints").glob("best-*.ckpt"))


def test_event_files_hold_dashboard_tags(trained: tuple[Path, str, Path]) -> None:
    path, _, _ = trained
    events = EventAccumulator(
        str(path.parent), size_guidance={"scalars": 0, "images": 0, "histograms": 0, "tensors": 0}
    )
    events.Reload()
    tags = events.Tags()
    for tag in ("train/loss", "train/lr", "val/rmse_m", "val/max_abs_m", "val/slope_rmse",
                "final/rmse_m", "final/max_abs_m", "final/slope_rmse"):
        assert tag in tags["scalars"], tag
    assert len(events.Scalars("val/rmse_m")) == 3  # one per epoch
    for tag in IMAGE_TAGS:
        assert tag in tags["images"], tag
    assert HISTOGRAM_TAG in tags["histograms"]
    # custom-scalars layout: the four categories, naming only logged scalar tags
    proto = events.Tensors("custom_scalars__config__")[0].tensor_proto
    layout = layout_pb2.Layout()
    layout.ParseFromString(proto.string_val[0])
    assert [c.title for c in layout.category] == ["loss", "accuracy", "slope", "lr"]
    named = {tag for c in layout.category for ch in c.chart for tag in ch.multiline.tag}
    assert named == {t for group in SCALAR_LAYOUT.values() for _, (_, ts) in group.items()
                     for t in ts}
    assert named <= set(tags["scalars"])
    # hparams with the final metrics
    content = events.PluginTagToContent("hparams")["_hparams_/experiment"]
    hparams = plugin_data_pb2.HParamsPluginData()
    hparams.ParseFromString(content)
    metric_tags = {m.name.tag for m in hparams.experiment.metric_infos}
    assert {"final/rmse_m", "final/max_abs_m", "final/slope_rmse"} <= metric_tags
    names = {h.name for h in hparams.experiment.hparam_infos}
    assert {"model/hidden", "model/lr", "data/batch_size", "tile"} <= names


def test_exported_map_reproduces_the_reported_metrics(
    trained: tuple[Path, str, Path], tile_path: Path
) -> None:
    path, _, _ = trained
    metrics = json.loads((path.parent / "metrics.json").read_text())
    net = load_map(path)
    tile = load_tile(tile_path, spacing=SPACING)
    again = evaluate_fit(net, tile).metrics
    assert again["rmse_m"] == pytest.approx(metrics["rmse_m"], rel=1e-9)
    assert again["max_abs_m"] == pytest.approx(metrics["max_abs_m"], rel=1e-9)
    assert net.tile_fingerprint == tile.fingerprint()


def test_resume_from_last_checkpoint(trained: tuple[Path, str, Path], tile_path: Path) -> None:
    path, _, runs = trained
    last = path.parent / "checkpoints" / "last.ckpt"
    resumed, _ = _run(_args(tile_path, runs, "--trainer.max_epochs", "4",
                            "--ckpt_path", str(last)))
    assert resumed is not None and resumed != path
    metrics = json.loads((resumed.parent / "metrics.json").read_text())
    first = json.loads((path.parent / "metrics.json").read_text())
    assert metrics["epochs"] == 4
    assert metrics["global_step"] > first["global_step"]
    assert metrics["train_points"] > first["train_points"]  # counter restored, not reset


def test_resume_with_other_network_settings_is_refused(
    trained: tuple[Path, str, Path], tile_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    path, _, runs = trained
    last = path.parent / "checkpoints" / "last.ckpt"
    with pytest.raises(SystemExit) as exit_info:
        main(_args(tile_path, runs, "--model.hidden", "24", "--ckpt_path", str(last)))
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert "hidden: checkpoint 16 vs config 24" in err and "Traceback" not in err


def test_fast_dev_run_exports(tile_path: Path, tmp_path: Path) -> None:
    path, stdout = _run(_args(tile_path, tmp_path, "--trainer.fast_dev_run", "true"))
    assert path == tmp_path / "tiny" / "fast_dev_run" / "neural_map.pt"
    assert path.is_file() and stdout.strip().splitlines()[-1] == str(path)
    xy = torch.tensor([[300.0, 450.0], [10.0, 1800.0]])
    assert torch.isfinite(load_map(path)(xy)).all()


def test_paper_preset_config(tile_path: Path, tmp_path: Path) -> None:
    path, _ = _run(["--config", str(REPO / "configs" / "paper_bp.yaml"),
                    "--data.path", str(tile_path), "--data.spacing", str(SPACING),
                    "--runs_dir", str(tmp_path), "--trainer.fast_dev_run", "true"])
    assert path is not None
    net = load_map(path)
    assert net.config["encoding"] == "none" and net.config["hidden"] == 30
    assert net.config["num_blocks"] == [3, 1] and net.config["depth"] == 1
    assert net.config["activation"] == "bipolar_sigmoid"
    xy = torch.tensor([[300.0, 450.0], [1000.0, 1200.0]])
    assert net.analytic_slope(xy).shape == (2, 2)


def test_default_config_is_the_repo_train_yaml(capsys: pytest.CaptureFixture[str]) -> None:
    assert default_config_path().resolve() == (REPO / "configs" / "train.yaml").resolve()
    with pytest.raises(SystemExit) as exit_info:
        main(["--print_config"])
    assert exit_info.value.code == 0
    printed = yaml.safe_load(capsys.readouterr().out)
    assert printed["data"]["path"] == "jacksboro"
    assert printed["model"]["encoding"] == "fourier"


@pytest.mark.parametrize(
    "extra, message",
    [
        (["--data.path", "/nonexistent/dir/tile.hgt"], "tile.hgt"),
        (["--data.path", "{tmp}/tile.xyz"], ".xyz"),
        (["--model.num_blocks", "[100, 100]"], "cannot feed"),
        (["--ckpt_path", "/nonexistent/last.ckpt"], "ckpt_path"),
        (["--model.optimizer", "rmsprop"], "model.optimizer"),
    ],
)
def test_bad_input_exits_2_with_a_clear_message(
    tile_path: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str], extra: list[str],
    message: str,
) -> None:
    (tmp_path / "tile.xyz").write_text("1 2 3\n")
    extra = [e.replace("{tmp}", str(tmp_path)) for e in extra]
    with pytest.raises(SystemExit) as exit_info:
        main(_args(tile_path, tmp_path, "--trainer.fast_dev_run", "true") + extra)
    assert exit_info.value.code == 2
    err = capsys.readouterr().err
    assert "error:" in err and message in err
    assert "Traceback" not in err


@pytest.mark.slow
def test_ddp_two_processes_on_cpu(tile_path: Path, tmp_path: Path) -> None:
    import subprocess

    cmd = [sys.executable, str(REPO / "train.py"),
           *_args(tile_path, tmp_path, "--trainer.max_epochs", "2",
                  "--trainer.strategy", "ddp", "--trainer.devices", "2",
                  "--trainer.accelerator", "cpu", "--trainer.enable_progress_bar", "false")]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=600, cwd=tmp_path)
    assert done.returncode == 0, done.stderr[-3000:]
    path = Path(done.stdout.strip().splitlines()[-1])
    assert path.is_file() and path.name == "neural_map.pt"
    metrics = json.loads((path.parent / "metrics.json").read_text())
    assert metrics["world_size"] == 2 and metrics["epochs"] == 2
    # both ranks trained: together they saw every training node once per epoch
    n_train = metrics["n_train"]
    assert n_train * 2 <= metrics["train_points"] <= n_train * 2 + 2 * 1024
    assert np.isfinite(metrics["rmse_m"])
