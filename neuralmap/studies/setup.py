"""The one setup every TAN-family study shares (tan, tan_outliers, tan_scale, learned,
dem_errors, acquisition, map_size): scenario, tile, neural map, truth terrain and
linearisation methods, frozen, built from explicit arguments (`prepare_tan`)."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, ClassVar

import torch

from neuralmap.dem.tile import DemTile
from neuralmap.exceptions import NeuralMapError
from neuralmap.lab.map_error import map_error_correlation, measure_map_error
from neuralmap.lab.scenario import Scenario, load_scenario, scenario_tile
from neuralmap.lab.truth_terrain import true_terrain
from neuralmap.linearize.factory import LINEARIZER_NAMES, TERRAIN_MODEL_METHODS, make_linearizer
from neuralmap.studies.base import StudyConfig
from neuralmap.studies.maps import check_map_tile, resolve_map_path
from neuralmap.terrain.export import load_map
from neuralmap.terrain.grid import GridTerrain

__all__ = ["DEFAULT_METHODS", "TanOptions", "TanSetup", "build_methods", "dem_error_model",
           "prepare_tan", "void_exposure"]

#: Methods evaluated when ``--methods`` is not given.
DEFAULT_METHODS: tuple[str, ...] = (
    "neural",
    "neural_region",
    "bilinear",
    "nine_point",
    "mean_point",
    "lsq_adaptive",
    "lsq_min",
)


@dataclass
class TanOptions(StudyConfig):
    """Options every Monte Carlo TAN study shares (``tan``, ``tan_scale``, ``tan_outliers``): what
    `prepare_tan` needs and the divergence rule.

    Attributes:
        map: Exported neural map (``neural_map.pt``); ``None`` = the newest
            ``<runs_dir>/*/version_*/neural_map.pt`` of the scenario's tile.
        scenario: Scenario name (``configs/scenarios/<name>.yaml``) or a YAML path.
        n_runs: Monte Carlo trajectories (the same truth for every method).
        methods: Linearisation methods to compare; ``neural`` uses the map with autograd.
        neural_fit_variance: Extra variance (m²) the neural methods add to R for the map
            error. ``None`` = measured: the map's mean squared error against the
            scenario's truth terrain at seeded random points between the nodes, less the
            scenario's ``fit_variance_m2`` that every method gets.
        map_error_points: Random points for that measurement.
        pcrb_factor: Divergence when the final error exceeds this times the final PCRB.
        divergence_sigma: Divergence when the final error exceeds this many times the
            filter's own 1σ horizontal bound ``sqrt(P_xx + P_yy)`` (9 = 3 × the 3σ bound).
    """

    map: str | None = None
    scenario: str = "jacksboro"
    n_runs: int = 1000
    methods: list[str] = field(default_factory=lambda: list(DEFAULT_METHODS))
    neural_fit_variance: float | None = None
    map_error_points: int = 20000
    pcrb_factor: float = 5.0
    divergence_sigma: float = 9.0

    #: Whether ``methods`` may also name registered navigation methods
    #: (`neuralmap.tan.registry.method_names`), flown through the Navigator by name.
    navigation_methods: ClassVar[bool] = False

    def known_methods(self) -> tuple[str, ...]:
        """The names ``--methods`` accepts."""
        from neuralmap.tan.registry import method_names

        names = tuple(LINEARIZER_NAMES)
        return names + method_names() if self.navigation_methods else names

    @property
    def linearized_methods(self) -> list[str]:
        """The methods that are EKF linearisations (built by `prepare_tan`)."""
        return [m for m in self.methods if m in LINEARIZER_NAMES]

    def validate(self) -> None:
        """Checks values; raises `NeuralMapError` naming the option and the fix."""
        super().validate()
        if self.n_runs < 1:
            raise NeuralMapError(f"--n_runs must be >= 1, got {self.n_runs}.")
        known = self.known_methods()
        if not self.methods:
            raise NeuralMapError(f"--methods is empty; pick one or more of {', '.join(known)}.")
        unknown = [m for m in self.methods if m not in known]
        if unknown:
            raise NeuralMapError(
                f"--methods: unknown method(s) {unknown}; known: {', '.join(known)}.")
        if len(set(self.methods)) != len(self.methods):
            raise NeuralMapError(f"--methods lists a method twice: {self.methods}.")
        if self.neural_fit_variance is not None and not self.neural_fit_variance >= 0:
            raise NeuralMapError(
                f"--neural_fit_variance must be >= 0 m^2 (or null), got {self.neural_fit_variance}."
            )
        if self.map_error_points < 100:
            raise NeuralMapError(f"--map_error_points must be >= 100, got {self.map_error_points}.")
        if not (self.pcrb_factor > 0 and self.divergence_sigma > 0):
            raise NeuralMapError(
                f"--pcrb_factor and --divergence_sigma must be > 0, got {self.pcrb_factor}, "
                f"{self.divergence_sigma}."
            )

    @property
    def needs_map(self) -> bool:
        """Whether any method needs the neural map."""
        return any(m in TERRAIN_MODEL_METHODS for m in self.methods)


def build_methods(
    names: list[str],
    *,
    tile: Any,
    terrain_map: Any,
    device: torch.device,
    fit_variance: float = 0.0,
) -> dict[str, Any]:
    """One linearizer per method name (``neural*`` = the map with autograd).

    Args:
        names: Method names (`neuralmap.linearize.factory.LINEARIZER_NAMES`).
        tile: The scenario's DEM tile (grid and plane-fit methods).
        terrain_map: The loaded neural map (None when no neural method is asked for).
        device: Device the filters run on.
        fit_variance: The neural map's error variance (m²), its linearisation variance.

    Returns:
        Method name -> `Linearizer`, in ``names`` order.
    """
    methods: dict[str, Any] = {}
    for name in names:
        if name in TERRAIN_MODEL_METHODS:
            linearizer = make_linearizer(
                name, tile=tile, terrain=terrain_map, fit_variance=fit_variance
            )
        else:
            linearizer = make_linearizer(name, tile=tile)
        methods[name] = linearizer.to(device)
    return methods


@dataclass(frozen=True)
class TanSetup:
    """What a TAN study flies: scenario, tile, truth terrain, map and methods.

    Attributes:
        scenario: The validated scenario.
        tile: Its DEM tile.
        seed: The seed used.
        truth_terrain: The truth terrain (one world per seed).
        terrain_map: The neural map (None when no method needs it).
        map_path: Its file.
        map_error: Its error against the truth between nodes (empty without a map).
        fit_variance: The extra R of the neural methods, m².
        methods: Method name -> linearizer.
        map_note: Why the terrain-model methods were left out (``map_optional`` and no
            map found); empty otherwise.
    """

    scenario: Any
    tile: Any
    seed: int
    truth_terrain: Any
    terrain_map: Any
    map_path: Path | None
    map_error: dict[str, Any]
    fit_variance: float
    methods: dict[str, Any]
    map_note: str = ""

    def pin(self, config: Any) -> None:
        """Records the map and seed actually used in ``config`` (its ``map`` and ``seed``),
        so that the saved config.yaml reruns exactly this study."""
        if self.map_path is not None:
            config.map = str(self.map_path)
        config.seed = self.seed

    def map_info(self) -> dict[str, Any]:
        """The map's description for results.json."""
        terrain_map = self.terrain_map
        return {
            "path": str(self.map_path) if self.map_path else None,
            "tile_name": getattr(terrain_map, "tile_name", ""),
            "tile_fingerprint": getattr(terrain_map, "tile_fingerprint", ""),
            "model": type(terrain_map).__name__ if terrain_map is not None else None,
            "num_parameters": int(sum(p.numel() for p in terrain_map.parameters()))
            if terrain_map is not None else None,
            "fit_metrics": dict(getattr(terrain_map, "metrics", None) or {}),
            "error_vs_truth": self.map_error,
            "neural_extra_variance_m2": self.fit_variance,
        }


