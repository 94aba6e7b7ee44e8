"""The GNSS/INS study end to end on the tiny config, its options, and the benchmark smoke run."""

from __future__ import annotations

import importlib.util
import json
import sys
from pathlib import Path
from types import ModuleType

import pytest

REPO_ROOT = Path(__file__).resolve().parents[2]
TINY = REPO_ROOT / "configs" / "gnss_ins_tiny.yaml"


def _load(name: str, path: Path) -> ModuleType:
    spec = importlib.util.spec_from_file_location(name, path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def evaluate() -> ModuleType:
    """The study command line behind ``evaluate.py`` (its ``main``)."""
    import neuralmap.studies.cli as cli

    return cli


def test_study_end_to_end(evaluate: ModuleType, tmp_path: Path,
                          capsys: pytest.CaptureFixture[str]) -> None:
    code = evaluate.main(["--config", str(TINY), "--runs_dir", str(tmp_path), "--n_runs", "4",
                          "--duration_s", "20", "--imu_rate_hz", "10", "--experiment", "e2e",
                          "--variants", "[plain,quality_inflation,quality_windowed]"])
    out = capsys.readouterr()
    assert code == 0, out.err
    folder = tmp_path / "e2e" / "version_0"
    for name in ("report.md", "results.json", "config.yaml", "error_vs_time.png",
                 "attitude_vs_time.png", "drive_map.png"):
        assert (folder / name).is_file(), name
    assert list(folder.glob("events.out.tfevents*"))
    results = json.loads((folder / "results.json").read_text())
    assert results["study"] == "gnss_ins"
    assert list(results["variants"]) == ["plain", "quality_inflation", "quality_windowed"]
    for entry in results["variants"].values():
        assert entry["n_runs"] == 4
        assert entry["counts"]["skipped_epochs"] == results["gnss"]["outage_epochs"]
    plain = results["variants"]["plain"]
    assert plain["divergence_rate"] == 0.0
    assert 0 < plain["rmse_horizontal_m"] < 0.5  # RTK-aided solution: centimetres
    assert len(results["curves"]["t"]) == 21
    report = (folder / "report.md").read_text()
    assert "Position error" in report and "SEEDS 003" in report
    claims = results["claims"]
    assert len(claims) == 3 and all(c["paper"] == "SEEDS 003" for c in claims)
    # a handful of runs: no verdict (the old study judged every claim from them)
    assert all(c["verdict"].startswith("not enough converged runs (") for c in claims)


def test_bad_options_exit_2(evaluate: ModuleType, capsys: pytest.CaptureFixture[str]) -> None:
    assert evaluate.main(["--config", str(TINY), "--variants", "[plain,sage_husa]"]) == 2
    assert "sage_husa" in capsys.readouterr().err
    assert evaluate.main(["--config", str(TINY), "--lever_arm_m", "[1.0,2.0]"]) == 2
    assert "lever_arm" in capsys.readouterr().err
    assert evaluate.main(["--config", str(TINY), "--imu_grade", "fog"]) == 2
    assert "unknown IMU grade" in capsys.readouterr().err
    assert evaluate.main(["--config", str(TINY), "--dtype", "float32"]) == 2
    assert "float64" in capsys.readouterr().err
    assert evaluate.main(["--config", str(TINY), "--window", "3"]) == 2
    assert "window" in capsys.readouterr().err
    assert evaluate.main(["--config", str(TINY), "--inflate_block", "[0,15]"]) == 2
    assert "inflate_block" in capsys.readouterr().err
    assert evaluate.main(["--config", str(TINY), "--alpha_cap", "0.5"]) == 2
    assert "alpha_cap" in capsys.readouterr().err


@pytest.mark.slow
def test_bench_ins_quick(capsys: pytest.CaptureFixture[str]) -> None:
    bench = _load("bench_ins_under_test", REPO_ROOT / "benchmarks" / "bench_ins.py")
    assert bench.main(["--quick"]) == 0
    out = capsys.readouterr().out
    assert "NumPy loop" in out and "block filter" in out and "per-sample filter" in out
    deviation = float(out.split("max difference ")[1].split(" m")[0])
    assert deviation < 1e-6  # same algorithm, same inputs, float64
