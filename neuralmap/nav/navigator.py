"""The navigator: terrain-aided fixes from a map, an INS and a radar altimeter, epoch by epoch.

`Navigator` turns a flight — a recorded log or a live sensor stream — into
`Fix` es with their covariance, for N vehicles at once (batch
first). It is built from

* a map: any `TerrainModel` (a DEM grid, a blockwise
  neural map, a latent map, a region map);
* a method (`NavigatorConfig`):

  - ``point_mass_tracker`` (default): the whole-flight Rao-Blackwellised point-mass
    tracker of `neuralmap.nav.tracking` (`PointMassTracker`, Bergman, Ljung and Gustafsson), started on the
    point-mass acquisition grid (`neuralmap.nav.acquisition`) when the initial
    horizontal σ exceeds ``acquisition.above_sigma_m`` and handed to the tracker once the
    grid posterior is unimodal and small (`handoff_ready`,
    `grid_posterior_moments`);
  - ``point_mass_ekf``: the acquisition grid, then the 5-state TAN EKF (SEEDS 004)
    linearised by autograd on the map;
  - any EKF linearizer name (`neuralmap.linearize.factory.LINEARIZER_NAMES`) with a
    robust/adaptive policy by registry name (`neuralmap.filters.policies.registry`);

* a sensor/noise config in YAML (`neuralmap.nav.navigator_config`) and the map's own
  error model (`neuralmap.nav.map_noise`): ``R = σ_alt² + σ_dem² + σ_fit²``.

State and timing (as `run_filter` and
`run_tracker`): the 5-state error ``δX = [δx, δy, δh, δv_x,
δv_y]`` = INS − truth; a fix is ``INS − δX̂``. The first epoch after `Navigator.reset`
is the prior (``δX̂ = 0``, ``P0``, no update); every later epoch predicts over the interval
since the previous one and updates with the altimeter: ``y = h_ins − clearance =
t(p_ins − δp) + δh − v``.

Integrity, per vehicle and epoch (status codes of `STATUS`):

* **Lost lock**: the mean NIS over the last ``integrity.lost_window`` updates above
  ``χ²_p(W)/W`` (``p = integrity.lost_prob``) **re-acquires from the open-loop prior**
  ``N(m_ol, P_ol)``: the prior propagated through every prediction without a measurement
  (``m_ol ← Φ m_ol``, ``P_ol ← Φ P_ol Φᵀ + Q``), the dead-reckoning bound of the INS error,
  which holds the truth wherever the filter lost it (a wrong terrain match). A prior wider
  than ``acquisition.above_sigma_m`` goes to the acquisition grid (always for
  ``point_mass_ekf``), a narrower one straight back into the tracker; EKF methods restart
  the EKF from it. Status ``lost`` at the detection, ``acquiring`` while the grid holds the
  vehicle or its horizontal σ exceeds ``integrity.acquired_sigma_m``, then ``tracking``.
  (The INS error must stay inside its model for the open-loop prior to hold the truth: a
  jump of the INS itself is not re-acquired.)
* **Off the map**: an estimate off the map's extent is predicted only (status ``off_map``).
* **No measurement**: a NaN clearance, or one outside ``[sensor.clearance_min_m,
  sensor.clearance_max_m]``, is not used: predicted only, status ``no_measurement``,
  counted (``missing_radar``, ``out_of_range``).
* **Time gaps**: an interval longer than ``sensor.dt_s`` is predicted across with its true
  length (``Q · Δt / T``, the transition with ``Δt``), counted (``gaps``); one longer than
  ``sensor.max_gap_s`` is predicted across too, but that epoch is not updated (status
  ``no_measurement``, counted ``long_gaps``; a log reader refuses such a log).
* **Altimeter spikes**: the point-mass tracker gates them: a clearance whose predictive NIS
  (against the predicted mixture, before the update) exceeds ``χ²₁(p)``, ``p =
  integrity.spike_gate_prob``, is not used (counted ``spikes``, status
  ``no_measurement``); the EKF methods take them through their policy (``raf``, ``igg3``,
  ``huber``, ``chi2``, ...); the acquisition grid has no gate (Gaussian likelihood by
  default; ``acquisition.outlier_prob`` makes it a Gaussian / uniform mixture): a spike in
  its first epochs can move its mass to a wrong match, which the lost-lock test catches
  after the hand-off. In
  every method (when the gate is on) the NIS entering the lost-lock window is capped at
  twice the test's threshold ``2 χ²_p(W)/W``: with W = 20 it takes 8 spikes in one window
  to fire the test, while a lost lock (every NIS large) still fires it once the window
  fills.

Streaming equals replay: `Navigator.replay` is `Navigator.step` over the epochs
(the filter is recursive; the batch is over vehicles), so the two agree bit for bit.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace
from typing import Any

import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.filters.point_mass_tracker import PointMassTracker, _chi2_mean_threshold
from neuralmap.nav.fix import STATUS_CODE, Fix, FixTrack
from neuralmap.nav.map_noise import MapNoise, load_noise_table, measurement_noise
from neuralmap.nav.model import N_STATES
from neuralmap.nav.navigator_config import NavigatorConfig, load_navigator_config
from neuralmap.terrain.base import inside_extent

__all__ = ["COUNT_KEYS", "Navigator"]

#: Counters of `FixTrack.counts` / `Navigator.counts`.
COUNT_KEYS = ("epochs", "missing_radar", "out_of_range", "spikes", "gaps", "long_gaps",
              "off_map_epochs", "lost", "reacquisitions", "handoffs", "updates")

_ACQ, _TRK, _LOST, _OFF, _NOMEAS = (STATUS_CODE[k] for k in (
    "acquiring", "tracking", "lost", "off_map", "no_measurement"))


@dataclass
class _StepOut:
    """What an engine reports for one epoch (``(N,)`` each)."""

    nis: torch.Tensor          # NIS of this epoch's update (NaN where none)
    applied: torch.Tensor      # bool, updated
    lost: torch.Tensor         # bool, lost-lock detected
    reacquired: torch.Tensor   # bool, re-acquisition from the open-loop prior started
    handoff: torch.Tensor      # bool, acquisition grid -> tracking filter
    off_map: torch.Tensor      # bool, estimate off the map: not updated


def _chi2_quantile(prob: float) -> float:
    """``χ²₁(prob)``: one consistent NIS exceeds it with probability ``1 − prob``."""
    return _chi2_mean_threshold(prob, 1)


def _largest_sigma(cov: torch.Tensor) -> torch.Tensor:
    """``(N,)`` ``sqrt(λ_max)`` of the horizontal block of ``cov (N, ≥2, ≥2)`` (closed form
    of a symmetric 2 × 2: ``(a + c)/2 + sqrt(((a − c)/2)² + b²)``)."""
    a, b, c = cov[:, 0, 0], 0.5 * (cov[:, 0, 1] + cov[:, 1, 0]), cov[:, 1, 1]
    lam = 0.5 * (a + c) + torch.sqrt((0.5 * (a - c)) ** 2 + b * b)
    return lam.clamp_min(0.0).sqrt()


def _transition(dt: float, dtype: torch.dtype, device: torch.device | None = None
                ) -> torch.Tensor:
    phi = torch.eye(N_STATES, dtype=dtype, device=device)
    phi[0, 3] = dt
    phi[1, 4] = dt
    return phi


def _map_tensors(terrain: Any) -> Any:
    """The map's parameters, then its buffers (none for a map that is not a module)."""
    for name in ("parameters", "buffers"):
        tensors = getattr(terrain, name, None)
        if callable(tensors):
            yield from tensors()


