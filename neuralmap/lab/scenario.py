"""Navigation scenarios: flight, INS and sensor errors, and the filter's tuning, from YAML.

A `Scenario` holds everything the simulator and the terrain-aided navigation (TAN)
filter need besides the map: the tile, the flight (start, speed, heading, waypoints,
altitude), the truth error models (INS initial errors and random walks, radar-altimeter
noise, DEM-making error, outliers) and the filter's tuning (``P0``, ``Q``, ``R``, map fit
variance). Shipped scenarios live in ``configs/scenarios/<name>.yaml`` (``paper``,
``jacksboro``, ``tiny``); `load_scenario` reads them by name or path.

Truth INS error model (SEEDS 004's 5-state error model driven by white noise): the error
``δX = [δx, δy, δh, δv_x, δv_y]`` (INS minus truth) starts at
``δX_0 ~ N(init_error_mean, diag(σ_p², σ_p², σ_h², σ_v², σ_v²))`` with
``σ_p = init_pos_sigma_m``, ``σ_h = init_alt_sigma_m``, ``σ_v = init_vel_sigma_mps``, and
propagates as ``δX_{k+1} = Φ δX_k + w_k``, ``w_k ~ N(0, Q_truth)`` with
``Q_truth = diag(q_p², q_p², q_h², vrw²·T, vrw²·T)`` (`Scenario.truth_process_noise`):
``q_p = pos_noise_sigma_m`` per step, ``q_h = alt_noise_sigma_m`` per step and the velocity
random walk ``vrw = vel_random_walk`` in m/s/√s. A scenario whose ``Q_diag`` equals
``Q_truth``, whose ``P0_diag`` equals the initial spread, with zero ``init_error_mean``
and ``R_m2`` equal to ``altimeter_sigma_m²``, has a consistent filter (NEES meaningful up to
the terrain linearisation error) — the ``jacksboro`` scenario is built that way.
"""

from __future__ import annotations

import dataclasses
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import yaml

from neuralmap.dem.tile import DemTile
from neuralmap.exceptions import NeuralMapError
from neuralmap.io import atomic_write_text, load_yaml
from neuralmap.resources import config_dir

#: Names of the shipped scenarios (``configs/scenarios/<name>.yaml``).
SCENARIO_NAMES = ("paper", "jacksboro", "tiny")

#: Folder of the shipped scenario files (repository checkout / editable install).
SCENARIO_DIR = config_dir() / "scenarios"

_FLOAT_FIELDS = (
    "dt", "duration_s", "start_spread_m", "speed_mps", "heading_deg", "turn_rate_dps",
    "altitude_agl_m", "climb_rate_mps", "init_pos_sigma_m", "init_alt_sigma_m",
    "init_vel_sigma_mps", "vel_random_walk", "pos_noise_sigma_m", "alt_noise_sigma_m",
    "altimeter_sigma_m", "dem_error_sigma_m", "dem_error_corr_m", "outlier_prob",
    "outlier_sigma_m", "R_m2", "fit_variance_m2", "spike_prob", "spike_min_m", "spike_max_m",
    "patch_prob", "patch_min_s", "patch_max_s", "patch_bias_min_m", "patch_bias_max_m",
    "lock_loss_prob", "beam_half_angle_deg",
)
_NONNEGATIVE_FIELDS = (
    "start_spread_m", "speed_mps", "init_pos_sigma_m", "init_alt_sigma_m",
    "init_vel_sigma_mps", "vel_random_walk", "pos_noise_sigma_m", "alt_noise_sigma_m",
    "altimeter_sigma_m", "dem_error_sigma_m", "outlier_sigma_m", "fit_variance_m2",
)


