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

One step per epoch: where the lattice runs its static driver (``compile: true``, or on
CUDA) the prediction waits for the update and the two run as one step
(`PointMassTracker.track`): the prediction, the map at the predicted cells
(`neuralmap.tan.cells.cell_heights`, fused into the compiled code with it), the spike gate,
the update, the moments and the radial mass profile the protection level reads
(`neuralmap.filters.lattice.kernels.radial_mass_profile`): one compiled call and one host
read for the whole tracking epoch. A rare event of the prediction, or a map that
``torch.compile`` cannot trace, falls back to the separate prediction and update (the same
results, tested).
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass

import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.filters.lattice.kernels import mass_radius
from neuralmap.filters.point_mass_tracker import (
    PointMassTracker,
    TrackerConfig,
    TrackerUpdate,
)
from neuralmap.filters.stats import symmetrize
from neuralmap.tan.cells import (
    cell_height_variance,
    cell_heights,
    heights_on_cells,
    lattice_protection_radius,
    map_dtype,
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
        # the whole epoch as one step (`PointMassTracker.track`) where the lattice runs its
        # static driver (compiled, or on CUDA): the prediction waits for its update
        self._pending = False
        self._map_dtype = map_dtype(context.terrain)
        self._R = torch.full((n,), float(context.R), **kw)
        self._mass: tuple[torch.Tensor, ...] | None = None  # (weights, reach, cumulative mass)
        self._mean: torch.Tensor | None = None  # the last estimate's mean

    def predict(self, dt: float) -> None:
        self._flush()
        if dt != self._dt:
            self._form = (self._nominal if dt == self.context.model.dt else
                          self.context.model.lattice_form(dt, dtype=self.dtype,
                                                          device=self.context.device))
            self.tracker.E, self.tracker.F = self._form.E, self._form.F
            self._dt = dt
        if self.tracker.rule.static and not self.options.flatten_likelihood:
            self._pending = True
        else:
            self.tracker.predict(Q_s=self._form.Q_s, Q_z=self._form.Q_z)

    def _flush(self) -> None:
        """Applies a prediction still waiting for its update."""
        if self._pending:
            self._pending = False
            self.tracker.predict(Q_s=self._form.Q_s, Q_z=self._form.Q_z)

    def update(self, ins: torch.Tensor, clearance: torch.Tensor, mask: torch.Tensor, *,
               gate: float = math.inf, quality: torch.Tensor | None = None) -> Innovation:
        trk, ctx = self.tracker, self.context
        y = (ins[:, 2] - clearance).to(self.dtype)
        if self._pending:
            self._pending = False
            fused = trk.track(Q_s=self._form.Q_s, Q_z=self._form.Q_z, measurement=y,
                              heights=cell_heights, heights_args=(
                                  ctx.terrain, ins[:, :2], ctx.extent, self._map_dtype),
                              R=self._R, mask=mask, gate=gate)
            if fused is not None:
                upd, nis_pred, gated, mass = fused
                self._mass = None if mass is None else (trk.weights, *mass)
                return self._innovation(upd, mask & ~gated, gated,
                                        nis_pred if gate < math.inf else None)
            trk.predict(Q_s=self._form.Q_s, Q_z=self._form.Q_z)
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
        return self._innovation(upd, use, gated, nis_pred)

    def _innovation(self, upd: TrackerUpdate, use: torch.Tensor, gated: torch.Tensor,
                    nis_pred: torch.Tensor | None) -> Innovation:
        """The method's `Innovation` of a lattice update (``use``: the runs it was asked to
        update; the gated ones report their predictive NIS)."""
        applied = upd.applied & use
        self.cell_updates += int(applied.sum()) * self.tracker.cells ** 2
        nan = torch.tensor(math.nan, dtype=torch.float64, device=applied.device)
        nis = torch.where(applied, upd.nis.double(), nan)
        if nis_pred is not None:
            nis = torch.where(gated, nis_pred.double(), nis)
        return Innovation(innovation=torch.where(applied, upd.innovation.double(), nan),
                          nis=nis, applied=applied, gated=gated, on_map=torch.ones_like(use))

    def estimate(self) -> tuple[torch.Tensor, torch.Tensor]:
        self._flush()
        mean, cov = self.tracker.moments()
        self._mean = mean.double()
        return self._mean, cov.double()

    def protection_level(self, risk: float, gaussian: torch.Tensor,
                         mean: torch.Tensor) -> torch.Tensor:
        """From the lattice's mass (`neuralmap.tan.cells.lattice_protection_radius`)."""
        self._flush()
        trk = self.tracker
        mass = self._mass
        if mass is not None and mass[0] is trk.weights and mean is self._mean:
            # the epoch's profile of the lattice around this very mean
            return torch.maximum(gaussian.double(), mass_radius(mass[1], mass[2], risk))
        return lattice_protection_radius(trk.points(), trk.weights, trk.axes, mean[:, :2],
                                         risk, gaussian)

    def load(self, mask: torch.Tensor, mean: torch.Tensor, cov: torch.Tensor) -> None:
        self._flush()
        cov = spd_floor(cov)
        m = mask[:, None]
        full_mean = torch.where(m, mean.to(self.dtype), 0.0)
        full_cov = torch.where(m[..., None], cov.to(self.dtype), self._dormant.expand_as(cov))
        self.tracker.reset(full_mean, full_cov, mask=mask)

    def drop(self, mask: torch.Tensor) -> None:
        self._flush()
        if bool(mask.any()):
            n = mask.shape[0]
            self.tracker.reset(torch.zeros(n, N_STATES, dtype=self.dtype,
                                           device=self.context.device), self._dormant, mask=mask)

    def counters(self) -> dict[str, torch.Tensor]:
        """``recoveries`` (updates whose likelihood vanished on every cell) and ``regrids``
        (lattice moves) of the tracker's lattice."""
        self._flush()
        return {"recoveries": self.tracker.recoveries, "regrids": self.tracker.regrids}

    def healthy(self) -> torch.Tensor:
        self._flush()
        return ~self.tracker.lost
