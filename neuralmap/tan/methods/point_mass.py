"""The point-mass grid (Bergman, Ljung and Gustafsson): acquisition from a wide prior.

The horizontal error ``s = δp`` on a regular grid that holds every terrain match at once
(`neuralmap.filters.point_mass.PointMassFilter`, the grid configuration of the one lattice
filter), the altitude error ``a = δh`` Rao-Blackwellised per cell, the measurement of each
cell read from the map at ``p_ins − s`` (`neuralmap.tan.cells`; cells off the map get no
likelihood). It is the Navigator's acquisition grid (every method whose ``acquisition`` rule
asks for it starts there and is handed off once the posterior is unimodal and small) and,
registered as ``point_mass``, a navigation method of its own for the whole flight.

Velocity error: the grid carries the horizontal error only. Its prediction uses the
position marginal of the prior ``[δp, δv]`` model (per axis ``P_pp ← P_pp + 2Δt P_pv + Δt²
P_vv + q_p``, ``P_pv ← P_pv + Δt P_vv``, ``P_vv ← P_vv + q_v``): the process noise of the
step is the growth of ``P_pp``. The estimate's velocity error is the Gaussian conditional on
the position posterior ``N(μ, Σ)``: ``B = P_pv / P_pp`` (per axis), ``δv̂ = v₀ + B (μ − m_p)``,
``cov(δv) = P_vv − B P_pp B + B Σ B``, ``cov(δp, δv) = Σ B``, ``cov(δv, δh) = B Σ_ps`` —
exact for a linear-Gaussian position measurement, an approximation otherwise.

The grid holds only its member vehicles (`load` appends, `drop` removes rows), so its cost
follows the number of vehicles acquiring; every member shares the grid size ``G`` of the
first prior it was sized for (a wider prior gets a coarser spacing, not more cells).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.filters.point_mass import PointMassConfig, PointMassFilter
from neuralmap.filters.stats import symmetrize
from neuralmap.tan.cells import (
    cell_height_variance,
    cells_on_map,
    heights_on_cells,
    is_bilinear_grid,
    lattice_bilinear,
    lattice_protection_radius,
    mask_voids,
)
from neuralmap.tan.method import Innovation, MethodContext, NavigationMethod
from neuralmap.tan.model import N_STATES
from neuralmap.tan.registry import register_method

__all__ = ["PointMassGrid", "PointMassOptions"]


@dataclass
class PointMassOptions(PointMassConfig):
    """Options of the point-mass grid: the grid's own (`PointMassConfig`, state units = m)
    plus how it is sized and fed.

    Attributes:
        cells: Cells per axis; None = from the prior: the fewest (≥ 32, ≤ ``max_cells``)
            that cover ± ``span_sigma`` σ at ``max_spacing``.
        max_spacing: Largest initial spacing when ``cells`` is None, m.
        max_cells: Most cells per axis when ``cells`` is None.
        dtype: ``float32`` (default) or ``float64``.
        flatten_likelihood: Add the map's height spread over each cell
            (`neuralmap.tan.cells.cell_height_variance`) to the likelihood's variance, so a
            coarse grid cannot step over a likelihood peak narrower than a cell.
        velocity_from_grid: Condition the velocity error on the grid posterior (module
            docstring); False: ``δv̂ = v₀``, ``cov = P_vv``, no correlation.
        spike_gate: Use the Navigator's spike gate (a clearance whose predictive NIS against
            the predicted grid mixture is past the gate is not used). Off by default: with
            every mode on the grid a spike moves little mass, and the lost-lock test catches
            a wrong match after the hand-off.
        growth_horizon_s: The grid is sized for the prior grown over this acquisition
            horizon by its velocity error and process noise (``P_pp + H (P_pv + P_vp) + H²
            P_vv + (H/T) Q_p``), not for the prior alone: a fixed grid must still hold the
            truth when the velocity error has carried it away (a small UAV's 0.2 m/s over
            150 s is 30 m against a 10 m prior). 0 = the prior's σ alone.

    The grid's own options (`PointMassConfig`) keep their meaning; defaults here:
    ``adaptive`` False (the prior's grid throughout: on jacksboro, σ0 = 1 km, 100 runs, the
    fixed 161² grid at 50 m diverged in 0 runs, the adaptive one in 4–5 — a posterior that
    collapses early is cut to its grid), ``min_spacing`` 2 m, ``min_half_width`` 600 m (an
    adaptive grid that shrank onto a wrong mode cut the truth off in 5 runs without it).
    """

    cells: int | None = None  # type: ignore[assignment]
    adaptive: bool = False
    min_spacing: float = 2.0
    min_half_width: float = 600.0
    max_spacing: float = 50.0
    max_cells: int = 256
    dtype: str = "float32"
    flatten_likelihood: bool = True
    velocity_from_grid: bool = True
    spike_gate: bool = False
    growth_horizon_s: float = 60.0

    def grid_cells(self, sigma: float) -> int:
        """Cells per axis for a prior of largest standard deviation ``sigma`` (m)."""
        if self.cells is not None:
            return int(self.cells)
        need = 2.0 * self.span_sigma * sigma / self.max_spacing + 1.0
        return int(min(max(math.ceil(need), 32), self.max_cells))

    def grid_config(self, sigma: float) -> PointMassConfig:
        """The grid's own options for a prior of largest σ ``sigma`` (validated)."""
        return PointMassConfig.validate(dataclasses.replace(self, cells=self.grid_cells(sigma)))

    def validate(self, where: str = "point_mass") -> PointMassOptions:  # type: ignore[override]
        """Checks the options (the grid's own through `PointMassConfig.validate`)."""
        if self.dtype not in ("float32", "float64"):
            raise NeuralMapError(f"{where}.dtype must be 'float32' or 'float64', got "
                                 f"{self.dtype!r}.")
        if not self.max_spacing > 0:
            raise NeuralMapError(f"{where}.max_spacing must be > 0 m, got {self.max_spacing!r}.")
        if isinstance(self.max_cells, bool) or not isinstance(self.max_cells, int) or (
                self.max_cells < 8):
            raise NeuralMapError(f"{where}.max_cells must be an integer >= 8, got "
                                 f"{self.max_cells!r}.")
        try:
            self.grid_config(0.0)
        except NeuralMapError as exc:
            raise NeuralMapError(f"{where}: {exc}") from exc
        return self


