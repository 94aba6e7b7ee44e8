"""The altimeter-fault study end to end on its tiny config, and its policy factory."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.studies import cli
from neuralmap.studies.tan_outliers import POLICIES, study_policy

REPO_ROOT = Path(__file__).resolve().parents[2]


def test_every_policy_builds_fresh_and_unknown_is_refused() -> None:
    """The study's policies are the registry's (same class and tuning), fresh per call,
    Sage-Husa clamped to R/4 … 100 R (the old test only checked "not None")."""
    from neuralmap.filters.policies import POLICIES as REGISTRY
    from neuralmap.filters.policies import make_policy

    for name in POLICIES:
        built = study_policy(name, R=106.0)
        reference = make_policy(name, {"R_min": 26.5, "R_max": 10600.0}
                                if name == "sage_husa" else None)
        assert type(built) is type(reference), name
        assert POLICIES[name] == REGISTRY[name].label
    sh = study_policy("sage_husa", R=106.0)
    assert (float(sh.R_min), float(sh.R_max)) == (26.5, 10600.0)
    assert study_policy("ekf", R=1.0) is None
    assert study_policy("raf", R=1.0) is not study_policy("raf", R=1.0)
    with pytest.raises(NeuralMapError, match="unknown policy"):
        study_policy("kalman", R=1.0)


def test_tan_outliers_tiny_end_to_end(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    from neuralmap.lab.scenario import load_scenario, scenario_tile
    from neuralmap.terrain.blockwise import BlockwiseTerrainNet
    from neuralmap.terrain.export import save_map

    torch.manual_seed(0)
    tile = scenario_tile(load_scenario("tiny"))
    map_path = tmp_path / "neural_map.pt"
    save_map(BlockwiseTerrainNet.from_tile(tile, hidden=8, n_frequencies=4), map_path)
    code = cli.main(["--config", str(REPO_ROOT / "configs" / "tan_outliers_tiny.yaml"),
                     "--map", str(map_path), "--runs_dir", str(tmp_path / "runs"),
                     "--n_runs", "12", "--policies", "[ekf,chi2,raf]"])
    out = capsys.readouterr()
    assert code == 0, out.err
    folder = tmp_path / "runs" / "tan_outliers_tiny" / "version_0"
    results = json.loads((folder / "results.json").read_text())
    for method in ("neural_region", "nine_point"):
        entry = results["methods"][method]
        assert set(entry) == {"clean", "ekf", "chi2", "raf"}
        assert entry["clean"]["n_included"] == 12
        # the nine-point plain EKF suffers from the faults; the gate holds it near clean
        assert entry["ekf"]["rmse_pos_m"] > entry["clean"]["rmse_pos_m"]
    nine = results["methods"]["nine_point"]
    assert nine["chi2"]["rmse_pos_m"] < nine["ekf"]["rmse_pos_m"]
    assert results["fault_share"]["spike"] > 0 and results["fault_share"]["patch"] > 0
    # 12 runs: no claim gets holds / does not hold (the old study judged them all)
    assert results["claims"]
    assert all(c["verdict"].startswith("not enough converged runs (") for c in results["claims"])
    report = (folder / "report.md").read_text()
    assert "SEEDS 002" in report and "toolkit target" in report and "divergence.png" in report
    assert (folder / "rmse_vs_time_nine_point.png").is_file()
    assert list(folder.glob("events.out.tfevents*"))


def test_fault_options_are_named_as_options(tmp_path: Path, tiny_map: Path,
                                            capsys: pytest.CaptureFixture) -> None:
    """A bad fault option was reported as a scenario-YAML key to fix."""
    code = cli.main(["--config", str(REPO_ROOT / "configs" / "tan_outliers_tiny.yaml"),
                     "--map", str(tiny_map), "--runs_dir", str(tmp_path / "runs"),
                     "--patch_min_s", "30", "--patch_max_s", "20"])
    err = capsys.readouterr().err
    assert code == 2
    assert "tan_outliers: --patch_min_s must be in (0, patch_max_s = 20.0], got 30.0." in err
    assert "scenario YAML" not in err
