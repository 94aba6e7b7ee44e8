"""End to end: ``python evaluate.py --config configs/wind_tiny.yaml`` and the study's checks."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from neuralmap.exceptions import NeuralMapError
from neuralmap.studies.cli import main
from neuralmap.studies.wind import WindStudyConfig

REPO_ROOT = Path(__file__).resolve().parents[2]
TINY = REPO_ROOT / "configs" / "wind_tiny.yaml"


def test_wind_study_end_to_end(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code = main(["--config", str(TINY), "--runs_dir", str(tmp_path), "--experiment", "w"])
    out = capsys.readouterr()
    assert code == 0, out.err
    folder = tmp_path / "w" / "version_0"
    for name in ("report.md", "results.json", "config.yaml", "wind_estimates.png",
                 "wind_outliers.png", "wind_outliers_zoom.png", "wind_shear.png",
                 "wind_error_clean.png", "track_error.png", "track_error_dr.png"):
        assert (folder / name).is_file(), name
    assert list(folder.glob("events.out.tfevents*"))
    results = json.loads((folder / "results.json").read_text())
    assert results["study"] == "wind"
    ran = results["filters"]
    assert "KF" in ran and "LTI" in ran
    assert ran == ["KF", "Sage-Husa", "RAF", "VB", "LTI"]
    for cond in ("clean", "outliers", "shear"):
        for name in ran:
            entry = results["conditions"][cond][name]
            assert entry["rmse_all"] > 0 and 0.0 <= entry["divergence_rate"] <= 1.0
    assert "patch_max_jump" in results["conditions"]["outliers"]["KF"]
    track = results["track"]["fixes_every_10"]
    # the correction with the true wind leaves only sensor and fix errors
    assert track["corrected (true wind)"]["max_rms"] < track["no correction"]["max_rms"] / 10
    assert len(results["claims"]) == 5
    # 6 runs: no verdict (the old study judged every claim from them)
    assert all(c["verdict"].startswith("not enough converged runs (6 of 6")
               for c in results["claims"])
    report = (folder / "report.md").read_text()
    assert "Track correction" in report and "claims" in report


@pytest.mark.parametrize(
    ("override", "match"),
    [
        ({"scale": 0.0}, "'scale'"),
        ({"process_var": -0.01}, "'process_var'"),
        ({"meas_var": 0.0}, "'meas_var'"),
        ({"correction_step": 2.0}, "'correction_step'"),
        ({"conditions": ["calm"]}, "unknown"),
        ({"filters": [{"name": "KF", "modle": "tvar"}]}, "unknown keys"),
        ({"filters": [{"name": "X", "model": "arma"}]}, "'model'"),
        ({"patch_std": -1.0}, "'patch_std'"),
        ({"filters": [{"name": "SH", "policy": "sage_husa", "policy_args": {"b": 1.0}}]},
         r"open interval \(0, 1\)"),
        ({"filters": [{"name": "SH", "policy": "sage_husa", "policy_args": {"b": 0.0}}]},
         "forgetting factor"),
        # policy_args as a list (not a mapping): a clear message, not a TypeError
        ({"filters": [{"name": "RAF", "policy": "raf", "policy_args": [1.5, 4.5]}]},
         "'policy_args' must be a mapping"),
        ({"filters": [{"name": "RAF", "policy": "RobustAdaptive"}]}, "unknown policy"),
        ({"filters": [{"name": "RAF", "policy": "raf", "policy_args": {"k2": 1.0}}]},
         "no option"),
    ],
)
def test_bad_study_options(override: dict, match: str) -> None:
    config = WindStudyConfig(**override)
    with pytest.raises(NeuralMapError, match=match):
        config.validate()


def test_bad_option_from_the_command_line_exits_2(tmp_path: Path,
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    code = main(["--config", str(TINY), "--runs_dir", str(tmp_path), "--scale", "-5"])
    assert code == 2
    assert "'scale'" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("before", "after", "expected"),
    [
        (104.0, 19.3, "partly"),        # halves, but meets neither of the paper's bounds
        (104.0, 80.0, "does not hold"),
        (8.0, 3.9, "holds"),            # < 10 m -> < 5 m
        (8.0, 5.5, "does not hold"),  # neither below 5 m nor halved
        (12.0, 4.5, "partly"),        # below 5 m and halved, but the paper started < 10 m
        (float("nan"), 3.0, "not measured (non-finite track error)"),
    ],
)
def test_track_claim_checks_the_papers_bounds(before: float, after: float,
                                              expected: str) -> None:
    """The old check was "halves" only: 104 m -> 19.3 m read "holds" against "< 10 m to
    < 5 m"."""
    from neuralmap.studies.wind import track_claim_verdict

    assert track_claim_verdict(before, after) == expected
