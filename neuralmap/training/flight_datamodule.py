"""FlightDataModule: flights for noise learning, simulated from a scenario or read from a log.

Simulated flights (default) come from `neuralmap.lab.simulator.simulate` over the
scenario's truth terrain with a seed; the validation flights use another seed (other
trajectories and noise, same world). A flight log (`neuralmap.learning.flight_log`)
replaces the simulation: a seeded fraction of its flights is held out for validation.
Each training batch is a set of flight indices; the module slices the flights itself.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import lightning.pytorch as pl
import torch
from torch.utils.data import DataLoader, TensorDataset

from neuralmap.exceptions import NeuralMapError
from neuralmap.lab.scenario import Scenario, load_scenario, scenario_tile
from neuralmap.learning.flight_log import read_flight_log
from neuralmap.learning.flights import FlightBatch

__all__ = ["FlightDataModule", "check_flights_fit_scenario", "check_same_world"]


def check_same_world(filter_scenario: Scenario, data_scenario: Scenario) -> None:
    """Refuses a filter scenario whose terrain or time step differs from the flights'.

    Learning Q and R through a filter on another tile, or with another Φ period, fits the
    wrong model: the learned R then absorbs the terrain mismatch.

    Raises:
        NeuralMapError: Different ``tile`` / ``tile_options`` or ``dt``.
    """
    def terrain(s: Scenario) -> tuple[str, str]:
        return str(s.tile), repr(sorted(dict(s.tile_options).items()))

    if terrain(filter_scenario) != terrain(data_scenario):
        raise NeuralMapError(
            f"the filter's scenario {filter_scenario.name!r} flies tile {filter_scenario.tile!r} "
            f"{dict(filter_scenario.tile_options) or ''}but the flights' scenario "
            f"{data_scenario.name!r} uses tile {data_scenario.tile!r} "
            f"{dict(data_scenario.tile_options) or ''}; give --model.scenario and "
            "--data.scenario the same scenario (or scenarios of the same tile).")
    if abs(filter_scenario.dt - data_scenario.dt) > 1e-9 * max(data_scenario.dt, 1.0):
        raise NeuralMapError(
            f"the filter's scenario {filter_scenario.name!r} steps dt = {filter_scenario.dt:g} s "
            f"but the flights' scenario {data_scenario.name!r} dt = {data_scenario.dt:g} s; "
            "give --model.scenario and --data.scenario the same time step.")


def check_flights_fit_scenario(flights: FlightBatch, scenario: Scenario, *, source: str) -> None:
    """Refuses flights a filter on ``scenario`` could not learn from.

    The time step must be the scenario's (the filter's Φ and Q are per ``dt``), some
    altimeter readings must exist, and some of them must lie on the scenario's tile (off
    the tile the filter makes no update): otherwise nothing is learned and the starting
    guess would be exported as "learned".

    Raises:
        NeuralMapError: Another ``dt``, no altimeter reading, or none on the tile.
    """
    if abs(flights.dt - scenario.dt) > 1e-6 * max(scenario.dt, 1e-9):
        raise NeuralMapError(
            f"{source}: the flights step {flights.dt:g} s but scenario {scenario.name!r} "
            f"has dt = {scenario.dt:g} s; resample the log to {scenario.dt:g} s or give a "
            f"scenario with dt: {flights.dt:g} (--data.scenario and --model.scenario).")
    measured = flights.measured.clone()
    measured[:, 0] = False  # sample 0 is the prior epoch (no update)
    if not bool(measured.any()):
        raise NeuralMapError(
            f"{source}: no altimeter reading in any flight (every 'radar' value is empty or "
            "nan); the filter would make no update and learn nothing.")
    tile = scenario_tile(scenario)
    x0, x1, y0, y1 = tile.extent
    xy = flights.ins_pos[..., :2]
    on_tile = (xy[..., 0] >= x0) & (xy[..., 0] <= x1) & (xy[..., 1] >= y0) & (xy[..., 1] <= y1)
    if not bool((measured & on_tile).any()):
        lo = xy[flights.valid].amin(0).tolist()
        hi = xy[flights.valid].amax(0).tolist()
        raise NeuralMapError(
            f"{source}: no altimeter reading lies on the tile {tile.name!r} of scenario "
            f"{scenario.name!r} (x {x0:g}..{x1:g} m, y {y0:g}..{y1:g} m); the INS positions "
            f"span x {lo[0]:g}..{hi[0]:g} m, y {lo[1]:g}..{hi[1]:g} m. ins_x / ins_y are "
            "metres east / north of the tile's south-west node.")


class FlightDataModule(pl.LightningDataModule):
    """Training and validation flights for `NoiseLearningModule`.

    Args:
        scenario: Scenario name or YAML path (the flights' tile, dt and truth models).
        n_flights: Simulated training flights.
        n_val_flights: Simulated validation flights (or held out from the log).
        seed: Simulation seed of the training flights (validation: ``seed + 1``).
        log_path: A flight log (CSV/NPZ) to learn from instead of simulating.
        batch_size: Flights per optimiser step (None = all).

    The scenario and a log are read and checked here, before any run folder exists:
    `check_flights_fit_scenario`.

    Raises:
        NeuralMapError: Counts < 1, a bad scenario or log, a log of another time step,
            without altimeter readings or off the tile, a log of fewer than 2 flights.
    """

    def __init__(self, scenario: str = "jacksboro", n_flights: int = 200,
                 n_val_flights: int = 50, seed: int = 0, log_path: str | None = None,
                 batch_size: int | None = None) -> None:
        super().__init__()
        if n_flights < 1 or n_val_flights < 1:
            raise NeuralMapError(
                f"--data.n_flights and --data.n_val_flights must be >= 1, got {n_flights} and "
                f"{n_val_flights}.")
        if batch_size is not None and batch_size < 1:
            raise NeuralMapError(f"--data.batch_size must be >= 1 (or null), got {batch_size}.")
        self.scenario_name = scenario
        self.n_flights = n_flights
        self.n_val_flights = n_val_flights
        self.seed = seed
        self.log_path = log_path
        self.batch_size = batch_size
        self.train_flights: FlightBatch | None = None
        self.val_flights: FlightBatch | None = None
        self.scenario = load_scenario(scenario)
        self.log_flights: FlightBatch | None = None
        if log_path is not None:
            flights = read_flight_log(log_path)
            check_flights_fit_scenario(flights, self.scenario, source=str(log_path))
            if flights.n_flights < 2:
                raise NeuralMapError(
                    f"{log_path}: noise learning needs >= 2 flights (one held out for "
                    f"validation), the log has {flights.n_flights}.")
            self.log_flights = flights

    @property
    def experiment_name(self) -> str:
        """Run folder name: ``learn_noise_<scenario>``."""
        return f"learn_noise_{Path(str(self.scenario_name)).stem}"

    def setup(self, stage: str) -> None:
        """Simulates (or reads) the flights once."""
        if self.train_flights is not None:
            return
        if self.log_flights is not None:
            flights = self.log_flights
            order = torch.randperm(flights.n_flights,
                                   generator=torch.Generator().manual_seed(self.seed))
            n_val = min(self.n_val_flights, flights.n_flights // 2)
            self.val_flights = flights.subset(order[:n_val])
            self.train_flights = flights.subset(order[n_val:])
            return
        from neuralmap.lab.simulator import simulate
        from neuralmap.lab.truth_terrain import true_terrain

        scenario = self.scenario
        tile = scenario_tile(scenario)
        world = true_terrain(scenario, tile, seed=self.seed)
        self.train_flights = FlightBatch.from_truth(
            simulate(scenario, tile, n_runs=self.n_flights, seed=self.seed, truth_terrain=world))
        self.val_flights = FlightBatch.from_truth(
            simulate(scenario, tile, n_runs=self.n_val_flights, seed=self.seed + 1,
                     truth_terrain=world))

    def train_dataloader(self) -> Any:
        """Batches of training-flight indices."""
        assert self.train_flights is not None
        ids = TensorDataset(torch.arange(self.train_flights.n_flights))
        return DataLoader(ids, batch_size=self.batch_size or self.train_flights.n_flights,
                          shuffle=True, generator=torch.Generator().manual_seed(self.seed))

    def val_dataloader(self) -> Any:
        """One batch: all validation flights."""
        assert self.val_flights is not None
        return DataLoader(TensorDataset(torch.arange(self.val_flights.n_flights)),
                          batch_size=self.val_flights.n_flights)
