"""A navigation method of one's own: one class and one registry line in this file, flown by
name through `Navigator.replay`, ``neuralmap-navigate`` and the ``tan`` study."""

from __future__ import annotations

import csv
import json
import math
from dataclasses import dataclass
from pathlib import Path

import pytest
import torch

from neuralmap import Navigator
from neuralmap.tan import Innovation, MethodContext, NavigationMethod
from neuralmap.tan.registry import method_names, register_method, unregister_method

REPO = Path(__file__).resolve().parents[2]


@dataclass
class DeadReckoningOptions:
    """Options of the toy method: how much to trust the INS (a scale on its growth)."""

    growth: float = 1.0


class DeadReckoning(NavigationMethod):
    """The INS alone (no altimeter update): the estimate is the open-loop prior,
    ``δX̂ = 0``, ``P ← Φ P Φᵀ + growth · Q``."""

    Options = DeadReckoningOptions

    def __init__(self, context: MethodContext, options: DeadReckoningOptions) -> None:
        super().__init__(context, options)
        n, dev = context.n_vehicles, context.device
        self.mean = torch.zeros(n, 5, dtype=torch.float64, device=dev)
        self.cov = context.model.filter_prior(device=dev).expand(n, 5, 5).clone()

    def predict(self, dt: float) -> None:
        phi = self.context.model.transition(dt)
        q = self.context.model.process_noise(dt) * self.options.growth
        self.mean = self.mean @ phi.T
        self.cov = phi @ self.cov @ phi.T + q

    def update(self, ins, clearance, mask, *, gate=math.inf, quality=None) -> Innovation:  # noqa: ANN001
        return Innovation.none(self.context.n_vehicles, self.context.device)

    def estimate(self) -> tuple[torch.Tensor, torch.Tensor]:
        return self.mean, self.cov

    def load(self, mask: torch.Tensor, mean: torch.Tensor, cov: torch.Tensor) -> None:
        self.mean = torch.where(mask[:, None], mean, self.mean)
        self.cov = torch.where(mask[:, None, None], cov, self.cov)


@pytest.fixture(scope="module", autouse=True)
def toy():  # noqa: ANN201
    register_method("dead_reckoning")(DeadReckoning)  # the one registry line
    yield DeadReckoning
    unregister_method("dead_reckoning")


@pytest.fixture(scope="module")
def flight():  # noqa: ANN201
    from neuralmap.lab.scenario import load_scenario, scenario_tile
    from neuralmap.lab.simulator import simulate
    from neuralmap.terrain.grid import GridTerrain

    scenario = load_scenario("tiny")
    tile = scenario_tile(scenario)
    return tile, simulate(scenario, tile, n_runs=3, seed=2), GridTerrain(tile, method="bilinear")


def test_the_toy_is_registered(toy) -> None:  # noqa: ANN001
    assert "dead_reckoning" in method_names() and toy.name == "dead_reckoning"


def test_replay_flies_the_toy(flight) -> None:  # noqa: ANN001
    _, truth, grid = flight
    nav = Navigator(grid, {"method": "dead_reckoning", "dead_reckoning": {"growth": 2.0},
                           "integrity": {"lost_window": 0}}, n_vehicles=3)
    track = nav.replay(truth.t, truth.ins_pos[..., :2], truth.ins_pos[..., 2], truth.radar)
    # no update: the fixes are the INS, the covariance the open-loop prior with growth 2
    torch.testing.assert_close(track.xy, truth.ins_pos[..., :2])
    model = nav.model
    P = model.filter_prior()
    for _ in range(truth.n_steps):
        P = model.transition() @ P @ model.transition().T + 2.0 * model.process_noise()
    torch.testing.assert_close(track.cov[0, -1], P)
    assert track.counts["updates"] == 0 and not bool(track.updated.any())


def test_neuralmap_navigate_flies_the_toy(flight, tmp_path: Path) -> None:  # noqa: ANN001
    import yaml

    from neuralmap.flights.cli import main
    from neuralmap.lab.scenario import load_scenario
    from neuralmap.lab.simulator import simulate
    from neuralmap.nav.map_source import resolve_map

    tile = resolve_map("synthetic").tile  # the embedded synthetic tile: --map synthetic
    truth = simulate(load_scenario("tiny"), tile, n_runs=2, seed=3)
    log = tmp_path / "flight.csv"
    with log.open("w", newline="") as handle:
        w = csv.writer(handle)
        w.writerow(["flight", "time", "ins_x", "ins_y", "ins_h", "radar"])
        for n in range(truth.n_runs):
            for k in range(truth.t.shape[0]):
                w.writerow([n, repr(float(truth.t[k]))]
                           + [repr(float(v)) for v in truth.ins_pos[n, k]]
                           + [repr(float(truth.radar[n, k]))])
    config = tmp_path / "nav.yaml"
    config.write_text(yaml.safe_dump({"method": "dead_reckoning"}))
    out = tmp_path / "out"
    code = main([str(log), "--map", "synthetic", "--config", str(config),
                 "--out", str(out), "--no_datum_check", "--tensorboard", "false",
                 "--progress", "false"])
    assert code == 0
    (version,) = out.glob("version_*")
    results = json.loads((version / "results.json").read_text())
    assert results["navigator"]["method"] == "dead_reckoning"
    assert results["counts"]["updates"] == 0


def test_the_tan_study_flies_the_toy(tmp_path: Path) -> None:
    from neuralmap.studies.cli import main

    code = main(["--config", str(REPO / "configs" / "tan_tiny.yaml"), "--runs_dir",
                 str(tmp_path), "--methods", "[bilinear,dead_reckoning]", "--n_runs", "6",
                 "--noise", "scenario", "--stated_r", "false", "--tensorboard", "false"])
    assert code == 0
    (folder,) = tmp_path.glob("*/version_0")
    results = json.loads((folder / "results.json").read_text())
    assert set(results["methods"]) == {"bilinear", "dead_reckoning"}
    # dead reckoning drifts with the INS: worse than the terrain-aided EKF
    assert results["methods"]["dead_reckoning"]["rmse_pos_m"] > (
        results["methods"]["bilinear"]["rmse_pos_m"])
