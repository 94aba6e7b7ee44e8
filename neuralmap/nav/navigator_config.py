"""The navigator's configuration: method, sensor, noise, map error and integrity, from YAML.

Scenario style (`neuralmap.nav.scenario`): one YAML file, sections of named options,
every option checked on load with the file and key in the message. The shipped default is
``configs/navigator.yaml`` (`DEFAULT_CONFIG`); a user file overrides any subset of it::

    method: point_mass_tracker        # or point_mass_ekf, or an EKF linearizer name
    sensor:   {dt_s: 1.0, max_gap_s: 5.0, altimeter_sigma_m: 10.0,
               clearance_min_m: 0.0, clearance_max_m: 8000.0}
    initial:  {position_sigma_m: 100.0, altitude_sigma_m: 30.0, velocity_sigma_mps: 0.5}
    process_noise: {position_sigma_m: 1.0, altitude_sigma_m: 1.0, velocity_sigma_mps: 0.05}
    map_error: {dem_accuracy_m: null, fit_rmse_m: null, linearisation_table: null}
    integrity: {lost_window: 20, lost_prob: 0.99999, acquired_sigma_m: 40.0,
                spike_gate_prob: 0.9999}

The filter's numbers follow (SEEDS 004, 5-state error ``[δx, δy, δh, δv_x, δv_y]``):
``P0 = diag(σ_p², σ_p², σ_h², σ_v², σ_v²)`` from ``initial``; ``Q`` per nominal period
``T = dt_s`` is ``diag(q_p², q_p², q_h², q_v², q_v²)`` from ``process_noise``
(``velocity_sigma_mps`` is the velocity random walk per period), and an interval ``Δt`` gets
``Q · Δt / T`` (random-walk scaling); ``R`` is built by `neuralmap.nav.map_noise`.
"""

from __future__ import annotations

import dataclasses
import math
import os
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.nav.acquisition import AcquisitionConfig
from neuralmap.nav.tracking import TrackerOptions

__all__ = ["DEFAULT_CONFIG", "NavigatorConfig", "load_navigator_config", "navigator_methods"]

#: The shipped default config (``configs/navigator.yaml`` in the package).
DEFAULT_CONFIG = "navigator.yaml"

#: Methods that start on the point-mass acquisition grid when the prior is wide.
GRID_METHODS = ("point_mass_tracker", "point_mass_ekf")


def navigator_methods() -> tuple[str, ...]:
    """Every method name a navigator accepts: the grid methods and the EKF linearizers."""
    from neuralmap.linearize.factory import LINEARIZER_NAMES

    return GRID_METHODS + tuple(LINEARIZER_NAMES)


@dataclass
class SensorConfig:
    """Radar altimeter and epoch timing.

    Attributes:
        dt_s: Nominal epoch period T, s (the process noise is given per T).
        max_gap_s: Longest interval predicted across; a longer one is counted
            (``long_gaps``) and its epoch is predicted only (status ``no_measurement``).
        altimeter_sigma_m: Altimeter noise σ, m.
        clearance_min_m: Smallest clearance the altimeter states it measures, m.
        clearance_max_m: Largest, m. Clearances outside ``[min, max]`` are not used
            (counted ``out_of_range``, status ``no_measurement``).
    """

    dt_s: float = 1.0
    max_gap_s: float = 5.0
    altimeter_sigma_m: float = 10.0
    clearance_min_m: float = 0.0
    clearance_max_m: float = 8000.0


@dataclass
class InitialConfig:
    """Initial INS error σ (the prior ``P0``)."""

    position_sigma_m: float = 100.0
    altitude_sigma_m: float = 30.0
    velocity_sigma_mps: float = 0.5


@dataclass
class ProcessNoiseConfig:
    """INS error growth per nominal period (``Q``)."""

    position_sigma_m: float = 1.0
    altitude_sigma_m: float = 1.0
    velocity_sigma_mps: float = 0.05


@dataclass
class MapErrorConfig:
    """The map's own error model (`neuralmap.nav.map_noise`).

    Attributes:
        dem_accuracy_m: The DEM's stated vertical accuracy (1σ), m; None = unknown (0).
        fit_rmse_m: A neural map's fit error, m; None = read it from the map's stored
            fit metrics (``offnode_rmse_m``, ``between_rmse_m`` or ``rmse_m``), 0 for a grid.
        linearisation_table: Path of a measured noise table (JSON of
            `NoiseTable`), EKF methods only.
    """

    dem_accuracy_m: float | None = None
    fit_rmse_m: float | None = None
    linearisation_table: str | None = None