@dataclass
class Scenario:
    """A TAN Monte Carlo scenario (flight, truth error models, filter tuning).

    Positions (``start_xy``, ``waypoints``) are metres east/north of the tile's south-west
    node (its ``origin``). Headings are degrees clockwise from north (90 = east).

    Attributes:
        name: Scenario name (reports, run folders).
        description: Free text: where the numbers come from.
        tile: Sample tile name (``"jacksboro"``, ``"synthetic"``) or path of a DEM file.
        tile_options: Keyword arguments for the tile: for ``"synthetic"`` those of
            `neuralmap.dem.synthetic_tile` (``shape``, ``spacing``, ``seed``,
            ``relief``, ``hurst``); otherwise those of `neuralmap.dem.load_tile`
            (``spacing``, ``origin``, ``name``).
        dt: Filter and sampling period T, s.
        duration_s: Flight duration, s; the simulation has ``K = round(duration_s / dt)``
            steps (``K + 1`` samples including t = 0).
        start_xy: Nominal start ``[x, y]`` relative to the tile origin, m; ``None`` centres
            the straight flight ``speed_mps · duration_s`` along ``heading_deg`` on the tile.
        start_spread_m: 1σ of the per-run random start offset (each run's path is the
            nominal path translated by its offset, so runs see different terrain), m.
        speed_mps: Ground speed, m/s.
        heading_deg: Initial heading, degrees clockwise from north.
        waypoints: ``[[x, y], ...]`` relative to the tile origin, flown in order after the
            start (rate-limited turns toward each, the next one taken when within the turn
            radius); straight flight after the last one. ``None`` = straight flight.
        turn_rate_dps: Maximum turn rate, degrees per second.
        altitude_agl_m: Flight altitude above the tile's highest node, m (the aircraft
            flies at ``max(heights) + altitude_agl_m``).
        climb_rate_mps: Constant climb rate, m/s (negative = descent).
        init_pos_sigma_m: 1σ spread of the initial INS horizontal error per axis, m.
        init_alt_sigma_m: 1σ spread of the initial INS altitude error, m.
        init_vel_sigma_mps: 1σ spread of the initial INS velocity error per axis, m/s.
        init_error_mean: Mean initial INS error ``[δx, δy, δh, δv_x, δv_y]`` (INS − truth).
        vel_random_walk: INS velocity random walk, m/s/√s (velocity error variance grows by
            ``vel_random_walk² · dt`` per step and axis).
        pos_noise_sigma_m: White INS horizontal position noise per step and axis, m.
        alt_noise_sigma_m: INS altitude random-walk increment per step, m.
        altimeter_sigma_m: Radar-altimeter noise 1σ, m.
        dem_error_sigma_m: 1σ of the DEM-making error (true terrain = DEM + a smooth random
            field, fixed per seed, same for all runs); 0 = the DEM is the truth.
        dem_error_corr_m: Correlation length of the DEM-making error, m (correlation
            ``exp(-r²/L²)``).
        outlier_prob: Probability that an altimeter sample is an outlier.
        outlier_sigma_m: 1σ of the extra error added to an outlier sample, m.
        spike_prob: Radar-altimeter fault: probability per epoch of an isolated spike of
            magnitude uniform in ``[spike_min_m, spike_max_m]`` and random sign.
        spike_min_m: Smallest spike, m.
        spike_max_m: Largest spike, m.
        patch_prob: Probability per epoch that a patch of consecutive biased returns (tree
            canopy, buildings) starts; it lasts uniform ``[patch_min_s, patch_max_s]`` and
            adds a bias uniform in ``[patch_bias_min_m, patch_bias_max_m]`` to the clearance.
        patch_min_s: Shortest patch, s.
        patch_max_s: Longest patch, s.
        patch_bias_min_m: Most negative patch bias, m (returns from the canopy top: shorter).
        patch_bias_max_m: Least negative patch bias, m.
        lock_loss_prob: Probability per epoch of a loss of lock (no measurement).
        beam_half_angle_deg: Altimeter beam half-angle: the footprint radius is
            ``height above ground · tan(angle)``, used for the roughness quality indicator.
        truth_model: ``"dem"`` (truth = bicubic DEM + DEM-making error) or ``"subgrid"``
            (also fractal detail below the grid spacing, on a finer grid; see
            `neuralmap.lab.truth_terrain`).
        subgrid_factor: Refinement of the ``subgrid`` truth grid (2 … 8).
        P0_diag: Filter's initial covariance diagonal ``(5,)``, m², m², m², (m/s)², (m/s)².
        Q_diag: Filter's process-noise diagonal per step ``(5,)``.
        R_m2: Altimeter noise variance the filter assumes, m².
        fit_variance_m2: Map fit variance added to R (SEEDS 004: 6 m²).
        seed: Default random seed of the simulation.
    """

    name: str = "custom"
    description: str = ""
    tile: str = "jacksboro"
    tile_options: dict[str, Any] = field(default_factory=dict)
    dt: float = 1.0
    duration_s: float = 100.0
    start_xy: list[float] | None = None
    start_spread_m: float = 0.0
    speed_mps: float = 200.0
    heading_deg: float = 90.0
    waypoints: list[list[float]] | None = None
    turn_rate_dps: float = 3.0
    altitude_agl_m: float = 1000.0
    climb_rate_mps: float = 0.0
    init_pos_sigma_m: float = 100.0
    init_alt_sigma_m: float = 10.0
    init_vel_sigma_mps: float = 1.0
    init_error_mean: list[float] = field(default_factory=lambda: [0.0] * 5)
    vel_random_walk: float = 0.05
    pos_noise_sigma_m: float = 1.0
    alt_noise_sigma_m: float = 1.0
    altimeter_sigma_m: float = 10.0
    dem_error_sigma_m: float = 0.0
    dem_error_corr_m: float = 300.0
    outlier_prob: float = 0.0
    outlier_sigma_m: float = 100.0
    spike_prob: float = 0.0
    spike_min_m: float = 50.0
    spike_max_m: float = 300.0
    patch_prob: float = 0.0
    patch_min_s: float = 5.0
    patch_max_s: float = 20.0
    patch_bias_min_m: float = -40.0
    patch_bias_max_m: float = -10.0
    lock_loss_prob: float = 0.0
    beam_half_angle_deg: float = 20.0
    truth_model: str = "dem"
    subgrid_factor: int = 4
    P0_diag: list[float] = field(default_factory=lambda: [1e4, 1e4, 100.0, 1.0, 1.0])
    Q_diag: list[float] = field(default_factory=lambda: [1.0, 1.0, 1.0, 0.0025, 0.0025])
    R_m2: float = 100.0
    fit_variance_m2: float = 0.0
    seed: int = 0

    @property
    def n_steps(self) -> int:
        """Number of filter steps K (the simulation has ``K + 1`` samples)."""
        return max(int(round(self.duration_s / self.dt)), 1)

    def truth_process_noise(self) -> list[float]:
        """Per-step variances of the truth INS error model's driving noise.

        Returns:
            ``[q_p², q_p², q_h², vrw²·dt, vrw²·dt]`` (see the module docstring).
        """
        qp = self.pos_noise_sigma_m**2
        qv = self.vel_random_walk**2 * self.dt
        return [qp, qp, self.alt_noise_sigma_m**2, qv, qv]

    def pcrb_kind(self) -> str:
        """``"bound"``, or ``"reference"`` when the initial error is fixed.

        The Bayesian PCRB takes the initial error as drawn from N(mean, P0). With a fixed
        (deterministic) initial error, as in paper 004's own scenario, it bounds nothing:
        reports label it a reference curve.
        """
        fixed = max(self.init_error_sigma()) == 0.0 or any(v != 0.0 for v in self.init_error_mean)
        return "reference" if fixed else "bound"

    def init_error_sigma(self) -> list[float]:
        """1σ of the initial INS error per state ``[σ_p, σ_p, σ_h, σ_v, σ_v]``."""
        p, h, v = self.init_pos_sigma_m, self.init_alt_sigma_m, self.init_vel_sigma_mps
        return [p, p, h, v, v]

    def to_dict(self) -> dict[str, Any]:
        """Plain-data (YAML/JSON-serialisable) copy of every field."""
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, data: dict[str, Any], *, where: str = "scenario") -> Scenario:
        """Builds and validates a scenario from a mapping of field values.

        Args:
            data: Field name to value; missing fields keep their defaults.
            where: Where the data came from (file path), used in error messages.

        Returns:
            The validated scenario.

        Raises:
            NeuralMapError: Not a mapping, unknown keys (the message lists the valid
                ones) or invalid values.
        """
        if not isinstance(data, dict):
            raise NeuralMapError(
                f"{where}: a scenario must be a mapping of keys to values, got "
                f"{type(data).__name__}."
            )
        valid = [f.name for f in dataclasses.fields(cls)]
        unknown = sorted(str(k) for k in data if k not in valid)
        if unknown:
            raise NeuralMapError(
                f"{where}: unknown scenario key(s) {unknown}. Valid keys: {', '.join(valid)}."
            )
        scenario = cls(**data)
        scenario.validate(where=where)
        return scenario

    def validate(self, *, where: str | None = None, options: bool = False) -> Scenario:
        """Checks types and ranges and normalises numbers to floats and lists.

        Args:
            where: Location used in error messages (default: ``scenario '<name>'``).
            options: The fields were set from a study's command-line options (a study that
                overrides scenario fields with its own options): the message names the
                option ``--<key>`` to fix instead of the scenario YAML.

        Returns:
            ``self`` (normalised in place), for chaining.

        Raises:
            NeuralMapError: The first invalid key, with its value and the allowed range.
        """
        where = where or f"scenario {self.name!r}"

        def bad(key: str, value: Any, need: str) -> NeuralMapError:
            if options:
                return NeuralMapError(f"{where}: --{key} must be {need}, got {value!r}.")
            return NeuralMapError(
                f"{where}: key '{key}' must be {need}, got {value!r}. Fix it in the scenario "
                "YAML (or the Scenario field of the same name)."
            )

        def number(key: str, value: Any) -> float:
            if isinstance(value, bool) or not isinstance(value, (int, float)):
                raise bad(key, value, "a number")
            value = float(value)
            if not math.isfinite(value):
                raise bad(key, value, "finite")
            return value

        def vector(key: str, value: Any, n: int) -> list[float]:
            if not isinstance(value, (list, tuple)) or len(value) != n:
                raise bad(key, value, f"a list of {n} numbers")
            return [number(key, v) for v in value]

        if not isinstance(self.name, str) or not self.name:
            raise bad("name", self.name, "a non-empty string")
        if not isinstance(self.description, str):
            raise bad("description", self.description, "a string")
        if not isinstance(self.tile, (str, os.PathLike)) or not str(self.tile):
            raise bad("tile", self.tile, "a sample tile name or a DEM file path")
        self.tile = str(self.tile)
        if not isinstance(self.tile_options, dict):
            raise bad("tile_options", self.tile_options, "a mapping of tile keyword arguments")
        for key in _FLOAT_FIELDS:
            setattr(self, key, number(key, getattr(self, key)))
        if isinstance(self.seed, bool) or not isinstance(self.seed, int) or self.seed < 0:
            raise bad("seed", self.seed, "an integer >= 0")
        for key in ("dt", "duration_s", "R_m2", "altitude_agl_m", "turn_rate_dps"):
            if getattr(self, key) <= 0.0:
                raise bad(key, getattr(self, key), "> 0")
        for key in _NONNEGATIVE_FIELDS:
            if getattr(self, key) < 0.0:
                raise bad(key, getattr(self, key), ">= 0 (a standard deviation or variance)")
        if self.duration_s < self.dt:
            raise bad("duration_s", self.duration_s, f">= dt ({self.dt} s)")
        for key in ("outlier_prob", "spike_prob", "patch_prob", "lock_loss_prob"):
            if not 0.0 <= getattr(self, key) <= 1.0:
                raise bad(key, getattr(self, key), "a probability in [0, 1]")
        if not 0.0 <= self.spike_min_m <= self.spike_max_m:
            raise bad("spike_min_m", self.spike_min_m, f"in [0, spike_max_m = {self.spike_max_m}]")
        if not 0.0 < self.patch_min_s <= self.patch_max_s:
            raise bad("patch_min_s", self.patch_min_s, f"in (0, patch_max_s = {self.patch_max_s}]")
        if not self.patch_bias_min_m <= self.patch_bias_max_m:
            raise bad("patch_bias_min_m", self.patch_bias_min_m,
                      f"<= patch_bias_max_m = {self.patch_bias_max_m}")
        if not 0.0 <= self.beam_half_angle_deg < 80.0:
            raise bad("beam_half_angle_deg", self.beam_half_angle_deg, "in [0, 80) degrees")
        if self.dem_error_sigma_m > 0.0 and self.dem_error_corr_m <= 0.0:
            raise bad("dem_error_corr_m", self.dem_error_corr_m,
                      "> 0 when dem_error_sigma_m > 0")
        if self.truth_model not in ("dem", "subgrid"):
            raise bad("truth_model", self.truth_model, "'dem' or 'subgrid'")
        if isinstance(self.subgrid_factor, bool) or not isinstance(self.subgrid_factor, int) or (
            not 2 <= self.subgrid_factor <= 8
        ):
            raise bad("subgrid_factor", self.subgrid_factor, "an integer in 2 ... 8")
        self.init_error_mean = vector("init_error_mean", self.init_error_mean, 5)
        self.P0_diag = vector("P0_diag", self.P0_diag, 5)
        self.Q_diag = vector("Q_diag", self.Q_diag, 5)
        if any(v <= 0.0 for v in self.P0_diag):
            raise bad("P0_diag", self.P0_diag, "5 variances > 0 (P0 must be positive definite)")
        if any(v < 0.0 for v in self.Q_diag):
            raise bad("Q_diag", self.Q_diag, "5 variances >= 0 (Q must be positive semi-definite)")
        if self.start_xy is not None:
            self.start_xy = vector("start_xy", self.start_xy, 2)
        if self.waypoints is not None:
            if not isinstance(self.waypoints, (list, tuple)) or len(self.waypoints) == 0:
                raise bad("waypoints", self.waypoints, "null or a non-empty list of [x, y]")
            self.waypoints = [vector("waypoints", w, 2) for w in self.waypoints]
        return self


