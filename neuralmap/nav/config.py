"""The navigator's configuration: method, sensor, noise, map error, integrity, from YAML.

One YAML file, sections of named options, every option checked on load with the file and
key in the message. The shipped default is ``configs/navigator.yaml`` (`DEFAULT_CONFIG`); a
user file overrides any subset of it::

    method: point_mass_tracker      # a registered method, or an EKF linearisation name
    sensor:   {dt_s: 1.0, max_gap_s: 5.0, altimeter_sigma_m: 10.0,
               clearance_min_m: 0.0, clearance_max_m: 8000.0}
    initial:  {position_sigma_m: 100.0, altitude_sigma_m: 30.0, velocity_sigma_mps: 0.5}
    process_noise: {position_sigma_m: 1.0, altitude_sigma_m: 1.0, velocity_sigma_mps: 0.05}
    altitude_error: {model: random_walk, time_constant_s: null, sigma_m: null}
    map_error: {dem_accuracy_m: null, fit_rmse_m: null, linearisation_table: null}
    integrity: {lost_window: 20, lost_prob: 0.99999, acquired_sigma_m: 40.0,
                spike_gate_prob: 0.9999, integrity_risk: 1.0e-4, alert_limit_m: null}
    acquisition: {above_sigma_m: 150.0, handoff_sigma_m: 40.0, ...}
    point_mass_tracker: {cells: 32, span_sigma: 5.0, dtype: float32, ...}
    point_mass: {max_spacing: 50.0, max_cells: 256, ...}     # also the acquisition grid
    ekf: {linearizer: neural, policy: ekf, policy_args: {}}

The sections of the methods are their options dataclasses
(`neuralmap.tan.method.NavigationMethod.Options`), one per registered name
(`neuralmap.tan.registry`), read straight into them; the product's sections are below.

The filter's numbers follow (SEEDS 004, 5-state error ``[δx, δy, δh, δv_x, δv_y]``):
``P0 = diag(σ_p², σ_p², σ_h², σ_v², σ_v²)`` from ``initial``; ``Q`` per nominal period
``T = dt_s`` is ``diag(q_p², q_p², q_h², q_v², q_v²)`` from ``process_noise``
(``velocity_sigma_mps`` is the velocity random walk per period); an interval ``Δt`` gets
``Q · Δt / T`` (random-walk scaling) — the altitude error's part follows ``altitude_error``
(a random walk, or a Gauss-Markov process of time constant τ and stationary σ: a barometric
bias); ``R`` is built by `neuralmap.nav.map_noise`. `NavigatorConfig.model` is the
`neuralmap.tan.model.TanModel` of these numbers.
"""

from __future__ import annotations

import dataclasses
import math
import os
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from neuralmap.exceptions import NeuralMapError
from neuralmap.tan.model import TanModel
from neuralmap.tan.registry import all_method_names, method_class, method_names, resolve_method

__all__ = ["DEFAULT_CONFIG", "NavigatorConfig", "load_navigator_config"]

#: The shipped default config (``configs/navigator.yaml`` in the package).
DEFAULT_CONFIG = "navigator.yaml"


