"""Test-suite settings and fixtures shared by every test module."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
import torch

# One torch thread: on the 2-core CI machine OpenMP oversubscription (torch threads next to
# numpy/BLAS and other processes) made small tensor operations 10-100x slower.
torch.set_num_threads(1)

REPO_ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="session")
def tiny_scenario() -> Any:  # noqa: ANN401 - Scenario
    """The shipped ``tiny`` scenario (configs/scenarios/tiny.yaml)."""
    from neuralmap.nav.scenario import load_scenario

    return load_scenario("tiny")


@pytest.fixture(scope="session")
def tiny_tile(tiny_scenario: Any) -> Any:  # noqa: ANN401 - DemTile
    """The tiny scenario's synthetic DEM tile."""
    from neuralmap.nav.scenario import scenario_tile

    return scenario_tile(tiny_scenario)


@pytest.fixture(scope="session")
def tiny_map(tmp_path_factory: pytest.TempPathFactory, tiny_tile: Any) -> Path:
    """An untrained neural map of the tiny tile (seed 0, 8 hidden, 4 frequencies): enough
    for the plumbing of every study, not for accuracy."""
    from neuralmap.terrain.blockwise import BlockwiseTerrainNet
    from neuralmap.terrain.export import save_map

    torch.manual_seed(0)
    path = tmp_path_factory.mktemp("tiny_map") / "neural_map.pt"
    save_map(BlockwiseTerrainNet.from_tile(tiny_tile, hidden=8, n_frequencies=4), path)
    return path