@dataclass
class IntegrityConfig:
    """Lost-lock detection and status thresholds.

    Attributes:
        lost_window: Updates in the windowed-NIS lost-lock test (0 disables it).
        lost_prob: χ² probability of its threshold: the mean NIS of ``lost_window``
            consistent updates exceeds ``χ²_p(W)/W`` with probability ``1 − p``.
        acquired_sigma_m: Largest horizontal σ (m, principal axis) reported ``tracking``;
            above it the status is ``acquiring``.
        spike_gate_prob: Point-mass tracker: a clearance whose predictive NIS (against the
            tracker's predicted mixture) exceeds ``χ²₁(p)`` is not used (counted
            ``spikes``, status ``no_measurement``); every method: the NIS entering the
            lost-lock window is capped at twice the test's threshold, so a few spikes cannot
            fire the test (8 in one window of 20 can) while a lost lock (every NIS large)
            still does. 0 disables both.
    """

    lost_window: int = 20
    lost_prob: float = 0.99999
    acquired_sigma_m: float = 40.0
    spike_gate_prob: float = 0.9999


@dataclass
class TrackerSection:
    """Lattice of the point-mass tracker (`TrackerOptions`).

    Attributes:
        cells, span_sigma, principal_axes, dtype, flatten_likelihood, min_cell_blur: As
            `TrackerOptions` (the lost-lock test is the
            navigator's, ``integrity``; the tracker's own widening is off).
    """

    cells: int = TrackerOptions.cells
    span_sigma: float = TrackerOptions.span_sigma
    principal_axes: bool = TrackerOptions.principal_axes
    dtype: str = TrackerOptions.dtype
    flatten_likelihood: bool = TrackerOptions.flatten_likelihood
    min_cell_blur: float = TrackerOptions.min_cell_blur


@dataclass
class AcquisitionSection:
    """The point-mass acquisition grid (`AcquisitionConfig`).

    Attributes:
        above_sigma_m: ``point_mass_tracker`` starts on the grid when the initial
            horizontal σ exceeds this (else on the tracker directly).
        max_spacing_m, max_cells, span_sigma, dtype, handoff_sigma_m, handoff_affinity,
        handoff_hold, min_acquire_steps, flatten_likelihood, reacquire_sigma_m,
        outlier_prob, outlier_width_m: As
            `AcquisitionConfig` (``outlier_prob`` > 0:
            the grid's likelihood is a Gaussian / uniform mixture; default 0: with 0.01 or
            0.001 and the flattened likelihood the grid never reached the hand-off on the
            tiny synthetic tile from σ0 = 250 m, not investigated).
    """

    above_sigma_m: float = 150.0
    # the grid's own options default to the acquisition grid's (one place for their values)
    max_spacing_m: float = AcquisitionConfig.max_spacing_m
    max_cells: int = AcquisitionConfig.max_cells
    span_sigma: float = AcquisitionConfig.span_sigma
    dtype: str = AcquisitionConfig.dtype
    handoff_sigma_m: float = AcquisitionConfig.handoff_sigma_m
    handoff_affinity: float = AcquisitionConfig.handoff_affinity
    handoff_hold: int = AcquisitionConfig.handoff_hold
    min_acquire_steps: int = AcquisitionConfig.min_acquire_steps
    flatten_likelihood: bool = AcquisitionConfig.flatten_likelihood
    reacquire_sigma_m: float = AcquisitionConfig.reacquire_sigma_m
    outlier_prob: float = AcquisitionConfig.outlier_prob
    outlier_width_m: float = AcquisitionConfig.outlier_width_m


_SECTIONS: dict[str, type] = {
    "sensor": SensorConfig, "initial": InitialConfig, "process_noise": ProcessNoiseConfig,
    "map_error": MapErrorConfig, "integrity": IntegrityConfig, "tracker": TrackerSection,
    "acquisition": AcquisitionSection,
}


