"""End-to-end tests of ``python evaluate.py`` (tiny scenario) and the filter benchmark smoke test."""

from __future__ import annotations

import importlib.util
import json
import math
import sys
from pathlib import Path
from types import ModuleType

import pytest
import torch

REPO_ROOT = Path(__file__).resolve().parents[1]
TINY_CONFIG = REPO_ROOT / "configs" / "tan_tiny.yaml"
METHODS = ["neural", "bilinear", "nine_point", "mean_point", "lsq_adaptive", "lsq_min",
           "point_mass_ekf", "point_mass_tracker"]


def _load_module(name: str, path: Path) -> ModuleType:
    spec = importlib.util.spec_from_file_location(name, path)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="module")
def evaluate() -> ModuleType:
    """The evaluate command's module (``evaluate.py`` only calls its ``main``, through the
    light entry point that makes Ctrl-C while importing an exit)."""
    from neuralmap import entry
    from neuralmap.studies import cli

    assert "from neuralmap.entry import evaluate" in (REPO_ROOT / "evaluate.py").read_text()
    assert "from neuralmap.studies.cli import main" in Path(entry.__file__).read_text()
    return cli


@pytest.fixture(scope="module")
def tiny_tile():  # noqa: ANN201 - DemTile
    from neuralmap.lab.scenario import load_scenario, scenario_tile

    return scenario_tile(load_scenario("tiny"))


def _fit(net: torch.nn.Module, tile, steps: int) -> float:  # noqa: ANN001
    """A few hundred full-batch Adam steps on the tile's nodes; returns the fit RMSE (m)."""
    xy = torch.as_tensor(tile.node_xy().reshape(-1, 2), dtype=torch.float32)
    h = torch.as_tensor(tile.heights.reshape(-1), dtype=torch.float32)
    opt = torch.optim.Adam(net.parameters(), lr=1e-2)
    schedule = torch.optim.lr_scheduler.CosineAnnealingLR(opt, steps)
    scale = float(net.height_scale)
    previous = torch.get_num_threads()
    torch.set_num_threads(1)  # small batches: one thread is fastest, even more so on a busy box
    try:
        for _ in range(steps):
            opt.zero_grad()
            loss = ((net(xy) - h) / scale).square().mean()
            loss.backward()
            opt.step()
            schedule.step()
    finally:
        torch.set_num_threads(previous)
    with torch.no_grad():
        return float((net(xy) - h).square().mean().sqrt())


@pytest.fixture(scope="module")
def runs_with_map(tmp_path_factory: pytest.TempPathFactory, tiny_tile) -> Path:  # noqa: ANN001
    """A runs/ folder holding a quickly fitted map of the tiny tile, where train.py puts it."""
    from neuralmap.terrain.blockwise import BlockwiseTerrainNet
    from neuralmap.terrain.export import save_map

    runs = tmp_path_factory.mktemp("runs")
    torch.manual_seed(0)
    net = BlockwiseTerrainNet.from_tile(tiny_tile, hidden=32, n_frequencies=8)
    rmse = _fit(net, tiny_tile, 300)
    assert rmse < 10.0  # a rough map: metres of error on a 300 m relief
    path = runs / "fit" / "version_0" / "neural_map.pt"
    path.parent.mkdir(parents=True)
    save_map(net, path, metrics={"rmse_m": rmse})
    return runs


def _strict_json(path: Path) -> dict:
    def no_constant(name: str) -> None:
        raise AssertionError(f"{path} holds the non-JSON constant {name}")

    return json.loads(path.read_text(), parse_constant=no_constant)


