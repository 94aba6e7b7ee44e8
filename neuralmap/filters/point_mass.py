"""Batched point-mass filter: grid Bayes over a 2-D state, a scalar Kalman part per cell.

The filter of SEEDS-style grid-based Bayes (Bergman, Ljung and Gustafsson's point-mass
filter; the convolution form of the prediction of Matoušek, Duník et al.) for N independent
runs at once. Each run carries

* a regular ``G × G`` grid over the 2-D state ``s = (s_x, s_y)`` (in terrain navigation the
  horizontal INS error), centred at ``centre (N, 2)`` with per-axis spacing
  ``spacing (N, 2)``; cell ``(i, j)`` (row ``i`` along y, column ``j`` along x) sits at
  ``centre + spacing · (j − h, i − h)``, ``h = (G − 1) / 2``;
* normalised cell masses ``w (N, G, G)`` (the discrete posterior, Dirac convention);
* a Rao-Blackwellised scalar Gaussian per cell, ``a | cell ij ~ N(m_ij, v)`` (the altitude
  error), entering the measurement linearly; the conditional variance ``v`` is one number
  per run (with a common ``R`` the scalar Kalman variance update does not depend on the
  cell, and the moment-matched prediction keeps the run's total variance
  ``v + Var_w(m)`` exact: ``v' = v + Σ w m² − Σ w' m'²``; exact in the linear-Gaussian
  case, where the conditional variance is the same in every cell).

Measurement model (one scalar per run and step)::

    y = g(s) + a + e,      e ~ N(0, R)  (optionally a Gaussian + uniform mixture)

where ``g`` is given per cell by the caller (``predicted (N, G, G)``, or a callable mapping
the cell coordinates ``(N, G, G, 2)`` to it): the filter knows nothing of what ``g`` is.
Update per cell (a scalar Kalman filter on ``a``): ``ν = y − g − m``, ``S = v + R``,
``log w += −½ ν²/S`` (``−½ log 2πS`` is common to the run's cells), ``m += v ν / S``,
``v ← v R / S`` — the marginalised
likelihood of the Rao-Blackwellised point-mass filter. Weights are updated in the log
domain and renormalised by their maximum; a run whose likelihood is zero (or not finite)
in every cell keeps its prior weights, and that recovery is counted in
`PointMassFilter.recoveries` — never NaN.

Prediction ``s_{k+1} = s_k + u_k + w_k``, ``w_k ~ N(0, diag(q_x, q_y))``: the grid centre is
moved by the known shift ``u`` (no interpolation) and the masses are convolved with the
process-noise density (separable: one 1-D kernel per axis and run; a sampled Gaussian for
``σ ≥ 0.7`` cells, the three-tap kernel ``[σ²/2, 1 − σ², σ²/2]`` below, so that the kernel
variance is ``σ²`` in both cases). The scalar part is mixed with the masses (moment
matching: the convolution of ``w`` and ``w m``; ``v`` from the total variance) and gets
``q_a`` added.

Adaptive grid: after each update, a run whose posterior needs less than ``shrink_ratio``
of the grid's half-width (``span_sigma`` standard deviations per axis), or whose mean left
the central ``recentre_fraction`` of the grid, or whose ``span_sigma`` box pokes out of
the grid, is moved to a new grid centred on its mean with the spacing that fits the box
(never below ``min_spacing``): coarse while the posterior is wide, fine once it is narrow.
The masses are carried over by bilinear interpolation of the density; when the posterior
is narrower than ``1.5`` old cells the Gaussian fit is used instead (too few cells to
interpolate a shape). Grid tensors are allocated once; the hot loop reuses them except
for the temporaries of the convolution and the update.

Kernels: the convolution, the measurement update (the scalar part is the ``nz = 1``,
``c = 1`` case of the per-cell Kalman update), the moments, the Gaussian masses and the
bilinear resampling are those of `neuralmap.filters.lattice.kernels`, shared with the
tracker (`neuralmap.filters.point_mass_tracker`); this module holds the lattice policy
of acquisition (fixed or adaptive axis-aligned grid, deferred diffusion).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.filters.lattice.kernels import (
    BANDED_MIN_HALF_LEN,
    blur,
    cell_log_likelihood,
    conditional_mean,
    convolve_axis,
    gaussian_kernels,
    gaussian_log_density,
    kalman_cells,
    mass_moments,
    normalised,
    resample_bilinear,
    toeplitz_kernels,
    weight_update,
)

# the kernels are those of `neuralmap.filters.lattice.kernels` (re-exported here)
__all__ = ["BANDED_MIN_HALF_LEN", "PointMassConfig", "PointMassFilter", "PointMassUpdate",
           "convolve_axis", "gaussian_kernels", "toeplitz_kernels"]

#: Per-run state tensors (what `PointMassFilter.take` and ``extend`` carry).
_STATE = ("weights", "scalar_mean", "scalar_var", "centre", "spacing", "recoveries", "regrids",
          "_pending")

#: Process noise is accumulated per run and applied once it reaches this many cells (1σ)
#: on an axis: a Gaussian blur far below one cell changes nothing a grid can show, and
#: variances add, so deferring it loses nothing but the blur of the interim steps.
DIFFUSE_MIN_CELLS = 0.3



@dataclass
class PointMassConfig:
    """Grid options of `PointMassFilter` (sound defaults for terrain navigation).

    Attributes:
        cells: Grid cells per axis ``G`` (≥ 8).
        span_sigma: Grid half-width in prior/posterior standard deviations per axis.
        spacing: Fixed initial spacing per axis in state units, or None (from the prior:
            ``span_sigma · σ / h``). A fixed spacing whose grid cannot cover
            ``± span_sigma · σ`` raises.
        min_spacing: Smallest spacing the adaptive grid may use (state units).
        adaptive: Re-centre and re-size the grid as the posterior moves and shrinks.
        shrink_ratio: Re-size when the needed half-width drops below this fraction of the
            current one.
        recentre_fraction: Re-centre when the mean is farther from the centre than this
            fraction of the half-width.
        grow_margin: A new grid's half-width is ``(1 + grow_margin) · span_sigma · σ``.
        min_half_width: A grid never shrinks below this half-width (state units): cells
            far from a posterior that collapsed early keep their (small) mass and can win
            back when the measurements say so, as on a fixed grid.
        weight_floor: Masses below ``weight_floor × max`` are raised to it after each
            update (keeps every cell alive; 0 disables).
        outlier_prob: Probability of a measurement outlier (0 = Gaussian likelihood);
            outliers are modelled as uniform over ``outlier_width``.
        outlier_width: Width of the uniform outlier density (measurement units).
    """

    cells: int = 64
    span_sigma: float = 4.0
    spacing: float | None = None
    min_spacing: float = 1.0
    adaptive: bool = True
    shrink_ratio: float = 0.5
    recentre_fraction: float = 0.25
    weight_floor: float = 1e-30
    grow_margin: float = 0.25
    min_half_width: float = 0.0
    outlier_prob: float = 0.0
    outlier_width: float = 1000.0

    def validate(self) -> PointMassConfig:
        """Checks ranges; raises `NeuralMapError` naming the bad option."""

        def bad(key: str, need: str) -> NeuralMapError:
            return NeuralMapError(
                f"PointMassConfig: '{key}' must be {need}, got {getattr(self, key)!r}."
            )

        if isinstance(self.cells, bool) or not isinstance(self.cells, int) or self.cells < 8:
            raise bad("cells", "an integer >= 8")
        if not self.min_half_width >= 0.0:
            raise bad("min_half_width", ">= 0")
        if not 0.0 <= self.grow_margin <= 1.0:
            raise bad("grow_margin", "in [0, 1]")
        for key in ("span_sigma", "min_spacing", "outlier_width"):
            if not getattr(self, key) > 0.0:
                raise bad(key, "> 0")
        if self.spacing is not None and not self.spacing > 0.0:
            raise bad("spacing", "None or > 0")
        if not 0.0 < self.shrink_ratio < 1.0:
            raise bad("shrink_ratio", "in (0, 1)")
        if not 0.0 < self.recentre_fraction < 1.0:
            raise bad("recentre_fraction", "in (0, 1)")
        if not 0.0 <= self.weight_floor < 1e-3:
            raise bad("weight_floor", "in [0, 1e-3)")
        if not 0.0 <= self.outlier_prob < 1.0:
            raise bad("outlier_prob", "a probability in [0, 1)")
        return self


@dataclass
class PointMassUpdate:
    """Per-run results of one `PointMassFilter.update`.

    Attributes:
        log_likelihood: ``(N,)`` log predictive density of the measurement
            ``log Σ_ij w_ij p(y | cell ij)`` (−inf where every cell gave zero).
        recovered: ``(N,)`` bool, the likelihood vanished in every cell (or was not finite)
            and the run kept its prior weights.
        applied: ``(N,)`` bool, the update changed the run (masked-in and not recovered).
    """

    log_likelihood: torch.Tensor
    recovered: torch.Tensor
    applied: torch.Tensor


def _as_batch(value: object, shape: tuple[int, ...], name: str, dtype: torch.dtype,
              device: torch.device) -> torch.Tensor:
    """Broadcasts a float or tensor to ``shape`` (raises on a shape that does not fit)."""
    t = torch.as_tensor(value, dtype=dtype, device=device)
    try:
        return t.expand(shape) if t.ndim <= len(shape) else t.reshape(shape)
    except RuntimeError as exc:
        raise NeuralMapError(
            f"PointMassFilter: {name} must broadcast to {shape}, got {tuple(t.shape)}."
        ) from exc


class PointMassFilter:
    """N point-mass filters over a 2-D state with a Rao-Blackwellised scalar, in lock-step.

    Args:
        mean: ``(N, 2)`` prior mean of the grid state.
        cov: ``(2, 2)`` or ``(N, 2, 2)`` prior covariance (symmetric positive definite).
        scalar_mean: Prior mean of the scalar part, float or ``(N,)``.
        scalar_var: Prior variance of the scalar part (> 0), float or ``(N,)``.
        config: Grid options (`PointMassConfig`).
        dtype: float32 or float64 (default float64).

    Attributes:
        weights: ``(N, G, G)`` normalised cell masses (rows along y, columns along x).
        scalar_mean: ``(N, G, G)`` per-cell mean of the scalar part.
        scalar_var: ``(N,)`` conditional variance of the scalar part (same in every cell).
        centre: ``(N, 2)`` grid centres.
        spacing: ``(N, 2)`` grid spacing per axis.
        recoveries: ``(N,)`` int64, count of updates whose likelihood vanished everywhere.
        regrids: ``(N,)`` int64, count of grid moves.

    Raises:
        NeuralMapError: Bad shapes, a covariance that is not positive definite, or a fixed
            spacing whose grid cannot cover the prior.
    """

    def __init__(
        self,
        mean: torch.Tensor,
        cov: torch.Tensor,
        *,
        scalar_mean: float | torch.Tensor = 0.0,
        scalar_var: float | torch.Tensor = 1.0,
        config: PointMassConfig | None = None,
        dtype: torch.dtype = torch.float64,
    ) -> None:
        self.config = (config or PointMassConfig()).validate()
        if dtype not in (torch.float32, torch.float64):
            raise NeuralMapError(f"PointMassFilter: dtype must be float32 or float64, got {dtype}.")
        mean = torch.as_tensor(mean)
        if mean.ndim != 2 or mean.shape[1] != 2 or mean.shape[0] < 1:
            raise NeuralMapError(
                f"PointMassFilter: mean must have shape (N, 2), got {tuple(mean.shape)}."
            )
        self.dtype, self.device = dtype, mean.device
        n, g = mean.shape[0], self.config.cells
        self.n_runs, self.cells = n, g
        self.half = 0.5 * (g - 1)
        self._offsets = torch.arange(g, dtype=dtype, device=self.device) - self.half
        self._c1 = torch.ones(1, dtype=dtype, device=self.device)  # measurement row of a
        self.weights = torch.empty(n, g, g, dtype=dtype, device=self.device)
        self.scalar_mean = torch.empty_like(self.weights)
        self.scalar_var = torch.empty(n, dtype=dtype, device=self.device)
        self.centre = torch.empty(n, 2, dtype=dtype, device=self.device)
        self.spacing = torch.empty(n, 2, dtype=dtype, device=self.device)
        self.recoveries = torch.zeros(n, dtype=torch.int64, device=self.device)
        self.regrids = torch.zeros(n, dtype=torch.int64, device=self.device)
        self._pending = torch.zeros(n, 2, dtype=dtype, device=self.device)
        self._allocate_buffers()
        self.reset(mean, cov, scalar_mean=scalar_mean, scalar_var=scalar_var)

    # ------------------------------------------------------------------ set-up
    def reset(
        self,
        mean: torch.Tensor,
        cov: torch.Tensor,
        *,
        scalar_mean: float | torch.Tensor = 0.0,
        scalar_var: float | torch.Tensor = 1.0,
        mask: torch.Tensor | None = None,
    ) -> None:
        """(Re-)initialises runs from a Gaussian prior on a grid sized from ``cov``.

        Args:
            mean: ``(N, 2)`` prior means.
            cov: ``(2, 2)`` or ``(N, 2, 2)`` prior covariances (positive definite).
            scalar_mean: Scalar-part mean, float or ``(N,)``.
            scalar_var: Scalar-part variance (> 0), float or ``(N,)``.
            mask: ``(N,)`` bool, the runs to reset (None = all).

        Raises:
            NeuralMapError: ``cov`` not positive definite (names the first bad run), or a
                fixed spacing that cannot cover ``± span_sigma · σ``.
        """
        n, dt, dev = self.n_runs, self.dtype, self.device
        mean = _as_batch(mean, (n, 2), "mean", dt, dev)
        cov = _as_batch(cov, (n, 2, 2), "cov", dt, dev)
        if not bool(torch.isfinite(mean).all()):
            raise NeuralMapError("PointMassFilter: mean has non-finite entries.")
        bad = ~(torch.isfinite(cov).flatten(1).all(1)
                & (torch.linalg.cholesky_ex(cov.double()).info == 0)
                & (cov - cov.transpose(1, 2)).abs().flatten(1).amax(1).le(
                    1e-9 * cov.abs().flatten(1).amax(1) + 1e-300))
        if bool(bad.any()):
            first = int(bad.nonzero()[0])
            raise NeuralMapError(
                f"PointMassFilter: the prior covariance of run {first} is not symmetric "
                f"positive definite ({cov[first].tolist()}). Pass variances > 0 and a "
                "correlation inside (-1, 1)."
            )
        s_mean = _as_batch(scalar_mean, (n,), "scalar_mean", dt, dev)
        s_var = _as_batch(scalar_var, (n,), "scalar_var", dt, dev)
        if not bool((s_var > 0).all()):
            raise NeuralMapError("PointMassFilter: scalar_var must be > 0 for every run.")
        sigma = torch.diagonal(cov, dim1=1, dim2=2).sqrt()
        need = self.config.span_sigma * sigma
        if self.config.spacing is None:
            spacing = (need / self.half).clamp_min(self.config.min_spacing)
        else:
            spacing = torch.full_like(sigma, self.config.spacing)
            short = (spacing * self.half) < need * (1.0 - 1e-9)
            if bool(short.any()):
                first = int(short.any(1).nonzero()[0])
                raise NeuralMapError(
                    f"PointMassFilter: a grid of {self.cells} cells at spacing "
                    f"{self.config.spacing:g} covers ±{self.config.spacing * self.half:g} "
                    f"but the prior of run {first} needs ±{need[first].max().item():g} "
                    f"({self.config.span_sigma:g} σ). Increase 'cells' or 'spacing', or "
                    "leave spacing None to size the grid from the prior."
                )
        weights = self._gaussian_weights(mean, cov, mean, spacing)
        self._assign(mask, mean, spacing, weights, s_mean[:, None, None].expand_as(weights),
                     s_var)

    def _assign(self, mask: torch.Tensor | None, centre: torch.Tensor, spacing: torch.Tensor,
                weights: torch.Tensor, s_mean: torch.Tensor, s_var: torch.Tensor) -> None:
        """Writes grid state for the runs in ``mask`` (all when None), in place."""
        if mask is None:
            self._pending.zero_()
            self.centre.copy_(centre)
            self.spacing.copy_(spacing)
            self.weights.copy_(weights)
            self.scalar_mean.copy_(s_mean)
            self.scalar_var.copy_(s_var)
        else:
            m1, m3 = mask[:, None], mask[:, None, None]
            self._pending.masked_fill_(m1, 0.0)
            self.centre.copy_(torch.where(m1, centre, self.centre))
            self.spacing.copy_(torch.where(m1, spacing, self.spacing))
            self.weights.copy_(torch.where(m3, weights, self.weights))
            self.scalar_mean.copy_(torch.where(m3, s_mean, self.scalar_mean))
            self.scalar_var.copy_(torch.where(mask, s_var, self.scalar_var))
        self._points_valid = False

    def _refresh_points(self) -> None:
        self._points_valid = True
        off = self._offsets
        self._points[..., 0] = self.centre[:, None, None, 0] + self.spacing[:, None, None, 0] * off
        self._points[..., 1] = (self.centre[:, None, None, 1]
                                + self.spacing[:, None, None, 1] * off[:, None])

    def _gaussian_weights(self, mean: torch.Tensor, cov: torch.Tensor, centre: torch.Tensor,
                          spacing: torch.Tensor) -> torch.Tensor:
        """Normalised masses of ``N(mean, cov)`` sampled on the grid ``(centre, spacing)``
        (`gaussian_log_density` in cell units)."""
        u = (mean - centre) / spacing
        cu = cov / (spacing[:, :, None] * spacing[:, None, :])
        return normalised(gaussian_log_density(self._offsets, u, cu))

    def take(self, index: torch.Tensor) -> PointMassFilter:
        """A new filter holding the runs ``index`` (copies; counters carried over).

        Args:
            index: ``(M,)`` long run indices (M ≥ 1).
        """
        out = object.__new__(PointMassFilter)
        out.config, out.dtype, out.device = self.config, self.dtype, self.device
        out.cells, out.half, out._offsets = self.cells, self.half, self._offsets
        out._c1 = self._c1
        out.n_runs = int(index.numel())
        out._points_valid = False
        for name in _STATE:
            setattr(out, name, getattr(self, name).index_select(0, index))
        out._allocate_buffers()
        return out

    def _allocate_buffers(self) -> None:
        """Work buffers (cell coordinates, convolution channels) for the current N."""
        n, g = self.n_runs, self.cells
        self._points = torch.empty(n, g, g, 2, dtype=self.dtype, device=self.device)
        self._chans = torch.empty(n, 2, g, g, dtype=self.dtype, device=self.device)
        self._points_valid = False

    def extend(self, other: PointMassFilter) -> PointMassFilter:
        """A new filter with the runs of ``self`` followed by those of ``other``."""
        out = self.take(torch.arange(self.n_runs, device=self.device))
        for name in _STATE:
            setattr(out, name, torch.cat([getattr(self, name), getattr(other, name)]))
        out.n_runs = self.n_runs + other.n_runs
        out._allocate_buffers()
        return out

    # ------------------------------------------------------------------ views
    @property
    def offsets(self) -> torch.Tensor:
        """``(G,)`` cell offsets ``j − (G − 1)/2`` (cell = centre + spacing · offset)."""
        return self._offsets

    def points(self) -> torch.Tensor:
        """``(N, G, G, 2)`` cell coordinates in the state space (a reused buffer, filled
        when the grids have moved since the last call)."""
        if not self._points_valid:
            self._refresh_points()
        return self._points

    def mean(self) -> torch.Tensor:
        """``(N, 2)`` posterior mean ``Σ w s``."""
        u, _ = mass_moments(self.weights, self._offsets)
        return self.centre + self.spacing * u

    def cov(self) -> torch.Tensor:
        """``(N, 2, 2)`` posterior covariance ``Σ w (s − s̄)(s − s̄)ᵀ`` plus the process
        noise not yet applied to the grid (see `DIFFUSE_MIN_CELLS`); symmetric."""
        return self._grid_cov() + torch.diag_embed(self._pending)

    def _grid_cov(self) -> torch.Tensor:
        """``(N, 2, 2)`` covariance of the masses alone."""
        _, cu = mass_moments(self.weights, self._offsets)
        return cu * (self.spacing[:, :, None] * self.spacing[:, None, :])

    def scalar_moments(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Mixture mean and variance ``(N,)`` of the scalar part over the grid."""
        w = self.weights
        m = (w * self.scalar_mean).sum((1, 2))
        v = self.scalar_var + (w * self.scalar_mean**2).sum((1, 2)) - m * m
        return m, v.clamp_min(0.0)

    def gaussian_affinity(self, index: torch.Tensor | None = None) -> torch.Tensor:
        """``(N,)`` (or ``(K,)`` for ``index``) Bhattacharyya coefficient between the grid
        posterior and its Gaussian fit.

        ``BC = Σ_ij sqrt(w_ij g_ij)`` with ``g`` the normalised masses of ``N(s̄, Σ + D/12)``
        on the same grid (``D = diag(spacing²)``: a posterior inside one cell still fits).
        1 for a Gaussian posterior; about ``1/√M`` for M well-separated equal modes.

        Args:
            index: ``(K,)`` runs to evaluate (None = all); the value of a run does not
                depend on the others.
        """
        cov = self.cov() + torch.diag_embed(self.spacing**2 / 12.0)
        mean, centre, spacing, w = self.mean(), self.centre, self.spacing, self.weights
        if index is not None:
            cov, mean, centre, spacing, w = (t.index_select(0, index)
                                             for t in (cov, mean, centre, spacing, w))
        g = self._gaussian_weights(mean, cov, centre, spacing)
        return (w * g).sqrt().sum((1, 2))

    # ------------------------------------------------------------------ predict
    def predict(
        self,
        *,
        Q: torch.Tensor | float,
        shift: torch.Tensor | None = None,
        scalar_q: float | torch.Tensor = 0.0,
    ) -> torch.Tensor:
        """Time update ``s ← s + shift + w``, ``w ~ N(0, diag(Q))``; scalar part ``+ scalar_q``.

        Args:
            Q: Process noise of the grid state: ``(2, 2)``, ``(N, 2, 2)`` (only the
                diagonal is used: the convolution is separable), ``(N, 2)`` variances, or
                a float (both axes).
            shift: ``(N, 2)`` known displacement (moves the grid centre), or None.
            scalar_q: Process-noise variance of the scalar part, float or ``(N,)``.

        Returns:
            ``(N,)`` bool, runs moved to a new grid (sized for the predicted density)
            before the convolution.
        """
        n = self.n_runs
        q = torch.as_tensor(Q, dtype=self.dtype, device=self.device)
        if q.ndim >= 2 and q.shape[-1] == 2 and q.shape[-2] == 2:
            q = torch.diagonal(q, dim1=-2, dim2=-1)
        q = _as_batch(q, (n, 2), "Q", self.dtype, self.device)
        if bool((q < 0).any()) or not bool(torch.isfinite(q).all()):
            raise NeuralMapError("PointMassFilter.predict: Q must be finite and >= 0.")
        if shift is not None:
            self.centre.add_(_as_batch(shift, (n, 2), "shift", self.dtype, self.device))
            self._points_valid = False
        if self.config.adaptive:
            regridded = self.regrid(extra_cov=q)
        else:
            regridded = torch.zeros(n, dtype=torch.bool, device=self.device)
        sq = _as_batch(scalar_q, (n,), "scalar_q", self.dtype, self.device)
        self._pending.add_(q)
        sigma_cells = self._pending.sqrt() / self.spacing  # (N, 2)
        due = (sigma_cells >= DIFFUSE_MIN_CELLS).any(1)
        if bool(due.all()):
            w, m, v = self._diffuse(self.weights, self.scalar_mean, self.scalar_var,
                                    sigma_cells, self._chans)
            self.weights.copy_(w)
            self.scalar_mean.copy_(m)
            self.scalar_var.copy_(v)
            self._pending.zero_()
        elif bool(due.any()):
            idx = due.nonzero().reshape(-1)
            w, m, v = self._diffuse(self.weights.index_select(0, idx),
                                    self.scalar_mean.index_select(0, idx),
                                    self.scalar_var.index_select(0, idx),
                                    sigma_cells.index_select(0, idx), None)
            self.weights.index_copy_(0, idx, w)
            self.scalar_mean.index_copy_(0, idx, m)
            self.scalar_var.index_copy_(0, idx, v)
            self._pending.masked_fill_(due[:, None], 0.0)
        self.scalar_var.add_(sq)
        return regridded

    def _diffuse(self, w: torch.Tensor, m: torch.Tensor, v: torch.Tensor,
                 sigma_cells: torch.Tensor,
                 buf: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Convolves masses ``(M, G, G)`` with per-run Gaussians of ``sigma_cells (M, 2)``
        cells and mixes the scalar part (module docstring); returns new ``w, m, v``."""
        n, g = w.shape[0], self.cells
        second = (w * m * m).sum((1, 2))
        chans = torch.empty(n, 2, g, g, dtype=w.dtype, device=w.device) if buf is None else buf
        chans[:, 0].copy_(w)
        torch.mul(w, m, out=chans[:, 1])
        chans = blur(chans, sigma_cells)
        w0 = chans[:, 0].clamp_(min=0.0)  # round-off can dip below 0
        total = w0.sum((1, 2), keepdim=True)
        m_mix = (w * m).sum((1, 2))[:, None]
        m_new = conditional_mean(w0, chans[:, 1:], m_mix)[:, 0]
        ok = (total.reshape(n) > 0) & torch.isfinite(total.reshape(n))
        w_new = w0 / torch.where(ok[:, None, None], total, 1.0)
        second_new = (w_new * m_new * m_new).sum((1, 2))
        v_new = (v + second - second_new).clamp_min(1e-6 * v)
        if not bool(ok.all()):
            ok3 = ok[:, None, None]
            w_new = torch.where(ok3, w_new, w)
            m_new = torch.where(ok3, m_new, m)
            v_new = torch.where(ok, v_new, v)
        return w_new, m_new, v_new

    # ------------------------------------------------------------------ update
    def update(
        self,
        measurement: torch.Tensor,
        predicted: torch.Tensor | Callable[[torch.Tensor], torch.Tensor],
        *,
        R: float | torch.Tensor,
        mask: torch.Tensor | None = None,
        cell_variance: torch.Tensor | None = None,
    ) -> PointMassUpdate:
        """Measurement update ``y = g(s) + a + e`` in every cell (see the module docstring).

        Args:
            measurement: ``(N,)`` measurement ``y``.
            predicted: ``(N, G, G)`` ``g`` at every cell, or a callable taking the cell
                coordinates ``(N, G, G, 2)`` (`points`) and returning it. Non-finite
                cells get zero likelihood.
            R: Measurement noise variance (> 0), float or ``(N,)``.
            mask: ``(N,)`` bool, runs to update (None = all).
            cell_variance: ``(N, G, G)`` extra variance of ``g`` within each cell (the
                spread of the model over the cell's area), or None. Added to ``S`` in
                the likelihood of that cell, so that a coarse grid does not miss a
                likelihood peak narrower than a cell ("likelihood flattening"); the
                scalar Kalman part keeps the run's ``S = v + R``.

        Returns:
            `PointMassUpdate`.
        """
        n, g = self.n_runs, self.cells
        y = _as_batch(measurement, (n,), "measurement", self.dtype, self.device)
        gval = predicted(self.points()) if callable(predicted) else predicted
        gval = torch.as_tensor(gval).to(self.dtype)
        if tuple(gval.shape) != (n, g, g):
            raise NeuralMapError(
                f"PointMassFilter.update: predicted must have shape (N, G, G) = ({n}, {g}, {g}), "
                f"got {tuple(gval.shape)}."
            )
        r = _as_batch(R, (n,), "R", self.dtype, self.device)
        if not bool((r > 0).all()):
            raise NeuralMapError("PointMassFilter.update: R must be > 0 for every run.")
        m, v = self.scalar_mean, self.scalar_var
        s_run = v + r  # (N,) innovation variance, the same in every cell
        nu = (y[:, None, None] - gval).sub_(m)
        loglik, resp = cell_log_likelihood(nu, s_run, cell_variance,
                                           outlier_prob=self.config.outlier_prob,
                                           outlier_width=self.config.outlier_width)
        upd = weight_update(self.weights, torch.nan_to_num(loglik, nan=-math.inf), s_run)
        w, log_lik, use = upd.weights, upd.log_likelihood, upd.use
        recovered = ~use
        if mask is not None:
            recovered = recovered & mask
            use = use & mask
        self.recoveries.add_(recovered.long())
        floor = self.config.weight_floor
        if floor > 0.0:  # keeps every cell alive; adds at most G² · floor of mass
            w.clamp_(min=floor)
        nu = torch.nan_to_num(nu, nan=0.0, posinf=0.0, neginf=0.0)
        # the scalar part is the nz = 1, c = 1 case of the per-cell Kalman update
        mu_new, p_new = kalman_cells(m[:, None], v[:, None, None], self._c1, nu, s_run, resp, w)
        m_new, v_new = mu_new[:, 0], p_new[:, 0, 0]
        if bool(use.all()):
            self.weights.copy_(w)
            self.scalar_mean.copy_(m_new)
            self.scalar_var.copy_(v_new)
        else:
            u3 = use[:, None, None]
            self.weights.copy_(torch.where(u3, w, self.weights))
            self.scalar_mean.copy_(torch.where(u3, m_new, m))
            self.scalar_var.copy_(torch.where(use, v_new, v))
        return PointMassUpdate(log_likelihood=log_lik, recovered=recovered, applied=use)

    # ------------------------------------------------------------------ adaptive grid
    def _moments(self, w: torch.Tensor, centre: torch.Tensor,
                 spacing: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Mean ``(N, 2)`` and covariance ``(N, 2, 2)`` of masses ``w`` on a grid."""
        saved = self.weights, self.centre, self.spacing
        self.weights, self.centre, self.spacing = w, centre, spacing
        try:
            return self.mean(), self._grid_cov()
        finally:
            self.weights, self.centre, self.spacing = saved

    def _sample_old(self, chans: torch.Tensor, halfw: torch.Tensor, centre: torch.Tensor,
                    spacing: torch.Tensor, anchor: torch.Tensor,
                    affine: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Bilinear samples of the old grid's channels at ``anchor + A (s − centre)``.

        ``s`` runs over the new grid ``(centre, spacing)``; returns the clamped mass
        channel ``(N, G, G)`` and all channels ``(N, 3, G, G)``.
        """
        n, g, off = self.n_runs, self.cells, self._offsets
        dx = (spacing[:, 0:1] * off)[:, None, :].expand(n, g, g)
        dy = (spacing[:, 1:2] * off)[:, :, None].expand(n, g, g)
        a = affine[:, :, :, None, None]
        px = anchor[:, 0, None, None] + a[:, 0, 0] * dx + a[:, 0, 1] * dy
        py = anchor[:, 1, None, None] + a[:, 1, 0] * dx + a[:, 1, 1] * dy
        grid = torch.stack([(px - self.centre[:, 0, None, None]) / halfw[:, 0, None, None],
                            (py - self.centre[:, 1, None, None]) / halfw[:, 1, None, None]], -1)
        out = resample_bilinear(chans, grid, padding="zeros")
        return out[:, 0].clamp_min(0.0), out

    def regrid(self, candidates: torch.Tensor | None = None, *,
               extra_cov: torch.Tensor | None = None) -> torch.Tensor:
        """Moves runs whose density no longer fits their grid (rule: module docstring).

        Args:
            candidates: ``(N,)`` bool, runs allowed to move (None = all).
            extra_cov: ``(N, 2)`` variances added to the posterior's when sizing the grid
                (the process noise of the coming prediction), or None.

        Returns:
            ``(N,)`` bool, runs moved.
        """
        cfg = self.config
        mean, cov = self.mean(), self.cov()
        sigma = torch.diagonal(cov, dim1=1, dim2=2).clamp_min(0.0).sqrt()
        var_next = sigma**2 if extra_cov is None else sigma**2 + extra_cov
        need = cfg.span_sigma * var_next.sqrt()
        halfw = self.spacing * self.half
        off = (mean - self.centre).abs()
        # new grids get a growth margin so that a slowly widening density does not move
        # its grid every step
        spacing = ((1.0 + cfg.grow_margin) * need.clamp_min(cfg.min_half_width)
                   / self.half).clamp_min(cfg.min_spacing)
        shrink = (need < cfg.shrink_ratio * halfw) & (spacing < self.spacing * (1 - 1e-6))
        move = (shrink.any(1)
                | (off > cfg.recentre_fraction * halfw).any(1)
                | (off + need > halfw * (1 + 1e-6)).any(1))
        if candidates is not None:
            move = move & candidates
        if not bool(move.any()):
            return move
        if bool(move.all()):  # every run moves (a shrinking posterior): in place, no copies
            pending = self._pending.clone()  # deferred process noise stays with the run
            self._move(mean, cov, sigma, spacing, halfw)
            self._pending.copy_(pending)
        else:
            idx = move.nonzero().reshape(-1)
            sub = self.take(idx)
            sub._move(mean[idx], cov[idx], sigma[idx], spacing[idx], halfw[idx])
            for name in ("weights", "scalar_mean", "scalar_var", "centre", "spacing"):
                getattr(self, name).index_copy_(0, idx, getattr(sub, name))
        self.regrids.add_(move.long())
        self._points_valid = False
        return move

    def _move(self, mean: torch.Tensor, cov: torch.Tensor, sigma: torch.Tensor,
              spacing: torch.Tensor, halfw: torch.Tensor) -> None:
        """Moves every run of this filter to the grid ``(mean, spacing)`` (see regrid)."""
        n = self.n_runs
        w = self.weights
        chans = torch.stack([w, w * self.scalar_mean], 1)
        s_m, s_v = self.scalar_moments()
        eye = torch.eye(2, dtype=self.dtype, device=self.device).expand(n, 2, 2)
        # pass 1: plain interpolation; pass 2: the new cells mapped by the affine map that
        # gives the interpolated density the old grid's mean and covariance exactly
        w0, out = self._sample_old(chans, halfw, mean, spacing, mean, eye)
        total = w0.sum((1, 2))
        w1 = w0 / torch.where(total > 0, total, 1.0)[:, None, None]
        mu2, c2 = self._moments(w1, mean, spacing)
        l1 = torch.linalg.cholesky_ex(cov.double())
        l2 = torch.linalg.cholesky_ex(c2.double())
        ok_aff = (l1.info == 0) & (l2.info == 0)
        eye64 = torch.eye(2, dtype=torch.float64, device=self.device)
        a = l2.L @ torch.linalg.inv(torch.where(ok_aff[:, None, None], l1.L, eye64))
        a = torch.where(ok_aff[:, None, None], a.to(self.dtype), eye)
        mu2 = torch.where(ok_aff[:, None], mu2, mean)
        w0, out = self._sample_old(chans, halfw, mean, spacing, mu2, a)
        total = w0.sum((1, 2), keepdim=True)
        live = w0 > torch.finfo(self.dtype).tiny * 1e6
        safe = torch.where(live, w0, 1.0)
        m_new = torch.where(live, out[:, 1] / safe, s_m[:, None, None])
        interp_ok = (total.reshape(n) > 0) & (sigma >= 1.5 * self.spacing).all(1)
        w_interp = w0 / torch.where(total > 0, total, 1.0)
        w_gauss = self._gaussian_weights(mean, cov + torch.diag_embed(self.spacing**2 / 12.0),
                                         mean, spacing)
        ok3 = interp_ok[:, None, None]
        weights = torch.where(ok3, w_interp, w_gauss)
        m_new = torch.where(ok3, m_new, s_m[:, None, None].expand_as(m_new))
        # keep the run's total scalar variance: v' = total − Var_w'(m')
        mbar = (weights * m_new).sum((1, 2))
        v_new = (s_v - (weights * m_new * m_new).sum((1, 2)) + mbar * mbar).clamp_min(
            1e-6 * self.scalar_var)
        self._assign(None, mean, spacing, weights, m_new, v_new)

