"""The TAN study on scenarios none of whose flights can be scored: one clean refusal (exit 2,
the reason and the fix), whatever methods run, nothing written."""

from __future__ import annotations

from pathlib import Path

import pytest

from neuralmap.studies import cli

REPO_ROOT = Path(__file__).resolve().parents[2]
TINY = REPO_ROOT / "configs" / "tan_tiny.yaml"
SCENARIO = (REPO_ROOT / "configs" / "scenarios" / "tiny.yaml").read_text()

#: Scenario edits: the flights start off the tile, leave it, or (1e6 m initial spread) start
#: nowhere near it.
CASES = {
    "starts_off": {"start_xy: [500.0, 500.0]": "start_xy: [-9000.0, -9000.0]"},
    "leaves": {"duration_s: 40.0": "duration_s: 400.0",
               "start_xy: [500.0, 500.0]": "start_xy: [2000.0, 2000.0]"},
    "huge_initial_error": {"start_spread_m: 100.0": "start_spread_m: 1000000.0"},
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_no_scorable_run_is_one_clean_refusal(case: str, tmp_path: Path, tiny_map: Path,
                                              capsys: pytest.CaptureFixture[str]) -> None:
    text = SCENARIO
    for old, new in CASES[case].items():
        assert old in text
        text = text.replace(old, new)
    scenario = tmp_path / f"{case}.yaml"
    scenario.write_text(text)
    # neural first: its measured-R pilot flights used to run on zero on-map points
    code = cli.main(["--config", str(TINY), "--map", str(tiny_map), "--scenario", str(scenario),
                     "--runs_dir", str(tmp_path / "runs"), "--n_runs", "8",
                     "--noise_pilot_runs", "8", "--methods", "[neural,bilinear]"])
    err = capsys.readouterr().err
    assert code == 2, err
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1 and ("error: no run could be scored: all 8 truth trajectories "
                                "left the tile") in lines[0], err
    assert "start_xy" in lines[-1] and "Traceback" not in err
    assert not any((tmp_path / "runs").rglob("*.json")) if (tmp_path / "runs").exists() else True


def test_tan_outliers_refusal_names_the_scenario_and_the_fix(tmp_path: Path, tiny_map: Path,
                                                             capsys: pytest.CaptureFixture[str]
                                                             ) -> None:
    scenario = tmp_path / "off.yaml"
    scenario.write_text(SCENARIO.replace("start_xy: [500.0, 500.0]",
                                         "start_xy: [-9000.0, -9000.0]"))
    code = cli.main(["--config", str(REPO_ROOT / "configs" / "tan_outliers_tiny.yaml"),
                     "--map", str(tiny_map), "--scenario", str(scenario),
                     "--runs_dir", str(tmp_path / "runs")])
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.strip()]
    assert code == 2 and len(lines) == 1, err
    assert "no run could be scored" in lines[0] and str(scenario) in lines[0]
    assert "start_xy" in lines[0]
