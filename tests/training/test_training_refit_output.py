"""train.py with a refit phase: held-out and in-sample errors under different names, the best
checkpoint ranked on held-out epochs only, and no third-party notices in the output."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

from neuralmap.dem import synthetic_tile

REPO = Path(__file__).resolve().parents[2]
EPOCHS, REFIT = 4, 2


@pytest.fixture(scope="module")
def refit_run(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, str]:
    """A 4-epoch fit whose last 2 epochs refit on every node, run as a user runs it
    (a subprocess, stdout and stderr captured together)."""
    root = tmp_path_factory.mktemp("refit")
    tile = root / "tiny.npy"
    np.save(tile, synthetic_tile((32, 32), spacing=30.0, seed=1).heights)
    args = [sys.executable, str(REPO / "train.py"), "--data.path", str(tile),
            "--data.spacing", "30", "--runs_dir", str(root / "runs"), "--experiment", "refit",
            "--model.block_nodes", "16", "--model.hidden", "8", "--model.n_frequencies", "4",
            "--data.batch_size", "256", "--data.val_fraction", "0.1",
            "--data.refit_epochs", str(REFIT), "--trainer.max_epochs", str(EPOCHS),
            "--trainer.enable_progress_bar", "true"]
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONWARNINGS": "default"}
    done = subprocess.run(args, cwd=root, env=env, capture_output=True, text=True, timeout=300)
    output = done.stdout + done.stderr
    assert done.returncode == 0, output
    return root / "runs" / "refit" / "version_0", output


def test_refit_epochs_log_refit_not_val(refit_run: tuple[Path, str]) -> None:
    run, _ = refit_run
    events = EventAccumulator(str(run), size_guidance={"scalars": 0})
    events.Reload()
    steps = {tag: [e.step for e in events.Scalars(tag)] for tag in events.Tags()["scalars"]}
    held = {"val/rmse_m", "val/max_abs_m", "val/mean_m", "val/slope_rmse"}
    for tag in held:
        refit_tag = tag.replace("val/", "refit/")
        assert len(steps[tag]) == EPOCHS - REFIT, (tag, steps[tag])
        assert len(steps[refit_tag]) == REFIT, (refit_tag, steps.get(refit_tag))
        # every refit value comes after every held-out one
        assert max(steps[tag]) < min(steps[refit_tag])


def test_best_checkpoint_is_a_held_out_epoch(refit_run: tuple[Path, str]) -> None:
    run, _ = refit_run
    best = sorted((run / "checkpoints").glob("best-*.ckpt"))
    assert len(best) == 1, best
    epoch = int(re.fullmatch(r"best-epoch(\d+)\.ckpt", best[0].name).group(1))
    assert epoch < EPOCHS - REFIT  # never a refit epoch, whose val nodes were trained on
    assert (run / "checkpoints" / "last.ckpt").is_file()


def test_epoch_lines_show_refit_metric_in_refit_epochs(refit_run: tuple[Path, str]) -> None:
    _, output = refit_run
    lines = [line for line in output.splitlines() if line.startswith("train: ")]
    assert len(lines) == EPOCHS
    for line in lines[: EPOCHS - REFIT]:
        assert "val/rmse_m" in line and "refit/" not in line, line
    for line in lines[EPOCHS - REFIT:]:
        assert "refit/rmse_m" in line and "val/rmse_m" not in line, line


def test_no_lightning_tips_nor_pytree_deprecation(refit_run: tuple[Path, str]) -> None:
    _, output = refit_run
    assert "GPU available" in output  # Lightning's own lines are still printed
    for notice in ("💡", "litlogger", "litmodels", "LeafSpec", "_pytree"):
        assert notice not in output, notice
