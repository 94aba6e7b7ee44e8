"""The Navigator: terrain-aided fixes from a map, an INS and a radar altimeter, epoch by epoch.

`Navigator` turns a flight — a recorded log, a live sensor stream, or the simulated
vehicles of a study — into `Fix` es with their covariance, protection levels and status,
for N vehicles at once (batch first). It is the one navigation pipeline of the toolkit: the
``neuralmap-navigate`` command and every study that flies TAN run it. It is built from

* a map: any `TerrainModel` (a DEM grid, a blockwise neural map, a latent map, a region
  map);
* a navigation method by name (`neuralmap.tan.registry`): ``point_mass_tracker`` (default),
  ``point_mass_ekf``, ``ekf`` with any linearisation and update policy (or a linearisation
  name), ``ekf_bank``, ``point_mass``, or any method registered by the user;
* a config in YAML (`neuralmap.nav.config`): sensor, noise, the altitude error model, the
  map's own error model (``R = σ_alt² + σ_dem² + σ_fit²``, `neuralmap.nav.map_noise`),
  integrity, and each method's options.

State and timing: the 5-state error ``δX = [δx, δy, δh, δv_x, δv_y]`` = INS − truth
(`neuralmap.tan.model`); a fix is ``INS − δX̂``. The first epoch after `Navigator.reset` is
the prior (``δX̂ = 0``, ``P0``, no update); every later epoch predicts over the interval since
the previous one and updates with the altimeter: ``y = h_ins − clearance = t(p_ins − δp) +
δh − v``.

The pipeline, per vehicle and epoch (status codes of `STATUS`):

* **Acquisition**: a method whose ``acquisition`` rule asks for it (``always``, or ``wide``
  when the prior's horizontal σ exceeds ``acquisition.above_sigma_m``) starts on the
  point-mass acquisition grid (`neuralmap.tan.methods.point_mass.PointMassGrid`, sized by
  the ``point_mass`` section) and is **handed off** to the method once the grid posterior is
  small (largest σ ≤ ``handoff_sigma_m`` for an EKF; ≤ ``above_sigma_m``, or
  ``handoff_sigma_m`` if larger, for a method of the ``wide`` rule, which holds a wide
  posterior itself) and unimodal (Bhattacharyya
  coefficient against its Gaussian fit ≥ ``handoff_affinity``) for ``handoff_hold`` epochs
  after at least ``min_acquire_steps`` grid updates; the method starts from the grid
  posterior's moments.
* **Lost lock**: the mean NIS over the last ``integrity.lost_window`` updates above
  ``χ²_p(W)/W`` (`neuralmap.filters.nis_window`) **re-acquires from the open-loop prior**
  ``N(m_ol, P_ol)``: the prior propagated through every prediction without a measurement
  (``m_ol ← Φ m_ol``, ``P_ol ← Φ P_ol Φᵀ + Q``), the dead-reckoning bound of the INS error,
  which holds the truth wherever the filter lost it (a wrong terrain match). The vehicle
  goes back to the acquisition grid (by the method's rule, with a horizontal σ of at least
  ``reacquire_sigma_m``) or straight back into the method. Status ``lost`` at the detection,
  ``acquiring`` while the grid holds the vehicle or its horizontal σ exceeds
  ``integrity.acquired_sigma_m``, then ``tracking``. (The INS error must stay inside its
  model for the open-loop prior to hold the truth: a jump of the INS itself is not
  re-acquired.)
* **Off the map**: an estimate off the map's extent is predicted only (``off_map``).
* **Voids of the map**: an estimate over a no-data cell of the map's DEM (filled from its
  neighbours, not a measured height) is predicted only (``no_map``, counted
  ``no_map_epochs``); a point-mass lattice gives such cells no likelihood.
* **No measurement**: a NaN clearance, or one outside ``[sensor.clearance_min_m,
  sensor.clearance_max_m]``, is not used: predicted only, status ``no_measurement``,
  counted (``missing_radar``, ``out_of_range``).
* **Time gaps**: an interval longer than ``sensor.dt_s`` is predicted across with its true
  length (``Φ(Δt)``, ``Q(Δt)``), counted (``gaps``); one longer than ``sensor.max_gap_s``
  is not predicted across (the INS error model does not hold over it): every vehicle
  restarts from the INS prior ``N(0, P0)`` as at the first epoch (acquisition again), and
  the restart is counted (``long_gaps``).
* **Altimeter spikes**: a method that gates (the point-mass tracker; the grid when its
  ``spike_gate`` is on) leaves out a clearance whose predictive NIS exceeds ``χ²₁(p)``, ``p
  = integrity.spike_gate_prob`` (counted ``spikes``, ``no_measurement``); the EKF methods
  take spikes through their policy (``raf``, ``igg3``, ``huber``, ``chi2``, ...). With the
  gate on, the NIS entering the lost-lock window is capped at twice the test's threshold.
* **Protection levels**: every fix carries its HPL and VPL at ``integrity.integrity_risk``
  (`neuralmap.nav.integrity`); a tracking fix whose HPL exceeds ``integrity.alert_limit_m``
  (or VPL ``vertical_alert_limit_m``) is ``unavailable``.

Streaming equals replay: `Navigator.replay` is `Navigator.step` over the epochs (the filter
is recursive; the batch is over vehicles), so the two agree bit for bit.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.filters.nis_window import NisWindow
from neuralmap.filters.stats import chi2_quantile, symmetrize
from neuralmap.nav.config import NavigatorConfig, load_navigator_config
from neuralmap.nav.fix import STATUS_CODE, Fix, FixTrack
from neuralmap.nav.integrity import largest_sigma, protection_levels
from neuralmap.nav.map_noise import MapNoise, load_noise_table, measurement_noise
from neuralmap.tan.method import MethodContext, NavigationMethod
from neuralmap.tan.methods.point_mass import PointMassGrid
from neuralmap.tan.methods.tracker import spd_floor
from neuralmap.tan.model import N_STATES, TanModel
from neuralmap.tan.registry import method_class
from neuralmap.terrain.base import inside_extent, model_device

__all__ = ["COUNT_KEYS", "Navigator"]

#: Counters of `FixTrack.counts` / `Navigator.counts` (summed over vehicles).
COUNT_KEYS = ("epochs", "missing_radar", "out_of_range", "spikes", "gaps", "long_gaps",
              "off_map_epochs", "no_map_epochs", "lost", "reacquisitions", "handoffs",
              "updates")

_ACQ, _TRK, _LOST, _OFF, _NOMEAS, _UNAV, _NOMAP = (STATUS_CODE[k] for k in (
    "acquiring", "tracking", "lost", "off_map", "no_measurement", "unavailable", "no_map"))

#: Per-vehicle counters (`Navigator.vehicle_counts`), besides ``first_handoff``, in the
#: column order of the one ``(N, C)`` counter tensor the pipeline adds to per epoch.
_VEHICLE_KEYS = ("missing_radar", "out_of_range", "spikes", "off_map_epochs",
                 "no_map_epochs", "updates", "lost", "handoffs")
_PER_EPOCH = 6  # the first six columns are counted every epoch, the last ones on events


def _resolve_device(device: Any, terrain: Any) -> torch.device:
    """The navigator's device: ``device`` (``"cpu"``, ``"cuda"``, ``"cuda:<i>"``, a
    `torch.device`) or, when None, the map's (its first parameter or buffer, else the CPU);
    a clear error when it is unknown, absent, or not where the map's tensors are."""
    on_map = model_device(terrain)
    if device is None:
        return on_map if on_map is not None else torch.device("cpu")
    try:
        dev = torch.device(device)
    except (RuntimeError, TypeError) as exc:
        raise NeuralMapError(f"Navigator: device={device!r} is not a torch device; use "
                             "'cpu', 'cuda', 'cuda:<i>' or a torch.device.") from exc
    if dev.type == "cuda" and not torch.cuda.is_available():
        raise NeuralMapError(f"Navigator: device={str(device)!r}, but CUDA is not available "
                             "on this machine; pass device='cpu' (or leave device unset).")
    if dev.type == "cuda" and dev.index is None:
        dev = torch.device("cuda", torch.cuda.current_device())
    if on_map is not None and on_map != dev:
        raise NeuralMapError(
            f"Navigator: device={str(device)!r}, but the map ({type(terrain).__name__}) is on "
            f"{on_map}; move the map first (terrain.to({str(dev)!r})) or pass "
            f"device={str(on_map)!r}.")
    return dev