@dataclass
class NavigatorConfig:
    """Everything a `Navigator` needs besides the map.

    Attributes:
        method: ``point_mass_tracker`` (default), ``point_mass_ekf`` or an EKF linearizer
            name (`neuralmap.linearize.factory.LINEARIZER_NAMES`).
        policy: Robust/adaptive update policy of the EKF methods, a
            `neuralmap.filters.policies.registry.POLICY_NAMES` name (``ekf`` = none).
        policy_args: Options of the policy.
        sensor, initial, process_noise, map_error, integrity, tracker, acquisition: The
            sections (their classes document the options).
        source: Where the config came from (for messages).
    """

    method: str = "point_mass_tracker"
    policy: str = "ekf"
    policy_args: dict[str, Any] = field(default_factory=dict)
    sensor: SensorConfig = field(default_factory=SensorConfig)
    initial: InitialConfig = field(default_factory=InitialConfig)
    process_noise: ProcessNoiseConfig = field(default_factory=ProcessNoiseConfig)
    map_error: MapErrorConfig = field(default_factory=MapErrorConfig)
    integrity: IntegrityConfig = field(default_factory=IntegrityConfig)
    tracker: TrackerSection = field(default_factory=TrackerSection)
    acquisition: AcquisitionSection = field(default_factory=AcquisitionSection)
    source: str = "<defaults>"

    # ------------------------------------------------------------------ building
    @classmethod
    def from_dict(cls, data: dict[str, Any], *, where: str = "<dict>",
                  base: NavigatorConfig | None = None) -> NavigatorConfig:
        """A config from a mapping, over ``base`` (default: the built-in defaults).

        Raises:
            NeuralMapError: Unknown section or key (lists the valid ones), a value of the
                wrong type or range (names the key and ``where``).
        """
        if not isinstance(data, dict):
            raise NeuralMapError(f"{where}: a navigator config must be a mapping of section: "
                                 f"options, got {type(data).__name__}.")
        cfg = dataclasses.replace(base) if base is not None else cls()
        for sec in _SECTIONS:
            setattr(cfg, sec, dataclasses.replace(getattr(cfg, sec)))
        cfg.policy_args = dict(cfg.policy_args)
        top = {"method", "policy", "policy_args"} | set(_SECTIONS)
        for key, value in data.items():
            if key not in top:
                raise NeuralMapError(f"{where}: unknown navigator option {key!r}; valid: "
                                     f"{', '.join(sorted(top))}.")
            if key in _SECTIONS:
                if value is None:
                    continue
                if not isinstance(value, dict):
                    raise NeuralMapError(f"{where}: section {key!r} must be a mapping of "
                                         f"option: value, got {value!r}.")
                section = getattr(cfg, key)
                names = {f.name for f in dataclasses.fields(section)}
                for opt, v in value.items():
                    if opt not in names:
                        raise NeuralMapError(f"{where}: unknown option {key}.{opt}; valid: "
                                             f"{', '.join(sorted(names))}.")
                    setattr(section, opt, v)
            elif key == "policy_args":
                cfg.policy_args = dict(value or {})
            else:
                setattr(cfg, key, value)
        cfg.source = where
        return cfg.validate()

    def validate(self) -> NavigatorConfig:
        """Checks every option; raises `NeuralMapError` naming it and the source."""
        where = self.source

        def bad(key: str, value: Any, need: str) -> NeuralMapError:
            return NeuralMapError(f"{where}: navigator option {key} must be {need}, got "
                                  f"{value!r}.")

        methods = navigator_methods()
        if self.method not in methods:
            raise bad("method", self.method, f"one of {', '.join(methods)}")
        from neuralmap.filters.policies.registry import POLICY_NAMES

        if self.policy not in POLICY_NAMES:
            raise bad("policy", self.policy, f"one of {', '.join(POLICY_NAMES)}")
        if not isinstance(self.policy_args, dict):
            raise bad("policy_args", self.policy_args, "a mapping")
        for sec in _SECTIONS:
            section = getattr(self, sec)
            for f in dataclasses.fields(section):
                value = getattr(section, f.name)
                key = f"{sec}.{f.name}"
                kind = f.type if isinstance(f.type, str) else getattr(f.type, "__name__", "")
                if "None" in kind and value is None:
                    continue
                if kind.startswith("bool"):
                    if not isinstance(value, bool):
                        raise bad(key, value, "true or false")
                elif kind.startswith("int"):
                    if isinstance(value, bool) or not isinstance(value, int) or value < 0:
                        raise bad(key, value, "an integer >= 0")
                elif kind.startswith("float"):
                    if isinstance(value, bool) or not isinstance(value, (int, float)) or not (
                            math.isfinite(value) and value >= 0):
                        raise bad(key, value, "a finite number >= 0")
                    setattr(section, f.name, float(value))
                elif kind.startswith("str") and not isinstance(value, str):
                    raise bad(key, value, "a string")
        s = self.sensor
        if not s.dt_s > 0:
            raise bad("sensor.dt_s", s.dt_s, "> 0 seconds")
        if not s.max_gap_s >= s.dt_s:
            raise bad("sensor.max_gap_s", s.max_gap_s, f">= sensor.dt_s ({s.dt_s:g} s)")
        if not s.altimeter_sigma_m > 0:
            raise bad("sensor.altimeter_sigma_m", s.altimeter_sigma_m, "> 0 m")
        if not s.clearance_max_m > s.clearance_min_m:
            raise bad("sensor.clearance_max_m", s.clearance_max_m,
                      f"> sensor.clearance_min_m ({s.clearance_min_m:g} m)")
        for key in ("position_sigma_m", "altitude_sigma_m", "velocity_sigma_mps"):
            if not getattr(self.initial, key) > 0:
                raise bad(f"initial.{key}", getattr(self.initial, key), "> 0")
        i = self.integrity
        if not 0.0 < i.lost_prob < 1.0:
            raise bad("integrity.lost_prob", i.lost_prob, "in (0, 1)")
        if not 0.0 <= i.spike_gate_prob < 1.0:
            raise bad("integrity.spike_gate_prob", i.spike_gate_prob, "in [0, 1) (0 = off)")
        if not i.acquired_sigma_m > 0:
            raise bad("integrity.acquired_sigma_m", i.acquired_sigma_m, "> 0 m")
        for sec in ("tracker", "acquisition"):
            dtype = getattr(self, sec).dtype
            if dtype not in ("float32", "float64"):
                raise bad(f"{sec}.dtype", dtype, "'float32' or 'float64'")
        if self.tracker.cells < 8:
            raise bad("tracker.cells", self.tracker.cells, "an integer >= 8")
        if not 0.0 <= self.acquisition.outlier_prob < 1.0:
            raise bad("acquisition.outlier_prob", self.acquisition.outlier_prob, "in [0, 1)")
        if not self.acquisition.outlier_width_m > 0:
            raise bad("acquisition.outlier_width_m", self.acquisition.outlier_width_m, "> 0 m")
        if not 0.0 < self.acquisition.handoff_affinity <= 1.0:
            raise bad("acquisition.handoff_affinity", self.acquisition.handoff_affinity,
                      "in (0, 1]")
        return self

    def to_dict(self) -> dict[str, Any]:
        """Plain form (YAML/JSON), every section included."""
        out: dict[str, Any] = {"method": self.method, "policy": self.policy,
                               "policy_args": dict(self.policy_args)}
        for sec in _SECTIONS:
            out[sec] = dataclasses.asdict(getattr(self, sec))
        return out

    # ------------------------------------------------------------------ filter numbers
    def prior(self, dtype: torch.dtype = torch.float64) -> torch.Tensor:
        """``(5, 5)`` ``P0 = diag(σ_p², σ_p², σ_h², σ_v², σ_v²)``."""
        i = self.initial
        return torch.diag(torch.tensor([i.position_sigma_m**2, i.position_sigma_m**2,
                                        i.altitude_sigma_m**2, i.velocity_sigma_mps**2,
                                        i.velocity_sigma_mps**2], dtype=dtype))

    def process_noise_per_period(self, dtype: torch.dtype = torch.float64) -> torch.Tensor:
        """``(5, 5)`` ``Q`` per nominal period ``T = sensor.dt_s``."""
        q = self.process_noise
        return torch.diag(torch.tensor([q.position_sigma_m**2, q.position_sigma_m**2,
                                        q.altitude_sigma_m**2, q.velocity_sigma_mps**2,
                                        q.velocity_sigma_mps**2], dtype=dtype))