class _VelocityPrior:
    """Per-axis ``[δp, δv]`` prior of the grid's members (module docstring); ``(M, 2)``
    each, float64."""

    def __init__(self, ppp: torch.Tensor, ppv: torch.Tensor, pvv: torch.Tensor,
                 v0: torch.Tensor, mp: torch.Tensor) -> None:
        self.ppp, self.ppv, self.pvv, self.v0, self.mp = ppp, ppv, pvv, v0, mp

    @classmethod
    def from_gaussian(cls, mean: torch.Tensor, cov: torch.Tensor) -> _VelocityPrior:
        """From ``N(mean (M, 5), cov (M, 5, 5))`` (float64)."""
        return cls(torch.diagonal(cov[:, :2, :2], dim1=1, dim2=2),
                   torch.stack([cov[:, 0, 3], cov[:, 1, 4]], 1),
                   torch.diagonal(cov[:, 3:, 3:], dim1=1, dim2=2),
                   mean[:, 3:].clone(), mean[:, :2].clone())

    def step(self, dt: float, qp: torch.Tensor, qv: torch.Tensor) -> torch.Tensor:
        """Propagates over ``dt``; returns the position-variance growth ``(M, 2)``."""
        grow = 2.0 * dt * self.ppv + dt * dt * self.pvv + qp
        self.ppp = self.ppp + grow
        self.ppv = self.ppv + dt * self.pvv
        self.pvv = self.pvv + qv
        self.mp = self.mp + dt * self.v0
        return grow

    def take(self, index: torch.Tensor) -> _VelocityPrior:
        return _VelocityPrior(*(t.index_select(0, index) for t in self._fields()))

    def extend(self, other: _VelocityPrior) -> _VelocityPrior:
        return _VelocityPrior(*(torch.cat([a, b]) for a, b in zip(self._fields(),
                                                                 other._fields(), strict=True)))

    def _fields(self) -> tuple[torch.Tensor, ...]:
        return self.ppp, self.ppv, self.pvv, self.v0, self.mp

    def state(self, mean3: torch.Tensor, cov3: torch.Tensor, condition: bool
              ) -> tuple[torch.Tensor, torch.Tensor]:
        """5-state mean ``(M, 5)`` and covariance ``(M, 5, 5)`` from the grid's ``[s, a]``
        moments ``mean3 (M, 3)``, ``cov3 (M, 3, 3)`` (module docstring)."""
        mu, sigma = mean3[:, :2], cov3[:, :2, :2]
        cov_as = cov3[:, 2, :2]
        b = self.ppv / self.ppp if condition else torch.zeros_like(self.ppv)
        bm = torch.diag_embed(b)
        v = self.v0 + b * (mu - self.mp)  # δv̂ = v₀ + B (μ − m_p)
        cov_vv = torch.diag_embed(self.pvv - b * b * self.ppp) + bm @ sigma @ bm
        cov_vs = bm @ sigma  # cov(δv, δp) = B Σ
        cov_va = b * cov_as  # cov(δv, δh) = B Σ_ps
        m = mean3.shape[0]
        x = torch.cat([mean3, v], 1)
        P = torch.zeros(m, N_STATES, N_STATES, dtype=mean3.dtype, device=mean3.device)
        P[:, :3, :3] = cov3
        P[:, 3:, :2] = cov_vs
        P[:, :2, 3:] = cov_vs.transpose(1, 2)
        P[:, 3:, 2] = cov_va
        P[:, 2, 3:] = cov_va
        P[:, 3:, 3:] = cov_vv
        return x, symmetrize(P)


