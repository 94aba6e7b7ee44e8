"""The whole-flight point-mass tracker (Bergman, Ljung and Gustafsson): the Navigator's default.

The 5-state TAN error model (SEEDS 004) in the Rao-Blackwellised form of the lattice
(`neuralmap.tan.model.TanModel.lattice_form`): ``s = δp`` on a lattice that follows the
posterior along its principal axes, ``z = [δh, δv_x, δv_y]`` a Kalman part per cell,

    s⁺ = s + Δt [δv_x, δv_y] + w_p,   z⁺ = diag(a, 1, 1) z + w_z,
    y = h_ins − clearance = t(p_ins − s) + δh − v,

``g(s) = t(p_ins − s)`` read from the map under test on every cell (any
`neuralmap.terrain.base.TerrainModel`; cells off the map get no likelihood), ``R`` the
context's. One `neuralmap.filters.point_mass_tracker.PointMassTracker` holds every vehicle;
vehicles the pipeline holds elsewhere (on the acquisition grid) are dormant rows: a benign
Gaussian, predicted, never updated.

Spike gate: a clearance whose predictive NIS against the predicted mixture (before the
update, `LatticeFilter.predictive_nis`) exceeds the Navigator's gate is not used.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.filters.point_mass_tracker import PointMassTracker, TrackerConfig
from neuralmap.filters.stats import symmetrize
from neuralmap.tan.cells import (
    cell_height_variance,
    heights_on_cells,
    lattice_protection_radius,
)
from neuralmap.tan.method import Innovation, MethodContext, NavigationMethod
from neuralmap.tan.model import N_STATES, TanModel
from neuralmap.tan.registry import register_method

__all__ = ["PointMassTrackerMethod", "TrackerOptions", "spd_floor", "transition_blur"]


def transition_blur(model: TanModel) -> float:
    """One period's horizontal transition spread ``b = sqrt(λ_max(Q_s) + T² λ_max(P0_v))``,
    m (the lattice floor of `TrackerOptions.min_cell_blur`)."""
    P0, Q = model.filter_prior(), model.filter_process_noise()
    q = torch.linalg.eigvalsh(symmetrize(Q[:2, :2]))[-1].clamp_min(0.0)
    v = torch.linalg.eigvalsh(symmetrize(P0[3:, 3:]))[-1].clamp_min(0.0)
    return float((q + float(model.dt) ** 2 * v).sqrt())


def spd_floor(cov: torch.Tensor, rel: float = 1e-9) -> torch.Tensor:
    """``cov (..., n, n)`` symmetric with its eigenvalues floored at ``rel`` × the largest
    (float64): a round-off guard before a filter that refuses a covariance that is not
    positive definite."""
    lam, vec = torch.linalg.eigh(symmetrize(cov.double()))
    lam = lam.clamp_min(rel * lam.abs().amax(-1, keepdim=True).clamp_min(1e-12))
    return symmetrize((vec * lam[..., None, :]) @ vec.transpose(-1, -2))


@dataclass
class TrackerOptions(TrackerConfig):
    """Options of the point-mass tracker: the lattice's own (`TrackerConfig`, state units =
    m) plus how it is fed.

    Attributes:
        dtype: ``float32`` (default, about 2× faster; linear-Gaussian agreement with the
            Kalman filter 2e-3 σ) or ``float64``.
        flatten_likelihood: Add the map's height spread over each cell to the likelihood
            variance (`neuralmap.tan.cells.cell_height_variance`): needed while the cells
            are coarser than the terrain's detail.
        min_cell_blur: Smallest cell step in units of one period's horizontal transition
            spread ``b`` (`transition_blur`; the lattice's minimum half-width is
            ``min_cell_blur · b · (G − 1) / 2``); 0 = no floor. A lattice finer than the
            transition blur gains nothing in accuracy, but the blur kernel of its prediction
            grows with it: with 1.5 the kernel stays below one cell σ (≤ 9 taps).
        dormant_sigma: Horizontal σ (m) of the benign Gaussian a dormant row holds.

    The lattice's own lost-track widening (``lost_window``) is off by default: the
    Navigator's lost-lock test and re-acquisition handle a lost lock for every method.
    """

    lost_window: int = 0
    dtype: str = "float32"
    flatten_likelihood: bool = False
    min_cell_blur: float = 1.5
    dormant_sigma: float = 40.0

    def lattice_config(self, blur_m: float) -> TrackerConfig:
        """The lattice's own options with the floor of ``min_cell_blur`` applied."""
        floor = self.min_cell_blur * blur_m * 0.5 * (self.cells - 1)
        return dataclasses.replace(self, min_half_width=max(self.min_half_width, floor))

    def validate(self, where: str = "point_mass_tracker") -> TrackerOptions:  # type: ignore[override]
        """Checks the options (the lattice's own through `TrackerConfig.validate`)."""
        if self.dtype not in ("float32", "float64"):
            raise NeuralMapError(f"{where}.dtype must be 'float32' or 'float64', got "
                                 f"{self.dtype!r}.")
        if not self.min_cell_blur >= 0.0:
            raise NeuralMapError(f"{where}.min_cell_blur must be >= 0, got "
                                 f"{self.min_cell_blur!r}.")
        if not self.dormant_sigma > 0.0:
            raise NeuralMapError(f"{where}.dormant_sigma must be > 0 m, got "
                                 f"{self.dormant_sigma!r}.")
        try:
            TrackerConfig.validate(self)
        except NeuralMapError as exc:
            raise NeuralMapError(f"{where}: {exc}") from exc
        return self


