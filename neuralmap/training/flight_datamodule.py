"""FlightDataModule: flights for noise learning, simulated from a scenario or read from a log.

Simulated flights (default) come from :func:`neuralmap.nav.simulator.simulate` over the
scenario's truth terrain with a seed; the validation flights use another seed (other
trajectories and noise, same world). A flight log (:mod:`neuralmap.learning.flight_log`)
replaces the simulation: a seeded fraction of its flights is held out for validation.
Each training batch is a set of flight indices; the module slices the flights itself.
"""

from __future__ import annotations

from typing import Any

import lightning.pytorch as pl
import torch
from torch.utils.data import DataLoader, TensorDataset

from neuralmap.exceptions import NeuralMapError
from neuralmap.learning.flights import FlightBatch

__all__ = ["FlightDataModule"]


class FlightDataModule(pl.LightningDataModule):
    """Training and validation flights for :class:`~neuralmap.training.noise_module.NoiseLearningModule`.

    Args:
        scenario: Scenario name or YAML path (the flights' tile, dt and truth models).
        n_flights: Simulated training flights.
        n_val_flights: Simulated validation flights (or held out from the log).
        seed: Simulation seed of the training flights (validation: ``seed + 1``).
        log_path: A flight log (CSV/NPZ) to learn from instead of simulating.
        batch_size: Flights per optimiser step (None = all).

    Raises:
        NeuralMapError: Counts < 1, a bad scenario or log.
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

    @property
    def experiment_name(self) -> str:
        """Run folder name: ``learn_noise_<scenario>``."""
        from pathlib import Path

        return f"learn_noise_{Path(str(self.scenario_name)).stem}"

    def setup(self, stage: str) -> None:
        """Simulates (or reads) the flights once."""
        if self.train_flights is not None:
            return
        if self.log_path is not None:
            from neuralmap.learning.flight_log import read_flight_log

            flights = read_flight_log(self.log_path)
            if flights.n_flights < 2:
                raise NeuralMapError(
                    f"{self.log_path}: noise learning needs >= 2 flights (one held out for "
                    f"validation), the log has {flights.n_flights}.")
            order = torch.randperm(flights.n_flights,
                                   generator=torch.Generator().manual_seed(self.seed))
            n_val = min(self.n_val_flights, flights.n_flights // 2)
            self.val_flights = flights.subset(order[:n_val])
            self.train_flights = flights.subset(order[n_val:])
            return
        from neuralmap.nav.scenario import load_scenario, scenario_tile
        from neuralmap.nav.simulator import simulate
        from neuralmap.nav.truth_terrain import true_terrain

        scenario = load_scenario(self.scenario_name)
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
