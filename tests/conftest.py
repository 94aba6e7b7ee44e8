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
    from neuralmap.lab.scenario import load_scenario

    return load_scenario("tiny")


@pytest.fixture(scope="session")
def tiny_wide_prior(tiny_scenario: Any) -> tuple[Any, ...]:
    """The tiny scenario with a 120 m prior (wide enough for the acquisition grid), 8 runs
    of 40 s: ``(scenario, tile, truth, bilinear GridTerrain)``."""
    import dataclasses

    from neuralmap.lab.scenario import scenario_tile
    from neuralmap.lab.simulator import simulate
    from neuralmap.terrain.grid import GridTerrain

    sig = 120.0
    scenario = dataclasses.replace(
        tiny_scenario, init_pos_sigma_m=sig, start_xy=[900.0, 900.0], start_spread_m=50.0,
        P0_diag=[sig**2, sig**2] + list(tiny_scenario.P0_diag[2:]), duration_s=40.0,
    ).validate()
    tile = scenario_tile(scenario)
    truth = simulate(scenario, tile, n_runs=8, seed=3)
    return scenario, tile, truth, GridTerrain(tile, method="bilinear")


@pytest.fixture(scope="session")
def tiny_tile(tiny_scenario: Any) -> Any:  # noqa: ANN401 - DemTile
    """The tiny scenario's synthetic DEM tile."""
    from neuralmap.lab.scenario import scenario_tile

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



@pytest.fixture
def fail_write(monkeypatch: pytest.MonkeyPatch) -> Any:  # noqa: ANN401 - Callable
    """``fail_write(n, error=None)``: the low-level writer of every atomic write
    (`neuralmap.io._write_temp`) fails part-way through its ``n``-th file and every later
    one: 100 bytes reach the temporary file, then ``error`` is raised (default: a full disk,
    ``OSError(ENOSPC)``). Files before the ``n``-th are written as usual."""
    import errno
    import io

    import neuralmap.io

    real = neuralmap.io._write_temp

    def arm(call: int, error: BaseException | None = None) -> None:
        calls: list[Path] = []

        def writer(path: Path, write: Any) -> str:  # noqa: ANN401
            calls.append(path)
            if len(calls) < call:
                return real(path, write)

            def partial(handle: Any) -> None:  # noqa: ANN401
                buffer = io.BytesIO()
                write(buffer)
                handle.write(buffer.getvalue()[:100])
                raise error or OSError(errno.ENOSPC, "No space left on device")

            return real(path, partial)

        monkeypatch.setattr(neuralmap.io, "_write_temp", writer)

    return arm


class PlaneFlight:
    """The tiny scenario over a tilted plane with the DEM as truth (`plane_flight`): the
    radar measurement is linear in the position, so the Bayes posterior is Gaussian and the
    EKF with the bilinear linearizer (exact on a plane) is the Kalman filter, the reference.

    Attributes:
        scenario: The scenario (prior σ ``sigma_m``, start (900, 900) m, no spread).
        tile: The plane's `DemTile`; ``grid`` its bilinear `GridTerrain`; ``lin`` its
            bilinear linearizer.
        truth: The simulated `Truth`.
        model: The filter's `TanModel` (the scenario's).
        kalman: The EKF's `FilterRun` (`fly` with ``{"method": "ekf", "ekf":
            {"linearizer": lin}}``, the study integrity settings: no lost-lock test).
    """

    def __init__(self, tiny_scenario: Any, *, duration_s: float,  # noqa: ANN401
                 sigma_m: float = 60.0, n_runs: int = 6) -> None:
        import dataclasses

        import numpy as np

        from neuralmap.dem.tile import DemTile
        from neuralmap.lab.simulator import simulate
        from neuralmap.linearize.factory import make_linearizer
        from neuralmap.tan.model import TanModel
        from neuralmap.terrain.grid import GridTerrain

        self.scenario = dataclasses.replace(
            tiny_scenario, truth_model="dem", init_pos_sigma_m=sigma_m, start_xy=[900.0, 900.0],
            start_spread_m=0.0,
            P0_diag=[sigma_m**2, sigma_m**2] + list(tiny_scenario.P0_diag[2:]),
            duration_s=duration_s,
        ).validate()
        xs = 30.0 * np.arange(96)
        x, y = np.meshgrid(xs, xs)
        self.tile = DemTile(heights=200.0 + 0.15 * x + 0.08 * y, spacing=(30.0, 30.0),
                            origin=(0.0, 0.0), name="plane")
        self.truth = simulate(self.scenario, self.tile, n_runs=n_runs, seed=1)
        self.grid = GridTerrain(self.tile, method="bilinear")
        self.lin = make_linearizer("bilinear", tile=self.tile)
        self.model = TanModel.from_scenario(self.scenario)
        self.kalman = self.fly({"method": "ekf", "ekf": {"linearizer": self.lin}})

    def config(self, method: str | dict[str, Any], overrides: dict[str, Any] | None = None,
               integrity: str = "study") -> Any:  # noqa: ANN401 - NavigatorConfig
        """`study_navigator_config` of this scenario."""
        from neuralmap.lab.monte_carlo import study_navigator_config

        return study_navigator_config(self.scenario, method, overrides=overrides,
                                      integrity=integrity)

    def fly(self, method: str | dict[str, Any], overrides: dict[str, Any] | None = None, *,
            truth: Any = None, terrain: Any = None, progress: Any = None) -> Any:  # noqa: ANN401
        """`neuralmap.lab.monte_carlo.fly` of ``method`` (a name or ``{"method": name,
        name: {options}}``) over this plane (or ``terrain``), R = the scenario's."""
        from neuralmap.lab.monte_carlo import fly

        name = method if isinstance(method, str) else method["method"]
        return fly(self.truth if truth is None else truth,
                   self.grid if terrain is None else terrain, self.config(method, overrides),
                   model=self.model, map_error_variance=self.model.fit_variance,
                   tile=self.tile, name=name, progress=progress)


@pytest.fixture(scope="session")
def plane_flight() -> Any:  # noqa: ANN401 - the flight builder
    """`PlaneFlight`: the tilted-plane flight, ``plane_flight(tiny_scenario, duration_s=...,
    sigma_m=60.0, n_runs=6)``."""
    return PlaneFlight
