"""The ``follow`` lattice rule of the point-mass filter: a lattice that follows the posterior.

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

**Grid following the posterior** (`FollowLattice.regrid`): after each update a
run moves to a new lattice centred on its mean, with cell steps ``span_sigma · σ_k / h``
along each axis ``k`` (the principal axes of its covariance when ``principal_axes``,
else x and y) — i.e. the spacing is ``1 / spacing_per_sigma`` of σ — when its mean left
the central ``recentre_fraction`` of the lattice, its ``± regrid_sigma σ`` box pokes out
(hysteresis: built for ``± span_sigma σ``),
or it needs less than ``1 / resize_ratio`` of the lattice. Masses and ``w μ`` are
resampled bilinearly (density interpolation), then the moment correction restores the
pre-regrid moments. Guard against collapse: the half-width is never below
``span_sigma · sqrt(σ² + q)`` (q: the next step's process noise) nor ``min_half_width``.

**Moment correction** (`FollowLattice.match_moments`): the lattice is moved by
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
shared with the acquisition grid); this rule adds the NIS report, the lost-track test
and the regrid after the update, its weight floor (relative to the peak, renormalised),
and implements the prediction, the regrid and the Gaussian lattice of a prior. The 2 × 2
moment-correction map is computed in float64 in both dtypes: from a float32 eigh an
elongated posterior's map could collapse the lattice.

**Implementation.** The kernels are `neuralmap.filters.lattice.follow_step`'s, run by one
of two drivers (`FollowLattice.static`):

* the **static** driver (``TrackerConfig.compile``, and any CUDA device): a prediction is
  one pass of static-shape kernels over every run (`follow_step.predict_step`), an update
  another (`follow_step.update_step`: the measurement update, the lost-track window, the
  regrid rule, the moved lattices — every run's, masked, or on a large CPU batch only the
  moved runs', `follow_step.regrid_rows_step` — and the moments of the result); each ends
  with one host read of its flags, and the rare runs (a posterior narrower than the cells,
  a widening, two eigenvalues of ``P`` at its floor, a blur longer than the band) go
  through the eager driver. Under ``torch.compile`` one vehicle's step is a few dozen
  aten calls instead of a few thousand;
* the **eager** driver (the CPU default without ``compile``): the same kernels with host
  branches that skip what no run needs (the blur when no run's noise reaches
  `BLUR_MIN_CELLS`, the resampling when no run moves, the rare corrections).

Both give the same results to round-off (tests/filters/test_lattice_step.py), and equal
the algorithm in NumPy, one run at a time (`neuralmap.filters.lattice.reference`;
tests/filters/test_lattice_reference.py).
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import torch

import neuralmap.filters.lattice.follow_step as fs
from neuralmap.exceptions import NeuralMapError
from neuralmap.filters.lattice.algebra2 import inv2, solve2, spd_ok
from neuralmap.filters.lattice.follow_step import (
    BLUR_MIN_CELLS,
    FAST_BAND,
    MIN_CELL_VARIANCE,
    FollowParams,
    Targets,
    floor_p_rows,
    lattice_for_core,
    matched_core,
    thin_flag,
)
from neuralmap.filters.lattice.kernels import (
    LatticeMoments,
    affine_field,
    gaussian_log_density,
    normalised,
)
from neuralmap.filters.stats import chi2_mean_threshold

if TYPE_CHECKING:
    from neuralmap.filters.lattice.filter import LatticeFilter, LatticeUpdate

__all__ = ["BLUR_MIN_CELLS", "MIN_CELL_VARIANCE", "FollowLattice", "TrackerConfig"]

#: Steps that need a narrower blur band before the static step narrows its band.
BAND_HOLD = 20

#: Runs from which a CPU batch resamples only its moved runs in a regrid (about a third of
#: them per step) rather than every run, masked.
COMPACT_MIN_RUNS = 64

#: Largest batch whose tracking epoch (`FollowLattice.track`) also sorts its cells by their
#: reach from the mean (`kernels.radial_mass_profile`, the protection radius): for one
#: vehicle the sort (about 0.06 ms) replaces about 0.2 ms of eager calls; for a fleet it
#: costs more than sorting only the runs whose tail needs it (measured: 2.5 ms an epoch at
#: 50 runs, compiled, one thread).
PROFILE_MAX_RUNS = 8


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
        compile: Run the prediction and the update under ``torch.compile`` (inductor: C++
            on the CPU, Triton on CUDA; the first step of each batch size compiles, tens of
            seconds). Off: the same kernels eagerly. A backend that fails to compile falls
            back to eager with a warning.
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
    compile: bool = False

    def validate(self) -> TrackerConfig:
        """Checks ranges; raises `NeuralMapError` naming the bad option."""

        def bad(key: str, need: str) -> NeuralMapError:
            return NeuralMapError(
                f"TrackerConfig: '{key}' must be {need}, got {getattr(self, key)!r}.")

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
        if not isinstance(self.compile, bool):
            raise bad("compile", "True or False")
        return self




def _sym(m: torch.Tensor) -> torch.Tensor:
    return 0.5 * (m + m.transpose(-1, -2))


class FollowLattice:
    """The ``follow`` lattice rule (module docstring) of a `LatticeFilter`.

    Two drivers of the same kernels (`neuralmap.filters.lattice.follow_step`):

    * **static** (``static`` True: compiled, or on CUDA): one pass of static-shape kernels
      per prediction and per update (every run computes every path, masked), one host read
      of the step's flags, and the eager driver on the rare step where a flag is set;
    * **eager** (the default on the CPU): the same kernels with host branches that skip
      what no run needs (the blur when no run's noise reaches a cell, the regrid when no run
      moves, the rare corrections), as cheap as a branch is on the CPU.

    Args:
        config: `TrackerConfig`.
        n_runs: Runs N.
        nz: Linear states per cell.
        dtype, device: Of the filter.

    Attributes:
        widenings: ``(N,)`` int64, lost-track widenings.
        lost: ``(N,)`` bool, lost beyond recovery (module docstring).
        static: Use the static driver (default: ``config.compile`` or a CUDA device).
    """

    reports_nis = True
    outlier_prob, outlier_width = 0.0, 1000.0

    def __init__(self, config: TrackerConfig, n_runs: int, nz: int, dtype: torch.dtype,
                 device: torch.device) -> None:
        self.config = config.validate()
        kw = {"dtype": dtype, "device": device}
        window = self.config.lost_window or 1
        self.widenings = torch.zeros(n_runs, dtype=torch.int64, device=device)
        self.lost = torch.zeros(n_runs, dtype=torch.bool, device=device)
        self._nis_win = torch.zeros(n_runs, window, **kw)
        self._nis_count = torch.zeros(n_runs, dtype=torch.int64, device=device)
        self._slots = torch.eye(window, dtype=torch.bool, device=device)
        self._step = 0
        self._q_next = torch.zeros(n_runs, 2, **kw)
        self._open_mean = torch.zeros(n_runs, 2 + nz, **kw)
        self._open_cov = torch.zeros(n_runs, 2 + nz, 2 + nz, **kw)
        self._band, self._band_low = 1, 0
        self._compile = self.config.compile
        self._track_compiles = True
        self.static = self.config.compile or torch.device(device).type == "cuda"
        self._consts: dict[Any, torch.Tensor] = {}

    _PER_RUN = ("widenings", "lost", "_nis_win", "_nis_count", "_q_next", "_open_mean",
                "_open_cov")

    def take(self, index: torch.Tensor) -> FollowLattice:
        out = object.__new__(FollowLattice)
        out.__dict__.update(self.__dict__)
        for name in self._PER_RUN:
            setattr(out, name, getattr(self, name).index_select(0, index))
        out._consts = {}
        return out

    def cat(self, other: FollowLattice) -> FollowLattice:
        out = object.__new__(FollowLattice)
        out.__dict__.update(self.__dict__)
        for name in self._PER_RUN:
            setattr(out, name, torch.cat([getattr(self, name), getattr(other, name)]))
        out._consts = {}
        return out

    def deferred_cov(self, f: LatticeFilter) -> None:
        """None: every prediction is applied to the lattice at once."""
        return None

    # ------------------------------------------------------------------ step plumbing
    def params(self, f: LatticeFilter, band: int | None = None) -> FollowParams:
        """The static options of a step (`follow_step.FollowParams`)."""
        cfg = self.config
        return FollowParams(
            cells=f.cells, half=f.half, span_sigma=cfg.span_sigma,
            principal_axes=cfg.principal_axes, recentre_fraction=cfg.recentre_fraction,
            regrid_box=1.0 if cfg.regrid_sigma is None else cfg.regrid_sigma / cfg.span_sigma,
            resize_ratio=cfg.resize_ratio, min_half_width=cfg.min_half_width,
            max_spacing=math.inf if cfg.max_spacing is None else cfg.max_spacing,
            weight_floor=cfg.weight_floor, f_identity=f._f_identity,
            band=self._band if band is None else band)

    def _run(self, name: str, fn: Any, *args: Any) -> Any:
        """``fn(*args)`` compiled (``config.compile``) or eagerly; a compiled step that
        fails falls back to eager once, with a warning, for good."""
        if self._compile:
            try:
                return fs.compiled(name, fn)(*args)
            except Exception as exc:  # noqa: BLE001 - any backend failure: run eagerly
                out = fn(*args)
                self._compile = False
                warnings.warn(f"PointMassTracker: torch.compile of the {name} step failed "
                              f"({type(exc).__name__}: {exc}); running it eagerly.",
                              RuntimeWarning, stacklevel=3)
                return out
        return fn(*args)

    def _const(self, key: Any, make: Any) -> torch.Tensor:
        """A constant tensor of the step (all-True mask, zero shift, R), made once."""
        t = self._consts.get(key)
        if t is None:
            t = self._consts[key] = make()
        return t

    # ------------------------------------------------------------------ set-up
    def reset(self, f: LatticeFilter, mean: torch.Tensor, cov: torch.Tensor,
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
        ok = spd_ok(cov)
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
        if not bool(torch.isfinite(mean).all()) or not bool(spd_ok(cov).all()):
            raise NeuralMapError("PointMassTracker.set_open_loop: the open-loop prior must be "
                                 "finite with a symmetric positive definite covariance.")
        self._open_mean = mean.expand(n, d).clone()
        self._open_cov = cov.clone()

    def open_loop(self, f: LatticeFilter) -> tuple[torch.Tensor, torch.Tensor]:
        """The open-loop prior ``(m_ol (N, 2+nz), P_ol (N, 2+nz, 2+nz))`` (module docstring)."""
        return self._open_mean, self._open_cov

    def _gaussian_state(self, f: LatticeFilter, mean: torch.Tensor, cov: torch.Tensor,
                        q: torch.Tensor | None = None) -> tuple[torch.Tensor, ...]:
        """Lattice, masses and linear part of ``N(mean, cov)`` (moments matched exactly)."""
        ms, mz = mean[:, :2], mean[:, 2:]
        css, czs, czz = cov[:, :2, :2], cov[:, 2:, :2], cov[:, 2:, 2:]
        centre, axes = self._lattice_for(f, ms, css, torch.zeros_like(ms) if q is None else q)
        inv_a = inv2(axes)
        cu = _sym(inv_a @ css @ inv_a.transpose(1, 2))
        zero = torch.zeros_like(ms)
        w = normalised(gaussian_log_density(f._off, zero, cu))
        gu = czs @ solve2(css, axes)  # (N, nz, 2): z-gain per cell step
        mu = mz[:, :, None, None] + affine_field(f._off, gu, zero)
        P = _sym(czz - czs @ solve2(css, czs.transpose(1, 2)))
        return self._matched(f, (w, mu, P, centre, axes), Targets(ms, css, mz, czz, czs),
                             fallback=False)

    def _lattice_for(self, f: LatticeFilter, mean: torch.Tensor, cov: torch.Tensor,
                     q: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Centre ``(N, 2)`` and cell steps ``(N, 2, 2)`` of a lattice for ``N(mean, cov)``;
        ``q (N, 2)``: process noise of the next step (collapse guard). Raises on cells
        coarser than ``max_spacing`` or not finite and positive."""
        centre, axes, step, coarse, bad = lattice_for_core(mean, cov, q, self.params(f))
        self._raise_lattice(f, step, coarse, bad)
        return centre, axes

    def _raise_lattice(self, f: LatticeFilter, step: torch.Tensor, coarse: torch.Tensor,
                       bad: torch.Tensor) -> None:
        cfg = self.config
        if bool(coarse.any()):
            i = int(coarse.nonzero()[0])
            raise NeuralMapError(
                f"PointMassTracker: run {i} needs cells of {step[i].max().item():.4g} to hold "
                f"± {cfg.span_sigma:g} σ on {f.cells} cells, above max_spacing "
                f"{cfg.max_spacing:g}. Increase 'cells' (or max_spacing).")
        if bool(bad.any()):
            raise NeuralMapError("PointMassTracker: a lattice with zero or non-finite cells; the "
                                 "covariance must be finite and positive definite.")

    def _set_subset(self, f: LatticeFilter, mask: torch.Tensor, mean: torch.Tensor,
                    cov: torch.Tensor) -> None:
        """Runs ``mask (N,)`` restart from ``N(mean, cov)`` (``(N, d)``, ``(N, d, d)``); the
        Gaussian lattice is built for those runs only (each run's is independent)."""
        idx = mask.nonzero().reshape(-1)
        gauss = self._gaussian_state(f, mean.index_select(0, idx), cov.index_select(0, idx))
        f.set_state(*(t.index_copy(0, idx, g) for t, g in zip(f.state(), gauss, strict=True)))

    # ------------------------------------------------------------------ moments
    def _matched(self, f: LatticeFilter, state: tuple[torch.Tensor, ...], t: Targets,
                 fallback: bool = True) -> tuple[torch.Tensor, ...]:
        """``state`` with its moments set to the targets ``t`` exactly (module docstring;
        `follow_step.matched_core`).

        A run whose masses sit in fewer cells than an affine map can stretch (covariance
        below ``MIN_CELL_VARIANCE`` cells² along an axis: a posterior narrower than the
        cells) gets the Gaussian with the target moments on a fresh lattice instead.
        """
        new, thin, floor = matched_core(*state, t, f._off)
        return self._fix_matched(f, new, t, thin if fallback else None, floor)

    def _fix_matched(self, f: LatticeFilter, new: tuple[torch.Tensor, ...], t: Targets,
                     thin: torch.Tensor | None, floor: torch.Tensor,
                     ) -> tuple[torch.Tensor, ...]:
        """The rare corrections of a moment correction, on the runs that need them: the
        Gaussian of the targets where ``thin`` (then matched again, as the step would), the
        eigenvalue floor of ``P`` where ``floor`` (`follow_step.floor_p_rows`)."""
        if thin is not None and bool(thin.any()):
            idx = thin.nonzero().reshape(-1)
            sub = Targets(*(x.index_select(0, idx) for x in t))
            mean, cov = fs.joint_moments(sub)
            gauss = self._matched(f, self._gaussian_state(f, mean, cov), sub, fallback=False)
            new = tuple(x.index_copy(0, idx, g) for x, g in zip(new, gauss, strict=True))
            floor = floor & ~thin
        if bool(floor.any()):
            idx = floor.nonzero().reshape(-1)
            P = new[2].index_copy(0, idx, floor_p_rows(new[2].index_select(0, idx)))
            new = (new[0], new[1], P, new[3], new[4])
        return new

    def match_moments(self, f: LatticeFilter, mean: torch.Tensor, cov: torch.Tensor) -> None:
        """Imposes mean ``(N, 2+nz)`` and covariance ``(N, 2+nz, 2+nz)`` exactly (affine
        lattice map + per-cell linear-part shift; module docstring)."""
        t = Targets(mean[:, :2], cov[:, :2, :2], mean[:, 2:], cov[:, 2:, 2:], cov[:, 2:, :2])
        f.set_state(*self._matched(f, f.state(), t))

    def _refit_thin(self, f: LatticeFilter) -> LatticeMoments:
        """Runs whose masses sit in too few cells (``MIN_CELL_VARIANCE``): their Gaussian
        fit, with the cells' own spread ``A Aᵀ / 12`` added, on a fresh lattice; returns the
        lattice moments of the state."""
        lm = f.lattice_moments()
        thin = thin_flag(lm.cu)
        if not bool(thin.any()):
            return lm
        idx = thin.nonzero().reshape(-1)
        axes = f.axes.index_select(0, idx)
        cu = lm.cu.index_select(0, idx) + torch.eye(2, dtype=f.dtype, device=f.device) / 12.0
        ms = f.centre.index_select(0, idx) + (axes @ lm.u[idx, :, None]).squeeze(-1)
        css = _sym(axes @ cu @ axes.transpose(1, 2))
        czs = lm.czu.index_select(0, idx) @ axes.transpose(1, 2)
        czz = _sym(f.lin_cov.index_select(0, idx) + lm.czz_b.index_select(0, idx))
        mean, cov = fs.joint_moments(Targets(ms, css, lm.mz.index_select(0, idx), czz, czs))
        gauss = self._gaussian_state(f, mean, cov)
        f.set_state(*(x.index_copy(0, idx, g) for x, g in zip(f.state(), gauss, strict=True)))
        f.regrids += thin.long()
        return f.lattice_moments()

    # ------------------------------------------------------------------ predict
    def predict(self, f: LatticeFilter, *, Q_s: torch.Tensor, Q_z: torch.Tensor,
                shift: torch.Tensor | None = None) -> None:
        """Time update of the model in the module docstring.

        Args:
            Q_s: ``(2, 2)`` or ``(N, 2, 2)`` process noise of ``s``.
            Q_z: ``(nz, nz)`` or ``(N, nz, nz)`` process noise of ``z``.
            shift: ``(N, 2)`` known displacement ``u`` of ``s`` (None = 0).
        """
        n, nz, dt, dev = f.n_runs, f.nz, f.dtype, f.device
        qs = _as(Q_s, dt, dev).expand(n, 2, 2)
        qz = _as(Q_z, dt, dev).expand(n, nz, nz)
        if shift is None:
            u = self._const(("zero", n), lambda: torch.zeros(n, 2, dtype=dt, device=dev))
        else:
            u = _as(shift, dt, dev).expand(n, 2)
        if self.static:
            lm = None if self._compile else f.lattice_moments().tensors()
            for _ in range(2):  # a kernel longer than the band: once more with its band
                state, pts, q_next, om, oc, healthy, read = self._run(
                    "predict", fs.predict_step, *f.state(), lm, f.E, f.F, qs, qz, u,
                    self._open_mean, self._open_cov, f._off, self.params(f))
                read = read.tolist()  # the step's one host read
                if not read[1] or any(read[i] for i in (0, 2, 3)):
                    break
                self._set_band(f, read[-1], now=True)
            if not any(read[:4]):
                f.set_state(*state)
                f._cache_points(state[3], state[4], pts)
                if read[4]:
                    self._guard(f, healthy)
                self._q_next, self._open_mean, self._open_cov = q_next, om, oc
                self._set_band(f, read[-1])
                return
        self._predict_eager(f, qs, qz, u)

    def _set_band(self, f: LatticeFilter, need: float, now: bool = False) -> None:
        """The static step's blur band (`follow_step.FAST_BAND`) for the band this step's
        kernel needed: wider at once (a band change compiles one more variant), narrower
        only after `BAND_HOLD` steps that needed less (a kernel that outgrows its band
        costs a second pass)."""
        band = 1 if need <= 1 else FAST_BAND if need <= FAST_BAND else f.cells - 1
        band = min(band, f.cells - 1)
        if now or band >= self._band:
            self._band, self._band_low = band, 0
            return
        self._band_low += 1
        if self._band_low >= BAND_HOLD:
            self._band, self._band_low = band, 0

    def _predict_eager(self, f: LatticeFilter, qs: torch.Tensor, qz: torch.Tensor,
                       u: torch.Tensor) -> None:
        """The time update with host branches (`follow_step.predict_prepare`,
        `follow_step.predict_finish`): the refit of thin runs, one kernel length for the
        batch (no blur when no run's noise reaches `BLUR_MIN_CELLS`), the moment
        correction's rare corrections, the guard."""
        lm = self._refit_thin(f)
        w, mu, P, centre, axes = f.state()
        prep = fs.predict_prepare(w, mu, P, centre, axes, lm.tensors(), f.E, f.F, qs, qz, u,
                                  self._open_mean, self._open_cov)
        blur_on, half_len, need = (float(x) for x in torch.stack(
            fs.kernel_length(prep["var_c"], f.cells)).tolist())
        band = int(need)  # the kernel's nonzero taps: 1 for the three-tap kernel
        state, thin, floor = fs.predict_finish(w, mu, P, lm.tensors(), prep, f.F, f._off,
                                               self.params(f, band=band), bool(blur_on),
                                               half_len)
        f.set_state(*self._fix_matched(f, state, prep["targets"], thin, floor))
        self._guard(f, prep["healthy"])
        self._q_next = prep["q_next"]
        self._open_mean, self._open_cov = prep["open_mean"], prep["open_cov"]
        self._set_band(f, need if blur_on else 0)

    # ------------------------------------------------------------------ update
    def _update_options(self, f: LatticeFilter, regrid: bool) -> tuple[Any, ...]:
        """``window``, ``slot``, ``threshold`` and the regrid mode of a static update."""
        cfg = self.config
        window = cfg.lost_window > 0
        slot = self._slots[self._step % cfg.lost_window] if window else self._slots[0]
        threshold = chi2_mean_threshold(cfg.lost_prob, cfg.lost_window) if window else 0.0
        mode = "none" if not regrid else "rule" if self._compact(f) else "all"
        return window, slot, threshold, mode

    def update(self, f: LatticeFilter, y: torch.Tensor, g: torch.Tensor, r: torch.Tensor,
               mask: torch.Tensor | None, cell_variance: torch.Tensor | None,
               regrid: bool) -> LatticeUpdate | None:
        """The static update (`follow_step.update_step`: the measurement update, the
        lost-track window, the regrid and the moments of the result, one host read), the
        moved runs of a large CPU batch resampled together (`follow_step.regrid_rows_step`),
        and the few runs a rare event touches through the eager path. None where the
        filter's eager update is to run instead (not ``static``)."""
        if not self.static:
            return None
        n = f.n_runs
        window, slot, threshold, mode = self._update_options(f, regrid)
        if mask is None:
            mask = self._const(("all", n), lambda: torch.ones(n, dtype=torch.bool,
                                                               device=f.device))
        out = self._run(
            "update", fs.update_step, *f.state(), f.c, y, g, r, mask, cell_variance,
            self._q_next, self._nis_win, self._nis_count, self.lost, slot, f.recoveries,
            f.regrids, f._off, self.params(f), threshold, window, mode)
        return self._finish_update(f, out, out[-1].tolist(), window, regrid)

    def track(self, f: LatticeFilter, *, Q_s: torch.Tensor, Q_z: torch.Tensor,
              y: torch.Tensor, heights: Any, heights_args: tuple[Any, ...], r: torch.Tensor,
              mask: torch.Tensor, gate: float,
              ) -> tuple[LatticeUpdate, torch.Tensor, torch.Tensor, Any] | None:
        """A whole epoch, prediction and update, as one static step (`follow_step.track_step`:
        under ``compile`` one compiled call with the map lookup and the spike gate in it).

        Args:
            Q_s, Q_z: Process noise, as `predict`.
            y: ``(N,)`` measurements (NaN: none).
            heights: Module-level function, ``heights(*heights_args, points (N, G, G, 2))
                -> (N, G, G)`` the measurement model at the cells (NaN: no likelihood).
            r: ``(N,)`` measurement variances.
            mask: ``(N,)`` bool, runs to update.
            gate: Spike gate on the predictive NIS (``inf``: none).

        Returns:
            The update, the predictive NIS ``(N,)``, the gated runs ``(N,)`` and the radial
            mass profile of the result around its mean (`kernels.radial_mass_profile`; for
            at most `PROFILE_MAX_RUNS` runs, else None); None, with nothing changed, where
            the epoch needs the separate prediction and update: not ``static``, a whole-epoch
            step that does not compile, or a flag of the prediction that its eager branches
            handle (a thin posterior, a kernel longer than the band, an eigenvalue floor, an
            unhealthy run).
        """
        if not self.static:
            return None
        n, nz, dt, dev = f.n_runs, f.nz, f.dtype, f.device
        qs = _as(Q_s, dt, dev).expand(n, 2, 2)
        qz = _as(Q_z, dt, dev).expand(n, nz, nz)
        u = self._const(("zero", n), lambda: torch.zeros(n, 2, dtype=dt, device=dev))
        window, slot, threshold, mode = self._update_options(f, True)
        args = (*f.state(), f.E, f.F, qs, qz, u, self._open_mean, self._open_cov, f.c, y,
                heights, tuple(heights_args), r, mask, float(gate), self._nis_win,
                self._nis_count, self.lost, slot, f.recoveries, f.regrids, f._off,
                self.params(f), threshold, window, mode, f.n_runs <= PROFILE_MAX_RUNS)
        if not self._compile:
            step = fs.track_step(*args)
        elif not self._track_compiles:
            return None  # the compiled prediction and update, separately
        else:
            try:
                step = fs.compiled("track", fs.track_step)(*args)
            except Exception as exc:  # noqa: BLE001 - e.g. a map torch.compile cannot trace
                self._track_compiles = False
                warnings.warn(f"PointMassTracker: torch.compile of the whole tracking epoch "
                              f"failed ({type(exc).__name__}: {exc}); the prediction and "
                              "the update run as two compiled steps.", RuntimeWarning,
                              stacklevel=3)
                return None
        predicted, out, nis_pred, gated, mass, read = step
        read = read.tolist()  # the epoch's one host read
        k = len(fs.PREDICT_FLAGS)
        if any(read[:k]):
            return None
        state, pts, q_next, om, oc = predicted[:5]
        f.set_state(*state)
        self._q_next, self._open_mean, self._open_cov = q_next, om, oc
        self._set_band(f, read[k])
        upd = self._finish_update(f, out, read[k + 1:], window, True)
        if any(read[k + 2:]):  # rows redone by the driver: the profile is not theirs
            mass = None
        return upd, nis_pred, gated, mass

    def _finish_update(self, f: LatticeFilter, out: tuple[Any, ...], read: list[float],
                       window: bool, regrid: bool) -> LatticeUpdate:
        """Commits the outputs of `follow_step.update_step` (its host read ``read``): the
        counters and window, the compacted regrid of a large batch, the rare runs through
        the eager path, the moments' cache."""
        from neuralmap.filters.lattice.filter import LatticeUpdate

        (state, pts, mean, cov, nis, innov, loglik, recovered, applied, recoveries,
         regrids, nis_win, nis_count, widen, special, move, _) = out
        r_bad, any_special, error, n_move = read
        if r_bad:
            raise NeuralMapError(f"{f.name}.update: R must be > 0 (and finite) for every run.")
        f.recoveries = recoveries
        if window:
            self._step += 1
            self._nis_win, self._nis_count = nis_win, nis_count
        if error:  # as the eager update: the measurement update stays, the regrid raises
            f.set_state(*state[:3], f.centre, f.axes)
            self.regrid(f)
        f.regrids = regrids
        if n_move:  # "rule": resample the moved runs together
            idx = move.nonzero().reshape(-1)
            st, m_r, c_r, p_r, keep, sp, err = self._run(
                "regrid_rows", fs.regrid_rows_step,
                *(t.index_select(0, idx) for t in state), self._q_next.index_select(0, idx),
                f._off, self.params(f))
            if bool(err.any()):
                f.set_state(*state)
                self.regrid(f)
            # the moved rows written in place into the step's own outputs (the lattice
            # tensors the step returned unchanged are the filter's: copied first)
            state = tuple(t.clone() if t is old else t
                          for t, old in zip(state, f.state(), strict=True))
            for x, a in zip((*state, mean, cov, pts), (*st, m_r, c_r, p_r), strict=True):
                k = keep.reshape(-1, *([1] * (a.ndim - 1)))
                x.index_copy_(0, idx, torch.where(k, a, x.index_select(0, idx)))
            special = special.index_copy(0, idx, sp | special.index_select(0, idx))
            any_special = any_special or bool(sp.any())
            f.regrids = f.regrids.index_add(0, idx, keep.long())
        f.set_state(*state)
        widened = torch.zeros_like(applied)
        if any_special:  # the rare runs (still at their updated state), the eager path
            idx = special.nonzero().reshape(-1)
            sub = f.take(idx)
            if window and bool(widen.any()):
                sub.rule._widen(sub, widen.index_select(0, idx))
                widened = widen
            if regrid:
                sub.rule.regrid(sub)
            f.set_state(*(t.index_copy(0, idx, v) for t, v in zip(f.state(), sub.state(),
                                                                   strict=True)))
            f.regrids = f.regrids.index_copy(0, idx, sub.regrids)
            for name in ("widenings", "lost", "_nis_count"):
                setattr(self, name, getattr(self, name).index_copy(
                    0, idx, getattr(sub.rule, name)))
            m_s, c_s = sub.moments()
            mean, cov = mean.index_copy(0, idx, m_s), cov.index_copy(0, idx, c_s)
            pts = pts.index_copy(0, idx, sub.points())
        f._cache_step(f.state(), mean, cov, pts)
        return LatticeUpdate(log_likelihood=loglik, recovered=recovered, applied=applied,
                             nis=nis, innovation=innov, widened=widened)

    def _compact(self, f: LatticeFilter) -> bool:
        """Resample only the moved runs (`follow_step.regrid_rows_step`): on the CPU, for a
        batch large enough that the moved third outweighs one more host read and call."""
        return f.device.type == "cpu" and f.n_runs >= COMPACT_MIN_RUNS

    def after_update(self, f: LatticeFilter, nis: torch.Tensor | None, applied: torch.Tensor,
                     regrid: bool) -> torch.Tensor:
        """The lost-track test on the update's NIS, then the regrid (``regrid``); returns
        ``(N,)`` bool, runs widened (the eager update's second half)."""
        cfg = self.config
        widened = torch.zeros_like(applied)
        if cfg.lost_window > 0:
            slot = self._slots[self._step % cfg.lost_window]
            self._step += 1
            thr = chi2_mean_threshold(cfg.lost_prob, cfg.lost_window)
            self._nis_win, self._nis_count, widen = fs.lost_window_core(
                self._nis_win, self._nis_count, self.lost, nis, applied, slot, thr)
            if bool(widen.any()):
                widened = self._widen(f, widen)
        if regrid:
            self.regrid(f)
        return widened

    def floor_weights(self, w: torch.Tensor) -> torch.Tensor:
        """Masses below ``weight_floor × max`` raised to it, renormalised."""
        return fs.floor_weights(w, self.config.weight_floor)

    def _widen(self, f: LatticeFilter, widened: torch.Tensor) -> torch.Tensor:
        """Widens the runs ``widened (N,)`` whose mean NIS over the window says the track is
        lost: around their mean for the first ``local_widenings`` times, then to the
        open-loop prior; returns ``widened``."""
        cfg = self.config
        mean, cov = f.moments()
        d = cov.shape[-1]
        eye = torch.eye(d, dtype=cov.dtype, device=cov.device)
        infl = cov.clone()
        infl[:, :2, :2] = cov[:, :2, :2] * cfg.widen_factor**2 + eye[:2, :2] * (
            cfg.widen_min_sigma**2)
        infl = _sym(infl + 1e-9 * eye)
        infl = torch.where(spd_ok(infl)[:, None, None], infl, eye)
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
        """Moves runs whose posterior no longer fits their lattice (module docstring;
        `follow_step.regrid_rule`, `follow_step.regrid_move` on the runs it moves).

        Args:
            force: ``(N,)`` bool, runs to move regardless of the rule.

        Returns:
            ``(N,)`` bool, runs moved.
        """
        lm = self._refit_thin(f)
        p = self.params(f)
        move = fs.regrid_rule(lm.tensors(), f.axes, self._q_next, force, p)
        if not bool(move.any()):
            return move
        every = bool(move.all())  # the common case while a posterior shrinks: no copies
        idx = move.nonzero().reshape(-1)

        def rows(t: torch.Tensor) -> torch.Tensor:
            return t if every else t.index_select(0, idx)

        state = tuple(rows(t) for t in f.state())
        new = fs.regrid_move(*state, tuple(rows(t) for t in lm.tensors()),
                             rows(self._q_next), f._off, p)
        self._raise_lattice(f, lattice_for_core(new["targets"].ms, new["targets"].css,
                                                rows(self._q_next), p)[2],
                            new["too_coarse"], new["bad"])
        moved = self._fix_matched(f, new["state"], new["targets"], new["thin"], new["floor"])
        if every:
            f.set_state(*moved)
        else:
            f.set_state(*(t.index_copy(0, idx, m) for t, m in zip(f.state(), moved,
                                                                  strict=True)))
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


def _as(x: torch.Tensor | float, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    """``x`` as a tensor of ``dtype`` on ``device`` (no copy when it already is)."""
    if isinstance(x, torch.Tensor) and x.dtype == dtype and x.device == device:
        return x
    return torch.as_tensor(x, dtype=dtype, device=device)
