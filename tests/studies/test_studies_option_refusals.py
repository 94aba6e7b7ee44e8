"""Study options refused at the start: exit 2, one ``error:`` line naming the option and the
fix, and no run folder."""

from __future__ import annotations

from pathlib import Path

import pytest

from neuralmap.studies import cli

REPO_ROOT = Path(__file__).resolve().parents[2]
ACQUISITION_TINY = REPO_ROOT / "configs" / "acquisition_tiny.yaml"


@pytest.mark.parametrize("value", ["0", "-3"])
def test_acquisition_bank_per_axis_below_one_is_refused(value: str, tmp_path: Path,
                                                        capsys: pytest.CaptureFixture[str]
                                                        ) -> None:
    code = cli.main(["--config", str(ACQUISITION_TINY), "--navigator",
                     f"{{ekf_bank: {{per_axis: {value}}}}}",
                     "--runs_dir", str(tmp_path / "runs")])
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.strip()]
    assert code == 2 and len(lines) == 1, err
    assert "error: --navigator:" in lines[0] and "ekf_bank.per_axis must be an integer >= 1" in (
        lines[0])
    assert f"got {value}" in lines[0]
    assert not (tmp_path / "runs").exists() or not any((tmp_path / "runs").rglob("*"))


TAN_TINY = REPO_ROOT / "configs" / "tan_tiny.yaml"


@pytest.mark.parametrize(("extra", "expected"), [
    (["--seed", "abc"], "error: --seed:"),
    (["--n_runs", "abc"], "error: --n_runs: Expected a <class 'int'>. Got value: abc"),
    (["--dtype", "float16"], "error: --dtype: Expected a typing.Literal['float64', 'float32']"),
    (["--no_such_option", "1"], "error: unrecognized arguments: --no_such_option 1"),
])
def test_parse_errors_are_one_line_naming_the_option(extra: list[str], expected: str,
                                                     tmp_path: Path,
                                                     capsys: pytest.CaptureFixture[str]) -> None:
    code = cli.main(["--config", str(TAN_TINY), "--runs_dir", str(tmp_path / "runs"), *extra])
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.strip()]
    assert code == 2 and len(lines) == 1, err
    assert expected in lines[0] and "evaluate.py --help" in lines[0], lines[0]
    assert "Parser key" not in lines[0]


@pytest.mark.parametrize(("extra", "expected"), [
    (["--n_steps", "5"], "error: --n_runs must be >= 1 and --n_steps >= 10, got"),
    (["--plot_run", "99999"], "error: --plot_run must be in [0, --n_runs)"),
    (["--conditions", "[]"], "error: --conditions: unknown or empty []; choose from"),
])
def test_wind_option_refusals_name_the_option(extra: list[str], expected: str, tmp_path: Path,
                                              capsys: pytest.CaptureFixture[str]) -> None:
    code = cli.main(["--config", str(REPO_ROOT / "configs" / "wind_tiny.yaml"),
                     "--runs_dir", str(tmp_path / "runs"), *extra])
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.strip()]
    assert code == 2 and len(lines) == 1 and expected in lines[0], err
