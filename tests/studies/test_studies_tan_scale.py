"""The chunked TAN study end to end on its tiny config."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from neuralmap.exceptions import NeuralMapError
from neuralmap.studies import cli
from neuralmap.studies.tan_scale import TanScaleConfig

REPO_ROOT = Path(__file__).resolve().parents[2]


def _run(tmp_path: Path, *extra: str) -> dict:
    code = cli.main(["--config", str(REPO_ROOT / "configs" / "tan_scale_tiny.yaml"),
                     "--runs_dir", str(tmp_path / "runs"), *extra])
    assert code == 0
    folders = sorted((tmp_path / "runs" / "tan_scale_tiny").glob("version_*"))
    return json.loads((folders[-1] / "results.json").read_text())


def test_tan_scale_tiny_end_to_end(tmp_path: Path) -> None:
    results = _run(tmp_path, "--n_runs", "40")
    entry = results["methods"]["bilinear"]
    assert entry["n_runs"] == 40 and len(entry["rmse_pos_curve"]) == len(results["t"])
    assert results["n_chunks"] == 1 and results["peak_rss_mb"] > 0


@pytest.mark.slow
def test_tan_scale_tiny_chunking_does_not_change_results(tmp_path: Path) -> None:
    three = _run(tmp_path, "--n_runs", "1100", "--chunk_runs", "1024", "--batch_runs", "1024")
    one = _run(tmp_path, "--n_runs", "1100", "--chunk_runs", "4096", "--batch_runs", "1024")
    assert (three["n_chunks"], one["n_chunks"]) == (2, 1)
    assert three["methods"]["bilinear"]["rmse_pos_curve"] == one["methods"]["bilinear"][
        "rmse_pos_curve"]
    assert three["methods"]["bilinear"]["n_included"] == 1100


def test_tan_scale_bad_options() -> None:
    with pytest.raises(NeuralMapError, match="workers"):
        TanScaleConfig(workers=0).validate()
    with pytest.raises(NeuralMapError, match="batch_runs"):
        TanScaleConfig(batch_runs=0).validate()
