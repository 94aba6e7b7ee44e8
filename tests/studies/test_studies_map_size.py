"""Map size study: end to end on the tiny scenario, fronts, targets and bad input."""

from __future__ import annotations

import itertools
import json
import random
from pathlib import Path
from types import ModuleType

import pytest
import torch

from neuralmap.studies.map_size import pareto_front

pytest.importorskip("imagecodecs")

REPO_ROOT = Path(__file__).resolve().parents[2]
TINY_CONFIG = REPO_ROOT / "configs" / "map_size_tiny.yaml"


def _evaluate() -> ModuleType:
    """The package's evaluate CLI (what ``python evaluate.py`` runs)."""
    from neuralmap.studies import cli

    return cli


def test_pareto_front_matches_brute_force() -> None:
    rng = random.Random(0)
    for _ in range(50):
        n = rng.randint(1, 12)
        sizes = [rng.choice([1, 2, 3, 5, 8]) for _ in range(n)]
        errors = [rng.choice([0.5, 1.0, 2.0, float("nan"), 4.0]) for _ in range(n)]
        front = pareto_front(sizes, errors)
        valid = [i for i in range(n) if errors[i] == errors[i]]
        # brute force: i is on the front unless some j is no larger and strictly more
        # accurate, or equal in both and earlier in the (size, error, index) order
        expected = []
        for i in valid:
            dominated = any(
                (sizes[j] <= sizes[i] and errors[j] < errors[i])
                or (sizes[j] < sizes[i] and errors[j] <= errors[i])
                or (sizes[j] == sizes[i] and errors[j] == errors[i] and j < i)
                for j in valid if j != i
            )
            if not dominated:
                expected.append(i)
        assert sorted(front) == sorted(expected)
        for a, b in itertools.pairwise(front):
            assert sizes[a] <= sizes[b] and errors[a] > errors[b]