def prepare_tan(
    *,
    scenario: str | Scenario,
    methods: Sequence[str],
    map_path: str | None,
    runs_dir: str,
    seed: int | None,
    neural_fit_variance: float | None,
    map_error_points: int,
    device: torch.device,
    measure_map: bool = True,
    tile: DemTile | None = None,
    map_optional: bool = False,
) -> TanSetup:
    """The one setup of every TAN-family study: scenario, tile, map, truth terrain and
    linearisation methods, from explicit arguments.

    Args:
        scenario: Scenario name, YAML path, or an already built `Scenario`.
        methods: Linearisation method names.
        map_path: Neural map file; None = the newest map of the scenario's tile under
            ``runs_dir`` (only read when a method needs a terrain model).
        runs_dir: Where trained maps are searched.
        seed: Seed of the truth terrain (None = the scenario's).
        neural_fit_variance: Extra R of the neural methods (m²); None = measured: the
            map's MSE against the truth between nodes minus the scenario's fit variance.
        map_error_points: Seeded random points of that measurement.
        device: Device of the linearizers.
        measure_map: Measure the map's error against the truth (``map_error``); False
            for a study that gives ``neural_fit_variance`` and reports no map error
            (``dem_errors``), so that no time goes into it.
        tile: The DEM tile to fly over; None = the scenario's (``acquisition`` passes a
            synthetic plane for its flat-terrain leg).
        map_optional: With ``map_path`` None and no map of the tile under ``runs_dir``,
            leave the terrain-model methods out (``map_note`` says why) instead of
            raising (``acquisition``: its neural-map rows are skipped).

    Returns:
        The frozen `TanSetup` (record its map and seed with `TanSetup.pin`).

    Raises:
        NeuralMapError: Bad scenario, no map, a map of another tile.
    """
    scenario = load_scenario(scenario) if isinstance(scenario, str) else scenario
    tile = scenario_tile(scenario) if tile is None else tile
    found: Path | None = None
    terrain_map = None
    map_note = ""
    if any(m in TERRAIN_MODEL_METHODS for m in methods):
        try:
            found = resolve_map_path(map_path, runs_dir, tile_fingerprint=tile.fingerprint())
        except NeuralMapError as exc:
            if map_path is not None or not map_optional:
                raise
            methods = [m for m in methods if m not in TERRAIN_MODEL_METHODS]
            map_note = str(exc)
        else:
            terrain_map = load_map(found)
            check_map_tile(terrain_map, tile, map_path=found, scenario_name=scenario.name)
    seed = scenario.seed if seed is None else int(seed)
    truth_terrain = true_terrain(scenario, tile, seed=seed)
    map_error: dict[str, Any] = {}
    if terrain_map is not None and measure_map:
        map_error = measure_map_error(terrain_map, truth_terrain.model, tile,
                                      n_points=map_error_points, seed=seed)
    if neural_fit_variance is None:
        if not measure_map:
            raise NeuralMapError(
                "prepare_tan: measure_map=False needs neural_fit_variance (the extra R of the "
                "neural methods comes from the measured map error otherwise)."
            )
        mse = map_error.get("mse_m2", 0.0) or 0.0
        fit_variance = max(float(mse) - scenario.fit_variance_m2, 0.0)
    else:
        fit_variance = float(neural_fit_variance)
    built = build_methods(list(methods), tile=tile, terrain_map=terrain_map, device=device,
                          fit_variance=fit_variance)
    return TanSetup(scenario, tile, seed, truth_terrain, terrain_map, found, map_error,
                    fit_variance, built, map_note)


