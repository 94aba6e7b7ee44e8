"""Acquisition study: a tiny run end to end (results, report, claims), bad options refused,
runs that leave the map are counted and excluded, never fatal; the rows on a Dask cluster
equal those of one process."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml

REPO = Path(__file__).resolve().parents[2]


def test_wide_start_spread_counts_off_map_runs_and_finishes(tmp_path: Path) -> None:
    scenario = yaml.safe_load((REPO / "configs" / "scenarios" / "tiny.yaml").read_text())
    scenario["start_spread_m"] = 450.0  # some runs start or end off the 2.9 km tile
    scenario_file = tmp_path / "wide.yaml"
    scenario_file.write_text(yaml.safe_dump(scenario))
    from neuralmap.studies.cli import main

    code = main(["--config", str(REPO / "configs" / "acquisition_tiny.yaml"),
                 "--scenario", str(scenario_file), "--runs_dir", str(tmp_path / "runs"),
                 "--n_runs", "40", "--sigmas_m", "[60.0]", "--methods",
                 "[ekf,point_mass_tracker]", "--flat_leg", "false"])
    assert code == 0
    folder = tmp_path / "runs" / "acquisition_tiny" / "version_0"
    results = json.loads((folder / "results.json").read_text())
    off = results["off_map"]["60/grid"]
    assert off["runs"] == 40 and 0 < off["off_map"] < 40
    rows = results["sigmas"]["60"]
    for key in ("grid/ekf", "grid/point_mass_tracker"):
        assert rows[key]["n_included"] == 40 - off["off_map"]
        assert rows[key]["n_off_map"] == off["off_map"]
    assert "off-map" in (folder / "report.md").read_text()


def test_tracker_rows_fly_the_first_n_runs_per_method_runs(tmp_path: Path) -> None:
    from neuralmap.studies.cli import main

    code = main(["--config", str(REPO / "configs" / "acquisition_tiny.yaml"),
                 "--runs_dir", str(tmp_path / "runs"), "--n_runs", "12",
                 "--n_runs_per_method", "{point_mass_tracker: 5}",
                 "--sigmas_m", "[60.0]", "--methods", "[ekf,point_mass_tracker]",
                 "--flat_leg", "false"])
    assert code == 0
    results = json.loads((tmp_path / "runs" / "acquisition_tiny" / "version_0" /
                          "results.json").read_text())
    rows = results["sigmas"]["60"]
    assert rows["grid/ekf"]["n_included"] == 12
    assert rows["grid/point_mass_tracker"]["n_included"] == 5
    # the map-aware PCRB beside the true-terrain one: the rows' RMS over the last half of
    # the curve, and the tracker's claim against it
    curve = results["curves"]["60/pcrb_map_aware"]
    tail = curve[len(curve) // 2:]
    rms = (sum(v * v for v in tail) / len(tail)) ** 0.5
    ekf = rows["grid/ekf"]
    assert abs(ekf["pcrb_map_pos_m"] - rms) <= 1e-9 * rms
    assert abs(ekf["pcrb_map_ratio_all"] - ekf["rmse_pos_m"] / rms) <= 1e-9
    assert rows["grid/point_mass_tracker"]["pcrb_map_pos_m"] > 0
    assert results["pcrb_map_aware"]["map_error_m2"] > 0
    claims = [c["claim"] for c in results["claims"]]
    assert any("point_mass_tracker" in c and "map-aware PCRB" in c for c in claims)


@pytest.mark.slow
def test_rows_on_a_local_dask_cluster_equal_this_process(tmp_path: Path) -> None:
    """Every row (σ0 × map × method) one task on two Dask workers: the rows, curves and
    off-map counts of this process, bit for bit (wall times aside)."""
    pytest.importorskip("distributed")
    from neuralmap.studies.cli import main

    def study(name: str, cluster: str) -> dict:  # type: ignore[type-arg]
        code = main(["--config", str(REPO / "configs" / "acquisition_tiny.yaml"),
                     "--runs_dir", str(tmp_path / name),
                     "--n_runs_per_method", "{point_mass_tracker: 4}",
                     "--flat_leg", "false", "--tensorboard", "false", "--cluster", cluster])
        assert code == 0
        return json.loads((tmp_path / name / "acquisition_tiny" / "version_0" /
                           "results.json").read_text())

    here, dask = study("here", "none"), study("dask", "local:2")
    timing = ("wall_s", "cell_updates_per_s")
    rows = [(s, k) for s, per in here["sigmas"].items() for k in per]
    assert len(rows) == 8
    for sigma, key in rows:
        a, b = here["sigmas"][sigma][key], dask["sigmas"][sigma][key]
        assert {k: v for k, v in a.items() if k not in timing} == {
            k: v for k, v in b.items() if k not in timing}, (sigma, key)
    assert here["curves"] == dask["curves"] and here["off_map"] == dask["off_map"]


def test_acquisition_study_end_to_end(tmp_path: Path) -> None:
    """``python evaluate.py --config configs/acquisition_tiny.yaml`` writes a complete run
    (the methods flown by name through the Navigator with the config's navigator options)."""
    from neuralmap.studies.cli import main

    config = REPO / "configs" / "acquisition_tiny.yaml"
    code = main(["--config", str(config), "--runs_dir", str(tmp_path), "--sigmas_m", "[80.0]",
                 "--methods", "[ekf,point_mass_ekf]", "--n_runs", "4", "--n_runs_flat", "2",
                 "--tensorboard", "false"])
    assert code == 0
    folder = tmp_path / "acquisition_tiny" / "version_0"
    results = json.loads((folder / "results.json").read_text())
    rows = results["sigmas"]["80"]
    assert set(rows) == {"grid/ekf", "grid/point_mass_ekf"}
    assert rows["grid/point_mass_ekf"]["n_included"] >= 1
    assert results["flat_leg"]["final_posterior_sigma_median_m"] > 40.0  # stays wide
    report = (folder / "report.md").read_text()
    assert "Flat-terrain leg" in report and "Hand-off test" in report
    # 4 runs: no divergence or PCRB verdict (the old study judged them)
    assert results["claims"]
    assert all(c["verdict"].startswith("not enough converged runs (") for c in results["claims"])
    assert not list(folder.glob("events.out.tfevents*"))  # --tensorboard false


def test_study_config_rejects_bad_values() -> None:
    from neuralmap.exceptions import NeuralMapError
    from neuralmap.studies.acquisition import AcquisitionStudyConfig

    with pytest.raises(NeuralMapError, match="methods"):
        AcquisitionStudyConfig(methods=["kalman"]).validate()
    with pytest.raises(NeuralMapError, match="sigmas_m"):
        AcquisitionStudyConfig(sigmas_m=[-1.0]).validate()
    with pytest.raises(NeuralMapError, match="maps"):
        AcquisitionStudyConfig(maps=["lidar"]).validate()
    with pytest.raises(NeuralMapError, match="navigator"):
        AcquisitionStudyConfig(navigator=["point_mass"]).validate()
