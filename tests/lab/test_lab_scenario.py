"""Scenario YAML: shipped configs, round trip, and clear errors for bad keys and values."""

from __future__ import annotations

import dataclasses

import pytest

from neuralmap.exceptions import NeuralMapError
from neuralmap.lab.scenario import (
    SCENARIO_NAMES,
    Scenario,
    load_scenario,
    save_scenario,
    scenario_tile,
)


@pytest.mark.parametrize("name", SCENARIO_NAMES)
def test_shipped_scenarios_load_and_round_trip(name: str, tmp_path) -> None:
    scenario = load_scenario(name)
    assert scenario.name == name
    path = save_scenario(scenario, tmp_path / f"{name}.yaml")
    again = load_scenario(path)
    assert again == scenario
    assert not list(tmp_path.glob("*.tmp"))  # atomic write left no temporary file


def test_paper_scenario_follows_seeds_004() -> None:
    s = load_scenario("paper")
    assert s.P0_diag == [1e4, 1e4, 1e4, 40.0, 40.0]
    assert s.Q_diag == [100.0, 100.0, 100.0, 10.0, 1.0]
    assert s.init_error_mean == [-200.0, 200.0, 100.0, 1.0, 1.0]
    assert s.start_xy == [3000.0, 4000.0]
    assert (s.speed_mps, s.heading_deg, s.dt) == (200.0, 90.0, 1.0)  # V_x = 200, V_y = 0
    assert 0.1 <= s.R_m2 <= 400.0 and s.fit_variance_m2 == 6.0
    assert s.tile == "jacksboro"


def test_jacksboro_scenario_filter_is_consistent_with_truth() -> None:
    s = load_scenario("jacksboro")
    assert s.init_pos_sigma_m == 100.0 and s.altimeter_sigma_m == 10.0 and s.dt == 1.0
    assert s.Q_diag == pytest.approx(s.truth_process_noise(), rel=1e-12)
    assert s.P0_diag == pytest.approx([v * v for v in s.init_error_sigma()], rel=1e-12)
    assert s.R_m2 == pytest.approx(s.altimeter_sigma_m**2)
    assert s.init_error_mean == [0.0] * 5


def test_unknown_key_lists_valid_keys(tmp_path) -> None:
    path = tmp_path / "bad.yaml"
    path.write_text("name: bad\nspeed: 100\n")
    with pytest.raises(NeuralMapError) as info:
        load_scenario(path)
    message = str(info.value)
    assert "speed" in message and "speed_mps" in message and str(path) in message


@pytest.mark.parametrize(
    ("key", "value", "fragment"),
    [
        ("R_m2", 0.0, "> 0"),
        ("R_m2", -1.0, "> 0"),
        ("dt", 0.0, "> 0"),
        ("P0_diag", [1.0, 1.0, 0.0, 1.0, 1.0], "positive definite"),
        ("Q_diag", [1.0, 1.0, 1.0], "5 numbers"),
        ("Q_diag", [1.0, 1.0, 1.0, -1.0, 1.0], "positive semi-definite"),
        ("altimeter_sigma_m", -2.0, ">= 0"),
        ("outlier_prob", 1.5, "[0, 1]"),
        ("speed_mps", "fast", "a number"),
        ("start_xy", [1.0], "2 numbers"),
        ("waypoints", [[1.0, 2.0], [3.0]], "2 numbers"),
        ("duration_s", 0.5, ">= dt"),
        ("seed", -3, "integer"),
    ],
)
def test_bad_values_name_the_key(key: str, value: object, fragment: str, tmp_path) -> None:
    data = load_scenario("tiny").to_dict()
    data[key] = value
    with pytest.raises(NeuralMapError) as info:
        Scenario.from_dict(data, where="my.yaml")
    message = str(info.value)
    assert key in message and fragment in message and "my.yaml" in message


def test_unknown_name_and_missing_file() -> None:
    with pytest.raises(NeuralMapError, match="unknown scenario"):
        load_scenario("no_such_scenario")
    with pytest.raises(NeuralMapError, match="does not exist"):
        load_scenario("missing/file.yaml")


def test_not_a_mapping(tmp_path) -> None:
    path = tmp_path / "list.yaml"
    path.write_text("- 1\n- 2\n")
    with pytest.raises(NeuralMapError, match="mapping"):
        load_scenario(path)


def test_tiny_tile_and_bad_tile_options() -> None:
    s = load_scenario("tiny")
    tile = scenario_tile(s)
    assert tile.shape == (96, 96) and tile.spacing == (30.0, 30.0)
    bad = dataclasses.replace(s, tile_options={"wrong": 1})
    with pytest.raises(NeuralMapError, match="tile_options"):
        scenario_tile(bad)


def test_n_steps_and_truth_noise() -> None:
    s = Scenario(dt=0.5, duration_s=10.0, vel_random_walk=0.2, pos_noise_sigma_m=2.0,
                 alt_noise_sigma_m=3.0).validate()
    assert s.n_steps == 20
    assert s.truth_process_noise() == pytest.approx([4.0, 4.0, 9.0, 0.02, 0.02])
