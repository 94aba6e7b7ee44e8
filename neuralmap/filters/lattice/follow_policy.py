"""The ``follow`` lattice policy of the point-mass filter: a lattice that follows the posterior.

The point-mass filter of Bergman, Ljung and Gustafsson run for the whole flight, for N
independent runs at once (no Python loop over runs or cells). The state splits into

* ``s`` (2-D, the nonlinear part: in terrain navigation the horizontal INS error), carried
  by masses ``w (N, G, G)`` on an affine lattice: cell ``(i, j)`` (row ``i``, column ``j``)
  sits at ``centre + A · (j − h, i − h)``, ``h = (G − 1)/2``, ``A (N, 2, 2)`` the two cell
  steps as columns (axis-aligned or along the posterior's principal axes);
* ``z`` (``nz``-D, the conditionally linear part: altitude and velocity errors), a Gaussian
  per cell (Rao-Blackwellised): ``z | cell ~ N(μ_cell, P)`` with ``μ (N, nz, G, G)`` and a
  conditional covariance ``P (N, nz, nz)`` common to the run's cells (exact for the linear
  Gaussian model, where the conditional covariance does not depend on ``s``).

Model::

    s_{k+1} = s_k + E z_k + u_k + w_s,   w_s ~ N(0, Q_s)
    z_{k+1} = F z_k + w_z,               w_z ~ N(0, Q_z)
    y_k     = g(s_k) + c·z_k + e_k,      e_k ~ N(0, R)

with ``g`` given per cell by the caller (a callable on the cell coordinates, e.g. a
`TerrainModel` lookup — a grid or a neural map).

**Update** (per cell, a Kalman update of ``z``): ``ν = y − g − c·μ``, ``S = cᵀPc + R`` (the
same in every cell), ``log w += −½ ν²/S``, ``μ += K ν``, ``P ← P − K S Kᵀ`` with
``K = P c / S``. A run whose likelihood vanishes in every cell keeps its prior masses
(counted in `PointMassTracker.recoveries`; never NaN).

**Prediction** (exact in its first two moments). The shift ``E μ_cell`` of each cell is
split by weighted least squares into an affine part ``D̄ + B (s − s̄)`` and a residual δ;
the affine part moves the lattice itself (``A ← (I + B) A``, no interpolation), the
residual and the transition noise ``E P Eᵀ + Q_s + Cov_w(δ)`` are convolved into the
masses (separable kernels along the lattice axes, `
gaussian_kernels`), and the per-cell ``z`` is carried by convolving ``w · (Fμ − L s)``
with ``L = F P Eᵀ Σ_η⁻¹`` (the Gaussian conditional of ``z'`` on ``s'``). The exact
predicted moments of the whole state — ``s̄ + D̄ + u``, ``Cov(s + E z) + Q_s``, ``F z̄``,
``F Cov(z) Fᵀ + Q_z`` and ``Cov(s + E z, F z)`` — are then imposed by a moment
correction (below), so the part of the kernel the separable convolution leaves out
(its cross-axis covariance) and the residual-as-noise approximation change only the
shape beyond the covariance, never the mean or covariance.

**Grid following the posterior** (`PointMassTracker.regrid`): after each update a
run moves to a new lattice centred on its mean, with cell steps ``span_sigma · σ_k / h``
along each axis ``k`` (the principal axes of its covariance when ``principal_axes``,
else x and y) — i.e. the spacing is ``1 / spacing_per_sigma`` of σ — when its mean left
the central ``recentre_fraction`` of the lattice, its ``± regrid_sigma σ`` box pokes out
(hysteresis: built for ``± span_sigma σ``),
or it needs less than ``1 / resize_ratio`` of the lattice. Masses and ``w μ`` are
resampled bilinearly (density interpolation), then the moment correction restores the
pre-regrid moments. Guard against collapse: the half-width is never below
``span_sigma · sqrt(σ² + q)`` (q: the next step's process noise) nor ``min_half_width``.

**Moment correction** (`PointMassTracker.match_moments`): the lattice is moved by
the affine map ``s ↦ m_t + T (s − m)`` with ``T = C^{-1/2}(C^{1/2} C_t C^{1/2})^{1/2}C^{-1/2}``
(the symmetric map closest to the identity taking covariance C to C_t), which gives the
masses mean ``m_t`` and covariance ``C_t`` exactly (an affine image of a discrete
distribution); the per-cell means get ``μ ← μ + Δz̄ + G (s − m_t)`` so that ``z̄`` and
``Cov(z, s)`` match, and ``P ← Cov_t(z) − Cov_w(μ)``. Mean and covariance are conserved to
round-off (float64: ≤ 1e-9 of σ; tested against a fine fixed-grid reference).

**Lost track**: the mean NIS over the last ``lost_window`` updates above
``χ²_{lost_prob}(W) / W`` widens the run's grid. The first ``local_widenings`` times it is a
Gaussian around the run's mean with the covariance times ``widen_factor²``, at least
``widen_min_sigma`` per axis (a track that slipped by a few σ); after that the run
**re-acquires from the open-loop prior** ``N(m_ol, P_ol)``: the prior propagated through
every prediction with no measurement (``m_ol ← A m_ol + u``, ``P_ol ← A P_ol Aᵀ + Q`` with
``A = [[I, E], [0, F]]``), i.e. the dead-reckoning bound of the error, which holds the
truth wherever the grid lost it (a track that locked onto a wrong terrain match
kilometres away). A run widened more than ``max_widenings`` times, or whose covariance
stops being finite, is flagged ``lost`` (counted and reported; its estimate is held,
never NaN). A tracker started mid-flight gets the open-loop prior of the original prior
from `PointMassTracker.set_open_loop`.

The measurement update is the lattice filter's (`neuralmap.filters.lattice.filter`,
shared with the acquisition grid); this policy adds the NIS report, the lost-track test
and the regrid after the update, its weight floor (relative to the peak, renormalised),
and implements the prediction, the regrid and the Gaussian lattice of a prior. The 2 × 2
moment-correction map is computed in float64 in both dtypes: from a float32 eigh an
elongated posterior's map could collapse the lattice.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.filters.lattice.algebra2 import eigh2, eigvalsh2, inv2, solve2, spd2_ok, sqrtm2
from neuralmap.filters.lattice.kernels import (
    LatticeMoments,
    affine_field,
    blur,
    conditional_mean,
    gaussian_log_density,
    normalised,
    resample_bilinear,
)

if TYPE_CHECKING:
    from neuralmap.filters.lattice.filter import LatticeFilter

__all__ = ["BLUR_MIN_CELLS", "MIN_CELL_VARIANCE", "FollowLattice", "TrackerConfig"]

#: Transition noise below this many cells (1σ, every run and axis) is left to the moment
#: correction alone (an affine stretch of the lattice) instead of a blur.
BLUR_MIN_CELLS = 1e-3

#: Smallest variance (cells², along any direction) of masses the moment correction may
#: stretch; a narrower posterior is replaced by its Gaussian fit on a fresh lattice.
MIN_CELL_VARIANCE = 0.25

#: Floor of the log ratio posterior / Gaussian fit in a regrid (relative to its peak).
_LOG_R_FLOOR = -60.0


@dataclass
class TrackerConfig:
    """Options of `PointMassTracker`.

    Attributes:
        cells: Lattice cells per axis ``G`` (≥ 8).
        span_sigma: Lattice half-width in posterior standard deviations per axis; the cell
            step is ``span_sigma · σ / h`` (``h = (G−1)/2``): with the defaults (32 cells,
            5 σ) a cell is σ / 3.1.
        principal_axes: Align the lattice with the posterior's principal axes.
        recentre_fraction: Regrid when the mean is farther from the centre than this
            fraction of the half-width along a lattice axis.
        regrid_sigma: Regrid when the posterior's ``± regrid_sigma σ`` box pokes out of the
            lattice (hysteresis: a lattice is built for ``± span_sigma σ`` and kept while the
            smaller box fits; None = ``span_sigma``, no hysteresis).
        resize_ratio: Regrid when the posterior needs less than ``1/resize_ratio`` of the
            lattice's half-width along an axis (keeps the cells a fixed fraction of σ).
        min_half_width: Smallest half-width (state units) of a lattice axis.
        max_spacing: Largest cell step allowed (state units; None = unbounded): a prior
            whose grid would need coarser cells raises (use more cells).
        weight_floor: Masses below ``weight_floor × max`` are raised to it after an update.
        lost_window: Updates in the lost-track NIS window (0 disables widening).
        lost_prob: χ² probability of the lost-track threshold.
        widen_factor: Standard-deviation factor of a widened grid.
        widen_min_sigma: Smallest per-axis σ of a widened grid (state units).
        local_widenings: Widenings around the run's own mean before a lost run re-acquires
            from the open-loop prior (module docstring).
        max_widenings: Widenings after which a run counts as lost beyond recovery.
    """

    cells: int = 32
    span_sigma: float = 5.0
    principal_axes: bool = True
    recentre_fraction: float = 0.1
    regrid_sigma: float | None = 4.0
    resize_ratio: float = 1.5
    min_half_width: float = 0.0
    max_spacing: float | None = None
    weight_floor: float = 0.0
    lost_window: int = 10
    lost_prob: float = 0.9999
    widen_factor: float = 3.0
    widen_min_sigma: float = 50.0
    local_widenings: int = 2
    max_widenings: int = 4

    def validate(self) -> TrackerConfig:
        """Checks ranges; raises `NeuralMapError` naming the bad option."""

        def bad(key: str, need: str) -> NeuralMapError:
            return NeuralMapError(f"TrackerConfig: '{key}' must be {need}, got {getattr(self, key)!r}.")

        if isinstance(self.cells, bool) or not isinstance(self.cells, int) or self.cells < 8:
            raise bad("cells", "an integer >= 8")
        h = 0.5 * (self.cells - 1)
        if not 1.0 <= self.span_sigma <= h:
            raise bad("span_sigma", f"in [1, (cells-1)/2 = {h:g}] (a cell at most 1 σ wide)")
        if not 0.0 < self.recentre_fraction < 1.0:
            raise bad("recentre_fraction", "in (0, 1)")
        if self.regrid_sigma is not None and not 1.0 <= self.regrid_sigma <= self.span_sigma:
            raise bad("regrid_sigma", f"None or in [1, span_sigma = {self.span_sigma:g}]")
        if not self.resize_ratio > 1.0:
            raise bad("resize_ratio", "> 1")
        if not self.min_half_width >= 0.0:
            raise bad("min_half_width", ">= 0")
        if self.max_spacing is not None and not self.max_spacing > 0.0:
            raise bad("max_spacing", "None or > 0")
        if not 0.0 <= self.weight_floor < 1e-3:
            raise bad("weight_floor", "in [0, 1e-3)")
        for key in ("lost_window", "local_widenings", "max_widenings"):
            v = getattr(self, key)
            if isinstance(v, bool) or not isinstance(v, int) or v < 0:
                raise bad(key, "an integer >= 0")
        if not 0.0 < self.lost_prob < 1.0:
            raise bad("lost_prob", "in (0, 1)")
        if not self.widen_factor >= 1.0:
            raise bad("widen_factor", ">= 1")
        if not self.widen_min_sigma >= 0.0:
            raise bad("widen_min_sigma", ">= 0")
        return self


@functools.lru_cache(maxsize=32)
def _chi2_mean_threshold(prob: float, window: int) -> float:
    """``χ²_prob(W) / W``: the mean NIS of W consistent updates exceeds it with 1 − prob."""
    from scipy.stats import chi2

    return float(chi2.ppf(prob, window)) / window


def _sym(m: torch.Tensor) -> torch.Tensor:
    return 0.5 * (m + m.transpose(-1, -2))


def _cholesky_ok(c: torch.Tensor) -> torch.Tensor:
    """``(N,)`` bool: finite, symmetric and positive definite (2 × 2: closed form)."""
    if c.shape[-1] == 2:
        return spd2_ok(c)
    finite = torch.isfinite(c).flatten(1).all(1)
    safe = torch.where(finite[:, None, None], c, torch.eye(c.shape[-1], dtype=c.dtype,
                                                          device=c.device))
    sym = (safe - safe.transpose(1, 2)).abs().flatten(1).amax(1) <= (
        1e-9 * safe.abs().flatten(1).amax(1) + 1e-300)
    return finite & sym & (torch.linalg.cholesky_ex(safe.double()).info == 0)


class FollowLattice:
    """The ``follow`` lattice policy (module docstring) of a `LatticeFilter`.

    Args:
        config: `TrackerConfig`.
        n_runs: Runs N.
        nz: Linear states per cell.
        dtype, device: Of the filter.

    Attributes:
        widenings: ``(N,)`` int64, lost-track widenings.
        lost: ``(N,)`` bool, lost beyond recovery (module docstring).
    """

    reports_nis = True
    outlier_prob, outlier_width = 0.0, 1000.0

    def __init__(self, config: TrackerConfig, n_runs: int, nz: int, dtype: torch.dtype,
                 device: torch.device) -> None:
        self.config = config.validate()
        kw = {"dtype": dtype, "device": device}
        self.widenings = torch.zeros(n_runs, dtype=torch.int64, device=device)
        self.lost = torch.zeros(n_runs, dtype=torch.bool, device=device)
        self._nis_win = torch.zeros(n_runs, self.config.lost_window or 1, **kw)
        self._nis_count = torch.zeros(n_runs, dtype=torch.int64, device=device)
        self._step = 0
        self._q_next = torch.zeros(n_runs, 2, **kw)
        self._open_mean = torch.zeros(n_runs, 2 + nz, **kw)
        self._open_cov = torch.zeros(n_runs, 2 + nz, 2 + nz, **kw)

    _PER_RUN = ("widenings", "lost", "_nis_win", "_nis_count", "_q_next", "_open_mean",
                "_open_cov")

    def take(self, index: torch.Tensor) -> FollowLattice:
        out = object.__new__(FollowLattice)
        out.__dict__.update(self.__dict__)
        for name in self._PER_RUN:
            setattr(out, name, getattr(self, name).index_select(0, index))
        return out

    def cat(self, other: FollowLattice) -> FollowLattice:
        out = object.__new__(FollowLattice)
        out.__dict__.update(self.__dict__)
        for name in self._PER_RUN:
            setattr(out, name, torch.cat([getattr(self, name), getattr(other, name)]))
        return out

    def deferred_cov(self, f: LatticeFilter) -> None:
        """None: every prediction is applied to the lattice at once."""
        return None

    # ------------------------------------------------------------------ set-up
    def reset(self, f: LatticeFilter, mean: torch.Tensor, cov: torch.Tensor, mask: torch.Tensor | None = None) -> None:
        """(Re-)initialises runs from a Gaussian prior ``N(mean, cov)`` over ``[s, z]``.

        Args:
            mean: ``(N, 2 + nz)``.
            cov: ``(2+nz, 2+nz)`` or ``(N, 2+nz, 2+nz)``, symmetric positive definite.
            mask: ``(N,)`` bool, runs to reset (None = all).

        Raises:
            NeuralMapError: ``cov`` not positive definite (names the first bad run); a prior
                that needs cells coarser than ``max_spacing``.
        """
        n, d, kw = f.n_runs, 2 + f.nz, {"dtype": f.dtype, "device": f.device}
        mean = torch.as_tensor(mean, **kw).expand(n, d)
        cov = torch.as_tensor(cov, **kw)
        if tuple(cov.shape) not in ((d, d), (n, d, d)):
            raise NeuralMapError(
                f"PointMassTracker: cov must have shape ({d}, {d}) or ({n}, {d}, {d}), got "
                f"{tuple(cov.shape)}.")
        cov = cov.expand(n, d, d)
        if not bool(torch.isfinite(mean).all()):
            raise NeuralMapError("PointMassTracker: the prior mean has non-finite entries.")
        ok = _cholesky_ok(cov)
        if not bool(ok.all()):
            first = int((~ok).nonzero()[0])
            raise NeuralMapError(
                f"PointMassTracker: the prior covariance of run {first} is not symmetric "
                f"positive definite (diagonal {cov[first].diagonal().tolist()}). Pass variances "
                "> 0 and correlations inside (-1, 1).")
        full = self._gaussian_state(f, mean, cov)
        if mask is None:
            f.set_state(*full)
        else:
            f.set_rows(mask, *full)

    def set_open_loop(self, f: LatticeFilter, mean: torch.Tensor, cov: torch.Tensor) -> None:
        """Sets the open-loop prior ``N(m_ol, P_ol)`` a lost run re-acquires from (module
        docstring); the constructor sets it to the prior. A tracker started mid-flight (from
        another filter's posterior) passes the original prior propagated to now.

        Args:
            mean: ``(2 + nz,)`` or ``(N, 2 + nz)``.
            cov: ``(2+nz, 2+nz)`` or ``(N, 2+nz, 2+nz)``, symmetric positive definite.

        Raises:
            NeuralMapError: Bad shapes, non-finite entries or ``cov`` not positive definite.
        """
        n, d, kw = f.n_runs, 2 + f.nz, {"dtype": f.dtype, "device": f.device}
        mean = torch.as_tensor(mean, **kw)
        cov = torch.as_tensor(cov, **kw)
        if tuple(mean.shape) not in ((d,), (n, d)) or tuple(cov.shape) not in ((d, d), (n, d, d)):
            raise NeuralMapError(
                f"PointMassTracker.set_open_loop: mean must have shape ({d},) or ({n}, {d}) and "
                f"cov ({d}, {d}) or ({n}, {d}, {d}); got {tuple(mean.shape)}, "
                f"{tuple(cov.shape)}.")
        cov = _sym(cov.expand(n, d, d))
        if not bool(torch.isfinite(mean).all()) or not bool(_cholesky_ok(cov).all()):
            raise NeuralMapError("PointMassTracker.set_open_loop: the open-loop prior must be "
                                 "finite with a symmetric positive definite covariance.")
        self._open_mean = mean.expand(n, d).clone()
        self._open_cov = cov.clone()

    def open_loop(self, f: LatticeFilter) -> tuple[torch.Tensor, torch.Tensor]:
        """The open-loop prior ``(m_ol (N, 2+nz), P_ol (N, 2+nz, 2+nz))`` (module docstring)."""
        return self._open_mean, self._open_cov

    def _predict_open_loop(self, f: LatticeFilter, qs: torch.Tensor, qz: torch.Tensor, u: torch.Tensor) -> None:
        """``m_ol ← A m_ol + u``, ``P_ol ← A P_ol Aᵀ + blkdiag(Q_s, Q_z)``, ``A = [[I, E],
        [0, F]]``: the prior through one prediction without a measurement."""
        A = torch.eye(2 + f.nz, dtype=f.dtype, device=f.device)  # [[I, E], [0, F]]
        A[:2, 2:] = f.E
        A[2:, 2:] = f.F
        m = self._open_mean @ A.T
        m[:, :2] += u
        P = A @ self._open_cov @ A.T
        P[:, :2, :2] += qs
        P[:, 2:, 2:] += qz
        self._open_mean = m
        self._open_cov = _sym(P)

    def _gaussian_state(self, f: LatticeFilter, mean: torch.Tensor, cov: torch.Tensor,
                        q: torch.Tensor | None = None) -> tuple[torch.Tensor, ...]:
        """Lattice, masses and linear part of ``N(mean, cov)`` (moments matched exactly)."""
        ms, mz = mean[:, :2], mean[:, 2:]
        css, czs, czz = cov[:, :2, :2], cov[:, 2:, :2], cov[:, 2:, 2:]
        centre, axes = self._lattice_for(f, ms, css, torch.zeros_like(ms) if q is None else q)
        inv_a = inv2(axes)
        cu = _sym(inv_a @ css @ inv_a.transpose(1, 2))
        w = normalised(self._log_gauss(f, torch.zeros_like(ms), cu))
        gu = czs @ solve2(css, axes)  # (N, nz, 2): z-gain per cell step
        mu = mz[:, :, None, None] + self._affine(f, gu, torch.zeros_like(ms))
        P = _sym(czz - czs @ solve2(css, czs.transpose(1, 2)))
        return self._matched(f, (w, mu, P, centre, axes), ms, css, mz, czz, czs, fallback=False)

    def _lattice_for(self, f: LatticeFilter, mean: torch.Tensor, cov: torch.Tensor,
                     q: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Centre ``(N, 2)`` and cell steps ``(N, 2, 2)`` of a lattice for ``N(mean, cov)``;
        ``q (N, 2)``: process noise of the next step (collapse guard)."""
        cfg = self.config
        if cfg.principal_axes:
            lam, vec = eigh2(_sym(cov))
            qa = torch.einsum("nki,nk->ni", vec * vec, q)  # q projected on the axes
        else:
            lam = torch.diagonal(cov, dim1=1, dim2=2)
            vec = torch.eye(2, dtype=cov.dtype, device=cov.device).expand_as(cov)
            qa = q
        halfw = (cfg.span_sigma * (lam.clamp_min(0.0) + qa).sqrt()).clamp_min(cfg.min_half_width)
        step = halfw / f.half
        if cfg.max_spacing is not None and bool((step > cfg.max_spacing * (1 + 1e-9)).any()):
            bad = int((step > cfg.max_spacing * (1 + 1e-9)).any(1).nonzero()[0])
            raise NeuralMapError(
                f"PointMassTracker: run {bad} needs cells of {step[bad].max().item():.4g} to hold "
                f"± {cfg.span_sigma:g} σ on {f.cells} cells, above max_spacing "
                f"{cfg.max_spacing:g}. Increase 'cells' (or max_spacing).")
        if not bool(torch.isfinite(step).all()) or not bool((step > 0).all()):
            raise NeuralMapError("PointMassTracker: a lattice with zero or non-finite cells; the "
                                 "covariance must be finite and positive definite.")
        return mean.clone(), vec * step[:, None, :]

    # ------------------------------------------------------------------ lattice helpers
    def _log_gauss(self, f: LatticeFilter, u: torch.Tensor, cu: torch.Tensor) -> torch.Tensor:
        """``(N, G, G)`` ``log N(o; u, cu)`` in cell coordinates (`gaussian_log_density`)."""
        return gaussian_log_density(f._off, u, cu)

    def _affine(self, f: LatticeFilter, g: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
        """``(N, nz, G, G)`` ``g · (o − u)`` for ``g (N, nz, 2)`` (`affine_field`)."""
        return affine_field(f._off, g, u)

    def _set_subset(self, f: LatticeFilter, mask: torch.Tensor, mean: torch.Tensor, cov: torch.Tensor) -> None:
        """Runs ``mask (N,)`` restart from ``N(mean, cov)`` (``(N, d)``, ``(N, d, d)``); the
        Gaussian lattice is built for those runs only (each run's is independent)."""
        idx = mask.nonzero().reshape(-1)
        gauss = self._gaussian_state(f, mean.index_select(0, idx), cov.index_select(0, idx))
        state = tuple(t.index_copy(0, idx, g) for t, g in zip(f.state(), gauss,
                                                              strict=True))
        f.set_state(*state)

    # ------------------------------------------------------------------ moments
    def _matched(self, f: LatticeFilter, state: tuple[torch.Tensor, ...], ms_t, css_t, mz_t, czz_t, czs_t,
                 fallback: bool = True) -> tuple[torch.Tensor, ...]:
        """``state`` with its moments set to the targets exactly (module docstring).

        A run whose masses sit in fewer cells than an affine map can stretch (covariance
        below ``MIN_CELL_VARIANCE`` cells² along an axis: a posterior narrower than the
        cells) gets the Gaussian with the target moments on a fresh lattice instead.
        """
        w, mu, P, centre, axes = state
        lm = f.lattice_moments(w, mu)
        thin = eigvalsh2(lm.cu)[:, 0] < MIN_CELL_VARIANCE
        if fallback and bool(thin.any()):
            idx = thin.nonzero().reshape(-1)
            mean_t = torch.cat([ms_t, mz_t], 1).index_select(0, idx)
            cov_t = torch.cat([torch.cat([css_t, czs_t.transpose(1, 2)], 2),
                               torch.cat([czs_t, czz_t], 2)], 1).index_select(0, idx)
            gauss = self._gaussian_state(f, mean_t, _sym(cov_t))
            state = tuple(t.index_copy(0, idx, g) for t, g in zip(state, gauss, strict=True))
            w, mu, P, centre, axes = state
            lm = f.lattice_moments(w, mu)
        css = _sym(axes @ lm.cu @ axes.transpose(1, 2))
        # the 2 x 2 map in float64: a float32 eigh of an elongated posterior (condition ~1e4)
        # returns a small eigenvalue at round-off level and T would collapse the lattice
        c64, ct64 = css.double(), css_t.double()
        lam, vec = eigh2(_sym(c64))
        lam = lam.clamp_min(torch.finfo(torch.float64).tiny)
        root = (vec * lam.sqrt()[:, None, :]) @ vec.transpose(1, 2)
        iroot = (vec * lam.rsqrt()[:, None, :]) @ vec.transpose(1, 2)
        T = (iroot @ sqrtm2(_sym(root @ ct64 @ root)) @ iroot).to(w.dtype)
        ok = torch.isfinite(T).flatten(1).all(1) & _cholesky_ok(css) & _cholesky_ok(_sym(css_t))
        eye = torch.eye(2, dtype=w.dtype, device=w.device).expand_as(T)
        T = torch.where(ok[:, None, None], T, eye)
        axes = T @ axes
        centre = ms_t - (axes @ lm.u[:, :, None]).squeeze(-1)
        # z: mean shift and a per-cell-step gain gu so that Cov(z, s) hits its target
        want = solve2(axes, czs_t.transpose(1, 2)).transpose(1, 2)  # czs_t A^-T
        gu = solve2(lm.cu, (want - lm.czu).transpose(1, 2)).transpose(1, 2)
        mu = mu + (mz_t - lm.mz)[:, :, None, None] + self._affine(f, gu, lm.u)
        czz_b = (lm.czz_b + gu @ lm.czu.transpose(1, 2) + lm.czu @ gu.transpose(1, 2)
                 + gu @ lm.cu @ gu.transpose(1, 2))
        P = _sym(czz_t - czz_b)
        if P.shape[-1] == 1:  # closed forms for one and two linear states
            lam, vec = P[:, :, 0], torch.ones_like(P)
        elif P.shape[-1] == 2:
            lam, vec = eigh2(P)
        else:
            lam, vec = torch.linalg.eigh(P)
        floor = 1e-12 * lam.abs().amax(-1, keepdim=True).clamp_min(1e-300)
        if bool((lam < floor).any()):  # round-off: keep the Kalman part positive definite
            P = _sym((vec * lam.clamp_min(floor)[:, None, :]) @ vec.transpose(1, 2))
        return w, mu, P, centre, axes

    def match_moments(self, f: LatticeFilter, mean: torch.Tensor, cov: torch.Tensor) -> None:
        """Imposes mean ``(N, 2+nz)`` and covariance ``(N, 2+nz, 2+nz)`` exactly (affine
        lattice map + per-cell linear-part shift; module docstring)."""
        f.set_state(*self._matched(f, f.state(), mean[:, :2], cov[:, :2, :2], mean[:, 2:],
                                 cov[:, 2:, 2:], cov[:, 2:, :2]))

    def _refit_thin(self, f: LatticeFilter) -> LatticeMoments:
        """Runs whose masses sit in too few cells (``MIN_CELL_VARIANCE``): their Gaussian
        fit, with the cells' own spread ``A Aᵀ / 12`` added, on a fresh lattice; returns the
        lattice moments of the state."""
        lm = f.lattice_moments(f.weights, f.lin_mean)
        thin = eigvalsh2(lm.cu)[:, 0] < MIN_CELL_VARIANCE
        if not bool(thin.any()):
            return lm
        idx = thin.nonzero().reshape(-1)
        axes = f.axes.index_select(0, idx)
        cu = lm.cu.index_select(0, idx) + torch.eye(2, dtype=f.dtype,
                                                    device=f.device) / 12.0
        ms = f.centre.index_select(0, idx) + (axes @ lm.u[idx, :, None]).squeeze(-1)
        css = _sym(axes @ cu @ axes.transpose(1, 2))
        czs = lm.czu.index_select(0, idx) @ axes.transpose(1, 2)
        czz = _sym(f.lin_cov.index_select(0, idx) + lm.czz_b.index_select(0, idx))
        mean = torch.cat([ms, lm.mz.index_select(0, idx)], 1)
        cov = torch.cat([torch.cat([css, czs.transpose(1, 2)], 2), torch.cat([czs, czz], 2)], 1)
        gauss = self._gaussian_state(f, mean, _sym(cov))
        for name, value in zip(("weights", "lin_mean", "lin_cov", "centre", "axes"), gauss,
                               strict=True):
            getattr(f, name).index_copy_(0, idx, value)
        f.regrids += thin.long()
        return f.lattice_moments(f.weights, f.lin_mean)

    # ------------------------------------------------------------------ predict
    def predict(self, f: LatticeFilter, *, Q_s: torch.Tensor, Q_z: torch.Tensor,
                shift: torch.Tensor | None = None) -> None:
        """Time update of the model in the module docstring.

        Args:
            Q_s: ``(2, 2)`` or ``(N, 2, 2)`` process noise of ``s``.
            Q_z: ``(nz, nz)`` or ``(N, nz, nz)`` process noise of ``z``.
            shift: ``(N, 2)`` known displacement ``u`` of ``s`` (None = 0).
        """
        n, nz = f.n_runs, f.nz
        kw = {"dtype": f.dtype, "device": f.device}
        qs = torch.as_tensor(Q_s, **kw).expand(n, 2, 2)
        qz = torch.as_tensor(Q_z, **kw).expand(n, nz, nz)
        lm = self._refit_thin(f)
        w, mu, P, centre, axes = f.state()
        ms, css, mz, czz, czs = f.state_moments(lm)
        E, F = f.E, f.F
        # exact predicted moments
        u = torch.zeros(n, 2, **kw) if shift is None else torch.as_tensor(shift, **kw).expand(n, 2)
        ms_t = ms + mz @ E.T + u
        csz = czs.transpose(1, 2)
        css_t = _sym(css + E @ czs + csz @ E.T + E @ czz @ E.T + qs)
        mz_t = mz @ F.T
        czz_t = _sym(F @ czz @ F.T + qz)
        czs_t = F @ (czs + czz @ E.T)
        # the per-cell z mean = its affine fit in the cell coordinates + a residual; the
        # affine part of the shift E μ moves the lattice (exact), the residual's spread is
        # transition noise
        gzu = solve2(lm.cu, lm.czu.transpose(1, 2)).transpose(1, 2)  # (N, nz, 2)
        cz_res = _sym(lm.czz_b - gzu @ lm.czu.transpose(1, 2))
        B_u = E @ gzu  # shift per cell step (N, 2, 2)
        axes_new = axes + B_u
        centre_new = ms_t - (axes_new @ lm.u[:, :, None]).squeeze(-1)
        sig_eta = _sym(E @ P @ E.T + qs + E @ cz_res @ E.T)
        # blur by separable kernels of exact variance along the lattice axes; the cross-axis
        # part and any remainder are carried by the moment correction (an affine stretch)
        inv_a = inv2(axes_new)
        k_cells = inv_a @ sig_eta @ inv_a.transpose(1, 2)
        var_c = torch.diagonal(k_cells, dim1=1, dim2=2).clamp_min(0.0)  # (N, 2) x, y
        w_new, mu_new = w, mu
        if float(var_c.max()) >= BLUR_MIN_CELLS**2:
            affine = mz[:, :, None, None] + self._affine(f, gzu, lm.u)
            chans = blur(torch.cat([w[:, None], w[:, None] * (mu - affine)], 1), var_c.sqrt())
            mass = chans[:, 0].clamp_min(0.0)
            w_new = mass / mass.sum((1, 2), keepdim=True).clamp_min(torch.finfo(f.dtype).tiny)
            mu_new = conditional_mean(mass, chans[:, 1:]) + affine
        if not f._f_identity:
            mu_new = torch.einsum("yz,nzij->nyij", F, mu_new)
        state = self._matched(f, (w_new, mu_new, P, centre_new, axes_new), ms_t, css_t, mz_t,
                              czz_t, czs_t)
        f.set_state(*state)
        self._guard(f, torch.isfinite(ms_t).all(1) & _cholesky_ok(css_t) & _cholesky_ok(czz_t))
        self._q_next = torch.diagonal(qs + E @ P @ E.T, dim1=1, dim2=2)
        self._predict_open_loop(f, qs, qz, u)

    # ------------------------------------------------------------------ update
    def after_update(self, f: LatticeFilter, nis: torch.Tensor | None, applied: torch.Tensor,
                     regrid: bool) -> torch.Tensor:
        """The lost-track test on the update's NIS, then the regrid (``regrid``); returns
        ``(N,)`` bool, runs widened."""
        widened = self._lost_test(f, nis, applied)
        if regrid:
            self.regrid(f)
        return widened

    def floor_weights(self, w: torch.Tensor) -> torch.Tensor:
        """Masses below ``weight_floor × max`` raised to it, renormalised."""
        if self.config.weight_floor > 0:
            w = w.clamp_min(self.config.weight_floor * w.amax((1, 2), keepdim=True))
            w = w / w.sum((1, 2), keepdim=True)
        return w

    def _lost_test(self, f: LatticeFilter, nis: torch.Tensor, active: torch.Tensor) -> torch.Tensor:
        """Widens runs whose mean NIS over the window says the track is lost: around their
        mean for the first ``local_widenings`` times, then to the open-loop prior."""
        cfg = self.config
        widened = torch.zeros_like(active)
        if cfg.lost_window <= 0:
            return widened
        slot = self._step % cfg.lost_window
        self._step += 1
        self._nis_win[:, slot] = torch.where(active, nis, self._nis_win[:, slot])
        self._nis_count += active.long()
        full = self._nis_count >= cfg.lost_window
        thr = _chi2_mean_threshold(cfg.lost_prob, cfg.lost_window)
        widened = full & (self._nis_win.mean(1) > thr) & ~self.lost
        if bool(widened.any()):
            mean, cov = f.moments()
            d = cov.shape[-1]
            infl = cov.clone()
            infl[:, :2, :2] = cov[:, :2, :2] * cfg.widen_factor**2 + torch.eye(
                2, dtype=cov.dtype, device=cov.device) * cfg.widen_min_sigma**2
            infl = _sym(infl + 1e-9 * torch.eye(d, dtype=cov.dtype, device=cov.device))
            ok = _cholesky_ok(infl)
            infl = torch.where(ok[:, None, None], infl, torch.eye(d, dtype=cov.dtype,
                                                                  device=cov.device))
            # local widenings first; then re-acquire from the open-loop prior
            reacquire = widened & (self.widenings >= cfg.local_widenings)
            mean = torch.where(reacquire[:, None], self._open_mean, mean)
            infl = torch.where(reacquire[:, None, None], self._open_cov, infl)
            self._set_subset(f, widened, mean, infl)
            self.widenings += widened.long()
            self._nis_count = torch.where(widened, 0, self._nis_count)
            self.lost |= self.widenings > cfg.max_widenings
        return widened

    # ------------------------------------------------------------------ regrid
    def regrid(self, f: LatticeFilter, force: torch.Tensor | None = None) -> torch.Tensor:
        """Moves runs whose posterior no longer fits their lattice (module docstring).

        Args:
            force: ``(N,)`` bool, runs to move regardless of the rule.

        Returns:
            ``(N,)`` bool, runs moved.
        """
        cfg = self.config
        lm = self._refit_thin(f)
        w, mu, P, centre, axes = f.state()
        inv_a = inv2(axes)
        u, k = lm.u, lm.cu  # mean and covariance in cells
        sig = torch.diagonal(k, dim1=1, dim2=2).clamp_min(0.0).sqrt()
        qc = torch.diagonal(inv_a @ torch.diag_embed(self._q_next) @ inv_a.transpose(1, 2),
                            dim1=1, dim2=2)
        need = cfg.span_sigma * (sig**2 + qc).sqrt()
        h = f.half
        rho = k[:, 0, 1] / (sig[:, 0] * sig[:, 1]).clamp_min(1e-300)
        off_centre = (u.abs() > cfg.recentre_fraction * h).any(1)
        box = need if cfg.regrid_sigma is None else need * (cfg.regrid_sigma / cfg.span_sigma)
        pokes_out = (u.abs() + box > h * (1 + 1e-6)).any(1)
        too_coarse = (need * cfg.resize_ratio < h).any(1)
        if cfg.min_half_width > 0:  # a guarded lattice at its floor is not "too coarse"
            floor_cells = cfg.min_half_width / torch.linalg.norm(axes, dim=1)
            too_coarse = too_coarse & ~(floor_cells >= h * (1 - 1e-6)).all(1)
        move = off_centre | pokes_out | too_coarse | ~torch.isfinite(need).all(1)
        if cfg.principal_axes:
            move = move | (rho.abs() > 0.5)
        if force is not None:
            move = move | force
        move = move & _cholesky_ok(lm.cu)
        if not bool(move.any()):
            return move
        every = bool(move.all())  # the common case while a posterior shrinks: no copies
        idx = move.nonzero().reshape(-1)

        def rows(t: torch.Tensor) -> torch.Tensor:
            return t if every else t.index_select(0, idx)

        w_o, mu_o, P_o, c_o, a_o = (rows(t) for t in (w, mu, P, centre, axes))
        u_o, cu_o = rows(u), rows(k)
        czu_o, mz_o = rows(lm.czu), rows(lm.mz)
        ms = c_o + (a_o @ u_o[:, :, None]).squeeze(-1)
        css = _sym(a_o @ cu_o @ a_o.transpose(1, 2))
        czs = czu_o @ a_o.transpose(1, 2)
        czz = _sym(P_o + rows(lm.czz_b))
        c_n, a_n = self._lattice_for(f, ms, css, rows(self._q_next))
        # old cell coordinates of the new cells: o_old = A_o⁻¹ (c_n − c_o) + A_o⁻¹ A_n o
        ia_o = inv2(a_o)
        base = (ia_o @ (c_n - c_o)[:, :, None]).squeeze(-1)
        lin = ia_o @ a_n
        o = f._off
        uv = (base[:, None, None, :] + lin[:, None, None, :, 0] * o[None, None, :, None]
              + lin[:, None, None, :, 1] * o[None, :, None, None]) / h
        # Gaussian-factored resampling: w = N(o; u, C_u) · r(o); the Gaussian factor is
        # evaluated exactly at the new cells, only log r (0 for a Gaussian posterior) and
        # the residual of the per-cell means from their affine fit (0 for a linear-Gaussian
        # model) are interpolated bilinearly: a Gaussian posterior moves without error
        tiny = torch.finfo(f.dtype).tiny
        log_r = w_o.clamp_min(tiny).log() - self._log_gauss(f, u_o, cu_o)
        log_r = (log_r - log_r.amax((1, 2), keepdim=True)).clamp_min(_LOG_R_FLOOR)
        # closed form (cu_o is positive definite for every moved run): deterministic to the
        # last bit, as the tracker must repeat itself exactly (streaming = replay)
        gzu = solve2(cu_o, czu_o.transpose(1, 2)).transpose(1, 2)
        resid = mu_o - mz_o[:, :, None, None] - self._affine(f, gzu, u_o)
        chans = torch.cat([log_r[:, None], resid], 1)
        out = resample_bilinear(chans, uv, padding="border")
        cu_n = _sym(inv2(a_n) @ css @ inv2(a_n).transpose(1, 2))
        zero = torch.zeros_like(ms)
        w_n = normalised(out[:, 0] + self._log_gauss(f, zero, cu_n))
        g_n = czs @ solve2(css, a_n)  # z-gain per new cell step
        mu_n = out[:, 1:] + mz_o[:, :, None, None] + self._affine(f, g_n, zero)
        new = self._matched(f, (w_n, mu_n, P_o, c_n, a_n), ms, css, mz_o, czz, czs)
        if every:
            f.set_state(*new)
        else:
            for name, value in zip(("weights", "lin_mean", "lin_cov", "centre", "axes"), new,
                                   strict=True):
                getattr(f, name).index_copy_(0, idx, value)
        f.regrids += move.long()
        return move

    def _guard(self, f: LatticeFilter, healthy: torch.Tensor) -> None:
        """Runs whose moments stopped being finite (``healthy (N,)`` False) are lost: reset
        to a wide Gaussian around the origin, flagged in `lost`, never NaN."""
        bad = ~healthy & ~self.lost
        if bool(bad.any()):
            d = 2 + f.nz
            eye = torch.eye(d, dtype=f.dtype, device=f.device)
            wide = eye.expand(f.n_runs, d, d) * max(self.config.widen_min_sigma, 1.0) ** 2
            zero = torch.zeros(f.n_runs, d, dtype=f.dtype, device=f.device)
            self._set_subset(f, bad, zero, wide)
            self.lost |= bad