def _map_device(terrain: Any) -> torch.device | None:
    """The device of the map's first parameter or buffer; None when it has none."""
    return next((t.device for t in _map_tensors(terrain)), None)


def _resolve_device(device: Any, terrain: Any) -> torch.device:
    """The navigator's device: ``device`` (``"cpu"``, ``"cuda"``, ``"cuda:<i>"``, a
    `torch.device`) or, when None, the map's (`_map_device`, else the CPU); a clear error
    when it is unknown, absent, or not where the map's tensors are."""
    on_map = _map_device(terrain)
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


def _track_to(track: FixTrack, device: torch.device) -> FixTrack:
    """``track`` with every tensor on ``device`` (itself when already there)."""
    if track.xy.device == device:
        return track
    moved = {f.name: getattr(track, f.name).to(device) for f in fields(track)
             if isinstance(getattr(track, f.name), torch.Tensor)}
    return replace(track, **moved)


def _spd_guard(cov: torch.Tensor) -> torch.Tensor:
    """Symmetric, eigenvalues floored at 1e-9 of the largest (float64)."""
    c64 = 0.5 * (cov + cov.transpose(-1, -2)).double()
    lam, vec = torch.linalg.eigh(c64)
    lam = lam.clamp_min(1e-9 * lam.abs().amax(-1, keepdim=True).clamp_min(1e-12))
    out = (vec * lam[..., None, :]) @ vec.transpose(-1, -2)
    return 0.5 * (out + out.transpose(-1, -2))


class _Window:
    """The windowed-NIS lost-lock test of the navigator (grid and EKF methods), and the
    windowed NIS every fix reports."""

    def __init__(self, n: int, window: int, prob: float, dtype: torch.dtype,
                 cap: float = math.inf, device: torch.device | None = None) -> None:
        """``cap`` finite: NIS entering the window are capped at twice the threshold."""
        self.w = max(int(window), 1)
        self.enabled = window > 0
        self.threshold = _chi2_mean_threshold(prob, self.w) if self.enabled else math.inf
        self.cap = 2.0 * self.threshold if cap < math.inf else math.inf
        self.values = torch.zeros(n, self.w, dtype=dtype, device=device)
        self.count = torch.zeros(n, dtype=torch.long, device=device)
        self.slot = torch.zeros(n, dtype=torch.long, device=device)
        self._rows = torch.arange(n, device=device)

    def add(self, nis: torch.Tensor, applied: torch.Tensor) -> None:
        cur = self.values[self._rows, self.slot]
        nis = nis.to(self.values.dtype).clamp(max=self.cap)
        self.values[self._rows, self.slot] = torch.where(applied, nis, cur)
        self.slot = torch.where(applied, (self.slot + 1) % self.w, self.slot)
        self.count = self.count + applied.long()

    def mean(self) -> torch.Tensor:
        """``(N,)`` mean NIS over the filled part of the window (NaN before any update)."""
        k = self.count.clamp(max=self.w)
        total = self.values.sum(1)  # unfilled slots hold 0
        return torch.where(k > 0, total / k.clamp_min(1).to(total.dtype), math.nan)

    def fired(self) -> torch.Tensor:
        if not self.enabled:
            return torch.zeros_like(self.count, dtype=torch.bool)
        return (self.count >= self.w) & (self.values.mean(1) > self.threshold)

    def clear(self, mask: torch.Tensor) -> None:
        self.values = torch.where(mask[:, None], 0.0, self.values)
        self.count = torch.where(mask, 0, self.count)
        self.slot = torch.where(mask, 0, self.slot)


