"""The differentiable-TAN study end to end on its tiny config, and its bad options."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from neuralmap.exceptions import NeuralMapError
from neuralmap.studies import cli
from neuralmap.studies.learned import LearnedStudyConfig

REPO_ROOT = Path(__file__).resolve().parents[2]


def test_bad_options_are_refused() -> None:
    for bad in ({"q_kind": "cholesky"}, {"map_source": "dem"}, {"method": "bilinear"},
                {"n_train_flights": 0}, {"bias_box": [5.0, 1.0, 0.0, 1.0]}, {"lr": 0.0}):
        with pytest.raises(NeuralMapError):
            LearnedStudyConfig(**bad).validate()


def test_learned_tiny_end_to_end(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    code = cli.main(["--config", str(REPO_ROOT / "configs" / "learned_tiny.yaml"),
                     "--runs_dir", str(tmp_path / "runs"), "--n_runs", "12",
                     "--n_train_flights", "16", "--epochs", "2", "--refine_epochs", "3",
                     "--em_max_iter", "50"])
    out = capsys.readouterr()
    assert code == 0, out.err
    folder = tmp_path / "runs" / "learned_tiny" / "version_0"
    results = json.loads((folder / "results.json").read_text())
    nav = results["navigation"]
    assert set(nav) == {"hand-tuned (paper 004)", "consistent (truth)", "mis-specified start",
                        "learned", "variational (from start)", "learned, biased map",
                        "learned + refined map"}
    assert all(m["n_runs"] == 12 for m in nav.values())
    hist = results["learning_history"]
    assert len(hist) == 3 and hist[-1]["log_likelihood_per_update"] > hist[0][
        "log_likelihood_per_update"]
    assert results["refinement"]["corridor_test"]["ratio"] < 1.0
    assert len(results["em"]["em_R_path"]) == 50
    report = (folder / "report.md").read_text()
    assert "Shumway" in report and "toolkit target" in report
    # 12 test draws: the NEES and navigation claims get no verdict; the learning and EM
    # claims do not rest on Monte Carlo runs
    verdicts = {c["claim"]: c["verdict"] for c in results["claims"]}
    for claim, text in verdicts.items():
        if "NEES" in claim or "navigation on the refined map" in claim:
            assert text.startswith("not enough converged runs (12 of 12"), (claim, text)
        else:
            assert text.split(" (")[0] in ("holds", "partly", "does not hold"), (claim, text)
    for name in ("learning", "error_vs_time", "em_vs_gradient"):
        assert (folder / f"{name}.png").is_file()
    assert list(folder.glob("events.out.tfevents*"))


def test_bias_box_off_the_tile_is_refused_before_learning(
        tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    """A bias box off the tile used to judge the refinement claims on 0 points
    ("nan → nan → does not hold"); now one clear error, exit 2, nothing written."""
    code = cli.main(["--config", str(REPO_ROOT / "configs" / "learned_tiny.yaml"),
                     "--runs_dir", str(tmp_path / "runs"),
                     "--bias_box", "[50000.0, 51000.0, 50000.0, 51000.0]"])
    err = capsys.readouterr().err
    assert code == 2
    assert "--bias_box [50000.0, 51000.0, 50000.0, 51000.0] leaves the tile" in err
    assert "Traceback" not in err and not list((tmp_path / "runs").rglob("results.json"))
