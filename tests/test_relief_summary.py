"""The relief summary table (benchmarks/relief_summary.py) from hand-written results files:
every number is the run's own, the newest run of each tile is read, a missing tile names the
command that makes it."""

from __future__ import annotations

import importlib.util
import json
import os
from pathlib import Path

import pytest

REPO_ROOT = Path(__file__).resolve().parents[1]


def _module():  # noqa: ANN202 - the script as a module
    spec = importlib.util.spec_from_file_location("relief_summary_under_test",
                                                  REPO_ROOT / "benchmarks" / "relief_summary.py")
    module = importlib.util.module_from_spec(spec)
    assert spec.loader is not None
    spec.loader.exec_module(module)
    return module


def _results(path: Path, ratio: float, mtime: float) -> None:
    path.mkdir(parents=True)
    risks = {"0.0001": {"misleading": {"count": 3, "epochs": 120000, "rate": 2.5e-05},
                        "diverged_flagged": {"runs": 2, "flagged": 2}},
             "0.01": {"misleading": {"count": 900, "epochs": 120000, "rate": 7.5e-03},
                      "diverged_flagged": {"runs": 2, "flagged": 1}}}
    results = {"methods": {"point_mass_tracker": {
        "n_runs": 1000, "n_included": 1000, "n_diverged": 2, "pcrb_ratio_all": ratio,
        "pcrb_map_ratio_all": 1.0625, "nees_in_band": 0.912}},
        "pcrb_map_aware": {"map_error_m2": 4.0, "map_error_corr": 0.5},
        "integrity": {"point_mass_tracker": {"risks": risks}}}
    (path / "results.json").write_text(json.dumps(results))
    os.utime(path / "results.json", (mtime, mtime))


def test_the_newest_run_of_a_tile_is_summarised(tmp_path: Path,
                                                capsys: pytest.CaptureFixture[str]) -> None:
    _results(tmp_path / "evaluate" / "version_0", 9.0, 1_000_000.0)
    _results(tmp_path / "evaluate" / "version_1", 1.25, 2_000_000.0)
    assert _module().main(["--runs_dir", str(tmp_path), "--no_relief",
                           "--tiles", "jacksboro", "gironde"]) == 0
    out = capsys.readouterr().out
    row = next(line for line in out.splitlines() if line.startswith("| jacksboro"))
    cells = [c.strip() for c in row.strip("|").split("|")]
    assert cells[2:] == ["2 m (ρ 0.50)", "1000", "1.250", "1.062", "0.2 % (2)", "91.2 %",
                         "2.5e-05 (3/120000)", "7.5e-03 (900/120000)", "1 of 2",
                         "evaluate/version_1"]
    assert "no run of gironde" in out and "configs/tan_gentle.yaml" in out