# ---------------------------------------------------------------------- track filters
class _TrackerFilter:
    """The point-mass tracker over all N vehicles (rows on the acquisition grid: dormant,
    a benign Gaussian predicted and never updated)."""

    def __init__(self, nav: Navigator) -> None:
        from neuralmap.nav.tracking import TrackerOptions, transition_blur

        cfg = nav.config
        tc = cfg.tracker
        self.dtype = torch.float32 if tc.dtype == "float32" else torch.float64
        self.device = dev = nav.device
        # the navigator runs the lost-lock test itself (no widening inside the tracker)
        opts = TrackerOptions(cells=tc.cells, span_sigma=tc.span_sigma,
                              principal_axes=tc.principal_axes, dtype=tc.dtype, lost_window=0,
                              flatten_likelihood=tc.flatten_likelihood,
                              min_cell_blur=tc.min_cell_blur)
        self.options = opts
        P0, Q, T = nav._P0, nav._Q, nav._T
        self.tcfg = opts.tracker_config(blur_m=transition_blur(P0, Q, T))
        kw = {"dtype": self.dtype, "device": dev}
        self.E_nominal = torch.tensor([[0.0, T, 0.0], [0.0, 0.0, T]], **kw)
        F = torch.eye(3, **kw)
        c = torch.tensor([1.0, 0.0, 0.0], **kw)
        n = nav.n_vehicles
        self.tracker = PointMassTracker(torch.zeros(n, N_STATES, **kw),
                                        P0.to(self.dtype), E=self.E_nominal, F=F, c=c,
                                        config=self.tcfg, dtype=self.dtype)
        self.qs, self.qz = Q[:2, :2].to(self.dtype), Q[2:, 2:].to(self.dtype)
        self._dt = T
        self._T = T
        dormant = P0.clone()
        dormant[:2, :] = 0.0
        dormant[:, :2] = 0.0
        dormant[0, 0] = dormant[1, 1] = cfg.acquisition.handoff_sigma_m ** 2
        self._dormant = dormant.to(self.dtype)
        self.terrain, self.extent = nav.terrain, nav.extent
        self.flatten = tc.flatten_likelihood
        self.R = nav.noise.R
        self.gate = nav._gate

    def _set_interval(self, dt: float) -> None:
        """Transition of the velocity into the position over ``dt`` (E and the open-loop
        transition of the tracker); untouched at the nominal period."""
        if dt == self._dt:
            return
        trk = self.tracker
        E = self.E_nominal if dt == self._T else torch.tensor(
            [[0.0, dt, 0.0], [0.0, 0.0, dt]], dtype=self.dtype, device=self.device)
        trk.E = E  # the open-loop transition [[I, E], [0, F]] follows from it
        self._dt = dt

    def predict(self, dt: float, scale: float) -> None:
        self._set_interval(dt)
        if scale == 1.0:
            self.tracker.predict(Q_s=self.qs, Q_z=self.qz)
        else:
            self.tracker.predict(Q_s=self.qs * scale, Q_z=self.qz * scale)

    def _predictive_nis(self, y: torch.Tensor, g: torch.Tensor) -> torch.Tensor:
        """``(N,)`` NIS of ``y`` against the predicted mixture, ``(y − ŷ)² / S_y`` with
        ``ŷ = Σ w (g + c·μ)``, ``S_y = Σ w (g + c·μ − ŷ)² + cᵀPc + R`` over the cells on the
        map (what `PointMassTracker.update` reports as its NIS)."""
        trk = self.tracker
        yc = g + torch.einsum("z,nzij->nij", trk.c, trk.lin_mean)
        w = trk.weights
        if bool(torch.isfinite(g).all()):  # every cell on the map (masses sum to 1)
            yhat = (w * yc).sum((1, 2))
            spread = (w * (yc - yhat[:, None, None]).square_()).sum((1, 2))
        else:
            ok = torch.isfinite(yc)
            w = torch.where(ok, w, 0.0)
            mass = w.sum((1, 2)).clamp_min(torch.finfo(w.dtype).tiny)
            yc = torch.where(ok, yc, 0.0)
            yhat = (w * yc).sum((1, 2)) / mass
            spread = (w * (yc - yhat[:, None, None]) ** 2).sum((1, 2)) / mass
        s_y = spread + (trk.lin_cov @ trk.c) @ trk.c + self.R
        return (y - yhat) ** 2 / s_y

    def update(self, ins_pos: torch.Tensor, y: torch.Tensor, mask: torch.Tensor | None
               ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Altimeter update of the rows in ``mask`` (None = all), clearances past the spike
        gate left out; returns ``nis`` (the gated rows' predictive NIS), ``applied``,
        ``gated``."""
        from neuralmap.nav.tracking import heights_on_cells

        trk = self.tracker
        y = y.to(self.dtype)
        g = heights_on_cells(self.terrain, ins_pos[:, :2], self.extent)(trk.points())
        gated = torch.zeros(y.shape[0], dtype=torch.bool, device=y.device)
        nis_pred = None
        if self.gate < math.inf:
            nis_pred = self._predictive_nis(y, g)
            gated = torch.isfinite(nis_pred) & (nis_pred > self.gate)
            if mask is not None:
                gated = gated & mask
            if bool(gated.any()):
                mask = ~gated if mask is None else mask & ~gated
        cell_var = None
        if self.flatten:
            from neuralmap.nav.acquisition import cell_height_variance

            cell_var = torch.nan_to_num(cell_height_variance(g), nan=0.0)
        upd = trk.update(y, g, R=self.R, mask=mask, cell_variance=cell_var)
        nis = upd.nis if nis_pred is None else torch.where(gated, nis_pred, upd.nis)
        return nis, upd.applied, gated

    def moments(self) -> tuple[torch.Tensor, torch.Tensor]:
        return self.tracker.moments()

    def load(self, mask: torch.Tensor, mean: torch.Tensor, cov: torch.Tensor) -> None:
        cov = _spd_guard(cov)
        m = mask[:, None]
        full_mean = torch.where(m, mean.to(self.dtype), 0.0)
        full_cov = torch.where(m[..., None], cov.to(self.dtype), self._dormant.expand_as(cov))
        self.tracker.reset(full_mean, full_cov, mask=mask)

    def drop(self, mask: torch.Tensor) -> None:
        n = mask.shape[0]
        self.tracker.reset(torch.zeros(n, N_STATES, dtype=self.dtype, device=self.device),
                           self._dormant, mask=mask)


class _EkfFilter:
    """The 5-state TAN EKF (SEEDS 004) over all N vehicles, one linearizer and policy."""

    def __init__(self, nav: Navigator, linearizer: Any, policy: Any, base_R: float) -> None:
        from neuralmap.filters.ekf import BatchedEKF

        self.dtype = nav.dtype
        n = nav.n_vehicles
        self.device = nav.device
        self.ekf = BatchedEKF(torch.zeros(n, N_STATES, dtype=self.dtype, device=self.device),
                              nav._P0.to(self.dtype))
        self.linearizer, self.policy, self.R = linearizer, policy, base_R
        self.extent = nav.extent
        self._Q = nav._Q.to(self.dtype)
        self._T = nav._T
        self._F = _transition(nav._T, self.dtype, self.device)
        self._pending: tuple[torch.Tensor, torch.Tensor] | None = None
        if policy is not None:
            policy.reset()

    def predict(self, dt: float, scale: float) -> None:
        F = self._F if dt == self._T else _transition(dt, self.dtype, self.device)
        Q = self._Q if scale == 1.0 else self._Q * scale
        self._pending = (F, Q)

    def update(self, ins_pos: torch.Tensor, clearance: torch.Tensor, mask: torch.Tensor | None
               ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Predict (pending) + update; returns ``nis, applied, on_map``."""
        from neuralmap.nav.tan import tan_filter_step

        assert self._pending is not None
        F, Q = self._pending
        self._pending = None
        diag = tan_filter_step(self.ekf, ins_pos.to(self.dtype), clearance.to(self.dtype),
                               self.linearizer, F=F, Q=Q, R=self.R, extent=self.extent,
                               mask=mask, policy=self.policy)
        if self.ekf.x.requires_grad or self.ekf.P.requires_grad:
            self.ekf.x, self.ekf.P = self.ekf.x.detach(), self.ekf.P.detach()
        upd = diag.updated.detach()
        return torch.where(upd, diag.nis.detach(), math.nan), upd, diag.on_map

    def moments(self) -> tuple[torch.Tensor, torch.Tensor]:
        return self.ekf.x, self.ekf.P

    def load(self, mask: torch.Tensor, mean: torch.Tensor, cov: torch.Tensor) -> None:
        self.ekf.x = torch.where(mask[:, None], mean.to(self.dtype), self.ekf.x)
        self.ekf.P = torch.where(mask[:, None, None], cov.to(self.dtype), self.ekf.P)

    def drop(self, mask: torch.Tensor) -> None:  # an EKF row costs nothing while dormant
        return None


# ---------------------------------------------------------------------- acquisition grid
class _Grid:
    """The point-mass acquisition grid over all N vehicles (rows not acquiring: frozen)."""

    def __init__(self, nav: Navigator, prior: torch.Tensor) -> None:
        from neuralmap.filters.point_mass import PointMassFilter
        from neuralmap.nav.acquisition import (
            AcquisitionConfig,
            _Float32Grid,
            _is_bilinear_grid,
            _VelocityPrior,
        )

        a = nav.config.acquisition
        self.acfg = AcquisitionConfig(max_spacing_m=a.max_spacing_m, max_cells=a.max_cells,
                                      span_sigma=a.span_sigma, dtype=a.dtype,
                                      handoff_sigma_m=a.handoff_sigma_m,
                                      handoff_affinity=a.handoff_affinity,
                                      handoff_hold=a.handoff_hold,
                                      min_acquire_steps=a.min_acquire_steps,
                                      flatten_likelihood=a.flatten_likelihood,
                                      reacquire_sigma_m=a.reacquire_sigma_m,
                                      outlier_prob=a.outlier_prob,
                                      outlier_width_m=a.outlier_width_m).validate()
        self.dtype = torch.float32 if a.dtype == "float32" else torch.float64
        n, P0 = nav.n_vehicles, prior
        sigma0 = float(P0[:2, :2].diagonal().max()) ** 0.5
        dev = nav.device
        self.pm = PointMassFilter(torch.zeros(n, 2, dtype=self.dtype, device=dev),
                                  P0[:2, :2].to(self.dtype),
                                  scalar_mean=0.0, scalar_var=float(P0[2, 2]),
                                  config=self.acfg.point_mass_config(sigma0), dtype=self.dtype)
        self.vel = _VelocityPrior(n, P0, torch.float64, dev)
        self.fast = _is_bilinear_grid(nav.terrain)
        self.terrain = (_Float32Grid(nav.terrain) if self.fast and self.dtype == torch.float32
                        else nav.terrain)
        self.extent = nav.extent
        self.R = nav.noise.R
        self.hold = torch.zeros(n, dtype=torch.long, device=dev)
        self.since = torch.zeros(n, dtype=torch.long, device=dev)
        self._Q = nav._Q

    def predict(self, dt: float, scale: float) -> None:
        q = self._Q * scale
        n = self.pm.n_runs
        grow = self.vel.step(dt, q[[0, 1], [0, 1]].expand(n, 2), q[[3, 4], [3, 4]].expand(n, 2))
        self.pm.predict(Q=grow.to(self.dtype), shift=(dt * self.vel.v0).to(self.dtype),
                        scalar_q=float(q[2, 2]))

    def update(self, ins_xy: torch.Tensor, y: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        from neuralmap.nav.acquisition import (
            _terrain_fn,
            cell_height_variance,
            cells_on_map,
            lattice_bilinear,
        )

        pm = self.pm
        if self.fast:
            pred = lattice_bilinear(self.terrain, ins_xy, pm.centre, pm.spacing, pm.offsets)
        else:
            pred = _terrain_fn(self.terrain, ins_xy)(pm.points())
        cell_var = cell_height_variance(pred) if self.acfg.flatten_likelihood else None
        on = cells_on_map(ins_xy, pm.centre, pm.spacing, pm.offsets, self.extent)
        pred = pred.masked_fill(~on, math.nan)
        upd = pm.update(y.to(self.dtype), pred, R=self.R, mask=mask, cell_variance=cell_var)
        self.since = self.since + mask.long()
        return upd.applied

    def moments(self) -> tuple[torch.Tensor, torch.Tensor]:
        """5-state mean and covariance of every row (velocity from the position posterior)."""
        pm = self.pm
        rows = torch.arange(pm.n_runs, device=self.hold.device)
        mu, sigma = pm.mean().double(), pm.cov().double()
        alt_m, alt_v = (t.double() for t in pm.scalar_moments())
        return self.vel.state(rows, mu, sigma, alt_m, alt_v, self.acfg.velocity_from_grid)

    def ready(self, acquiring: torch.Tensor) -> torch.Tensor:
        """``(N,)`` bool: acquiring rows that passed the hand-off test long enough."""
        from neuralmap.nav.acquisition import handoff_ready

        pm, cfg = self.pm, self.acfg
        cov = pm.cov().double()
        small = torch.linalg.eigvalsh(cov)[:, -1].clamp_min(0.0).sqrt() <= cfg.handoff_sigma_m
        cand = (small & acquiring).nonzero().reshape(-1)
        affinity = torch.zeros(pm.n_runs, dtype=torch.float64, device=cov.device)
        if cand.numel() > 0:
            affinity[cand] = pm.gaussian_affinity(cand).double()
        ok = handoff_ready(affinity, cov, max_sigma=cfg.handoff_sigma_m,
                           min_affinity=cfg.handoff_affinity) & acquiring
        self.hold = torch.where(ok, self.hold + 1, 0)
        return (self.hold >= max(cfg.handoff_hold, 1)) & (self.since >= cfg.min_acquire_steps)

    def handoff_moments(self, rows: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        from neuralmap.nav.tracker_handoff import grid_posterior_moments

        v = self.vel
        return grid_posterior_moments(self.pm, rows, ppp=v.ppp[rows], ppv=v.ppv[rows],
                                      pvv=v.pvv[rows], v0=v.v0[rows], mp=v.mp[rows],
                                      condition=self.acfg.velocity_from_grid)

    def restart(self, mask: torch.Tensor, mean: torch.Tensor, cov: torch.Tensor) -> None:
        """Rows ``mask`` back on the grid with ``N(mean (N, 5), cov (N, 5, 5))`` (float64),
        horizontal σ at least ``reacquire_sigma_m``."""
        floor = self.acfg.reacquire_sigma_m ** 2
        var = torch.diagonal(cov[:, :2, :2], dim1=1, dim2=2)
        d = torch.ones(cov.shape[0], N_STATES, dtype=cov.dtype, device=cov.device)
        d[:, :2] = (var.clamp_min(floor) / var.clamp_min(1e-300)).sqrt()
        cov = _spd_guard(d[:, :, None] * cov * d[:, None, :])  # D P D, D = diag(scale, 1)
        self.pm.reset(mean[:, :2].to(self.dtype), cov[:, :2, :2].to(self.dtype),
                      scalar_mean=mean[:, 2].to(self.dtype),
                      scalar_var=cov[:, 2, 2].clamp_min(1.0).to(self.dtype), mask=mask)
        ppp = torch.diagonal(cov[:, :2, :2], dim1=1, dim2=2)
        ppv = torch.stack([cov[:, 0, 3], cov[:, 1, 4]], 1)
        pvv = torch.diagonal(cov[:, 3:, 3:], dim1=1, dim2=2)
        self.vel.reset(mask, ppp, ppv, pvv, mean[:, 3:], mean[:, :2])
        self.hold = torch.where(mask, 0, self.hold)
        self.since = torch.where(mask, 0, self.since)


# ---------------------------------------------------------------------- the navigator
class Navigator:
    """Terrain-aided navigation of N vehicles over one map, epoch by epoch.

    Args:
        terrain: The map, any `TerrainModel` with an
            ``extent`` (``forward(xy (..., 2)) -> (...)`` heights).
        config: A `NavigatorConfig`, a mapping or YAML path of overrides over the
            shipped ``configs/navigator.yaml``, or None (the shipped defaults).
        n_vehicles: N, the batch size of every input.
        map_frame: Anything with ``to_geo(x, y) -> (lat, lon)`` (e.g.
            `neuralmap.nav.georef.MapFrame`); fixes then carry lat/lon.
        map_error_variance: Overrides the map's error variance in ``R`` (m²), e.g. a
            study's DEM error measured against its truth terrain; None = from the config
            and the map's stored fit metrics (`neuralmap.nav.map_noise`).
        dtype: dtype of the fixes (float64 default).
        device: Where the filter state lives and runs: ``"cpu"``, ``"cuda"``,
            ``"cuda:<i>"`` or a `torch.device`; None (default) = the map's device (its
            first parameter or buffer, else the CPU). A map with tensors must already be
            on it (``terrain.to(device)``). Inputs to `step` / `replay` may be on any
            device (they are moved); `step` returns its `Fix` on this device (no copy
            per epoch), `replay` returns its `FixTrack` on the CPU.
        tile: The DEM tile, for the EKF linearizers that read the DEM itself (``bilinear``,
            ``nine_point``, ...); None = rebuilt from a grid map's heights.

    Attributes:
        config: The validated config.
        noise: `MapNoise`, the parts of ``R``.
        counts: Counters summed over vehicles since `reset` (`COUNT_KEYS`).

    Raises:
        NeuralMapError: Bad config, a map without an extent, ``n_vehicles < 1``, a policy
            that needs an altimeter quality record, a linearizer that cannot be built, or
            a device that is unknown, absent (CUDA asked for without it) or not the map's.
    """

    def __init__(self, terrain: Any, config: NavigatorConfig | dict | str | Any = None, *,
                 n_vehicles: int = 1, map_frame: Any = None,
                 map_error_variance: float | None = None, dtype: torch.dtype = torch.float64,
                 tile: Any = None, device: str | torch.device | None = None) -> None:
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
        self.device = _resolve_device(device, terrain)
        self.terrain = terrain
        self.extent = tuple(float(e) for e in extent)
        self.n_vehicles, self.map_frame, self.dtype, self.tile = n_vehicles, map_frame, dtype, tile
        self.noise: MapNoise = measurement_noise(self.config, terrain,
                                                 map_error_variance=map_error_variance)
        self._P0 = self.config.prior().to(self.device)
        self._Q = self.config.process_noise_per_period().to(self.device)
        self._T = float(self.config.sensor.dt_s)
        gate_p = self.config.integrity.spike_gate_prob
        self._gate = _chi2_quantile(gate_p) if gate_p > 0 else math.inf
        self.method = self.config.method
        self._linearizer: Any = None
        if self.method not in ("point_mass_tracker",):
            self._linearizer = self._build_linearizer()
        self.reset()

    # ------------------------------------------------------------------ set-up
    def _build_linearizer(self) -> Any:
        from neuralmap.linearize.factory import make_linearizer

        name = "neural" if self.method == "point_mass_ekf" else self.method
        table_path = self.config.map_error.linearisation_table
        if name in ("neural", "neural_region"):
            lin = make_linearizer(name, tile=None, terrain=self.terrain)
        else:
            lin = make_linearizer(name, tile=self._dem_tile())
        if table_path:
            from neuralmap.linearize.measured_noise import MeasuredNoiseLinearizer

            lin = MeasuredNoiseLinearizer(lin, load_noise_table(table_path))
        return lin

    def _dem_tile(self) -> Any:
        from neuralmap.dem.tile import DemTile

        if self.tile is not None:
            return self.tile
        heights = getattr(self.terrain, "heights", None)
        if heights is None or getattr(self.terrain, "origin", None) is None:
            raise NeuralMapError(
                f"Navigator: method {self.method!r} reads the DEM itself; pass tile=<the "
                "DemTile> or use a grid map, or choose 'neural' (autograd on any map) or "
                "the default point_mass_tracker.")
        return DemTile(heights=heights.detach().double().cpu().numpy(),
                       spacing=tuple(self.terrain.spacing), origin=tuple(self.terrain.origin),
                       name=getattr(self.terrain, "tile_name", "") or "map")

    def _make_policy(self) -> Any:
        from neuralmap.filters.policies.compose import quality_members
        from neuralmap.filters.policies.registry import make_policy

        policy = make_policy(self.config.policy, self.config.policy_args,
                             where=f"{self.config.source}: policy")
        if quality_members(policy):
            raise NeuralMapError(
                f"{self.config.source}: policy {self.config.policy!r} needs the altimeter's "
                "quality record, which a navigator input does not carry; choose a policy "
                "without 'quality' (raf, igg3, huber, chi2, yang, sage_husa, ...).")
        return policy

    def reset(self) -> None:
        """Starts a new flight for every vehicle: the next `step` is the prior."""
        n, cfg = self.n_vehicles, self.config
        sigma0 = float(self._P0[:2, :2].diagonal().max()) ** 0.5
        self._grid: _Grid | None = None
        on_grid = False
        if self.method == "point_mass_tracker":
            self._track: Any = _TrackerFilter(self)
            if sigma0 > cfg.acquisition.above_sigma_m:
                self._grid, on_grid = _Grid(self, self._P0), True
        else:
            base_R = (self.noise.altimeter_m2 if cfg.map_error.linearisation_table
                      else self.noise.R)
            self._track = _EkfFilter(self, self._linearizer, self._make_policy(), base_R)
            if self.method == "point_mass_ekf":
                self._grid, on_grid = _Grid(self, self._P0), True
        # the grid holds the vehicle (acquisition); else the track filter does
        dev = self.device
        self._on_grid = torch.full((n,), on_grid, dtype=torch.bool, device=dev)
        self._window = _Window(n, cfg.integrity.lost_window, cfg.integrity.lost_prob,
                               torch.float64, cap=self._gate, device=dev)
        self._open_cov1 = self._P0.clone()
        self._t_prev: float | None = None
        self._ins_prev: torch.Tensor | None = None
        self._mean = torch.zeros(n, N_STATES, dtype=torch.float64, device=dev)
        self._cov = self._P0.expand(n, N_STATES, N_STATES).clone()
        self.counts = dict.fromkeys(COUNT_KEYS, 0)
        self._dt_last = self._T

    # ------------------------------------------------------------------ inputs
    def _inputs(self, t: Any, ins_position: Any, ins_altitude: Any, clearance: Any
                ) -> tuple[float, torch.Tensor, torch.Tensor, torch.Tensor]:
        n = self.n_vehicles
        f64 = torch.float64
        tt = torch.as_tensor(t, dtype=f64).reshape(-1)
        if tt.numel() not in (1, n) or not bool(torch.isfinite(tt).all()):
            raise NeuralMapError(f"Navigator.step: t must be a finite time (a number or ({n},) "
                                 f"equal values), got shape {tuple(tt.shape)}.")
        if tt.numel() > 1 and not bool((tt == tt[0]).all()):
            raise NeuralMapError("Navigator.step: every vehicle of one navigator shares the "
                                 "epoch time; run one Navigator per clock.")
        pos = torch.as_tensor(ins_position)
        alt = torch.as_tensor(ins_altitude)
        clr = torch.as_tensor(clearance)
        if tuple(pos.shape) != (n, 2) or tuple(alt.shape) != (n,) or tuple(clr.shape) != (n,):
            raise NeuralMapError(
                f"Navigator.step: for {n} vehicles ins_position must be ({n}, 2), ins_altitude "
                f"and clearance ({n},); got {tuple(pos.shape)}, {tuple(alt.shape)}, "
                f"{tuple(clr.shape)}.")
        if not bool(torch.isfinite(pos).all()) or not bool(torch.isfinite(alt).all()):
            raise NeuralMapError("Navigator.step: the INS position and altitude must be finite "
                                 "(NaN is allowed in the clearance only).")
        dev = self.device
        return (float(tt[0]), pos.to(dev, f64), alt.to(dev, f64), clr.to(dev, f64))

    # ------------------------------------------------------------------ one epoch
    def step(self, t: float | torch.Tensor, ins_position: torch.Tensor,
             ins_altitude: torch.Tensor, clearance: torch.Tensor) -> Fix:
        """One epoch for every vehicle: predict over the interval, update, report.

        Args:
            t: Epoch time, s (a number, or ``(N,)`` equal values); strictly increasing.
            ins_position: ``(N, 2)`` INS horizontal position in the map frame, m.
            ins_altitude: ``(N,)`` INS altitude, m (the map's vertical datum).
            clearance: ``(N,)`` radar-altimeter clearance, m (NaN = no measurement).

        Returns:
            `Fix`, its tensors on the navigator's device (``Navigator.device``).

        Raises:
            NeuralMapError: Bad shapes, non-finite INS inputs, time not increasing.
        """
        t_k, pos, alt, clr = self._inputs(t, ins_position, ins_altitude, clearance)
        n = self.n_vehicles
        counts = self.counts
        counts["epochs"] += n
        dev = self.device
        nomeas = torch.zeros(n, dtype=torch.bool, device=dev)
        lost = torch.zeros(n, dtype=torch.bool, device=dev)
        off = torch.zeros(n, dtype=torch.bool, device=dev)
        if self._t_prev is None:  # the prior epoch
            vel_ins = torch.full((n, 2), math.nan, dtype=torch.float64, device=dev)
            off = ~inside_extent(pos, self.extent)
        else:
            dt = t_k - self._t_prev
            if not dt > 0:
                raise NeuralMapError(f"Navigator.step: time must increase; got t = {t_k!r} s "
                                     f"after {self._t_prev!r} s.")
            long_gap = dt > self.config.sensor.max_gap_s
            if long_gap:
                counts["long_gaps"] += n
            elif dt > self._T * (1.0 + 1e-9):
                counts["gaps"] += n
            vel_ins = (pos - self._ins_prev) / dt
            out = self._advance(dt, pos, alt, clr, long_gap)
            nomeas = out[0]
            step = out[1]
            lost, off = step.lost, step.off_map
            counts["lost"] += int(step.lost.sum())
            counts["reacquisitions"] += int(step.reacquired.sum())
            counts["handoffs"] += int(step.handoff.sum())
            counts["updates"] += int(step.applied.sum())
        counts["off_map_epochs"] += int(off.sum())
        self._t_prev, self._ins_prev = t_k, pos
        return self._fix(t_k, pos, alt, vel_ins, lost, off, nomeas)

    def _advance(self, dt: float, pos: torch.Tensor, alt: torch.Tensor, clr: torch.Tensor,
                 long_gap: bool) -> tuple[torch.Tensor, _StepOut]:
        n, s = self.n_vehicles, self.config.sensor
        nominal = dt == self._T
        scale = 1.0 if nominal else dt / self._T
        missing = ~torch.isfinite(clr)
        out_range = ~missing & ((clr < s.clearance_min_m) | (clr > s.clearance_max_m))
        self.counts["missing_radar"] += int(missing.sum())
        self.counts["out_of_range"] += int(out_range.sum())
        valid = ~missing & ~out_range & (not long_gap)
        # predicted estimate on the map? (δp⁻ = δp + Δt δv of the last posterior)
        pred_err = self._mean[:, :2] + dt * self._mean[:, 3:]
        on_map = inside_extent(pos - pred_err, self.extent)
        y = alt - clr
        self._propagate_open_loop(dt, scale)
        zeros = torch.zeros(n, dtype=torch.bool, device=self.device)
        nis = torch.full((n,), math.nan, dtype=torch.float64, device=self.device)
        applied, reacq, handoff = zeros.clone(), zeros.clone(), zeros.clone()
        lost, spikes = zeros.clone(), zeros.clone()
        grid, track = self._grid, self._track
        on_grid = self._on_grid
        if grid is not None and bool(on_grid.any()):
            grid.predict(dt, scale)
        tracking = ~on_grid
        use = valid & on_map
        if isinstance(track, _TrackerFilter):
            track.predict(dt, scale)
            mask = tracking & use
            all_in = bool(mask.all())
            t_nis, t_app, gated = track.update(torch.cat([pos, alt[:, None]], 1), y,
                                               None if all_in else mask)
            applied = applied | (t_app & mask)
            nis = torch.where((t_app & mask) | gated, t_nis.double(), nis)
            self.counts["spikes"] += int(gated.sum())
            spikes = gated
            off_est = tracking & ~on_map
        else:
            track.predict(dt, scale)
            mask = tracking & valid
            ins3 = torch.cat([pos, alt[:, None]], 1)
            e_nis, e_app, e_on = track.update(ins3, torch.where(valid, clr, math.nan),
                                              None if bool(mask.all()) else mask)
            e_app = e_app & mask
            applied = applied | e_app
            nis = torch.where(e_app, e_nis.double(), nis)
            off_est = tracking & ~e_on
        if grid is not None and bool(on_grid.any()):
            g_mask = on_grid & use
            g_app = grid.update(pos, y, g_mask)
            applied = applied | (g_app & g_mask)
        self._window.add(nis, (applied | spikes) & tracking)
        if self._window.enabled:
            fired = tracking & self._window.fired()
            if bool(fired.any()):
                lost = lost | fired
                reacq = reacq | fired
                self._reacquire(fired)
        grid = self._grid
        if grid is not None and bool(self._on_grid.any()):
            go = grid.ready(self._on_grid & ~lost)
            if bool(go.any()):
                rows = go.nonzero().reshape(-1)
                xg, Pg = grid.handoff_moments(rows)
                mean = torch.zeros(n, N_STATES, dtype=torch.float64, device=self.device)
                cov = self._P0.expand(n, N_STATES, N_STATES).clone()
                mean[rows], cov[rows] = xg, Pg
                track.load(go, mean, cov)
                self._on_grid = self._on_grid & ~go
                self._window.clear(go)
                handoff = go
        if bool(lost.any()):
            self._window.clear(lost)
        self._update_moments()
        off_now = (~on_map & ~self._on_grid) | off_est
        step = _StepOut(nis=nis, applied=applied, lost=lost, reacquired=reacq,
                        handoff=handoff, off_map=off_now & ~lost)
        return ~valid | spikes, step

    def _propagate_open_loop(self, dt: float, scale: float) -> None:
        """``m_ol ← Φ m_ol``, ``P_ol ← Φ P_ol Φᵀ + Q Δt/T``: the prior without measurements.

        Every vehicle shares it (same prior, same epochs, no measurement), and its mean
        stays 0 (``m_0 = 0``), so one ``(5, 5)`` covariance is carried."""
        phi = _transition(dt, torch.float64, self.device)
        P = phi @ self._open_cov1 @ phi.T + self._Q * scale
        self._open_cov1 = 0.5 * (P + P.T)

    @property
    def _open_mean(self) -> torch.Tensor:
        return torch.zeros(self.n_vehicles, N_STATES, dtype=torch.float64, device=self.device)

    @property
    def _open_cov(self) -> torch.Tensor:
        return self._open_cov1.expand(self.n_vehicles, N_STATES, N_STATES).clone()

    def _reacquire(self, mask: torch.Tensor) -> None:
        """Vehicles ``mask`` restart from the open-loop prior ``N(m_ol, P_ol)``: on the
        acquisition grid when its horizontal σ exceeds ``acquisition.above_sigma_m`` (always
        for ``point_mass_ekf``), else in the tracking filter itself (EKF methods: always)."""
        sigma = _largest_sigma(self._open_cov)
        if self.method == "point_mass_ekf":
            to_grid = mask
        elif self.method == "point_mass_tracker":
            to_grid = mask & (sigma > self.config.acquisition.above_sigma_m)
        else:
            to_grid = torch.zeros_like(mask)
        direct = mask & ~to_grid
        if bool(direct.any()):
            self._track.load(direct, self._open_mean, self._open_cov)
        if bool(to_grid.any()):
            if self._grid is None:  # sized for the widest prior it must hold now
                floor = self.config.acquisition.reacquire_sigma_m
                widest = self._open_cov1.clone()
                widest[:2, :2] *= max(1.0, floor / float(sigma.max())) ** 2
                self._grid = _Grid(self, widest)
            self._grid.restart(to_grid, self._open_mean, self._open_cov)
            self._track.drop(to_grid)
            self._on_grid = self._on_grid | to_grid

    def _update_moments(self) -> None:
        mean, cov = self._track.moments()
        mean, cov = mean.double(), cov.double()
        if self._grid is not None and bool(self._on_grid.any()):
            gm, gc = self._grid.moments()
            m = self._on_grid
            mean = torch.where(m[:, None], gm, mean)
            cov = torch.where(m[:, None, None], gc, cov)
        self._mean, self._cov = mean, cov

    def _fix(self, t: float, pos: torch.Tensor, alt: torch.Tensor, vel_ins: torch.Tensor,
             lost: torch.Tensor, off: torch.Tensor, nomeas: torch.Tensor) -> Fix:
        n, dt = self.n_vehicles, self.dtype
        mean, cov = self._mean, self._cov
        sigma = _largest_sigma(cov)
        wide = self._on_grid | (sigma > self.config.integrity.acquired_sigma_m)
        status = torch.where(wide, _ACQ, _TRK)
        status = torch.where(nomeas, _NOMEAS, status)
        status = torch.where(off, _OFF, status)
        status = torch.where(lost, _LOST, status)
        xy = pos - mean[:, :2]
        lat = lon = None
        if self.map_frame is not None:
            xg = xy if xy.device.type == "cpu" else xy.cpu()  # geodesy runs on the CPU
            la, lo = self.map_frame.to_geo(xg[:, 0], xg[:, 1])
            lat = torch.as_tensor(la, dtype=torch.float64).reshape(n).to(pos.device, dt)
            lon = torch.as_tensor(lo, dtype=torch.float64).reshape(n).to(pos.device, dt)
        return Fix(t=torch.full((n,), t, dtype=dt, device=pos.device), xy=xy.to(dt),
                   altitude=(alt - mean[:, 2]).to(dt), velocity=(vel_ins - mean[:, 3:]).to(dt),
                   cov=cov.to(dt), status=status.long(), nis=self._window.mean().to(dt),
                   lat=lat, lon=lon)

    # ------------------------------------------------------------------ whole flights
    def replay(self, t: torch.Tensor, ins_position: torch.Tensor, ins_altitude: torch.Tensor,
               clearance: torch.Tensor) -> FixTrack:
        """A whole flight: `reset`, then `step` at every epoch.

        Args:
            t: ``(K,)`` epoch times, s, strictly increasing.
            ins_position: ``(N, K, 2)`` INS horizontal positions, m.
            ins_altitude: ``(N, K)`` INS altitudes, m.
            clearance: ``(N, K)`` clearances, m (NaN = no measurement).

        Returns:
            `FixTrack` on the CPU whatever the navigator's device (equal, bit for bit, to
            the fixes of `step` called K times after `reset`, moved to the CPU), with
            `counts`.
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
        self.reset()
        fixes = [self.step(t[i], ins_position[:, i], ins_altitude[:, i], clearance[:, i])
                 for i in range(k)]
        return _track_to(FixTrack.stack(fixes, counts=self.counts), torch.device("cpu"))

    @property
    def R(self) -> float:
        """The measurement variance ``σ_alt² + σ_dem² + σ_fit²``, m²."""
        return self.noise.R

    def describe(self) -> dict[str, Any]:
        """Method, noise and integrity settings in plain form (for reports)."""
        return {"method": self.method, "policy": self.config.policy,
                "acquisition_grid": self._grid is not None, "noise": self.noise.to_dict(),
                "lost_window": self.config.integrity.lost_window,
                "lost_prob": self.config.integrity.lost_prob, "config": self.config.source}
