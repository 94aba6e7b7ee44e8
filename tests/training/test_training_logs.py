"""train.py with stdout redirected: one plain line per epoch, no progress-bar updates."""

from __future__ import annotations

import io
import re
from contextlib import redirect_stderr, redirect_stdout
from pathlib import Path

import numpy as np
import pytest
import torch

from neuralmap.dem import synthetic_tile
from neuralmap.training.cli import main

EPOCHS = 3


@pytest.fixture(autouse=True)
def _restore_threads() -> object:
    threads = torch.get_num_threads()
    yield
    torch.set_num_threads(threads)


def test_redirected_training_log_has_one_line_per_epoch(tmp_path: Path) -> None:
    tile = tmp_path / "tiny.npy"
    np.save(tile, synthetic_tile((32, 32), spacing=30.0, seed=1).heights)
    args = ["--data.path", str(tile), "--data.spacing", "30", "--runs_dir", str(tmp_path),
            "--experiment", "log", "--model.block_nodes", "16", "--model.hidden", "8",
            "--model.n_frequencies", "4", "--data.batch_size", "256",
            "--data.val_fraction", "0.05", "--data.refit_epochs", "0",
            "--trainer.max_epochs", str(EPOCHS), "--trainer.enable_progress_bar", "true"]
    out, err = io.StringIO(), io.StringIO()  # not terminals
    with redirect_stdout(out), redirect_stderr(err):
        path = main(args)
    assert path is not None and path.exists()
    text = out.getvalue() + err.getvalue()
    assert "\r" not in text  # no progress-bar redraws
    lines = [line for line in out.getvalue().splitlines() if line.startswith("train: ")]
    assert [int(re.match(r"train: (\d+)/3 epoch", line).group(1)) for line in lines] == [1, 2, 3]
    pattern = (r"train: \d+/3 epoch \(\d+%\), [\d.e+]+ epoch/s, [\dhms.]+ elapsed, "
               r"[\dhms.]+ left \| [\d.e+]+ step/s, .*train/loss [\d.e+-]+.*")
    for line in lines:
        assert re.fullmatch(pattern, line), line
    assert ", 0.0s left | " in lines[-1]
    assert "val/rmse_m" in lines[-1]
