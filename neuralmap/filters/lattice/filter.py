"""The one batched point-mass lattice filter: state, measurement update and moments; how the
lattice moves (prediction and regrid) is a lattice-rule object.

N independent runs in lock-step (no Python loop over runs or cells). The state splits into

* ``s`` (2-D, the nonlinear part; in terrain navigation the horizontal INS error), carried
  by masses ``w (N, G, G)`` on an affine lattice: cell ``(i, j)`` (row ``i``, column ``j``)
  sits at ``centre + A · (j − h, i − h)``, ``h = (G − 1)/2``, ``A = axes (N, 2, 2)`` the
  two cell steps as columns (diagonal for the axis-aligned grid of acquisition);
* ``z`` (``nz``-D, the conditionally linear part), a Gaussian per cell
  (Rao-Blackwellised): ``z | cell ~ N(μ_cell, P)`` with ``μ = lin_mean (N, nz, G, G)`` and
  one conditional covariance ``P = lin_cov (N, nz, nz)`` per run (exact for the
  linear-Gaussian model). The acquisition grid is the case ``nz = 1``, ``E = 0``,
  ``F = 1``, ``c = 1`` (the altitude error).

Model::

    s_{k+1} = s_k + E z_k + u_k + w_s,   z_{k+1} = F z_k + w_z,   y_k = g(s_k) + c·z_k + e_k

**Update** (`LatticeFilter.update`, the same for every lattice rule; SEEDS point-mass
filter of Bergman, Ljung and Gustafsson): ``ν = y − g − c·μ``, ``S = cᵀPc + R`` (the same
in every cell), ``log w += −½ ν²/S`` (optionally a Gaussian + uniform mixture and a
per-cell likelihood flattening), ``μ += K ν``, ``P ← P − K S Kᵀ``, ``K = P c / S``
(`neuralmap.filters.lattice.follow_step.update_core` on the kernels of
`neuralmap.filters.lattice.kernels`). A run whose likelihood vanishes in every cell keeps
its prior masses (counted in ``recoveries``; never NaN); a NaN measurement is no
measurement. `LatticeFilter.predictive_nis` gives the NIS of a measurement against the
predicted mixture before the update (a spike gate's test).

**Lattice rule** (`neuralmap.filters.lattice.grid_rule.GridLattice`: fixed / adaptive grid
with deferred diffusion; `neuralmap.filters.lattice.follow_rule.FollowLattice`: the lattice
that follows the posterior, moment-exact prediction and regrid, lost-track test): the
rule object (attribute ``rule``) holds the lattice options and its own per-run bookkeeping
(deferred process noise; NIS window, widenings, open-loop prior) and implements
``predict``, ``regrid``, the post-update step and the initial lattice of a Gaussian prior.
The following lattice can run the update with its lost-track window, regrid and moments as
one pass of static-shape kernels (`neuralmap.filters.lattice.follow_step`; compiled with
``TrackerConfig.compile``). The filter holds the state
once; `neuralmap.filters.point_mass.PointMassFilter` (acquisition, hand-off) and
`neuralmap.filters.point_mass_tracker.PointMassTracker` (tracking) are configurations of
it (a rule and a model).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import torch

import neuralmap.filters.lattice.follow_step as fs
from neuralmap.exceptions import NeuralMapError
from neuralmap.filters.lattice.kernels import LatticeMoments

__all__ = ["STATE", "LatticeFilter", "LatticeUpdate", "to_state"]

#: The per-run state tensors of a lattice filter (masses, linear part, lattice, counters).
STATE = ("weights", "lin_mean", "lin_cov", "centre", "axes", "recoveries", "regrids")


def to_state(u: torch.Tensor, cu: torch.Tensor, centre: torch.Tensor,
             axes: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Mean ``(N, 2)`` and covariance ``(N, 2, 2)`` in state units of lattice moments ``u
    (N, 2)``, ``cu (N, 2, 2)`` (cells): ``centre + A u`` and ``A cu Aᵀ`` (symmetric)."""
    ms = centre + (axes @ u[:, :, None]).squeeze(-1)
    css = axes @ cu @ axes.transpose(1, 2)
    return ms, 0.5 * (css + css.transpose(1, 2))