def void_exposure(tile: Any, truth: Any) -> dict[str, int]:
    """Truth samples (and runs) whose terrain height is read from a DEM void.

    Under a void the truth terrain is the grid's nearest-node fill, not real terrain; the
    count goes into the report so that a study over voids is never silently wrong.
    """
    if tile.n_void == 0:
        return {"samples": 0, "runs": 0}
    under = tile.void_under(truth.pos[..., :2].detach().cpu().double().numpy(), halo=1)
    return {"samples": int(under.sum()), "runs": int(under.any(axis=1).sum())}


def dem_error_model(scenario: Any, tile: Any, truth_terrain: Any, *, n_points: int,
                    seed: int) -> dict[str, Any]:
    """The bilinear DEM as a map, with its error against the truth terrain: the noise of the
    map-aware PCRB (`neuralmap.lab.pcrb.map_aware_pcrb`).

    Args:
        scenario: The study's scenario (its speed × period is the correlation lag).
        tile: The DEM tile.
        truth_terrain: The study's `TrueTerrain`.
        n_points: Seeded random points between the nodes.
        seed: Seed of the points.

    Returns:
        ``{"terrain": GridTerrain (bilinear), "mse_m2": mean squared error against the
        truth, "corr": its correlation over one step's flight, "lag_m": that distance}``.
    """
    grid = GridTerrain(tile, method="bilinear")
    err = measure_map_error(grid, truth_terrain.model, tile, n_points=n_points, seed=seed)
    lag = float(scenario.speed_mps) * float(scenario.dt)
    corr = map_error_correlation(grid, truth_terrain.model, tile, lag_m=lag, n_points=n_points,
                                 seed=seed)
    return {"terrain": grid, "mse_m2": float(err.get("mse_m2", 0.0)), "corr": corr, "lag_m": lag}