@pytest.fixture(scope="module")
def tiny_map(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A roughly fitted small map of the tiny scenario's tile."""
    from neuralmap.lab.scenario import load_scenario, scenario_tile
    from neuralmap.terrain.blockwise import BlockwiseTerrainNet
    from neuralmap.terrain.export import save_map

    tile = scenario_tile(load_scenario("tiny"))
    torch.manual_seed(0)
    net = BlockwiseTerrainNet.from_tile(tile, block_nodes=32, hidden=16, n_frequencies=6)
    xy = torch.as_tensor(tile.node_xy().reshape(-1, 2), dtype=torch.float32)
    h = torch.as_tensor(tile.heights.reshape(-1), dtype=torch.float32)
    opt = torch.optim.Adam(net.parameters(), lr=1e-2)
    for _ in range(60):
        opt.zero_grad()
        ((net(xy) - h) / net.height_scale).square().mean().backward()
        opt.step()
    path = tmp_path_factory.mktemp("runs") / "small" / "version_0" / "neural_map.pt"
    return save_map(net, path)


def test_map_size_end_to_end(tiny_map: Path, tmp_path: Path) -> None:
    from neuralmap.outputs import MIN_CONVERGED

    evaluate = _evaluate()
    code = evaluate.main([
        "--config", str(TINY_CONFIG), "--runs_dir", str(tmp_path / "runs"),
        "--neural_maps", f"[{tiny_map}]",
    ])
    assert code == 0
    out = tmp_path / "runs" / "map_size_tiny" / "version_0"
    results = json.loads((out / "results.json").read_text())
    maps = {m["name"]: m for m in results["maps"]}
    # 1 raw + 3 codecs x (2 full-resolution errors + 1 decimated) + 1 map x 2 stored forms
    # + the int8 form baked onto the nodes
    assert len(maps) == 1 + 3 * 3 + 2 + 1
    raw = maps["raw float32 grid"]
    assert raw["bytes"] == 96 * 96 * 4 and raw["node_max_m"] == 0.0
    # the full grid against itself: ratio 1 on every resample
    assert raw["nav_rmse_converged_vs_grid"] == pytest.approx(1.0)
    assert raw["nav_rmse_converged_vs_grid_ci"] == pytest.approx([1.0, 1.0])
    assert raw["offnode_rmse_m"] == pytest.approx(0.0, abs=1e-9)
    for name, m in maps.items():
        if m["kind"] == "grid" and m.get("decimation") == 1 and m["codec"]:
            assert m["node_max_m"] <= m["error_bound_m"] + 1e-9, name
        assert m["queries_per_s"] > 0, name
        assert m["bits_per_node"] == pytest.approx(8 * m["bytes"] / (96 * 96))
        for key in ("nav_rmse", "nav_rmse_converged"):
            low, high = m[f"{key}_ci_m"]
            assert low <= m[f"{key}_m"] <= high, (name, key)
        if raw["truth_rmse_m"] > 0:  # the tiny scenario's truth is its DEM: ratio undefined
            assert m["truth_vs_bicubic_dem"] == pytest.approx(
                m["truth_rmse_m"] / raw["truth_rmse_m"])
    float_map, int8_map = maps["small none"], maps["small int8_channel"]
    assert float_map["family"] == "neural blockwise"
    assert float_map["bytes"] - int8_map["bytes"] >= 2 * int8_map["num_parameters"]
    assert (out / "maps" / "small_int8_channel.pt").stat().st_size == int8_map["bytes"]
    # quantisation moves the map by far less than its own fit error
    assert abs(int8_map["node_rmse_m"] - float_map["node_rmse_m"]) < 0.2 * float_map[
        "node_rmse_m"] + 0.05
    baked = maps["small int8_channel baked"]
    assert baked["bytes"] == int8_map["bytes"] and baked["kind"] == "neural"
    # at the nodes the baked grid holds the network's own values, and between them it is
    # the bicubic of those values: what the map's own nodes give
    assert baked["node_rmse_m"] == pytest.approx(int8_map["node_rmse_m"], abs=1e-3)
    assert baked["truth_rmse_m"] == pytest.approx(int8_map["own_nodes_truth_rmse_m"], abs=1e-3)
    summary = results["summary"]
    assert summary["fronts"]["grid:node_max_m"][0]["bytes"] == min(
        m["bytes"] for m in maps.values() if m["kind"] == "grid")
    assert set(summary["bd_rate_node_rmse"]) == {"neural blockwise", "neural blockwise baked"}
    # 8 runs cannot decide equal navigation accuracy (the TAN study's minimum)
    assert 8 < MIN_CONVERGED
    assert summary["equal_accuracy_converged"]["verdict"].startswith("not enough converged")
    nav_claims = [c for c in results["claims"] if "navigation accuracy" in c["claim"]]
    weakest = min(m["n_converged"] for m in maps.values())
    assert nav_claims and nav_claims[0]["verdict"].startswith(
        f"not enough converged runs ({weakest} of 8")
    between = {b["name"]: b for b in summary["between_nodes"]}
    assert between["small none"]["met"] == (float_map["truth_rmse_m"] <= raw["truth_rmse_m"])
    report = (out / "report.md").read_text()
    assert "SEEDS 004" in report and "bytes_vs_nav_rmse" in report and "BD-rate" in report
    for figure in ("bytes_vs_max_error", "bytes_vs_node_rmse", "bytes_vs_nav_rmse_converged"):
        assert (out / f"{figure}.png").is_file(), figure


def test_storage_claim_counts_the_raw_grid_as_a_grid() -> None:
    """A map larger than the raw grid with no compressed grid as accurate is not smaller
    than 'the grid': the raw grid (lossless) is as accurate and smaller."""
    from neuralmap.studies.map_size import _storage_claim

    rows = [
        {"name": "raw float32 grid", "family": "raw grid", "kind": "grid", "bytes": 1000,
         "node_max_m": 0.0},
        {"name": "lerc e=5", "family": "lerc", "kind": "grid", "bytes": 100, "node_max_m": 5.0},
        {"name": "big", "family": "neural blockwise", "kind": "neural", "bytes": 4000,
         "node_max_m": 1.0},
    ]
    text, verdict = _storage_claim(rows, 1000)
    assert verdict == "does not hold"
    assert "raw float32 grid" in text
    rows[2]["bytes"] = 500  # smaller than raw, and no compressed grid reaches 1 m
    assert _storage_claim(rows, 1000)[1] == "holds"


def _saved_map(tile: object, path: Path, *, fingerprint: str | None) -> Path:
    from neuralmap.terrain.blockwise import BlockwiseTerrainNet
    from neuralmap.terrain.export import save_map

    net = BlockwiseTerrainNet.from_tile(tile, block_nodes=48, hidden=4, n_frequencies=2)
    if fingerprint is not None:
        net.tile_info["fingerprint"] = fingerprint
        net.tile_fingerprint = fingerprint
    return save_map(net, path)


@pytest.mark.parametrize("fingerprint", ["", "0123456789abcdef"])
def test_map_without_or_with_another_fingerprint_is_refused(
    fingerprint: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from neuralmap.lab.scenario import load_scenario, scenario_tile

    tile = scenario_tile(load_scenario("tiny"))
    path = _saved_map(tile, tmp_path / "m" / "version_0" / "neural_map.pt",
                      fingerprint=fingerprint)
    code = _evaluate().main(["--config", str(TINY_CONFIG), "--runs_dir", str(tmp_path),
                             "--neural_maps", f"[{path}]"])
    assert code == 2
    err = capsys.readouterr().err
    assert f"fingerprint {fingerprint or 'none'}" in err and "tiny" in err
    assert not (tmp_path / "map_size_tiny" / "version_0" / "results.json").exists()


def test_bad_options_exit_2(capsys: pytest.CaptureFixture[str], tmp_path: Path) -> None:
    evaluate = _evaluate()
    base = ["--config", str(TINY_CONFIG), "--runs_dir", str(tmp_path)]
    assert evaluate.main([*base, "--max_errors", "[0.0]"]) == 2
    assert "max_errors" in capsys.readouterr().err
    assert evaluate.main([*base, "--codecs", "[png]"]) == 2
    assert evaluate.main([*base, "--quantizations", "[int4]"]) == 2
    assert evaluate.main([*base, "--decimations", "[0]"]) == 2
    assert evaluate.main([*base, "--baked", "[fp16]"]) == 2
    assert evaluate.main([*base, "--neural_maps", f"[{tmp_path / 'nope.pt'}]"]) == 2