class Navigator:
    """Terrain-aided navigation of N vehicles over one map, epoch by epoch.

    Args:
        terrain: The map, any `TerrainModel` with an ``extent`` (``forward(xy (..., 2)) ->
            (...)`` heights).
        config: A `NavigatorConfig`, a mapping or YAML path of overrides over the shipped
            ``configs/navigator.yaml``, or None (the shipped defaults).
        n_vehicles: N, the batch size of every input.
        map_frame: Anything with ``to_geo(x, y) -> (lat, lon)`` (e.g.
            `neuralmap.nav.georef.MapFrame`); fixes then carry lat/lon.
        map_error_variance: Overrides the map's error variance in ``R`` (m²), e.g. a
            study's DEM error measured against its truth terrain; None = from the config
            and the map's stored fit metrics (`neuralmap.nav.map_noise`).
        dtype: dtype of the fixes (float64 default).
        tile: The DEM tile, for the EKF linearisations that read the DEM itself
            (``bilinear``, ``nine_point``, ...); None = rebuilt from a grid map's heights.
        device: Where the filter state lives and runs: ``"cpu"``, ``"cuda"``,
            ``"cuda:<i>"`` or a `torch.device`; None (default) = the map's device (its
            first parameter or buffer, else the CPU). A map with tensors must already be
            on it (``terrain.to(device)``). Inputs to `step` / `replay` may be on any
            device (they are moved); `step` returns its `Fix` on this device, `replay`
            returns its `FixTrack` on the CPU.
        model: The TAN model to fly (`neuralmap.tan.model.TanModel`, or an augmented one):
            ``P0``, ``Q``, the altitude error model and the altimeter's variance; None = the
            config's (`NavigatorConfig.model`). A simulation study passes its scenario's.

    Attributes:
        config (NavigatorConfig): The validated config.
        model (TanModel): The TAN model.
        noise (MapNoise): The parts of ``R``.
        method (str): The registered name of the navigation method.
        counts (dict[str, int]): Counters summed over vehicles since `reset`
            (`COUNT_KEYS`).
        vehicle_counts (dict[str, torch.Tensor]): The same per vehicle ``(N,)``, and
            ``first_handoff`` (epoch, −1).

    Raises:
        NeuralMapError: Bad config, a map without an extent, ``n_vehicles < 1``, a
            linearisation that cannot be built, or a device that is unknown, absent (CUDA
            asked for without it) or not the map's.
    """

    def __init__(self, terrain: Any, config: NavigatorConfig | dict | str | Any = None, *,
                 n_vehicles: int = 1, map_frame: Any = None,
                 map_error_variance: float | None = None, dtype: torch.dtype = torch.float64,
                 tile: Any = None, device: str | torch.device | None = None,
                 model: TanModel | Any = None) -> None:
        self.config = load_navigator_config(config)
        if isinstance(n_vehicles, bool) or not isinstance(n_vehicles, int) or n_vehicles < 1:
            raise NeuralMapError(f"Navigator: n_vehicles must be an integer >= 1, got "
                                 f"{n_vehicles!r}.")
        extent = getattr(terrain, "extent", None)
        if extent is None or len(tuple(extent)) != 4:
            raise NeuralMapError(f"Navigator: the map ({type(terrain).__name__}) has no extent "
                                 "(xmin, xmax, ymin, ymax); pass a neuralmap TerrainModel.")
        if map_frame is not None and not callable(getattr(map_frame, "to_geo", None)):
            raise NeuralMapError("Navigator: map_frame must have a to_geo(x, y) -> (lat, lon) "
                                 f"method, got {type(map_frame).__name__}.")
        if dtype not in (torch.float32, torch.float64):
            raise NeuralMapError(f"Navigator: dtype must be float32 or float64, got {dtype}.")
        cfg = self.config
        self.device = _resolve_device(device, terrain)
        self.terrain = terrain
        self.extent = tuple(float(e) for e in extent)
        self.n_vehicles, self.map_frame, self.dtype, self.tile = n_vehicles, map_frame, dtype, tile
        self.model = cfg.model() if model is None else model
        if abs(float(self.model.dt) - cfg.sensor.dt_s) > 1e-9 * cfg.sensor.dt_s:
            raise NeuralMapError(
                f"Navigator: the model's period {self.model.dt:g} s is not the config's "
                f"sensor.dt_s ({cfg.sensor.dt_s:g} s); set sensor.dt_s to the model's.")
        self.noise: MapNoise = measurement_noise(
            cfg, terrain, map_error_variance=map_error_variance,
            altimeter_variance=None if model is None else float(self.model.R_altimeter))
        self.method, self._options = cfg.method_options()
        self._method_cls = method_class(self.method)
        table = cfg.map_error.linearisation_table
        self._context = MethodContext(
            terrain=terrain, extent=self.extent, model=self.model, R=self.noise.R,
            R_altimeter=self.noise.altimeter_m2, n_vehicles=n_vehicles, device=self.device,
            tile=tile, noise_table=load_noise_table(table) if table else None)
        gate_p = cfg.integrity.spike_gate_prob
        self._gate = chi2_quantile(gate_p, 1) if gate_p > 0 else math.inf
        self._P0 = self.model.filter_prior(device=self.device)[:N_STATES, :N_STATES]
        self._T = float(self.model.dt)
        dev, f64 = self.device, torch.float64
        self._T_t = torch.tensor(self._T, dtype=f64, device=dev)
        self._phi_T = self.model.transition(device=dev)[:N_STATES, :N_STATES]
        self._q_T = self.model.process_noise(device=dev)[:N_STATES, :N_STATES]
        self._no = torch.zeros(n_vehicles, dtype=torch.bool, device=dev)
        self._nan = torch.full((n_vehicles,), math.nan, dtype=f64, device=dev)
        self._nan2 = torch.full((n_vehicles, 2), math.nan, dtype=f64, device=dev)
        self.reset()

    # ------------------------------------------------------------------ set-up
    def reset(self) -> None:
        """Starts a new flight for every vehicle: the next `step` is the prior."""
        n, dev = self.n_vehicles, self.device
        self._track: NavigationMethod = self._method_cls(self._context, self._options)
        self._grid: PointMassGrid | None = None
        if self._method_cls.acquisition != "never":
            self._grid = PointMassGrid(self._context, self.config.methods["point_mass"])
        self._on_grid = torch.zeros(n, dtype=torch.bool, device=dev)
        self._window = NisWindow(n, self.config.integrity.lost_window,
                                 self.config.integrity.lost_prob,
                                 capped=self._gate < math.inf, device=dev)
        self._t_prev: float | None = None
        self._ins_prev: torch.Tensor | None = None
        self._epoch = -1
        self._counters = torch.zeros(n, len(_VEHICLE_KEYS), dtype=torch.long, device=dev)
        self._first_handoff = torch.full((n,), -1, dtype=torch.long, device=dev)
        self._epoch_counts = dict.fromkeys(("epochs", "gaps", "long_gaps"), 0)
        self._start_from_prior()

    def _start_from_prior(self) -> None:
        """Every vehicle (re)starts from the INS prior ``N(0, P0)``: on the acquisition grid
        when the method's rule asks for it, else in the method; the open-loop prior, the
        NIS windows and the hand-off counters start over."""
        n, cfg, dev = self.n_vehicles, self.config, self.device
        everyone = torch.ones(n, dtype=torch.bool, device=dev)
        mean = torch.zeros(n, N_STATES, dtype=torch.float64, device=dev)
        cov = self._P0.expand(n, N_STATES, N_STATES).clone()
        rule = self._method_cls.acquisition
        sigma0 = float(largest_sigma(self._P0[None])[0])
        on_grid = rule == "always" or (rule == "wide" and sigma0 > cfg.acquisition.above_sigma_m)
        if on_grid:
            self._grid.load(everyone, mean, cov)
            self._track.drop(everyone)
        else:
            if self._grid is not None:
                self._grid.drop(everyone)
            self._track.load(everyone, mean, cov)
        self._on_grid = torch.full((n,), on_grid, dtype=torch.bool, device=dev)
        self._window.clear(everyone)
        self._open_cov1 = self._P0.clone()
        self._hold = torch.zeros(n, dtype=torch.long, device=dev)
        self._since = torch.zeros(n, dtype=torch.long, device=dev)
        self._mean, self._cov = mean, cov

    @property
    def vehicle_counts(self) -> dict[str, torch.Tensor]:
        """Per-vehicle counters ``(N,)`` since `reset` (`COUNT_KEYS` that are per vehicle;
        ``reacquisitions`` = ``lost``), ``first_handoff`` (epoch, −1 = none), and the
        methods' own counters (``recoveries``, ...)."""
        out = {k: self._counters[:, i] for i, k in enumerate(_VEHICLE_KEYS)}
        out["reacquisitions"] = out["lost"]
        out["first_handoff"] = self._first_handoff
        for method in (self._track, self._grid):
            for key, value in ({} if method is None else method.counters()).items():
                out[key] = out[key] + value if key in out else value
        return out

    @property
    def counts(self) -> dict[str, int]:
        """What the navigator counted since `reset`, summed over vehicles (`COUNT_KEYS`),
        and the likelihood evaluations of its methods (``cell_updates``)."""
        out = dict(self._epoch_counts)
        totals = self._counters.sum(0).tolist()
        out.update(zip(_VEHICLE_KEYS, totals, strict=True))
        out["reacquisitions"] = out["lost"]
        out["cell_updates"] = self._track.cell_updates + (
            self._grid.cell_updates if self._grid is not None else 0)
        return {k: out[k] for k in (*COUNT_KEYS, "cell_updates")}

    @property
    def R(self) -> float:
        """The measurement variance ``σ_alt² + σ_dem² + σ_fit²``, m²."""
        return self.noise.R

    # ------------------------------------------------------------------ inputs
    def _inputs(self, t: Any, ins_position: Any, ins_altitude: Any, clearance: Any,
                quality: Any) -> tuple[float, torch.Tensor, torch.Tensor, torch.Tensor, Any]:
        n, dev, f64 = self.n_vehicles, self.device, torch.float64
        if isinstance(t, torch.Tensor) and t.numel() > 1:
            if t.numel() != n or not bool((t == t.reshape(-1)[0]).all()):
                raise NeuralMapError("Navigator.step: every vehicle of one navigator shares "
                                     f"the epoch time (a number or ({n},) equal values); run "
                                     "one Navigator per clock.")
            t = t.reshape(-1)[0]
        try:
            t_k = float(t)
        except (TypeError, ValueError, RuntimeError):
            t_k = math.nan
        if not math.isfinite(t_k):
            raise NeuralMapError(f"Navigator.step: t must be a finite time in seconds (a "
                                 f"number or ({n},) equal values), got {t!r}.")
        pos = torch.as_tensor(ins_position)
        alt = torch.as_tensor(ins_altitude)
        clr = torch.as_tensor(clearance)
        if pos.shape != (n, 2) or alt.shape != (n,) or clr.shape != (n,):
            raise NeuralMapError(
                f"Navigator.step: for {n} vehicles ins_position must be ({n}, 2), ins_altitude "
                f"and clearance ({n},); got {tuple(pos.shape)}, {tuple(alt.shape)}, "
                f"{tuple(clr.shape)}.")
        if pos.dtype != f64 or pos.device != dev:
            pos = pos.to(dev, f64)
        if alt.dtype != f64 or alt.device != dev:
            alt = alt.to(dev, f64)
        if clr.dtype != f64 or clr.device != dev:
            clr = clr.to(dev, f64)
        if not math.isfinite(float(pos.sum() + alt.sum())):
            raise NeuralMapError("Navigator.step: the INS position and altitude must be finite "
                                 "(NaN is allowed in the clearance only).")
        if quality is not None:
            quality = torch.as_tensor(quality)
            if quality.ndim != 2 or quality.shape[0] != n:
                raise NeuralMapError(f"Navigator.step: quality must be ({n}, q) (the "
                                     f"altimeter's quality record), got {tuple(quality.shape)}.")
            quality = quality.to(dev)
        return t_k, pos, alt, clr, quality

    # ------------------------------------------------------------------ one epoch
    def step(self, t: float | torch.Tensor, ins_position: torch.Tensor,
             ins_altitude: torch.Tensor, clearance: torch.Tensor,
             quality: torch.Tensor | None = None) -> Fix:
        """One epoch for every vehicle: predict over the interval, update, report.

        Args:
            t: Epoch time, s (a number, or ``(N,)`` equal values); strictly increasing.
            ins_position: ``(N, 2)`` INS horizontal position in the map frame, m.
            ins_altitude: ``(N,)`` INS altitude, m (the map's vertical datum).
            clearance: ``(N,)`` radar-altimeter clearance, m (NaN = no measurement).
            quality: ``(N, q)`` the altimeter's quality record, for an update policy that
                reads it (``quality_raf``, ...); None otherwise.

        Returns:
            `Fix`, its tensors on the navigator's device (``Navigator.device``).

        Raises:
            NeuralMapError: Bad shapes, non-finite INS inputs, time not increasing, a policy
                that needs the quality record without it.
        """
        t_k, pos, alt, clr, quality = self._inputs(t, ins_position, ins_altitude, clearance,
                                                   quality)
        n = self.n_vehicles
        self._epoch += 1
        self._epoch_counts["epochs"] += n
        dt = math.nan if self._t_prev is None else t_k - self._t_prev
        if self._t_prev is not None and not dt > 0:
            raise NeuralMapError(f"Navigator.step: time must increase; got t = {t_k!r} s "
                                 f"after {self._t_prev!r} s.")
        long_gap = dt > self.config.sensor.max_gap_s
        if self._t_prev is None or long_gap:  # the prior epoch (again after a long gap)
            if long_gap:
                self._epoch_counts["long_gaps"] += n
                self._start_from_prior()
            vel_ins = self._nan2
            off = ~inside_extent(pos, self.extent)
            self._counters[:, 3] += off
            events = {"nomeas": self._no, "lost": self._no, "off": off, "nis": self._nan,
                      "innovation": self._nan, "updated": self._no}
        else:
            if dt > self._T * (1.0 + 1e-9):
                self._epoch_counts["gaps"] += n
            vel_ins = (pos - self._ins_prev) / dt
            events = self._advance(dt, pos, alt, clr, quality)
        self._t_prev, self._ins_prev = t_k, pos
        return self._fix(t_k, pos, alt, vel_ins, events)

    def _advance(self, dt: float, pos: torch.Tensor, alt: torch.Tensor, clr: torch.Tensor,
                 quality: Any) -> dict[str, torch.Tensor]:
        """Predict, update, integrity: the pipeline of one epoch (module docstring)."""
        s = self.config.sensor
        missing = torch.isnan(clr)
        in_range = (clr >= s.clearance_min_m) & (clr <= s.clearance_max_m)
        valid = in_range  # NaN is not in range
        # the predicted estimate on the map? (δp⁻ = δp + Δt δv of the last posterior) over a
        # void of its DEM (a filled no-data node: not a measured height)?
        estimate = pos - torch.addcmul(self._mean[:, :2], self._mean[:, 3:], self._dt_t(dt))
        on_map = inside_extent(estimate, self.extent)
        void = self._void_at(estimate)
        self._propagate_open_loop(dt)
        grid, track, on_grid = self._grid, self._track, self._on_grid
        grid_busy = grid is not None and grid.pm is not None
        if grid_busy:
            grid.predict(dt)
        track.predict(dt)
        tracking = ~on_grid
        ins3 = torch.cat([pos, alt[:, None]], 1)
        use = valid & on_map
        if void is not None:
            void = void & on_map
            use = use & ~void
        inn = track.update(ins3, clr, tracking & use, gate=self._gate, quality=quality)
        applied = inn.applied & tracking
        spikes = inn.gated & tracking
        nis = torch.where(applied | spikes, inn.nis, math.nan)
        innovation = torch.where(applied, inn.innovation, math.nan)
        off_est = tracking & ~inn.on_map
        if grid_busy:
            g = grid.update(ins3, clr, on_grid & use, gate=self._gate)
            applied = applied | (g.applied & on_grid)
            spikes = spikes | (g.gated & on_grid)
            self._since = self._since + (on_grid & use).long()
            off_est = off_est | (on_grid & ~g.on_map)  # no cell of its grid on the map
        self._window.add(nis, (applied | spikes) & tracking)
        lost = tracking & self._window.fired()
        if bool(lost.any()):
            self._counters[:, 6] += lost
            self._reacquire(lost)
            self._window.clear(lost)
        if grid_busy:
            self._handoff(lost)
        self._estimate()
        off_now = ((~on_map & ~self._on_grid) | off_est) & ~lost
        no_map = self._no if void is None else void & ~lost
        self._counters[:, :_PER_EPOCH] += torch.stack(
            [missing, ~missing & ~in_range, spikes, off_now, no_map, applied], 1)
        return {"nomeas": ~valid | spikes, "lost": lost, "off": off_now, "nis": nis,
                "innovation": innovation, "updated": applied, "void": no_map}

    def _void_at(self, xy: torch.Tensor) -> torch.Tensor | None:
        """``(N,)`` bool: the map reads a void of its DEM at ``xy``; None for a map without
        voids or one that does not report them."""
        if not getattr(self.terrain, "n_filled", 0) or not callable(
                getattr(self.terrain, "void_at", None)):
            return None
        return self.terrain.void_at(xy)

    def _dt_t(self, dt: float) -> torch.Tensor | float:
        """``dt`` as the multiplier of `torch.addcmul` (a cached tensor at the period)."""
        return self._T_t if dt == self._T else torch.tensor(dt, dtype=torch.float64,
                                                             device=self.device)

    def _handoff(self, lost: torch.Tensor) -> None:
        """Grid vehicles whose posterior passed the hand-off test long enough go to the
        method, from the grid posterior's moments (module docstring)."""
        a, grid = self.config.acquisition, self._grid
        cand = self._on_grid & ~lost
        gmean, gcov = grid.estimate()
        # a method that holds a wide posterior itself (rule "wide": the point-mass tracker)
        # takes it back as soon as it would have started without the grid; an EKF only
        # once the posterior is small enough to linearise
        limit = (max(a.above_sigma_m, a.handoff_sigma_m) if self._method_cls.acquisition == "wide"
                 else a.handoff_sigma_m)
        small = cand & (largest_sigma(gcov) <= limit)
        ok = small & (grid.unimodality(small) >= a.handoff_affinity)
        self._hold = torch.where(ok, self._hold + 1, 0)
        go = ((self._hold >= max(a.handoff_hold, 1)) & (self._since >= a.min_acquire_steps)
              & cand)
        if bool(go.any()):
            self._track.load(go, gmean, gcov)
            grid.drop(go)
            self._on_grid = self._on_grid & ~go
            self._window.clear(go)
            self._counters[:, 7] += go
            self._first_handoff = torch.where(go & (self._first_handoff < 0), self._epoch,
                                              self._first_handoff)

    def _propagate_open_loop(self, dt: float) -> None:
        """``m_ol ← Φ m_ol``, ``P_ol ← Φ P_ol Φᵀ + Q(Δt)``: the prior without measurements.

        Every vehicle shares it (same prior, same epochs, no measurement), and its mean
        stays 0 (``m_0 = 0``), so one ``(5, 5)`` covariance is carried."""
        if dt == self._T:
            phi, q = self._phi_T, self._q_T
        else:
            phi = self.model.transition(dt, device=self.device)[:N_STATES, :N_STATES]
            q = self.model.process_noise(dt, device=self.device)[:N_STATES, :N_STATES]
        self._open_cov1 = symmetrize(phi @ self._open_cov1 @ phi.T + q)

    def _reacquire(self, mask: torch.Tensor) -> None:
        """Vehicles ``mask`` restart from the open-loop prior ``N(0, P_ol)``: on the
        acquisition grid by the method's rule (horizontal σ at least ``reacquire_sigma_m``),
        else in the method itself."""
        n, dev = self.n_vehicles, self.device
        mean = torch.zeros(n, N_STATES, dtype=torch.float64, device=dev)
        cov = self._open_cov1.expand(n, N_STATES, N_STATES)
        rule, a = self._method_cls.acquisition, self.config.acquisition
        sigma = float(largest_sigma(self._open_cov1[None])[0])
        to_grid = mask if rule == "always" else (
            mask if rule == "wide" and sigma > a.above_sigma_m else torch.zeros_like(mask))
        direct = mask & ~to_grid
        if bool(direct.any()):
            self._track.load(direct, mean, cov)
        if bool(to_grid.any()):
            var = torch.diagonal(cov[:, :2, :2], dim1=1, dim2=2)
            d = torch.ones(n, N_STATES, dtype=cov.dtype, device=dev)
            d[:, :2] = (var.clamp_min(a.reacquire_sigma_m ** 2) / var.clamp_min(1e-300)).sqrt()
            wide = spd_floor(d[:, :, None] * cov * d[:, None, :])  # D P D, D = diag(scale, 1)
            self._grid.load(to_grid, mean, wide)
            self._track.drop(to_grid)
            self._on_grid = self._on_grid | to_grid
            self._hold = torch.where(to_grid, 0, self._hold)
            self._since = torch.where(to_grid, 0, self._since)

    def _estimate(self) -> None:
        mean, cov = self._track.estimate()
        if self._grid is not None and bool(self._on_grid.any()):
            gm, gc = self._grid.estimate()
            m = self._on_grid
            mean = torch.where(m[:, None], gm, mean)
            cov = torch.where(m[:, None, None], gc, cov)
        self._mean, self._cov = mean, cov

    def _fix(self, t: float, pos: torch.Tensor, alt: torch.Tensor, vel_ins: torch.Tensor,
             ev: dict[str, torch.Tensor]) -> Fix:
        n, dt, integ = self.n_vehicles, self.dtype, self.config.integrity
        mean, cov = self._mean, self._cov
        sigma = largest_sigma(cov)
        hpl, vpl = self._protection(integ.integrity_risk, sigma)
        extra = [self._protection(r, sigma) for r in integ.report_risks]
        wide = self._on_grid | (sigma > integ.acquired_sigma_m)
        status = torch.where(wide, _ACQ, _TRK)
        if integ.alert_limit_m is not None or integ.vertical_alert_limit_m is not None:
            over = self._no
            if integ.alert_limit_m is not None:
                over = over | (hpl > integ.alert_limit_m)
            if integ.vertical_alert_limit_m is not None:
                over = over | (vpl > integ.vertical_alert_limit_m)
            status = torch.where(over & ~wide, _UNAV, status)
        status = torch.where(ev["nomeas"], _NOMEAS, status)
        if "void" in ev:
            status = torch.where(ev["void"], _NOMAP, status)
        status = torch.where(ev["off"], _OFF, status)
        status = torch.where(ev["lost"], _LOST, status)
        xy = pos - mean[:, :2]
        lat = lon = None
        if self.map_frame is not None:
            xg = xy if xy.device.type == "cpu" else xy.cpu()  # geodesy runs on the CPU
            la, lo = self.map_frame.to_geo(xg[:, 0], xg[:, 1])
            lat = torch.as_tensor(la, dtype=torch.float64).reshape(n).to(pos.device, dt)
            lon = torch.as_tensor(lo, dtype=torch.float64).reshape(n).to(pos.device, dt)
        healthy = self._track.healthy()
        if self._grid is not None and self._grid.pm is not None:
            healthy = torch.where(self._on_grid, self._grid.healthy(), healthy)

        def out(x: torch.Tensor) -> torch.Tensor:
            return x if x.dtype == dt else x.to(dt)

        return Fix(t=torch.full((n,), t, dtype=dt, device=pos.device), xy=out(xy),
                   altitude=out(alt - mean[:, 2]), velocity=out(vel_ins - mean[:, 3:]),
                   cov=out(cov), status=status, hpl=out(hpl), vpl=out(vpl),
                   nis=out(ev["nis"]), mean_nis=out(self._window.mean()),
                   innovation=out(ev["innovation"]), updated=ev["updated"],
                   correction=out(mean), healthy=healthy, lat=lat, lon=lon,
                   hpl_extra=torch.stack([h for h, _ in extra], 1).to(dt) if extra else None,
                   vpl_extra=torch.stack([v for _, v in extra], 1).to(dt) if extra else None)

    def _protection(self, risk: float, sigma: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(N,)`` HPL and VPL at ``risk``: the Gaussian levels of the covariance
        (`neuralmap.nav.integrity`; ``sigma`` its largest horizontal σ), the horizontal one
        from the method's (or the grid's) own posterior where it is not Gaussian."""
        hpl, vpl = protection_levels(self._cov, risk, sigma=sigma)
        out = self._track.protection_level(risk, hpl, self._mean)
        if self._grid is not None and bool(self._on_grid.any()):
            out = torch.where(self._on_grid, self._grid.protection_level(risk, hpl, self._mean),
                              out)
        return out, vpl

    # ------------------------------------------------------------------ whole flights
    def replay(self, t: torch.Tensor, ins_position: torch.Tensor, ins_altitude: torch.Tensor,
               clearance: torch.Tensor, quality: torch.Tensor | None = None, *,
               progress: Callable[[float], None] | None = None,
               reset: bool = True) -> FixTrack:
        """A whole flight: `reset`, then `step` at every epoch; or, with ``reset=False``, the
        next part of one.

        Args:
            t: ``(K,)`` epoch times, s, strictly increasing.
            ins_position: ``(N, K, 2)`` INS horizontal positions, m.
            ins_altitude: ``(N, K)`` INS altitudes, m.
            clearance: ``(N, K)`` clearances, m (NaN = no measurement).
            quality: ``(N, K, q)`` the altimeter's quality record, or None.
            progress: Called with the fraction of the flight each epoch is (``1/K``), e.g.
                a progress bar's ``update``; None = silent.
            reset: True (default) starts a new flight (`reset` first). False continues the
                flight where the last `step` or `replay` left it: a long log replayed in
                chunks of epochs (`neuralmap.flights.flight`) gives, chunk after chunk, the
                fixes of one replay of the whole log, bit for bit; ``t`` must then start
                after the last epoch already navigated.

        Returns:
            `FixTrack` on the CPU whatever the navigator's device (equal, bit for bit, to
            the fixes of `step` called K times after `reset`, moved to the CPU), with
            `counts` and `vehicle_counts` (counted since the last `reset`: after the last
            chunk of a flight, those of the whole flight).
        """
        t = torch.as_tensor(t)
        n = self.n_vehicles
        if t.ndim != 1 or t.numel() < 1:
            raise NeuralMapError(f"Navigator.replay: t must have shape (K,), got "
                                 f"{tuple(t.shape)}.")
        k = t.shape[0]
        ins_position, ins_altitude, clearance = (torch.as_tensor(v) for v in (
            ins_position, ins_altitude, clearance))
        if (tuple(ins_position.shape) != (n, k, 2) or tuple(ins_altitude.shape) != (n, k)
                or tuple(clearance.shape) != (n, k)):
            raise NeuralMapError(
                f"Navigator.replay: for {n} vehicles and {k} epochs ins_position must be "
                f"({n}, {k}, 2), ins_altitude and clearance ({n}, {k}); got "
                f"{tuple(ins_position.shape)}, {tuple(ins_altitude.shape)}, "
                f"{tuple(clearance.shape)}.")
        if quality is not None and (torch.as_tensor(quality).ndim != 3
                                    or tuple(quality.shape[:2]) != (n, k)):
            raise NeuralMapError(f"Navigator.replay: quality must be ({n}, {k}, q), got "
                                 f"{tuple(torch.as_tensor(quality).shape)}.")
        if reset:
            self.reset()
        track: FixTrack | None = None
        cpu = torch.device("cpu")
        for i in range(k):
            fix = self.step(t[i], ins_position[:, i], ins_altitude[:, i], clearance[:, i],
                            None if quality is None else quality[:, i])
            if track is None:
                track = FixTrack.empty_like(_fix_to(fix, cpu), k)
            track.put(i, _fix_to(fix, cpu))
            if progress is not None:
                progress(1.0 / k)
        track.counts = self.counts
        track.vehicle_counts = {key: v.cpu() for key, v in self.vehicle_counts.items()}
        return track

    def describe(self) -> dict[str, Any]:
        """Method, noise and integrity settings in plain form (for reports)."""
        return {"method": self.method, "config_method": self.config.method,
                "acquisition": self._method_cls.acquisition, "noise": self.noise.to_dict(),
                "lost_window": self.config.integrity.lost_window,
                "lost_prob": self.config.integrity.lost_prob,
                "integrity_risk": self.config.integrity.integrity_risk,
                "config": self.config.source}


def _fix_to(fix: Fix, device: torch.device) -> Fix:
    """``fix`` with every tensor on ``device`` (itself when already there)."""
    if fix.xy.device == device:
        return fix
    from dataclasses import fields, replace

    return replace(fix, **{f.name: getattr(fix, f.name).to(device) for f in fields(fix)
                           if isinstance(getattr(fix, f.name), torch.Tensor)})