@dataclass
class SensorConfig:
    """Radar altimeter and epoch timing.

    Attributes:
        dt_s: Nominal epoch period T, s (the process noise is given per T).
        max_gap_s: Longest interval predicted across; after a longer one every vehicle
            restarts from the INS prior (acquisition again), counted ``long_gaps``.
        altimeter_sigma_m: Altimeter noise σ, m.
        clearance_min_m: Smallest clearance the altimeter states it measures, m (may be
            ``-.inf``: no lower limit).
        clearance_max_m: Largest, m (may be ``.inf``). Clearances outside ``[min, max]``
            are not used (counted ``out_of_range``, status ``no_measurement``).
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
    """INS error growth per nominal period (``Q``); the altitude part is a random walk's
    unless ``altitude_error`` says Gauss-Markov."""

    position_sigma_m: float = 1.0
    altitude_sigma_m: float = 1.0
    velocity_sigma_mps: float = 0.05


#: Models of the altitude error (`AltitudeErrorConfig.model`).
ALTITUDE_MODELS = ("random_walk", "gauss_markov")


@dataclass
class AltitudeErrorConfig:
    """The INS altitude error model (a barometric altimeter's bias, typically).

    Attributes:
        model: ``random_walk`` (growth ``process_noise.altitude_sigma_m`` per period) or
            ``gauss_markov``: ``δh⁺ = a δh + w``, ``a = exp(−Δt/τ)``, ``Var w = σ² (1 −
            a²)`` (stationary σ).
        time_constant_s: τ, s (``gauss_markov``); e.g. a decay factor of 0.96925 per second
            is τ = 32 s.
        sigma_m: Stationary σ of the error, m (``gauss_markov``).
    """

    model: str = "random_walk"
    time_constant_s: float | None = None
    sigma_m: float | None = None


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
    """Lost-lock detection, status thresholds and protection levels.

    Attributes:
        lost_window: Updates in the windowed-NIS lost-lock test (0 disables it).
        lost_prob: χ² probability of its threshold: the mean NIS of ``lost_window``
            consistent updates exceeds ``χ²_p(W)/W`` with probability ``1 − p``.
        acquired_sigma_m: Largest horizontal σ (m, principal axis) reported ``tracking``;
            above it the status is ``acquiring``.
        spike_gate_prob: A clearance whose predictive NIS exceeds ``χ²₁(p)`` is not used
            by the methods that gate (the point-mass tracker; counted ``spikes``, status
            ``no_measurement``); every method: the NIS entering the lost-lock window is
            capped at twice the test's threshold, so a few spikes cannot fire the test (8
            in one window of 20 can) while a lost lock (every NIS large) still does. 0
            disables both.
        integrity_risk: Probability per epoch that the error exceeds the protection level
            (the HPL and VPL of every fix, `neuralmap.nav.integrity`).
        alert_limit_m: Horizontal alert limit, m: a fix whose HPL exceeds it has status
            ``unavailable``; None = no limit.
        vertical_alert_limit_m: Vertical alert limit on the VPL, m; None = no limit.
        report_risks: Further integrity risks whose protection levels every fix carries
            too (`Fix.hpl_extra`, `Fix.vpl_extra`; a study reports its integrity at
            several risks from one flight); empty by default.
    """

    lost_window: int = 20
    lost_prob: float = 0.99999
    acquired_sigma_m: float = 40.0
    spike_gate_prob: float = 0.9999
    integrity_risk: float = 1.0e-4
    alert_limit_m: float | None = None
    vertical_alert_limit_m: float | None = None
    report_risks: list[float] = field(default_factory=list)


@dataclass
class AcquisitionConfig:
    """The pipeline's acquisition rule: when a vehicle starts on the point-mass grid (the
    ``point_mass`` section sizes the grid), when it is handed to the method.

    Attributes:
        above_sigma_m: A method with the ``wide`` acquisition rule (the point-mass tracker)
            starts on the grid when the prior's horizontal σ exceeds this, m.
        handoff_sigma_m: Hand-off to an EKF when the grid posterior's largest σ is at most
            this, m (a method of the ``wide`` rule, the point-mass tracker, takes it back at
            ``above_sigma_m``: it holds a wide posterior itself) ...
        handoff_affinity: ... and its Bhattacharyya coefficient against its Gaussian fit is
            at least this (unimodal) ...
        handoff_hold: ... for this many consecutive epochs ...
        min_acquire_steps: ... after at least this many grid updates.
        reacquire_sigma_m: A re-acquisition grid's horizontal σ is at least this, m.
    """

    above_sigma_m: float = 150.0
    handoff_sigma_m: float = 40.0
    handoff_affinity: float = 0.9
    handoff_hold: int = 3
    min_acquire_steps: int = 5
    reacquire_sigma_m: float = 200.0


_SECTIONS: dict[str, type] = {
    "sensor": SensorConfig, "initial": InitialConfig, "process_noise": ProcessNoiseConfig,
    "altitude_error": AltitudeErrorConfig, "map_error": MapErrorConfig,
    "integrity": IntegrityConfig, "acquisition": AcquisitionConfig,
}

#: Options that may be infinite (a stated "no limit").
_MAY_BE_INFINITE = {"sensor.clearance_min_m", "sensor.clearance_max_m", "sensor.max_gap_s"}
#: Options that may be negative.
_SIGNED = {"sensor.clearance_min_m"}


def _kind(owner: type, name: str) -> str:
    """The annotation of field ``name`` of dataclass ``owner`` as text ("float | None")."""
    hints = typing.get_type_hints(owner)
    hint = hints.get(name, Any)
    return getattr(hint, "__name__", None) or str(hint).replace("typing.", "")


def _check_fields(section: Any, prefix: str, bad: Any) -> None:
    """Type and range checks of a section's plain fields (bool, int, float, str)."""
    for f in dataclasses.fields(section):
        value = getattr(section, f.name)
        key = f"{prefix}.{f.name}"
        kind = _kind(type(section), f.name)
        if "None" in kind and value is None:
            continue
        if kind.startswith("bool"):
            if not isinstance(value, bool):
                raise bad(key, value, "true or false")
        elif kind.startswith("int"):
            if isinstance(value, bool) or not isinstance(value, int) or value < 0:
                raise bad(key, value, "an integer >= 0")
        elif kind.startswith("float"):
            finite = key not in _MAY_BE_INFINITE
            ok = (not isinstance(value, bool) and isinstance(value, (int, float))
                  and not math.isnan(value) and (math.isfinite(value) or not finite)
                  and (value >= 0 or key in _SIGNED))
            if not ok:
                need = "a finite number >= 0" if finite else "a number"
                raise bad(key, value, need)
            setattr(section, f.name, float(value))
        elif kind.startswith("str") and not isinstance(value, str):
            raise bad(key, value, "a string")