def _scenario_path(name_or_path: str | os.PathLike[str]) -> Path:
    """Resolves a shipped scenario name or a YAML path."""
    text = str(name_or_path)
    path = Path(text)
    if path.suffix.lower() in (".yaml", ".yml") or path.exists():
        if not path.is_file():
            raise NeuralMapError(
                f"load_scenario: scenario file {text!r} does not exist. Pass a YAML path or "
                f"one of the shipped names {', '.join(SCENARIO_NAMES)}."
            )
        return path
    for folder in (SCENARIO_DIR, Path.cwd() / "configs" / "scenarios"):
        candidate = folder / f"{text}.yaml"
        if candidate.is_file():
            return candidate
    raise NeuralMapError(
        f"load_scenario: unknown scenario {text!r}. Use one of the shipped names "
        f"{', '.join(SCENARIO_NAMES)} (configs/scenarios/<name>.yaml) or a path to a YAML file."
    )


def load_scenario(name_or_path: str | os.PathLike[str] | Scenario) -> Scenario:
    """Loads and validates a scenario.

    Args:
        name_or_path: A shipped name (``"paper"``, ``"jacksboro"``, ``"tiny"``, read from
            ``configs/scenarios/<name>.yaml``), a YAML file path, or a `Scenario`
            (validated and returned).

    Returns:
        The validated `Scenario`.

    Raises:
        NeuralMapError: Unknown name, missing or unreadable file, unknown keys (the message
            lists the valid keys) or invalid values (the message names the key and file).
    """
    if isinstance(name_or_path, Scenario):
        return name_or_path.validate()
    path = _scenario_path(name_or_path)
    try:
        data = load_yaml(path.read_text(encoding="utf-8"))
    except (OSError, UnicodeDecodeError, yaml.YAMLError) as exc:
        raise NeuralMapError(f"{path}: cannot read the scenario YAML ({exc}).") from exc
    if data is None or data == {}:
        raise NeuralMapError(
            f"{path}: the scenario file is empty. Copy a shipped scenario "
            f"({', '.join(SCENARIO_NAMES)}: configs/scenarios/<name>.yaml) and edit it."
        )
    if isinstance(data, dict) and "name" not in data:
        data = {**data, "name": path.stem}
    return Scenario.from_dict(data, where=str(path))


