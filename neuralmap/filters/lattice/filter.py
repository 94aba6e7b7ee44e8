"""The one batched point-mass lattice filter: state, measurement update and moments; the
lattice rule (prediction and regrid) is a policy object.

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

**Update** (`LatticeFilter.update`, the same for every policy; SEEDS point-mass filter of
Bergman, Ljung and Gustafsson): ``ν = y − g − c·μ``, ``S = cᵀPc + R`` (the same in every
cell), ``log w += −½ ν²/S`` (optionally a Gaussian + uniform mixture and a per-cell
likelihood flattening), ``μ += K ν``, ``P ← P − K S Kᵀ``, ``K = P c / S`` (the kernels of
`neuralmap.filters.lattice.kernels`). A run whose likelihood vanishes in every cell keeps
its prior masses (counted in ``recoveries``; never NaN); a NaN measurement is no
measurement.

**Policy** (`neuralmap.filters.lattice.grid_policy.GridLattice`: fixed / adaptive grid with
deferred diffusion; `neuralmap.filters.lattice.follow_policy.FollowLattice`: the lattice
that follows the posterior, moment-exact prediction and regrid, lost-track test): the
policy object holds the lattice options and its own per-run bookkeeping (deferred process
noise; NIS window, widenings, open-loop prior) and implements ``predict``, ``regrid``, the
post-update step and the initial lattice of a Gaussian prior. The filter holds the state
once; `neuralmap.filters.point_mass.PointMassFilter` (acquisition, hand-off) and
`neuralmap.filters.point_mass_tracker.PointMassTracker` (tracking) are configurations of
it (a policy and a model).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.filters.lattice.kernels import (
    LatticeMoments,
    cell_log_likelihood,
    kalman_cells,
    weight_update,
)

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
            applied), or None when the policy does not report it.
        innovation: ``y − ŷ``, or None (as ``nis``).
        widened: bool, the policy's lost-track test widened the run's lattice, or None.
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
    `neuralmap.filters.lattice.policy.make_lattice_filter`); the constructor allocates the
    state, the policy then writes the prior into it.

    Args:
        policy: The lattice policy object (``GridLattice`` or ``FollowLattice``).
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
        policy: The lattice policy.
    """

    def __init__(self, policy: Any, n_runs: int, *, E: torch.Tensor, F: torch.Tensor,
                 c: torch.Tensor, dtype: torch.dtype, device: torch.device | None = None,
                 name: str = "LatticeFilter") -> None:
        if dtype not in (torch.float32, torch.float64):
            raise NeuralMapError(f"{name}: dtype must be float32 or float64, got {dtype}.")
        kw = {"dtype": dtype, "device": device}
        self.name, self.policy = name, policy
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
        g = policy.config.cells
        self.n_runs, self.nz, self.cells = n_runs, nz, g
        self.half = 0.5 * (g - 1)
        self._off = torch.arange(g, **kw) - self.half
        self._f_identity = bool(torch.equal(self.F, torch.eye(nz, **kw)))
        self.weights = torch.zeros(n_runs, g, g, **kw)
        self.lin_mean = torch.zeros(n_runs, nz, g, g, **kw)
        self.lin_cov = torch.zeros(n_runs, nz, nz, **kw)
        self.centre = torch.zeros(n_runs, 2, **kw)
        self.axes = torch.zeros(n_runs, 2, 2, **kw)
        self.recoveries = torch.zeros(n_runs, dtype=torch.int64, device=self.device)
        self.regrids = torch.zeros_like(self.recoveries)
        self._moments_cache: tuple[Any, ...] | None = None
        self._points_cache: tuple[Any, ...] | None = None

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
        o = self._off
        col = axes[:, None, None, :, 0] * o[None, None, :, None]
        row = axes[:, None, None, :, 1] * o[None, :, None, None]
        pts = centre[:, None, None, :] + col + row
        self._points_cache = (centre, axes, centre._version, axes._version, pts)
        return pts

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
        masses and the linear part in state units (without the policy's deferred noise)."""
        lm = self.lattice_moments() if lm is None else lm
        ms, css = to_state(lm.u, lm.cu, self.centre, self.axes)
        czs = lm.czu @ self.axes.transpose(1, 2)
        czz = self.lin_cov + lm.czz_b
        return ms, css, lm.mz, 0.5 * (czz + czz.transpose(1, 2)), czs

    def moments(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Mean ``(N, 2+nz)`` and covariance ``(N, 2+nz, 2+nz)`` of the whole state ``[s, z]``
        (the policy's process noise not yet applied to the lattice included)."""
        ms, css, mz, czz, czs = self.state_moments()
        deferred = self.policy.deferred_cov(self)
        if deferred is not None:
            css = css + deferred
        mean = torch.cat([ms, mz], 1)
        cov = torch.cat([torch.cat([css, czs.transpose(1, 2)], 2),
                         torch.cat([czs, czz], 2)], 1)
        return mean, 0.5 * (cov + cov.transpose(1, 2))

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
        counters and the policy's per-run bookkeeping carried over)."""
        out = object.__new__(type(self))
        out.__dict__.update(self.__dict__)
        out.n_runs = int(index.numel())
        for name in STATE:
            setattr(out, name, getattr(self, name).index_select(0, index))
        out.policy = self.policy.take(index)
        out._moments_cache = out._points_cache = None
        return out

    def extend(self, other: LatticeFilter) -> LatticeFilter:
        """A new filter with the runs of ``self`` followed by those of ``other`` (same
        configuration)."""
        out = self.take(torch.arange(self.n_runs, device=self.device))
        for name in STATE:
            setattr(out, name, torch.cat([getattr(self, name), getattr(other, name)]))
        out.n_runs = self.n_runs + other.n_runs
        out.policy = self.policy.cat(other.policy)
        return out

    # ------------------------------------------------------------------ predict / regrid
    def predict(self, **kwargs: Any) -> Any:
        """Time update by the lattice policy (``GridLattice.predict`` /
        ``FollowLattice.predict``)."""
        return self.policy.predict(self, **kwargs)

    def regrid(self, *args: Any, **kwargs: Any) -> torch.Tensor:
        """Moves runs whose posterior no longer fits their lattice (the policy's rule);
        returns ``(N,)`` bool, runs moved."""
        return self.policy.regrid(self, *args, **kwargs)

    # ------------------------------------------------------------------ update
    def update(self, measurement: torch.Tensor | float,
               predicted: torch.Tensor | Callable[[torch.Tensor], torch.Tensor], *,
               R: float | torch.Tensor, mask: torch.Tensor | None = None,
               cell_variance: torch.Tensor | None = None, regrid: bool = True,
               ) -> LatticeUpdate:
        """Measurement update ``y = g(s) + c·z + e`` in every cell (module docstring), then
        the policy's post-update step (the following lattice's lost-track test and regrid).

        Args:
            measurement: ``(N,)`` ``y`` (NaN = no measurement for that run).
            predicted: ``(N, G, G)`` ``g`` at the cells, or a callable on the cell
                coordinates ``(N, G, G, 2)`` (`points`); non-finite cells get zero
                likelihood.
            R: Measurement variance (> 0), float or ``(N,)``.
            mask: ``(N,)`` bool, runs to update (None = all).
            cell_variance: ``(N, G, G)`` spread of ``g`` over each cell, added to ``S`` in
                the likelihood only (a coarse lattice cannot step over a narrow peak).
            regrid: Let a policy that regrids after the update do so (``follow``; the grid
                policies regrid in `predict`).

        Returns:
            `LatticeUpdate`.
        """
        pol = self.policy
        n, g, kw = self.n_runs, self.cells, {"dtype": self.dtype, "device": self.device}
        y = _batch(measurement, (n,), "measurement", self.name, kw)
        gval = predicted(self.points()) if callable(predicted) else predicted
        gval = torch.as_tensor(gval).to(**kw)
        if tuple(gval.shape) != (n, g, g):
            raise NeuralMapError(
                f"{self.name}.update: predicted must have shape (N, G, G) = ({n}, {g}, {g}), "
                f"got {tuple(gval.shape)}.")
        r = _batch(R, (n,), "R", self.name, kw)
        if not bool((r > 0).all()) or not bool(torch.isfinite(r).all()):
            raise NeuralMapError(f"{self.name}.update: R must be > 0 (and finite) for every run.")
        w, mu, P, c = self.weights, self.lin_mean, self.lin_cov, self.c
        s_run = ((P @ c) @ c) + r  # (N,) S = cᵀPc + R, the same in every cell
        yhat_cell = gval + torch.einsum("z,nzij->nij", c, mu)
        nu = y[:, None, None] - yhat_cell  # ν = y − g − c·μ
        finite_cell = torch.isfinite(nu)
        all_finite = bool(finite_cell.all())
        nis = innov = None
        if pol.reports_nis:  # the mixture's predictive moments of y
            if all_finite:
                yhat = (w * yhat_cell).sum((1, 2))
                s_y = (w * (yhat_cell - yhat[:, None, None]) ** 2).sum((1, 2)) + s_run
            else:
                yhat_c = torch.where(finite_cell, yhat_cell, 0.0)
                w_ok = torch.where(finite_cell, w, 0.0)
                mass_ok = w_ok.sum((1, 2)).clamp_min(torch.finfo(self.dtype).tiny)
                yhat = (w_ok * yhat_c).sum((1, 2)) / mass_ok
                s_y = ((w_ok * (yhat_c - yhat[:, None, None]) ** 2).sum((1, 2)) / mass_ok
                       + s_run)
            innov = y - yhat
            nis = innov * innov / s_y
        if not all_finite:
            nu = torch.where(finite_cell, nu, 0.0)
        loglik, resp = cell_log_likelihood(nu, s_run, cell_variance,
                                           outlier_prob=pol.outlier_prob,
                                           outlier_width=pol.outlier_width)
        if not all_finite:
            loglik = torch.where(finite_cell, loglik, -math.inf)
        upd = weight_update(w, torch.nan_to_num(loglik, nan=-math.inf, neginf=-math.inf), s_run)
        has_y = torch.isfinite(y)
        use = upd.use & has_y
        recovered = ~upd.use & has_y
        if mask is not None:
            recovered = recovered & mask
            use = use & mask
        self.recoveries += recovered.long()
        wn = pol.floor_weights(upd.weights)
        mu_new, P_new = kalman_cells(mu, P, c, nu, s_run, resp, wn)
        if bool(use.all()):
            self.weights, self.lin_mean, self.lin_cov = wn, mu_new, P_new
        else:
            a3, a4 = use[:, None, None], use[:, None, None, None]
            self.weights = torch.where(a3, wn, w)
            self.lin_mean = torch.where(a4, mu_new, mu)
            self.lin_cov = torch.where(a3, P_new, P)
        widened = pol.after_update(self, nis, use, regrid)
        if nis is not None:
            nis = torch.where(use, nis, math.nan)
        return LatticeUpdate(log_likelihood=upd.log_likelihood, recovered=recovered,
                             applied=use, nis=nis, innovation=innov, widened=widened)


def _batch(value: object, shape: tuple[int, ...], what: str, name: str,
           kw: dict[str, Any]) -> torch.Tensor:
    """Broadcasts a float or tensor to ``shape`` (raises on a shape that does not fit)."""
    t = torch.as_tensor(value, **kw)
    try:
        return t.expand(shape) if t.ndim <= len(shape) else t.reshape(shape)
    except RuntimeError as exc:
        raise NeuralMapError(
            f"{name}: {what} must broadcast to {shape}, got {tuple(t.shape)}.") from exc