@dataclass
class NavigatorConfig:
    """Everything a `Navigator` needs besides the map.

    Attributes:
        method: A registered navigation method (`neuralmap.tan.registry.method_names`:
            ``point_mass_tracker`` (default), ``point_mass_ekf``, ``ekf``, ``ekf_bank``,
            ``point_mass``, ...) or an EKF linearisation name (``bilinear``, ``neural``, ...:
            the ``ekf`` method with that linearisation).
        sensor, initial, process_noise, altitude_error, map_error, integrity, acquisition:
            The product's sections (their classes document the options).
        methods: Each registered method's options (its ``Options`` dataclass), by name.
        source: Where the config came from (for messages).
    """

    method: str = "point_mass_tracker"
    sensor: SensorConfig = field(default_factory=SensorConfig)
    initial: InitialConfig = field(default_factory=InitialConfig)
    process_noise: ProcessNoiseConfig = field(default_factory=ProcessNoiseConfig)
    altitude_error: AltitudeErrorConfig = field(default_factory=AltitudeErrorConfig)
    map_error: MapErrorConfig = field(default_factory=MapErrorConfig)
    integrity: IntegrityConfig = field(default_factory=IntegrityConfig)
    acquisition: AcquisitionConfig = field(default_factory=AcquisitionConfig)
    methods: dict[str, Any] = field(default_factory=dict)
    source: str = "<defaults>"

    def __post_init__(self) -> None:
        for name in method_names():
            self.methods.setdefault(name, method_class(name).Options())

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
        cfg = base.copy() if base is not None else cls()
        names = method_names()
        top = {"method"} | set(_SECTIONS) | set(names)
        for key, value in data.items():
            if key not in top:
                raise NeuralMapError(f"{where}: unknown navigator option {key!r}; valid: "
                                     f"{', '.join(sorted(top))}.")
            if key == "method":
                cfg.method = value
                continue
            if value is None:
                continue
            if not isinstance(value, dict):
                raise NeuralMapError(f"{where}: section {key!r} must be a mapping of "
                                     f"option: value, got {value!r}.")
            section = getattr(cfg, key) if key in _SECTIONS else cfg.methods[key]
            valid = {f.name for f in dataclasses.fields(section)}
            for opt, v in value.items():
                if opt not in valid:
                    raise NeuralMapError(f"{where}: unknown option {key}.{opt}; valid: "
                                         f"{', '.join(sorted(valid))}.")
                setattr(section, opt, v)
        cfg.source = where
        return cfg.validate()

    def copy(self) -> NavigatorConfig:
        """A copy whose sections can be changed without touching this one."""
        out = dataclasses.replace(self, methods={k: dataclasses.replace(v) for k, v in
                                                 self.methods.items()})
        for sec in _SECTIONS:
            setattr(out, sec, dataclasses.replace(getattr(self, sec)))
        return out

    def validate(self) -> NavigatorConfig:
        """Checks every option; raises `NeuralMapError` naming it and the source."""
        where = self.source

        def bad(key: str, value: Any, need: str) -> NeuralMapError:
            return NeuralMapError(f"{where}: navigator option {key} must be {need}, got "
                                  f"{value!r}.")

        if not isinstance(self.method, str):
            raise bad("method", self.method, f"one of {', '.join(all_method_names())}")
        resolve_method(self.method, where=f"{where}: method")
        for sec in _SECTIONS:
            _check_fields(getattr(self, sec), sec, bad)
        for name, options in self.methods.items():
            check = getattr(options, "validate", None)
            if callable(check):  # the method's own checks first: they say the most
                try:
                    check(name)
                except NeuralMapError as exc:
                    raise NeuralMapError(f"{where}: {exc}") from exc
                except TypeError:  # a value of the wrong type: the generic check names it
                    pass
            _check_fields(options, name, bad)
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
        a = self.altitude_error
        if a.model not in ALTITUDE_MODELS:
            raise bad("altitude_error.model", a.model, f"one of {', '.join(ALTITUDE_MODELS)}")
        if a.model == "gauss_markov" and not (a.time_constant_s and a.sigma_m):
            raise bad("altitude_error", {"time_constant_s": a.time_constant_s,
                                         "sigma_m": a.sigma_m},
                      "given time_constant_s > 0 and sigma_m > 0 for model gauss_markov")
        i = self.integrity
        if not 0.0 < i.lost_prob < 1.0:
            raise bad("integrity.lost_prob", i.lost_prob, "in (0, 1)")
        if not 0.0 <= i.spike_gate_prob < 1.0:
            raise bad("integrity.spike_gate_prob", i.spike_gate_prob, "in [0, 1) (0 = off)")
        if not i.acquired_sigma_m > 0:
            raise bad("integrity.acquired_sigma_m", i.acquired_sigma_m, "> 0 m")
        if not 0.0 < i.integrity_risk < 0.5:
            raise bad("integrity.integrity_risk", i.integrity_risk, "in (0, 0.5)")
        if not isinstance(i.report_risks, (list, tuple)) or not all(
                isinstance(r, (int, float)) and not isinstance(r, bool) and 0.0 < r < 0.5
                for r in i.report_risks):
            raise bad("integrity.report_risks", i.report_risks,
                      "a list of probabilities in (0, 0.5)")
        i.report_risks = [float(r) for r in i.report_risks]
        for key in ("alert_limit_m", "vertical_alert_limit_m"):
            if getattr(i, key) is not None and not getattr(i, key) > 0:
                raise bad(f"integrity.{key}", getattr(i, key), "> 0 m or null (no limit)")
        q = self.acquisition
        if not 0.0 < q.handoff_affinity <= 1.0:
            raise bad("acquisition.handoff_affinity", q.handoff_affinity, "in (0, 1]")
        for key in ("handoff_sigma_m", "reacquire_sigma_m"):
            if not getattr(q, key) > 0:
                raise bad(f"acquisition.{key}", getattr(q, key), "> 0 m")
        return self

    def to_dict(self) -> dict[str, Any]:
        """Plain form (YAML/JSON), every section included (an option holding an object,
        e.g. a linearizer given in Python, is written as its class name)."""

        def plain(value: Any) -> Any:
            if value is None or isinstance(value, (bool, int, float, str)):
                return value
            if isinstance(value, dict):
                return {k: plain(v) for k, v in value.items()}
            if isinstance(value, (list, tuple)):
                return [plain(v) for v in value]
            return f"<{type(value).__name__}>"

        out: dict[str, Any] = {"method": self.method}
        for sec in _SECTIONS:
            out[sec] = dataclasses.asdict(getattr(self, sec))
        for name, options in self.methods.items():
            out[name] = {f.name: plain(getattr(options, f.name))
                         for f in dataclasses.fields(options)}
        return out

    # ------------------------------------------------------------------ the method
    def method_options(self) -> tuple[str, Any]:
        """The registered method and its options, the alias's overrides applied (an EKF
        linearisation name as ``method`` sets the ``ekf`` section's ``linearizer``)."""
        name, overrides = resolve_method(self.method, where=f"{self.source}: method")
        return name, dataclasses.replace(self.methods[name], **overrides)

    # ------------------------------------------------------------------ filter numbers
    def model(self) -> TanModel:
        """The `TanModel` of these numbers (module docstring): ``P0``, ``Q`` per period,
        the altitude error model, ``R_altimeter`` (the map's part is the Navigator's)."""
        i, q, a = self.initial, self.process_noise, self.altitude_error
        tau, q_h = None, q.altitude_sigma_m ** 2
        if a.model == "gauss_markov":
            tau = float(a.time_constant_s)
            q_h = a.sigma_m ** 2 * (1.0 - math.exp(-2.0 * self.sensor.dt_s / tau))
        return TanModel(
            dt=float(self.sensor.dt_s),
            P0=(i.position_sigma_m ** 2, i.position_sigma_m ** 2, i.altitude_sigma_m ** 2,
                i.velocity_sigma_mps ** 2, i.velocity_sigma_mps ** 2),
            Q=(q.position_sigma_m ** 2, q.position_sigma_m ** 2, q_h,
               q.velocity_sigma_mps ** 2, q.velocity_sigma_mps ** 2),
            R_altimeter=float(self.sensor.altimeter_sigma_m) ** 2,
            altitude_time_constant_s=tau)


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