def _default_path() -> Path:
    from neuralmap.resources import config_file

    return config_file(DEFAULT_CONFIG)


def load_navigator_config(source: NavigatorConfig | dict[str, Any] | str | os.PathLike[str]
                          | None = None) -> NavigatorConfig:
    """A validated config: the shipped defaults, overridden by ``source``.

    Args:
        source: None (the shipped ``navigator.yaml``), a `NavigatorConfig`
            (validated, returned), a mapping or a YAML file path (overrides over the
            shipped defaults).

    Raises:
        NeuralMapError: Missing or unreadable file, unknown keys, bad values.
    """
    if isinstance(source, NavigatorConfig):
        return source.validate()
    from neuralmap.io import load_yaml

    def read(path: Path) -> dict[str, Any]:
        try:
            data = load_yaml(path.read_text(encoding="utf-8"))
        except OSError as exc:
            raise NeuralMapError(f"{path}: cannot read the navigator config ({exc}).") from exc
        except Exception as exc:  # yaml errors carry the line and column
            raise NeuralMapError(f"{path}: not valid YAML ({exc}).") from exc
        return {} if data is None else data

    default = _default_path()
    base = NavigatorConfig()
    if default.is_file():
        base = NavigatorConfig.from_dict(read(default), where=str(default))
    if source is None:
        return base
    if isinstance(source, dict):
        return NavigatorConfig.from_dict(source, where="<dict>", base=base)
    path = Path(source)
    if not path.is_file():
        raise NeuralMapError(f"{path}: no such navigator config file (copy the shipped "
                             f"{default} and edit it).")
    return NavigatorConfig.from_dict(read(path), where=str(path), base=base)
