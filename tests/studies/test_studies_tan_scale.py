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


@pytest.mark.slow
def test_tan_scale_on_a_local_dask_cluster_equals_one_process(tmp_path: Path) -> None:
    """``--cluster local:2`` (two worker processes) against ``--cluster none``: the results
    of the study, bit for bit (3 chunks of one seed block each; the chunks themselves run
    by run on a 2-worker cluster by default in tests/nav/test_nav_chunked.py)."""
    pytest.importorskip("distributed")
    args = ("--n_runs", "2100", "--chunk_runs", "1024", "--batch_runs", "1024")
    here = _run(tmp_path / "here", *args)
    dask = _run(tmp_path / "dask", *args, "--cluster", "local:2")
    assert here["n_chunks"] == dask["n_chunks"] == 3
    assert dask["cluster"]["worker_threads"] == 2 and here["cluster"]["worker_threads"] == 1
    assert dask["methods"]["bilinear"]["n_runs"] == 2100
    for key in ("n_included", "n_diverged", "rmse_pos_m", "final_pos_m", "rmse_pos_curve"):
        assert dask["methods"]["bilinear"][key] == here["methods"]["bilinear"][key], key


def test_tan_scale_defaults_to_a_local_cluster() -> None:
    assert TanScaleConfig().cluster_spec.kind == "local"


def test_tan_scale_bad_options() -> None:
    with pytest.raises(NeuralMapError, match="cluster"):
        TanScaleConfig(cluster="locl:2").validate()
    with pytest.raises(NeuralMapError, match="local:"):
        TanScaleConfig(cluster="local:0").validate()
    with pytest.raises(NeuralMapError, match="batch_runs"):
        TanScaleConfig(batch_runs=0).validate()