def save_scenario(scenario: Scenario, path: str | os.PathLike[str]) -> Path:
    """Writes a scenario as YAML atomically (temporary file + rename).

    Args:
        scenario: The scenario (validated before writing).
        path: Destination file.

    Returns:
        The written path.
    """
    scenario.validate()
    return atomic_write_text(path, yaml.safe_dump(scenario.to_dict(), sort_keys=False))


def scenario_tile(scenario: Scenario) -> DemTile:
    """Loads the scenario's DEM tile.

    ``tile == "synthetic"`` calls `neuralmap.dem.synthetic_tile` with
    ``tile_options``; anything else calls `neuralmap.dem.load_tile` with them.

    Args:
        scenario: The scenario.

    Returns:
        The tile.

    Raises:
        NeuralMapError: The tile cannot be loaded, or ``tile_options`` has keys the loader
            does not take.
    """
    from neuralmap.dem import load_tile, synthetic_tile

    options = dict(scenario.tile_options)
    loader = synthetic_tile if scenario.tile == "synthetic" else load_tile
    try:
        if scenario.tile == "synthetic":
            if "shape" in options and isinstance(options["shape"], list):
                options["shape"] = tuple(options["shape"])
            return synthetic_tile(**options)
        return load_tile(scenario.tile, **options)
    except TypeError as exc:
        raise NeuralMapError(
            f"scenario {scenario.name!r}: tile_options {options} do not fit "
            f"{loader.__name__} ({exc}). Check the 'tile_options' keys."
        ) from exc