@dataclass
class LatticeUpdate:
    """Per-run results of one `LatticeFilter.update` (``(N,)`` each).

    Attributes:
        log_likelihood: log predictive density ``log Σ w p(y | cell)`` (−inf where it
            vanished in every cell).
        recovered: bool, the likelihood vanished everywhere (or was not finite); the run
            kept its prior masses.
        applied: bool, the update changed the run (masked in, a measurement, not recovered).
        nis: NIS of the mixture's predictive measurement ``(y − ŷ)² / S_y`` (NaN where not
            applied), or None when the lattice rule does not report it.
        innovation: ``y − ŷ``, or None (as ``nis``).
        widened: bool, the rule's lost-track test widened the run's lattice, or None.
    """

    log_likelihood: torch.Tensor
    recovered: torch.Tensor
    applied: torch.Tensor
    nis: torch.Tensor | None = None
    innovation: torch.Tensor | None = None
    widened: torch.Tensor | None = None


class LatticeFilter:
    """N point-mass filters on lattices in lock-step (model: module docstring).

    Built by a configuration (`PointMassFilter`, `PointMassTracker`, or
    `neuralmap.filters.lattice.rule.make_lattice_filter`); the constructor allocates the
    state, the lattice rule then writes the prior into it.

    Args:
        rule: The lattice rule object (``GridLattice`` or ``FollowLattice``).
        n_runs: Runs N (≥ 1).
        E: ``(2, nz)`` effect of ``z`` on the next ``s``.
        F: ``(nz, nz)`` transition of ``z``.
        c: ``(nz,)`` measurement row of ``z``.
        dtype: float32 or float64.
        device: Torch device.

    Attributes:
        weights: ``(N, G, G)`` normalised cell masses (rows along the second lattice axis).
        lin_mean: ``(N, nz, G, G)`` per-cell mean of ``z``.
        lin_cov: ``(N, nz, nz)`` conditional covariance of ``z`` (common to the cells).
        centre: ``(N, 2)`` lattice centres; ``axes``: ``(N, 2, 2)`` cell steps (columns).
        recoveries, regrids: ``(N,)`` int64 counters.
        rule: The lattice rule.
        E, F, c: The model (assigning ``E`` or ``F`` takes effect at the next prediction).
    """

    def __init__(self, rule: Any, n_runs: int, *, E: torch.Tensor, F: torch.Tensor,
                 c: torch.Tensor, dtype: torch.dtype, device: torch.device | None = None,
                 name: str = "LatticeFilter") -> None:
        if dtype not in (torch.float32, torch.float64):
            raise NeuralMapError(f"{name}: dtype must be float32 or float64, got {dtype}.")
        kw = {"dtype": dtype, "device": device}
        self.name, self.rule = name, rule
        self.dtype, self.device = dtype, torch.device(device or "cpu")
        self.E = torch.as_tensor(E, **kw)
        self.F = torch.as_tensor(F, **kw)
        self.c = torch.as_tensor(c, **kw)
        nz = self.c.shape[0] if self.c.ndim == 1 else -1
        if (self.c.ndim != 1 or tuple(self.E.shape) != (2, nz)
                or tuple(self.F.shape) != (nz, nz)):
            raise NeuralMapError(
                f"{name}: E, F, c must have shapes (2, nz), (nz, nz), (nz,); got "
                f"{tuple(self.E.shape)}, {tuple(self.F.shape)}, {tuple(self.c.shape)}.")
        g = rule.config.cells
        self.n_runs, self.nz, self.cells = n_runs, nz, g
        self.half = 0.5 * (g - 1)
        self._off = torch.arange(g, **kw) - self.half
        self.weights = torch.zeros(n_runs, g, g, **kw)
        self.lin_mean = torch.zeros(n_runs, nz, g, g, **kw)
        self.lin_cov = torch.zeros(n_runs, nz, nz, **kw)
        self.centre = torch.zeros(n_runs, 2, **kw)
        self.axes = torch.zeros(n_runs, 2, 2, **kw)
        self.recoveries = torch.zeros(n_runs, dtype=torch.int64, device=self.device)
        self.regrids = torch.zeros_like(self.recoveries)
        self._moments_cache: tuple[Any, ...] | None = None
        self._points_cache: tuple[Any, ...] | None = None
        self._joint_cache: tuple[Any, ...] | None = None

    # ------------------------------------------------------------------ model, rule
    @property
    def F(self) -> torch.Tensor:  # noqa: N802 - the model's name
        """``(nz, nz)`` transition of ``z``."""
        return self._F

    @F.setter
    def F(self, value: torch.Tensor) -> None:  # noqa: N802
        self._F = torch.as_tensor(value, dtype=self.dtype, device=self.device)
        nz = self._F.shape[-1]
        self._f_identity = bool(torch.equal(self._F, torch.eye(nz, dtype=self.dtype,
                                                               device=self.device)))

    @property
    def E(self) -> torch.Tensor:  # noqa: N802 - the model's name
        """``(2, nz)`` effect of ``z`` on the next ``s``."""
        return self._E

    @E.setter
    def E(self, value: torch.Tensor) -> None:  # noqa: N802
        self._E = torch.as_tensor(value, dtype=self.dtype, device=self.device)

    # ------------------------------------------------------------------ views
    @property
    def offsets(self) -> torch.Tensor:
        """``(G,)`` cell offsets ``j − (G − 1)/2``."""
        return self._off

    def points(self) -> torch.Tensor:
        """``(N, G, G, 2)`` cell coordinates ``centre + A (j − h, i − h)`` in the state space
        (cached while the lattice is unchanged; a moved lattice gets a new tensor)."""
        centre, axes = self.centre, self.axes
        cached = self._points_cache
        if (cached is not None and cached[0] is centre and cached[1] is axes
                and cached[2] == centre._version and cached[3] == axes._version):
            return cached[4]
        pts = fs.lattice_points(centre, axes, self._off)
        self._cache_points(centre, axes, pts)
        return pts

    def _cache_points(self, centre: torch.Tensor, axes: torch.Tensor, pts: torch.Tensor) -> None:
        """Remembers ``pts`` as the cells of the lattice ``(centre, axes)``."""
        self._points_cache = (centre, axes, centre._version, axes._version, pts)

    def _cache_step(self, state: tuple[torch.Tensor, ...], mean: torch.Tensor,
                    cov: torch.Tensor, pts: torch.Tensor) -> None:
        """Remembers the moments and cells a step computed for the lattice state ``state``
        (used while the filter holds exactly those tensors, unmodified)."""
        self._joint_cache = (state, tuple(t._version for t in state), mean, cov)
        self._cache_points(state[3], state[4], pts)

    def lattice_moments(self, w: torch.Tensor | None = None,
                        mu: torch.Tensor | None = None) -> LatticeMoments:
        """`LatticeMoments` of ``(w, mu)`` (default: the state), reused while both tensors
        are the same objects at the same version (a step asks for the moments of one state
        several times)."""
        w = self.weights if w is None else w
        mu = self.lin_mean if mu is None else mu
        cached = self._moments_cache
        if (cached is not None and cached[0] is w and cached[1] is mu
                and cached[2] == w._version and cached[3] == mu._version):
            return cached[4]
        lm = LatticeMoments(w, mu, self._off)
        self._moments_cache = (w, mu, w._version, mu._version, lm)
        return lm

    def state_moments(self, lm: LatticeMoments | None = None) -> tuple[torch.Tensor, ...]:
        """``ms (N, 2), css (N, 2, 2), mz (N, nz), czz (N, nz, nz), czs (N, nz, 2)`` of the
        masses and the linear part in state units (without the rule's deferred noise)."""
        lm = self.lattice_moments() if lm is None else lm
        return tuple(fs.state_moments(lm.tensors(), self.lin_cov, self.centre, self.axes))

    def moments(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Mean ``(N, 2+nz)`` and covariance ``(N, 2+nz, 2+nz)`` of the whole state ``[s, z]``
        (the rule's process noise not yet applied to the lattice included)."""
        state = self.state()
        cached = self._joint_cache
        if (cached is not None and all(a is b for a, b in zip(cached[0], state, strict=True))
                and cached[1] == tuple(t._version for t in state)):
            return cached[2], cached[3]
        t = fs.Targets(*self.state_moments())
        deferred = self.rule.deferred_cov(self)
        if deferred is not None:
            t = t._replace(css=t.css + deferred)
        return fs.joint_moments(t)

    def predictive_nis(self, y: torch.Tensor | float, g: torch.Tensor,
                       R: float | torch.Tensor) -> torch.Tensor:
        """``(N,)`` NIS of the scalar measurement ``y`` against the predicted mixture, before
        the update (a spike gate's test).

        ``ŷ = Σ w (g + c·μ)``, ``S_y = Σ w (g + c·μ − ŷ)² + cᵀ P c + R``, NIS
        ``= (y − ŷ)² / S_y``; cells where ``g`` is not finite get zero mass (the others
        renormalised). The same moments as the NIS `update` reports.

        Args:
            y: ``(N,)`` measurements (NaN: no measurement).
            g: ``(N, G, G)`` ``g`` at the cells (NaN off the map).
            R: Measurement variance, float or ``(N,)``.

        Returns:
            ``(N,)`` NIS in the filter's dtype; NaN where ``y`` is NaN or no cell is valid.
        """
        n, kw = self.n_runs, {"dtype": self.dtype, "device": self.device}
        y = _batch(y, (n,), "y", f"{self.name}.predictive_nis", kw)
        r = _batch(R, (n,), "R", f"{self.name}.predictive_nis", kw)
        g = torch.as_tensor(g).to(**kw)
        if tuple(g.shape) != (n, self.cells, self.cells):
            raise NeuralMapError(
                f"{self.name}.predictive_nis: g must have shape (N, G, G) = ({n}, "
                f"{self.cells}, {self.cells}), got {tuple(g.shape)}.")
        return fs.predictive_nis_core(self.weights, self.lin_mean, self.lin_cov, self.c, y,
                                      g, r)

    # ------------------------------------------------------------------ state rows
    def state(self) -> tuple[torch.Tensor, ...]:
        """``(weights, lin_mean, lin_cov, centre, axes)``."""
        return self.weights, self.lin_mean, self.lin_cov, self.centre, self.axes

    def set_state(self, w: torch.Tensor, mu: torch.Tensor, P: torch.Tensor,
                  centre: torch.Tensor, axes: torch.Tensor) -> None:
        """Replaces the lattice state of every run."""
        self.weights, self.lin_mean, self.lin_cov, self.centre, self.axes = (
            w, mu, P, centre, axes)

    def set_rows(self, mask: torch.Tensor, w: torch.Tensor, mu: torch.Tensor, P: torch.Tensor,
                 centre: torch.Tensor, axes: torch.Tensor) -> None:
        """Replaces the lattice state of the runs ``mask (N,)`` (full-size tensors)."""
        m1, m2, m3 = (mask.view(-1, *([1] * k)) for k in (1, 2, 3))
        self.weights = torch.where(m2, w, self.weights)
        self.lin_mean = torch.where(m3, mu, self.lin_mean)
        self.lin_cov = torch.where(m2, P, self.lin_cov)
        self.centre = torch.where(m1, centre, self.centre)
        self.axes = torch.where(m2, axes, self.axes)

    def copy_rows(self, idx: torch.Tensor, w: torch.Tensor, mu: torch.Tensor, P: torch.Tensor,
                  centre: torch.Tensor, axes: torch.Tensor) -> None:
        """Writes the state of runs ``idx (K,)`` from ``(K, ...)`` tensors, in place."""
        for t, v in zip(self.state(), (w, mu, P, centre, axes), strict=True):
            t.index_copy_(0, idx, v.to(t.dtype))

    def take(self, index: torch.Tensor) -> LatticeFilter:
        """A new filter of the same configuration holding the runs ``index (M,)`` (copies;
        counters and the rule's per-run bookkeeping carried over)."""
        out = object.__new__(type(self))
        out.__dict__.update(self.__dict__)
        out.n_runs = int(index.numel())
        for name in STATE:
            setattr(out, name, getattr(self, name).index_select(0, index))
        out.rule = self.rule.take(index)
        out._moments_cache = out._points_cache = out._joint_cache = None
        return out

    def extend(self, other: LatticeFilter) -> LatticeFilter:
        """A new filter with the runs of ``self`` followed by those of ``other`` (same
        configuration)."""
        out = self.take(torch.arange(self.n_runs, device=self.device))
        for name in STATE:
            setattr(out, name, torch.cat([getattr(self, name), getattr(other, name)]))
        out.n_runs = self.n_runs + other.n_runs
        out.rule = self.rule.cat(other.rule)
        return out

    # ------------------------------------------------------------------ predict / regrid
    def predict(self, **kwargs: Any) -> Any:
        """Time update by the lattice rule (``GridLattice.predict`` /
        ``FollowLattice.predict``)."""
        return self.rule.predict(self, **kwargs)

    def regrid(self, *args: Any, **kwargs: Any) -> torch.Tensor:
        """Moves runs whose posterior no longer fits their lattice (the rule's); returns
        ``(N,)`` bool, runs moved."""
        return self.rule.regrid(self, *args, **kwargs)

    # ------------------------------------------------------------------ update
    def update(self, measurement: torch.Tensor | float,
               predicted: torch.Tensor | Callable[[torch.Tensor], torch.Tensor], *,
               R: float | torch.Tensor, mask: torch.Tensor | None = None,
               cell_variance: torch.Tensor | None = None, regrid: bool = True,
               ) -> LatticeUpdate:
        """Measurement update ``y = g(s) + c·z + e`` in every cell (module docstring), then
        the rule's post-update step (the following lattice's lost-track test and regrid).

        Args:
            measurement: ``(N,)`` ``y`` (NaN = no measurement for that run).
            predicted: ``(N, G, G)`` ``g`` at the cells, or a callable on the cell
                coordinates ``(N, G, G, 2)`` (`points`); non-finite cells get zero
                likelihood.
            R: Measurement variance (> 0), float or ``(N,)``.
            mask: ``(N,)`` bool, runs to update (None = all).
            cell_variance: ``(N, G, G)`` spread of ``g`` over each cell, added to ``S`` in
                the likelihood only (a coarse lattice cannot step over a narrow peak).
            regrid: Let a rule that regrids after the update do so (``follow``; the grid
                rules regrid in `predict`).

        Returns:
            `LatticeUpdate`.
        """
        rule = self.rule
        n, g, kw = self.n_runs, self.cells, {"dtype": self.dtype, "device": self.device}
        y = _batch(measurement, (n,), "measurement", self.name, kw)
        gval = predicted(self.points()) if callable(predicted) else predicted
        gval = _as(gval, **kw)
        if tuple(gval.shape) != (n, g, g):
            raise NeuralMapError(
                f"{self.name}.update: predicted must have shape (N, G, G) = ({n}, {g}, {g}), "
                f"got {tuple(gval.shape)}.")
        r = _batch(R, (n,), "R", self.name, kw)
        if isinstance(R, (int, float)) and not (math.isfinite(R) and R > 0):
            raise NeuralMapError(f"{self.name}.update: R must be > 0 (and finite) for every run.")
        if cell_variance is not None:
            cell_variance = _as(cell_variance, **kw).clamp_min(0.0)
        if hasattr(rule, "update"):  # the rule's one-pass update (None: run the one below)
            done = rule.update(self, y, gval, r, mask, cell_variance, regrid)
            if done is not None:
                return done
        out = fs.update_core(self.weights, self.lin_mean, self.lin_cov, self.c, y, gval, r,
                             mask, cell_variance, reports_nis=rule.reports_nis,
                             outlier_prob=rule.outlier_prob, outlier_width=rule.outlier_width,
                             floor_weights=rule.floor_weights)
        if bool(out["r_bad"].any()):
            raise NeuralMapError(f"{self.name}.update: R must be > 0 (and finite) for every run.")
        self.recoveries += out["recovered"].long()
        self.weights, self.lin_mean, self.lin_cov = out["state"]
        use, nis = out["applied"], out["nis"]
        widened = rule.after_update(self, nis, use, regrid)
        if nis is not None:
            nis = torch.where(use, nis, math.nan)
        return LatticeUpdate(log_likelihood=out["log_likelihood"], recovered=out["recovered"],
                             applied=use, nis=nis, innovation=out["innovation"],
                             widened=widened)


def _as(x: object, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """``x`` as a tensor of ``dtype`` on ``device`` (no copy when it already is)."""
    if isinstance(x, torch.Tensor) and x.dtype == dtype and x.device == device:
        return x
    return torch.as_tensor(x).to(dtype=dtype, device=device)


def _batch(value: object, shape: tuple[int, ...], what: str, name: str,
           kw: dict[str, Any]) -> torch.Tensor:
    """Broadcasts a float or tensor to ``shape`` (raises on a shape that does not fit)."""
    t = torch.as_tensor(value, **kw)
    try:
        return t.expand(shape) if t.ndim <= len(shape) else t.reshape(shape)
    except RuntimeError as exc:
        raise NeuralMapError(
            f"{name}: {what} must broadcast to {shape}, got {tuple(t.shape)}.") from exc
