"""Batched point-mass tracker: a lattice that follows the posterior, a Kalman part per cell.

The tracking configuration of the one lattice filter
(`neuralmap.filters.lattice.filter.LatticeFilter`): the point-mass filter of Bergman, Ljung
and Gustafsson run for the whole flight, for N independent runs at once, with the
``follow`` lattice rule (`neuralmap.filters.lattice.follow_rule.FollowLattice`: an
affine lattice along the posterior's principal axes, moment-exact prediction and regrid,
lost-track test and open-loop re-acquisition). The state splits into ``s`` (2-D, the
horizontal INS error, on the lattice) and ``z`` (``nz``-D, altitude and velocity errors, a
Kalman part per cell)::

    s_{k+1} = s_k + E z_k + u_k + w_s,   w_s ~ N(0, Q_s)
    z_{k+1} = F z_k + w_z,               w_z ~ N(0, Q_z)
    y_k     = g(s_k) + c·z_k + e_k,      e_k ~ N(0, R)

with ``g`` given per cell by the caller (a callable on the cell coordinates, e.g. a
`TerrainModel` lookup — a grid or a neural map). The update is the lattice filter's; the
prediction, the regrid, the moment correction and the lost-track rules are described in
`neuralmap.filters.lattice.follow_rule`; the step's kernels (static shapes, one host read
per step, optionally under ``torch.compile``: ``TrackerConfig.compile``) in
`neuralmap.filters.lattice.follow_step`.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.filters.lattice.filter import LatticeFilter, LatticeUpdate
from neuralmap.filters.lattice.follow_rule import (
    BLUR_MIN_CELLS,
    MIN_CELL_VARIANCE,
    FollowLattice,
    TrackerConfig,
)

__all__ = ["BLUR_MIN_CELLS", "MIN_CELL_VARIANCE", "PointMassTracker", "TrackerConfig",
           "TrackerUpdate"]

#: Per-run results of `PointMassTracker.update` (the lattice filter's).
TrackerUpdate = LatticeUpdate


class PointMassTracker(LatticeFilter):
    """N Rao-Blackwellised point-mass trackers in lock-step: the lattice filter with the
    ``follow`` lattice rule (model: module docstring).

    Args:
        mean: ``(N, 2 + nz)`` prior mean ``[s, z]``.
        cov: ``(2+nz, 2+nz)`` or ``(N, 2+nz, 2+nz)`` prior covariance (positive definite).
        E: ``(2, nz)`` effect of ``z`` on the next ``s`` (e.g. ``T`` on the velocities).
        F: ``(nz, nz)`` transition of ``z``.
        c: ``(nz,)`` measurement row of ``z``.
        config: `TrackerConfig`.
        dtype: float32 or float64 (default float64).

    Attributes:
        weights: ``(N, G, G)`` normalised cell masses.
        lin_mean: ``(N, nz, G, G)`` per-cell mean of ``z``.
        lin_cov: ``(N, nz, nz)`` conditional covariance of ``z`` (common to the cells).
        centre: ``(N, 2)`` lattice centres; ``axes``: ``(N, 2, 2)`` cell steps (columns).
        recoveries, regrids, widenings: ``(N,)`` int64 counters.
        lost: ``(N,)`` bool, lost beyond recovery.

    Raises:
        NeuralMapError: Bad shapes, a prior covariance that is not positive definite (names
            the run), or a prior the lattice cannot hold at ``max_spacing``.
    """

    def __init__(self, mean: torch.Tensor, cov: torch.Tensor, *, E: torch.Tensor,
                 F: torch.Tensor, c: torch.Tensor, config: TrackerConfig | None = None,
                 dtype: torch.dtype = torch.float64) -> None:
        config = (config or TrackerConfig()).validate()
        if dtype not in (torch.float32, torch.float64):
            raise NeuralMapError(
                f"PointMassTracker: dtype must be float32 or float64, got {dtype}.")
        mean = torch.as_tensor(mean)
        if mean.ndim != 2 or mean.shape[1] < 3 or mean.shape[0] < 1:
            raise NeuralMapError(
                f"PointMassTracker: mean must have shape (N, 2 + nz) with nz >= 1, got "
                f"{tuple(mean.shape)}.")
        n, d = mean.shape
        nz = d - 2
        kw = {"dtype": dtype, "device": mean.device}
        E, F, c = (torch.as_tensor(t, **kw) for t in (E, F, c))
        if tuple(E.shape) != (2, nz) or tuple(F.shape) != (nz, nz) or tuple(c.shape) != (nz,):
            raise NeuralMapError(
                f"PointMassTracker: E, F, c must have shapes (2, {nz}), ({nz}, {nz}), ({nz},); "
                f"got {tuple(E.shape)}, {tuple(F.shape)}, {tuple(c.shape)}.")
        super().__init__(FollowLattice(config, n, nz, dtype, mean.device), n, E=E, F=F, c=c,
                         dtype=dtype, device=mean.device, name="PointMassTracker")
        self.config = config
        self.reset(mean, cov)
        self.set_open_loop(mean, cov)

    # ------------------------------------------------------------------ rule state
    @property
    def widenings(self) -> torch.Tensor:
        """``(N,)`` int64, lost-track widenings (the rule's)."""
        return self.rule.widenings

    @property
    def lost(self) -> torch.Tensor:
        """``(N,)`` bool, lost beyond recovery (the rule's)."""
        return self.rule.lost

    # ------------------------------------------------------------------ set-up
    def reset(self, mean: torch.Tensor, cov: torch.Tensor,
              mask: torch.Tensor | None = None) -> None:
        """(Re-)initialises runs from a Gaussian prior ``N(mean, cov)`` over ``[s, z]``.

        Args:
            mean: ``(N, 2 + nz)``.
            cov: ``(2+nz, 2+nz)`` or ``(N, 2+nz, 2+nz)``, symmetric positive definite.
            mask: ``(N,)`` bool, runs to reset (None = all).

        Raises:
            NeuralMapError: ``cov`` not positive definite (names the first bad run); a prior
                that needs cells coarser than ``max_spacing``.
        """
        self.rule.reset(self, mean, cov, mask)

    def set_open_loop(self, mean: torch.Tensor, cov: torch.Tensor) -> None:
        """Sets the open-loop prior a lost run re-acquires from (`FollowLattice.set_open_loop`).

        Args:
            mean: ``(2 + nz,)`` or ``(N, 2 + nz)``.
            cov: ``(2+nz, 2+nz)`` or ``(N, 2+nz, 2+nz)``, symmetric positive definite.

        Raises:
            NeuralMapError: Bad shapes, non-finite entries or ``cov`` not positive definite.
        """
        self.rule.set_open_loop(self, mean, cov)

    def open_loop(self) -> tuple[torch.Tensor, torch.Tensor]:
        """The open-loop prior ``(m_ol (N, 2+nz), P_ol (N, 2+nz, 2+nz))``."""
        return self.rule.open_loop(self)

    def match_moments(self, mean: torch.Tensor, cov: torch.Tensor) -> None:
        """Imposes mean ``(N, 2+nz)`` and covariance ``(N, 2+nz, 2+nz)`` exactly (affine
        lattice map + per-cell linear-part shift; `FollowLattice.match_moments`)."""
        self.rule.match_moments(self, mean, cov)

    # ------------------------------------------------------------------ predict / update
    def predict(self, *, Q_s: torch.Tensor, Q_z: torch.Tensor,
                shift: torch.Tensor | None = None) -> None:
        """Time update, exact in its first two moments (`FollowLattice.predict`).

        Args:
            Q_s: ``(2, 2)`` or ``(N, 2, 2)`` process noise of ``s``.
            Q_z: ``(nz, nz)`` or ``(N, nz, nz)`` process noise of ``z``.
            shift: ``(N, 2)`` known displacement ``u`` of ``s`` (None = 0).
        """
        self.rule.predict(self, Q_s=Q_s, Q_z=Q_z, shift=shift)

    def update(self, measurement: torch.Tensor,
               predicted: torch.Tensor | Callable[[torch.Tensor], torch.Tensor], *,
               R: float | torch.Tensor, mask: torch.Tensor | None = None,
               cell_variance: torch.Tensor | None = None, regrid: bool = True) -> TrackerUpdate:
        """Measurement update ``y = g(s) + c·z + e`` in every cell (`LatticeFilter.update`),
        the lost-track test, then the regrid.

        Args:
            measurement: ``(N,)`` ``y`` (NaN = no measurement for that run).
            predicted: ``(N, G, G)`` ``g`` at the cells, or a callable on the cell
                coordinates ``(N, G, G, 2)``; non-finite cells get zero likelihood.
            R: Measurement variance (> 0), float or ``(N,)``.
            mask: ``(N,)`` bool, runs to update (None = all).
            cell_variance: ``(N, G, G)`` spread of ``g`` over each cell, added to ``S`` in
                the likelihood only (a coarse lattice cannot step over a narrow peak).
            regrid: Move runs whose posterior no longer fits their lattice.

        Returns:
            `TrackerUpdate`.
        """
        return super().update(measurement, predicted, R=R, mask=mask,
                              cell_variance=cell_variance, regrid=regrid)

    def track(self, *, Q_s: torch.Tensor, Q_z: torch.Tensor, measurement: torch.Tensor,
              heights: Callable[..., torch.Tensor], heights_args: tuple[Any, ...],
              R: torch.Tensor, mask: torch.Tensor, gate: float = math.inf,
              ) -> tuple[TrackerUpdate, torch.Tensor, torch.Tensor, Any] | None:
        """`predict` then `update` as one static step, the map lookup and a spike gate in it
        (`FollowLattice.track`; one compiled call with ``config.compile``).

        Args:
            Q_s: ``(2, 2)`` or ``(N, 2, 2)`` process noise of ``s``.
            Q_z: ``(nz, nz)`` or ``(N, nz, nz)`` process noise of ``z``.
            measurement: ``(N,)`` ``y`` in the filter's dtype (NaN = no measurement).
            heights: A module-level function: ``heights(*heights_args, points)`` is ``g``
                ``(N, G, G)`` at the predicted cells ``points (N, G, G, 2)`` (NaN: no
                likelihood), e.g. `neuralmap.tan.cells.cell_heights`.
            heights_args: Its other arguments (the map, the INS positions, ...).
            R: ``(N,)`` measurement variances (> 0) in the filter's dtype.
            mask: ``(N,)`` bool, runs to update.
            gate: Leave out ``y`` where its NIS against the predicted mixture
                (`predictive_nis`) exceeds ``gate``.

        Returns:
            The update, the predictive NIS ``(N,)``, the gated runs ``(N,)`` and the radial
            mass profile ``(reach, cumulative mass)`` of the result around its mean
            (`neuralmap.filters.lattice.kernels.radial_mass_profile`; None for a large
            batch); None, with nothing changed, where the epoch is to run as `predict` and `update` (the eager
            driver, or a rare event of the prediction).
        """
        return self.rule.track(self, Q_s=Q_s, Q_z=Q_z, y=measurement, heights=heights,
                               heights_args=heights_args, r=R, mask=mask, gate=gate)

    def regrid(self, force: torch.Tensor | None = None) -> torch.Tensor:
        """Moves runs whose posterior no longer fits their lattice (`FollowLattice.regrid`).

        Args:
            force: ``(N,)`` bool, runs to move regardless of the rule.

        Returns:
            ``(N,)`` bool, runs moved.
        """
        return self.rule.regrid(self, force)

    # ------------------------------------------------------------------ lattice helpers
    def _gaussian_state(self, mean: torch.Tensor, cov: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """Lattice, masses and linear part of ``N(mean, cov)`` (moments matched exactly)."""
        return self.rule._gaussian_state(self, mean, cov)

    def _set_subset(self, mask: torch.Tensor, mean: torch.Tensor, cov: torch.Tensor) -> None:
        """Runs ``mask (N,)`` restart from ``N(mean, cov)`` (their Gaussian lattice only)."""
        self.rule._set_subset(self, mask, mean, cov)

    def _state(self) -> tuple[torch.Tensor, ...]:
        return self.state()
