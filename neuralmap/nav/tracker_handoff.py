"""Hand-off from the acquisition grid to the whole-flight point-mass tracker.

Acquisition from a large initial error runs on the fixed point-mass grid of
`neuralmap.nav.acquisition` (the prior's grid, which holds every mode at once); once a
run's grid posterior is unimodal and small (`handoff_ready`)
the run is handed to a `PointMassTracker`
instead of the EKF. The tracker starts from the grid posterior's moments
(`grid_posterior_moments`), exactly: its lattice is built around them and
`reset` imposes the mean and
covariance of the whole 5-state ``[δp, δh, δv]`` to round-off.

Why the moments and not the grid's masses resampled onto the lattice: at hand-off the
posterior (σ ≤ ``handoff_sigma_m``, 40 m by default) spans one to three cells of the
acquisition grid (25 m cells at σ0 = 100 m, 50 m at 1 km, 94 m at 3 km), so its shape beyond
the first two moments is the grid's quantisation, not information; the hand-off test has
already required it to be close to its Gaussian fit (Bhattacharyya coefficient ≥ 0.9).

`TrackerPool` holds one tracker over all N runs; runs not handed off (or sent back
to acquisition by the lost-lock test) are dormant: predicted, never updated, their output
ignored, so the pool never re-allocates and no Python loop runs over runs.

Moments of the grid posterior (`grid_posterior_moments`), per run, with ``w`` the
cell masses, ``s`` the cell coordinates, ``a`` the per-cell altitude-error mean and ``v_a``
its common conditional variance::

    s̄ = Σ w s,   Σ_ss = cov_grid (incl. pending process noise),
    ā = Σ w a,   σ²_a = v_a + Σ w (a − ā)²,   Σ_as = Σ w (a − ā)(s − s̄)ᵀ,

and the velocity error from the Gaussian conditional on the position (module docstring of
`neuralmap.nav.acquisition`): ``δv = v₀ + B (s − m_p) + ε``, so
``Cov(δv, s) = B Σ_ss``, ``Cov(δv) = P_vv − B P_pp B + B Σ_ss B`` and
``Cov(δv, a) = B Σ_sa``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import torch

from neuralmap.filters.lattice.filter import to_state
from neuralmap.filters.lattice.kernels import LatticeMoments
from neuralmap.filters.point_mass import PointMassFilter
from neuralmap.filters.point_mass_tracker import PointMassTracker, TrackerConfig
from neuralmap.nav.model import N_STATES

__all__ = ["PoolStep", "TrackerPool", "grid_posterior_moments"]


def grid_posterior_moments(pm: PointMassFilter, index: torch.Tensor, *, ppp: torch.Tensor,
                           ppv: torch.Tensor, pvv: torch.Tensor, v0: torch.Tensor,
                           mp: torch.Tensor, condition: bool = True,
                           ) -> tuple[torch.Tensor, torch.Tensor]:
    """5-state mean and covariance of grid runs ``index`` (module docstring).

    The ``(s, a)`` moments are the lattice kernels' (`LatticeMoments`, `to_state`: the
    ones `LatticeFilter.moments` uses) on the selected runs, accumulated in float64
    whatever the grid's dtype; the pending process noise (``deferred_cov``) is added.

    Args:
        pm: The acquisition grid (``M`` runs).
        index: ``(K,)`` rows of ``pm`` to take.
        ppp: ``(K, 2)`` per-axis prior position variance of the velocity model.
        ppv: ``(K, 2)`` per-axis prior position-velocity covariance.
        pvv: ``(K, 2)`` per-axis prior velocity variance.
        v0: ``(K, 2)`` prior velocity-error mean.
        mp: ``(K, 2)`` prior position-error mean of the velocity model.
        condition: Condition the velocity on the position posterior (False: ``B = 0``).

    Returns:
        Mean ``(K, 5)`` and covariance ``(K, 5, 5)`` in float64, ``[δx, δy, δh, δv_x, δv_y]``.
    """
    f64 = torch.float64
    # the lattice kernels' moments (`LatticeMoments`, `to_state`), accumulated in float64
    lm = LatticeMoments(pm.weights.index_select(0, index).to(f64),
                        pm.lin_mean.index_select(0, index).to(f64), pm.offsets.to(f64))
    axes = pm.axes.index_select(0, index).to(f64)
    mean_s, cov_s = to_state(lm.u, lm.cu, pm.centre.index_select(0, index).to(f64), axes)
    cov_s = cov_s + pm.policy.deferred_cov(pm).index_select(0, index).to(f64)  # pending Q
    a_bar = lm.mz[:, 0]  # ā = Σ w a
    var_a = pm.lin_cov.index_select(0, index)[:, 0, 0].to(f64) + lm.czz_b[:, 0, 0]
    cov_as = (lm.czu @ axes.transpose(1, 2))[:, 0]  # Σ_as = Σ w (a − ā)(s − s̄)ᵀ, (K, 2)
    ppp, ppv, pvv = ppp.to(f64), ppv.to(f64), pvv.to(f64)
    b = ppv / ppp if condition else torch.zeros_like(ppv)
    bm = torch.diag_embed(b)
    v = v0.to(f64) + b * (mean_s - mp.to(f64))
    cov_vv = torch.diag_embed(pvv - b * b * ppp) + bm @ cov_s @ bm
    cov_vs = bm @ cov_s
    cov_va = b * cov_as
    k = index.numel()
    x = torch.cat([mean_s, a_bar[:, None], v], 1)
    P = torch.zeros(k, N_STATES, N_STATES, dtype=f64, device=axes.device)
    P[:, :2, :2] = cov_s
    P[:, 2, 2] = var_a
    P[:, 2, :2] = cov_as
    P[:, :2, 2] = cov_as
    P[:, 3:, :2] = cov_vs
    P[:, :2, 3:] = cov_vs.transpose(1, 2)
    P[:, 3:, 2] = cov_va
    P[:, 2, 3:] = cov_va
    P[:, 3:, 3:] = cov_vv
    return x, 0.5 * (P + P.transpose(1, 2))


@dataclass
class PoolStep:
    """Per-run results of one `TrackerPool.step` (``(N,)`` each; dormant runs:
    ``updated`` False, ``nis`` NaN, ``residual`` 0)."""

    nis: torch.Tensor
    residual: torch.Tensor
    updated: torch.Tensor


class TrackerPool:
    """One `PointMassTracker` over all N runs; the members are the runs handed off.

    Args:
        n: Runs N.
        P0: ``(5, 5)`` prior covariance of the TAN state (its altitude and velocity blocks
            set the dormant runs' state; the horizontal block is replaced by
            ``dormant_sigma_m²``).
        Q: ``(5, 5)`` process noise per step (``Q_s`` its position block, ``Q_z`` its
            altitude/velocity block; cross terms are not used).
        dt: Filter period T, s.
        config: Tracker lattice options (its lost-track widening is normally disabled:
            the caller's lost-lock test sends a run back to the acquisition grid).
        dtype: Tracker dtype.
        dormant_sigma_m: Horizontal σ of a dormant run's Gaussian (keeps it cheap).
        out_dtype: dtype of `x`, `P`.

    Attributes:
        member: ``(N,)`` bool, runs the tracker is tracking.
        x: ``(N, 5)`` tracker mean of the members (other rows: stale).
        P: ``(N, 5, 5)`` tracker covariance of the members.
        tracker: The `PointMassTracker`.
        cell_updates: Cell measurement updates done for members.
    """

    def __init__(self, n: int, P0: torch.Tensor, Q: torch.Tensor, dt: float,
                 config: TrackerConfig, *,
                 dtype: torch.dtype = torch.float32, dormant_sigma_m: float = 40.0,
                 out_dtype: torch.dtype = torch.float64,
                 device: torch.device | str = "cpu") -> None:
        kw = {"dtype": dtype, "device": device}
        E = torch.tensor([[0.0, dt, 0.0], [0.0, 0.0, dt]], **kw)
        F = torch.eye(3, **kw)
        c = torch.tensor([1.0, 0.0, 0.0], **kw)
        dormant = torch.as_tensor(P0, dtype=torch.float64).clone()
        dormant[:2, :] = 0.0
        dormant[:, :2] = 0.0
        dormant[0, 0] = dormant[1, 1] = dormant_sigma_m**2
        self._dormant_cov = dormant.to(**kw)
        self.tracker = PointMassTracker(torch.zeros(n, N_STATES, **kw), self._dormant_cov,
                                        E=E, F=F, c=c, config=config, dtype=dtype)
        self.member = torch.zeros(n, dtype=torch.bool, device=device)
        self.x = torch.zeros(n, N_STATES, dtype=out_dtype, device=device)
        self.P = torch.zeros(n, N_STATES, N_STATES, dtype=out_dtype, device=device)
        self.cell_updates = 0
        self._n = n
        Q = torch.as_tensor(Q, dtype=torch.float64)
        self._qs = Q[:2, :2].to(**kw)
        self._qz = Q[2:, 2:].to(**kw)

    @property
    def healthy(self) -> torch.Tensor:
        """``(N,)`` bool: not flagged lost by the tracker's guard (non-finite moments)."""
        return ~self.tracker.lost

    def add(self, mask: torch.Tensor, mean: torch.Tensor, cov: torch.Tensor) -> None:
        """Hands runs ``mask (N,)`` to the tracker with ``N(mean (N, 5), cov (N, 5, 5))``
        (rows outside ``mask`` are ignored)."""
        dt = self.tracker.dtype
        m = mask[:, None]
        # round-off guard: the tracker refuses a covariance that is not positive definite
        c64 = 0.5 * (cov + cov.transpose(1, 2)).double()
        lam, vec = torch.linalg.eigh(c64)
        lam = lam.clamp_min(1e-9 * lam.abs().amax(1, keepdim=True).clamp_min(1e-12))
        cov = (vec * lam[:, None, :]) @ vec.transpose(1, 2)
        cov = 0.5 * (cov + cov.transpose(1, 2))
        full_mean = torch.where(m, mean.to(dt), torch.zeros_like(mean, dtype=dt))
        full_cov = torch.where(m[..., None], cov.to(dt), self._dormant_cov.expand_as(cov))
        self.tracker.reset(full_mean, full_cov, mask=mask)
        self.member = self.member | mask
        self.x = torch.where(m, mean.to(self.x.dtype), self.x)
        self.P = torch.where(m[..., None], cov.to(self.P.dtype), self.P)

    def drop(self, mask: torch.Tensor) -> None:
        """Returns runs ``mask (N,)`` to dormancy (a benign Gaussian at the origin)."""
        if not bool(mask.any()):
            return
        dt = self.tracker.dtype
        zero = torch.zeros(self._n, N_STATES, dtype=dt, device=self.member.device)
        self.tracker.reset(zero, self._dormant_cov, mask=mask)
        self.member = self.member & ~mask

    def step(self, ins_xy: torch.Tensor, y: torch.Tensor, heights: Any,
             R: float) -> PoolStep:
        """Predicts every run and updates the members with the altimeter.

        Args:
            ins_xy: ``(N, 2)`` INS horizontal positions of this step.
            y: ``(N,)`` ``h_ins − h_radar``.
            heights: Callable ``(ins_xy (N, 2)) -> g`` with ``g(points (N, G, G, 2))`` the
                map heights at ``p_ins − s`` (NaN off the map), as
                `neuralmap.nav.tracking._heights`.
            R: Measurement variance, m².

        Returns:
            `PoolStep`.
        """
        trk = self.tracker
        trk.predict(Q_s=self._qs, Q_z=self._qz)
        g = heights(ins_xy)(trk.points())
        upd = trk.update(y.to(trk.dtype), g, R=R, mask=self.member)
        self.cell_updates += int(self.member.sum()) * trk.cells**2
        mean, cov = trk.moments()
        m = self.member[:, None]
        self.x = torch.where(m, mean.to(self.x.dtype), self.x)
        self.P = torch.where(m[..., None], cov.to(self.P.dtype), self.P)
        applied = upd.applied & self.member
        nis = torch.where(applied, upd.nis, math.nan).to(self.x.dtype)
        res = torch.where(applied, upd.innovation, 0.0).to(self.x.dtype)
        return PoolStep(nis=nis, residual=res, updated=applied)