def test_evaluate_end_to_end(
    evaluate: ModuleType, runs_with_map: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    code = evaluate.main(
        ["--config", str(TINY_CONFIG), "--runs_dir", str(runs_with_map), "--experiment", "e2e"]
    )
    out = capsys.readouterr()
    assert code == 0, out.err
    folder = runs_with_map / "e2e" / "version_0"
    assert out.out.strip().splitlines()[-1] == f"results written to {folder}"
    for name in (
        "report.md",
        "results.json",
        "config.yaml",
        "error_vs_time.png",
        "trajectories.png",
        "final_error_hist.png",
    ):
        assert (folder / name).is_file(), name
    assert list(folder.glob("events.out.tfevents*")), "no TensorBoard event file"
    assert not [p for p in (runs_with_map / "e2e").iterdir() if p.name.startswith(".")]
    tracks = (folder / "trajectories.csv").read_text().splitlines()
    assert tracks[0] == "track,run,step,t_s,x_m,y_m,h_m"  # a synthetic tile: tile frame only
    assert len(tracks) == 1 + (2 + len(METHODS)) * 16 * 41  # truth, ins, methods x runs x steps

    results = _strict_json(folder / "results.json")
    assert list(results["methods"]) == METHODS
    for name, entry in results["methods"].items():
        for key in (
            "rmse_pos_m",
            "rmse_pos_converged_m",
            "rmse_vel_mps",
            "sigma_pos_m",
            "divergence_rate",
            "nees_in_band",
            "nees_time_avg",
            "pcrb_ratio_all",
            "pcrb_ratio_converged",
            "numerical_failure_rate",
        ):
            assert key in entry, (name, key)
        assert entry["n_runs"] == 16
        assert entry["rmse_pos_m"] is not None and entry["rmse_pos_m"] > 0
    assert results["pcrb_pos_m"] > 0 and math.isfinite(results["pcrb_pos_m"])
    assert "diverged" in results["divergence_rule"]
    assert results["config"]["n_runs"] == 16
    assert results["config"]["map"].endswith("neural_map.pt")  # the newest map was found
    measured = results["map"]["error_vs_truth"]
    assert measured["n_points"] == 2000 and measured["rmse_m"] > 0
    uncovered = measured["mse_m2"] - results["scenario"]["fit_variance_m2"]
    assert results["map"]["neural_extra_variance_m2"] == pytest.approx(max(uncovered, 0.0))
    assert results["truth_model"]["kind"] == "dem" and results["pcrb_kind"] == "bound"
    assert results["study"] == "tan"
    assert set(results["off_map"]["per_method"]) == set(METHODS)
    assert len(results["curves"]["t"]) == 41  # tiny: 40 steps
    # the run is a real filter: the estimate beats the prior's radial RMS error
    prior = results["scenario"]["init_pos_sigma_m"] * math.sqrt(2.0)
    assert results["methods"]["bilinear"]["rmse_pos_converged_m"] < 0.7 * prior
    # the point-mass-started EKF: R = altimeter + the DEM table at sigma = 0 (both filters)
    # + the table's excess over it (the EKF), so the EKF's R is the measured table
    started = results["navigator"]["point_mass_ekf"]
    table = started["table"]
    assert started["R_m2"] == pytest.approx(
        results["scenario"]["R_m2"] + table["variance_m2"][0], rel=1e-12)
    assert table["sigmas_m"][0] == 0.0
    # the tracker flown again with the R a user has (altimeter + stated DEM accuracy²); its
    # truth-tuned RMSE is the metrics' all-run last-half RMSE of the tracker's row
    stated = results["navigator"]["point_mass_tracker"]["stated_R"]
    assert stated["R_m2"] == pytest.approx(
        results["scenario"]["R_m2"] + results["scenario"]["dem_error_sigma_m"] ** 2, rel=1e-12)
    assert stated["truth_tuned_rmse_last_half_m"] == pytest.approx(
        results["methods"]["point_mass_tracker"]["rmse_pos_m"], rel=1e-6)
    assert stated["rmse_last_half_m"] > 0
    claims = [c["claim"] for c in results["claims"] if "recommended EKF method" in c["claim"]]
    assert len(claims) == 1 and claims[0].startswith("point_mass_ekf (recommended EKF method)")

    report = (folder / "report.md").read_text()
    assert "![" in report and "error_vs_time.png" in report
    assert "Divergence rule" in report and "position error < 50 m" in report
    assert "the R a user has against the truth-tuned R" in report
    assert " nan " not in report.lower()

    # the saved config parses back to the same options
    from neuralmap.studies.cli import parse_config

    again = parse_config(["--config", str(folder / "config.yaml")])
    assert again.methods == METHODS and again.n_runs == 16 and again.map == results["config"]["map"]

    # a second run gets the next version folder
    code = evaluate.main(
        [
            "--config",
            str(TINY_CONFIG),
            "--runs_dir",
            str(runs_with_map),
            "--experiment",
            "e2e",
            "--n_runs",
            "4",
            "--methods",
            "[bilinear]",
            "--tensorboard",
            "false",
            "--dtype",
            "float32",
        ]
    )
    assert code == 0
    assert (runs_with_map / "e2e" / "version_1" / "results.json").is_file()


def test_missing_map_message(
    evaluate: ModuleType, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    code = evaluate.main(["--config", str(TINY_CONFIG), "--runs_dir", str(tmp_path / "runs")])
    err = capsys.readouterr().err
    assert code == 2
    assert "no trained map found under" in err and "python train.py" in err
    assert "Traceback" not in err
    assert not (tmp_path / "runs").exists()  # nothing written

    code = evaluate.main(["--config", str(TINY_CONFIG), "--map", str(tmp_path / "nope.pt")])
    assert code == 2 and "file not found" in capsys.readouterr().err


def test_map_of_another_tile_is_rejected(
    evaluate: ModuleType, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from neuralmap.dem import synthetic_tile
    from neuralmap.terrain.blockwise import BlockwiseTerrainNet
    from neuralmap.terrain.export import save_map

    other = synthetic_tile((40, 40), spacing=(30.0, 30.0), seed=99, name="other")
    path = tmp_path / "other.pt"
    save_map(BlockwiseTerrainNet.from_tile(other, block_nodes=48, hidden=8), path)
    code = evaluate.main(
        ["--config", str(TINY_CONFIG), "--map", str(path), "--runs_dir", str(tmp_path / "runs")]
    )
    err = capsys.readouterr().err
    assert code == 2
    assert "other" in err and "fingerprint" in err and "--scenario" in err
    assert not (tmp_path / "runs").exists()

    # same name as the scenario's tile, other content (e.g. a changed reader): say so
    same_name = synthetic_tile((96, 96), spacing=(30.0, 30.0), seed=4)
    save_map(BlockwiseTerrainNet.from_tile(same_name, block_nodes=48, hidden=8), path)
    code = evaluate.main(["--config", str(TINY_CONFIG), "--map", str(path)])
    err = capsys.readouterr().err
    assert code == 2 and "Same tile name, different content" in err and "retrain" in err


def test_bad_options_exit_2(evaluate: ModuleType, capsys: pytest.CaptureFixture[str]) -> None:
    assert evaluate.main(["--config", str(TINY_CONFIG), "--methods", "[neural,kriging]"]) == 2
    assert "kriging" in capsys.readouterr().err
    assert evaluate.main(["--config", str(TINY_CONFIG), "--n_runs", "0"]) == 2
    assert "--n_runs" in capsys.readouterr().err
    assert evaluate.main(["--config", str(TINY_CONFIG), "--dtype", "float16"]) == 2
    if not torch.cuda.is_available():
        assert evaluate.main(["--config", str(TINY_CONFIG), "--device", "cuda"]) == 2
        assert "CUDA is not available" in capsys.readouterr().err


def test_find_latest_map_prefers_newest(tmp_path: Path) -> None:
    import os

    from neuralmap.studies.maps import find_latest_map

    assert find_latest_map(tmp_path) is None
    paths = []
    for i, exp in enumerate(["a", "b", "a"]):
        path = tmp_path / exp / f"version_{i}" / "neural_map.pt"
        path.parent.mkdir(parents=True)
        path.write_bytes(b"x")
        os.utime(path, (1000 + i, 1000 + i))
        paths.append(path)
    assert find_latest_map(tmp_path) == paths[2]
    os.utime(paths[1], (5000, 5000))
    assert find_latest_map(tmp_path) == paths[1]


def test_bench_filter_quick(capsys: pytest.CaptureFixture[str]) -> None:
    bench = _load_module("bench_filter_under_test", REPO_ROOT / "benchmarks" / "bench_filter.py")
    argv = ["--quick", "--scenario", "tiny", "--runs_dir", "/nonexistent", "--threads", "1"]
    assert bench.main(argv) == 0
    out = capsys.readouterr().out
    table = [line for line in out.splitlines() if line.startswith("| (")]
    policies = [line for line in table if line.startswith("| (e)")]
    assert len(policies) == len(bench.policy_factories())  # (e) one row per policy
    assert all("the plain step" in line for line in policies)
    latent = [line for line in table if line.startswith("| (f)")]
    assert latent and "torch bicubic grid" in latent[0]  # (f) the grid, then latent maps
    # (a) 2, (b) 2, (c) 1, (d) 6 (neural, 4 grids, scipy), (e) policies, (f) latent queries
    assert len(table) == 11 + len(policies) + len(latent)
    assert any("FilterPy" in line for line in table) and any("scipy" in line for line in table)
    cross = next(line for line in out.splitlines() if "cross-check" in line)
    assert float(cross.rsplit("=", 1)[1]) < 1e-6  # torch and FilterPy solve the same problem