@register_method("point_mass")
class PointMassGrid(NavigationMethod):
    """The point-mass grid over the vehicles loaded into it (module docstring).

    Registered as ``point_mass``: the grid for the whole flight (``adaptive: true`` lets it
    follow and shrink with the posterior); every vehicle starts on it, so it needs no
    acquisition of its own. The Navigator's acquisition grid is the same class.
    """

    Options = PointMassOptions

    def __init__(self, context: MethodContext, options: PointMassOptions) -> None:
        super().__init__(context, options)
        self.dtype = torch.float32 if options.dtype == "float32" else torch.float64
        self.fast = is_bilinear_grid(context.terrain)
        self._heights = (context.terrain.heights.to(self.dtype) if self.fast else None)
        model, dev = context.model, context.device
        q = model.process_noise(dtype=torch.float64, device=dev)
        self._q_nominal = (q[[0, 1], [0, 1]], q[[3, 4], [3, 4]], float(q[2, 2]))
        n = context.n_vehicles
        self.members = torch.zeros(0, dtype=torch.long, device=dev)  # vehicle of each row
        self.pm: PointMassFilter | None = None
        self.vel: _VelocityPrior | None = None
        self._mean = torch.zeros(n, N_STATES, dtype=torch.float64, device=dev)
        self._cov = model.filter_prior(device=dev).expand(n, N_STATES, N_STATES).clone()
        self.recoveries = torch.zeros(n, dtype=torch.long, device=dev)
        self._dirty = False

    # ------------------------------------------------------------------ rows
    @property
    def member_mask(self) -> torch.Tensor:
        """``(N,)`` bool: vehicles on the grid."""
        mask = torch.zeros(self.context.n_vehicles, dtype=torch.bool,
                           device=self.context.device)
        mask[self.members] = True
        return mask

    def load(self, mask: torch.Tensor, mean: torch.Tensor, cov: torch.Tensor) -> None:
        """Vehicles ``mask`` (re)start on the grid from ``N(mean, cov)`` (float64)."""
        self.drop(mask)
        rows = mask.nonzero().reshape(-1)
        if rows.numel() == 0:
            return
        mean, cov = mean.index_select(0, rows), symmetrize(cov.index_select(0, rows))
        dt = self.dtype
        sigma = float(torch.linalg.eigvalsh(self._grown(cov))[:, -1].max().clamp_min(0.0).sqrt())
        cells = self.pm.cells if self.pm is not None else self.options.grid_cells(sigma)
        spacing = max(self.options.span_sigma * sigma / (0.5 * (cells - 1)),
                      self.options.min_spacing)  # one spacing: the grown prior of every row
        fresh = PointMassFilter(mean[:, :2].to(dt), cov[:, :2, :2].to(dt),
                                scalar_mean=mean[:, 2].to(dt),
                                scalar_var=cov[:, 2, 2].clamp_min(1.0).to(dt),
                                config=dataclasses.replace(self.options.grid_config(sigma),
                                                           cells=cells, spacing=spacing),
                                dtype=dt)
        vel = _VelocityPrior.from_gaussian(mean, cov)
        if self.pm is None:
            self.pm, self.vel = fresh, vel
        else:
            self.pm, self.vel = self.pm.extend(fresh), self.vel.extend(vel)
        self.members = torch.cat([self.members, rows])
        self._dirty = True

    def _grown(self, cov: torch.Tensor) -> torch.Tensor:
        """``(M, 2, 2)`` the position covariance grown over `growth_horizon_s`
        (``P_pp + H (P_pv + P_vp) + H² P_vv + (H/T) Q_p``)."""
        h = float(self.options.growth_horizon_s)
        if h <= 0:
            return cov[:, :2, :2]
        qp = torch.diag_embed(self._q_nominal[0].to(cov))
        pv = cov[:, :2, 3:]
        return symmetrize(cov[:, :2, :2] + h * (pv + pv.transpose(1, 2)) + h * h * cov[:, 3:, 3:]
                          + (h / self.context.model.dt) * qp)

    def drop(self, mask: torch.Tensor) -> None:
        """Vehicles ``mask`` leave the grid (their rows are removed)."""
        if self.pm is None:
            return
        keep = (~mask.index_select(0, self.members)).nonzero().reshape(-1)
        if keep.numel() == self.members.numel():
            return
        self.members = self.members.index_select(0, keep)
        if keep.numel() == 0:
            self.pm = self.vel = None
        else:
            self.pm, self.vel = self.pm.take(keep), self.vel.take(keep)
        self._dirty = True

    # ------------------------------------------------------------------ the protocol
    def predict(self, dt: float) -> None:
        if self.pm is None:
            return
        qp, qv, qh = self._q_nominal
        model = self.context.model
        if dt != model.dt:
            q = model.process_noise(dt, dtype=torch.float64, device=self.context.device)
            qp, qv, qh = q[[0, 1], [0, 1]], q[[3, 4], [3, 4]], float(q[2, 2])
        m = self.members.numel()
        grow = self.vel.step(dt, qp.expand(m, 2), qv.expand(m, 2))
        decay = model.altitude_decay(dt)
        if decay != 1.0:  # Gauss-Markov altitude error: a ← decay · a before its noise
            self.pm.lin_mean.mul_(decay)
            self.pm.lin_cov.mul_(decay * decay)
        self.pm.predict(Q=grow.to(self.dtype), shift=(dt * self.vel.v0).to(self.dtype),
                        scalar_q=qh)
        self._dirty = True

    def _cell_heights(self, ins_xy: torch.Tensor
                      ) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor]:
        """``(M, G, G)`` map heights at ``p_ins − s`` of every member's cells, NaN off the
        map; their spread (likelihood flattening) or None; ``(M,)`` any cell on the map."""
        pm, ext = self.pm, self.context.extent
        if self.fast:
            t = self.context.terrain
            pred = lattice_bilinear(self._heights, t.origin, t.spacing, ins_xy, pm.centre,
                                    pm.spacing, pm.offsets)
        else:
            pred = heights_on_cells(self.context.terrain, ins_xy, ext,
                                    mask_off_map=False)(pm.points())
        spread = cell_height_variance(pred) if self.options.flatten_likelihood else None
        on = cells_on_map(ins_xy, pm.centre, pm.spacing, pm.offsets, ext)
        if self.fast and self.context.terrain.n_filled:  # cells on DEM voids: no likelihood
            pred = mask_voids(self.context.terrain,
                              ins_xy[:, None, None, :].to(pred.dtype) - pm.points(), pred)
        return pred.masked_fill(~on, math.nan), spread, on.flatten(1).any(1)

    def update(self, ins: torch.Tensor, clearance: torch.Tensor, mask: torch.Tensor, *,
               gate: float = math.inf, quality: torch.Tensor | None = None) -> Innovation:
        n, dev = self.context.n_vehicles, self.context.device
        out = Innovation.none(n, dev)
        if self.pm is None:
            return out
        rows = self.members
        use = mask.index_select(0, rows)
        y = (ins.index_select(0, rows)[:, 2] - clearance.index_select(0, rows)).to(self.dtype)
        pred, spread, any_on = self._cell_heights(ins.index_select(0, rows)[:, :2])
        out.on_map[rows] = any_on
        R = self.context.R
        gated = torch.zeros_like(use)
        if self.options.spike_gate and gate < math.inf:
            nis_pred = self.pm.predictive_nis(y, pred, R)
            gated = use & torch.isfinite(nis_pred) & (nis_pred > gate)
            out.nis[rows] = torch.where(gated, nis_pred.double(), math.nan)
        upd = self.pm.update(y, pred, R=R, mask=use & ~gated, cell_variance=spread)
        self.recoveries.index_add_(0, rows, upd.recovered.long())
        self.cell_updates += int(use.sum()) * self.pm.cells ** 2
        out.applied[rows] = upd.applied & use
        out.gated[rows] = gated
        self._dirty = True
        return out

    def estimate(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Mean and covariance of every vehicle (members: from the grid's moments, module
        docstring; others: their last)."""
        if self._dirty and self.pm is not None:
            mean3, cov3 = self.pm.moments()
            x, P = self.vel.state(mean3.double(), cov3.double(),
                                  self.options.velocity_from_grid)
            self._mean[self.members] = x
            self._cov[self.members] = P
        self._dirty = False
        return self._mean, self._cov

    def protection_level(self, risk: float, gaussian: torch.Tensor,
                         mean: torch.Tensor) -> torch.Tensor:
        """From the grid's mass for its members (`lattice_protection_radius`)."""
        out = gaussian.double().clone()
        if self.pm is not None:
            rows = self.members
            out[rows] = lattice_protection_radius(
                self.pm.points(), self.pm.weights, self.pm.axes, mean.index_select(0, rows)[:, :2],
                risk, gaussian.index_select(0, rows))
        return out

    def unimodality(self, candidates: torch.Tensor) -> torch.Tensor:
        """``(N,)`` Bhattacharyya coefficient between a member's grid posterior and its
        Gaussian fit (1 for a Gaussian posterior, about ``1/√M`` for M separate modes;
        `PointMassFilter.gaussian_affinity`), for the members in ``candidates (N,)`` (a
        pass over every cell: only where asked); 0 elsewhere."""
        out = torch.zeros(self.context.n_vehicles, dtype=torch.float64,
                          device=self.context.device)
        if self.pm is not None:
            idx = candidates.index_select(0, self.members).nonzero().reshape(-1)
            if idx.numel() > 0:
                out[self.members.index_select(0, idx)] = (
                    self.pm.gaussian_affinity(idx).double())
        return out

    def counters(self) -> dict[str, torch.Tensor]:
        """``recoveries``: updates whose likelihood vanished on every cell of the grid."""
        return {"recoveries": self.recoveries}

    def healthy(self) -> torch.Tensor:
        ok = torch.ones(self.context.n_vehicles, dtype=torch.bool, device=self.context.device)
        if self.pm is not None:
            ok[self.members] = torch.isfinite(self.pm.weights).flatten(1).all(1)
        return ok