@register_method("point_mass_tracker")
class PointMassTrackerMethod(NavigationMethod):
    """The point-mass tracker over N vehicles (module docstring); started on the
    acquisition grid when the prior is wide."""

    Options = TrackerOptions
    acquisition = "wide"

    def __init__(self, context: MethodContext, options: TrackerOptions) -> None:
        super().__init__(context, options)
        self.dtype = torch.float32 if options.dtype == "float32" else torch.float64
        model, dev = context.model, context.device
        kw = {"dtype": self.dtype, "device": dev}
        self._nominal = model.lattice_form(**kw)
        self._dt = model.dt
        P0 = model.filter_prior(**kw)
        dormant = P0.clone()
        dormant[:2, :] = 0.0
        dormant[:, :2] = 0.0
        dormant[0, 0] = dormant[1, 1] = options.dormant_sigma ** 2
        self._dormant = dormant
        form, n = self._nominal, context.n_vehicles
        self.tracker = PointMassTracker(torch.zeros(n, N_STATES, **kw), P0, E=form.E, F=form.F,
                                        c=form.c, config=options.lattice_config(
                                            transition_blur(model)), dtype=self.dtype)
        self._form = form

    def predict(self, dt: float) -> None:
        if dt != self._dt:
            self._form = (self._nominal if dt == self.context.model.dt else
                          self.context.model.lattice_form(dt, dtype=self.dtype,
                                                          device=self.context.device))
            self.tracker.E, self.tracker.F = self._form.E, self._form.F
            self._dt = dt
        self.tracker.predict(Q_s=self._form.Q_s, Q_z=self._form.Q_z)

    def update(self, ins: torch.Tensor, clearance: torch.Tensor, mask: torch.Tensor, *,
               gate: float = math.inf, quality: torch.Tensor | None = None) -> Innovation:
        trk, ctx = self.tracker, self.context
        y = (ins[:, 2] - clearance).to(self.dtype)
        g = heights_on_cells(ctx.terrain, ins[:, :2], ctx.extent)(trk.points())
        gated = torch.zeros_like(mask)
        nis_pred = None
        if gate < math.inf:
            nis_pred = trk.predictive_nis(y, g, ctx.R)
            gated = mask & torch.isfinite(nis_pred) & (nis_pred > gate)
        use = mask & ~gated
        spread = None
        if self.options.flatten_likelihood:
            spread = torch.nan_to_num(cell_height_variance(g), nan=0.0)
        upd = trk.update(y, g, R=ctx.R, mask=None if bool(use.all()) else use,
                         cell_variance=spread)
        applied = upd.applied & use
        self.cell_updates += int(applied.sum()) * trk.cells ** 2
        nan = torch.tensor(math.nan, dtype=torch.float64, device=applied.device)
        nis = torch.where(applied, upd.nis.double(), nan)
        if nis_pred is not None:
            nis = torch.where(gated, nis_pred.double(), nis)
        return Innovation(innovation=torch.where(applied, upd.innovation.double(), nan),
                          nis=nis, applied=applied, gated=gated, on_map=torch.ones_like(mask))

    def estimate(self) -> tuple[torch.Tensor, torch.Tensor]:
        mean, cov = self.tracker.moments()
        return mean.double(), cov.double()

    def protection_level(self, risk: float, gaussian: torch.Tensor,
                         mean: torch.Tensor) -> torch.Tensor:
        """From the lattice's mass (`neuralmap.tan.cells.lattice_protection_radius`)."""
        trk = self.tracker
        return lattice_protection_radius(trk.points(), trk.weights, trk.axes, mean[:, :2],
                                         risk, gaussian)

    def load(self, mask: torch.Tensor, mean: torch.Tensor, cov: torch.Tensor) -> None:
        cov = spd_floor(cov)
        m = mask[:, None]
        full_mean = torch.where(m, mean.to(self.dtype), 0.0)
        full_cov = torch.where(m[..., None], cov.to(self.dtype), self._dormant.expand_as(cov))
        self.tracker.reset(full_mean, full_cov, mask=mask)

    def drop(self, mask: torch.Tensor) -> None:
        if bool(mask.any()):
            n = mask.shape[0]
            self.tracker.reset(torch.zeros(n, N_STATES, dtype=self.dtype,
                                           device=self.context.device), self._dormant, mask=mask)

    def counters(self) -> dict[str, torch.Tensor]:
        """``recoveries`` (updates whose likelihood vanished on every cell) and ``regrids``
        (lattice moves) of the tracker's lattice."""
        return {"recoveries": self.tracker.recoveries, "regrids": self.tracker.regrids}

    def healthy(self) -> torch.Tensor:
        return ~self.tracker.lost
