"""The grid lattice rules of the point-mass filter: ``fixed`` and ``adaptive``.

An axis-aligned regular ``G × G`` grid (``axes = diag(spacing)``), the lattice rule of
acquisition (Bergman, Ljung and Gustafsson's point-mass filter; the convolution form of the
prediction of Matoušek, Duník et al.):

* **prediction** ``s_{k+1} = s_k + u_k + w_k``, ``w_k ~ N(0, diag(q_x, q_y))``: the grid
  centre is moved by the known shift ``u`` (no interpolation); the process noise is
  accumulated per run and convolved into the masses (separable Gaussian kernels, `blur`)
  once it reaches ``DIFFUSE_MIN_CELLS`` on an axis (deferred diffusion: variances add, a
  blur far below one cell changes nothing a grid can show). The scalar linear part (the
  ``nz = 1``, ``E = 0``, ``F = c = 1`` case of the lattice filter: the altitude error) is
  mixed with the masses (the convolution of ``w`` and ``w m``) and its variance keeps the
  run's total ``v' = v + Σ w m² − Σ w' m'²``, then gets ``q_a`` added;
* **adaptive regrid** (``adaptive``, before each prediction): a run whose posterior needs
  less than ``shrink_ratio`` of the grid's half-width (``span_sigma`` σ per axis), whose
  mean left the central ``recentre_fraction``, or whose ``span_sigma`` box pokes out, moves
  to a grid centred on its mean with the spacing that fits the box (never below
  ``min_spacing``). Masses are carried over by bilinear interpolation of the density
  mapped affinely so that the old mean and covariance are kept; a posterior narrower than
  1.5 old cells gets its Gaussian fit instead;
* the ``fixed`` grid is sized once from the prior.

The measurement update is the lattice filter's (`neuralmap.filters.lattice.filter`); this
rule adds its weight floor (masses below ``weight_floor`` raised to it, no
renormalisation) and the Gaussian + uniform outlier likelihood.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.filters.lattice.filter import to_state
from neuralmap.filters.lattice.kernels import (
    blur,
    conditional_mean,
    gaussian_log_density,
    mass_moments,
    normalised,
    resample_bilinear,
)

if TYPE_CHECKING:
    from neuralmap.filters.lattice.filter import LatticeFilter

__all__ = ["DIFFUSE_MIN_CELLS", "GridLattice", "PointMassConfig"]

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


def _spacing(f: LatticeFilter) -> torch.Tensor:
    """``(N, 2)`` grid spacing: the diagonal of the (diagonal) cell steps (a view)."""
    return torch.diagonal(f.axes, dim1=1, dim2=2)


def _batch(value: object, shape: tuple[int, ...], name: str, dtype: torch.dtype,
           device: torch.device) -> torch.Tensor:
    """Broadcasts a float or tensor to ``shape`` (raises on a shape that does not fit)."""
    t = torch.as_tensor(value, dtype=dtype, device=device)
    try:
        return t.expand(shape) if t.ndim <= len(shape) else t.reshape(shape)
    except RuntimeError as exc:
        raise NeuralMapError(
            f"PointMassFilter: {name} must broadcast to {shape}, got {tuple(t.shape)}."
        ) from exc


class GridLattice:
    """The ``fixed`` / ``adaptive`` grid rule (module docstring) of a `LatticeFilter`.

    Args:
        config: `PointMassConfig` (``adaptive`` selects the rule).
        n_runs: Runs N.
        dtype, device: Of the filter.

    Attributes:
        pending: ``(N, 2)`` process-noise variance accumulated but not yet convolved into
            the masses (part of the posterior covariance).
    """

    reports_nis = False

    def __init__(self, config: PointMassConfig, n_runs: int, dtype: torch.dtype,
                 device: torch.device) -> None:
        self.config = config.validate()
        self.outlier_prob, self.outlier_width = config.outlier_prob, config.outlier_width
        self.pending = torch.zeros(n_runs, 2, dtype=dtype, device=device)
        self._chans = torch.empty(n_runs, 2, config.cells, config.cells, dtype=dtype,
                                  device=device)

    # ------------------------------------------------------------------ per-run bookkeeping
    def take(self, index: torch.Tensor) -> GridLattice:
        out = object.__new__(GridLattice)
        out.__dict__.update(self.__dict__)
        out.pending = self.pending.index_select(0, index)
        out._chans = torch.empty(int(index.numel()), *self._chans.shape[1:],
                                 dtype=self._chans.dtype, device=self._chans.device)
        return out

    def cat(self, other: GridLattice) -> GridLattice:
        out = self.take(torch.arange(self.pending.shape[0], device=self.pending.device))
        out.pending = torch.cat([self.pending, other.pending])
        out._chans = torch.empty(out.pending.shape[0], *self._chans.shape[1:],
                                 dtype=self._chans.dtype, device=self._chans.device)
        return out

    def deferred_cov(self, f: LatticeFilter) -> torch.Tensor:
        """``(N, 2, 2)`` process noise not yet applied to the grid."""
        return torch.diag_embed(self.pending)

    # ------------------------------------------------------------------ update hooks
    def floor_weights(self, w: torch.Tensor) -> torch.Tensor:
        """Masses below ``weight_floor`` raised to it (keeps every cell alive; adds at most
        ``G² · floor`` of mass)."""
        floor = self.config.weight_floor
        return w.clamp_(min=floor) if floor > 0.0 else w

    def after_update(self, f: LatticeFilter, nis: torch.Tensor | None, applied: torch.Tensor,
                     regrid: bool) -> None:
        """Nothing: the grid regrids before the prediction."""
        return None

    # ------------------------------------------------------------------ moments
    def mean_cov(self, f: LatticeFilter, w: torch.Tensor | None = None,
                 centre: torch.Tensor | None = None,
                 axes: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
        """Mean ``(N, 2)`` and covariance ``(N, 2, 2)`` of the masses alone (default: the
        state's)."""
        w = f.weights if w is None else w
        u, cu = mass_moments(w, f.offsets)
        return to_state(u, cu, f.centre if centre is None else centre,
                        f.axes if axes is None else axes)

    def gaussian_weights(self, f: LatticeFilter, mean: torch.Tensor, cov: torch.Tensor,
                         centre: torch.Tensor, spacing: torch.Tensor) -> torch.Tensor:
        """Normalised masses of ``N(mean, cov)`` sampled on the grid ``(centre, spacing)``
        (`gaussian_log_density` in cell units)."""
        u = (mean - centre) / spacing
        cu = cov / (spacing[:, :, None] * spacing[:, None, :])
        return normalised(gaussian_log_density(f.offsets, u, cu))

    # ------------------------------------------------------------------ prior
    def reset(self, f: LatticeFilter, mean: torch.Tensor, cov: torch.Tensor,
              scalar_mean: float | torch.Tensor, scalar_var: float | torch.Tensor,
              mask: torch.Tensor | None) -> None:
        """Writes the Gaussian prior ``N(mean, cov)``, scalar part ``N(scalar_mean,
        scalar_var)``, on a grid sized from ``cov`` into the runs ``mask`` (None = all)."""
        n, dt, dev = f.n_runs, f.dtype, f.device
        cfg, half = self.config, f.half
        mean = _batch(mean, (n, 2), "mean", dt, dev)
        cov = _batch(cov, (n, 2, 2), "cov", dt, dev)
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
        s_mean = _batch(scalar_mean, (n,), "scalar_mean", dt, dev)
        s_var = _batch(scalar_var, (n,), "scalar_var", dt, dev)
        if not bool((s_var > 0).all()):
            raise NeuralMapError("PointMassFilter: scalar_var must be > 0 for every run.")
        sigma = torch.diagonal(cov, dim1=1, dim2=2).sqrt()
        need = cfg.span_sigma * sigma
        if cfg.spacing is None:
            spacing = (need / half).clamp_min(cfg.min_spacing)
        else:
            spacing = torch.full_like(sigma, cfg.spacing)
            short = (spacing * half) < need * (1.0 - 1e-9)
            if bool(short.any()):
                first = int(short.any(1).nonzero()[0])
                raise NeuralMapError(
                    f"PointMassFilter: a grid of {f.cells} cells at spacing "
                    f"{cfg.spacing:g} covers ±{cfg.spacing * half:g} "
                    f"but the prior of run {first} needs ±{need[first].max().item():g} "
                    f"({cfg.span_sigma:g} σ). Increase 'cells' or 'spacing', or "
                    "leave spacing None to size the grid from the prior."
                )
        weights = self.gaussian_weights(f, mean, cov, mean, spacing)
        self.assign(f, mask, mean, spacing, weights, s_mean[:, None, None].expand_as(weights),
                    s_var)

    def assign(self, f: LatticeFilter, mask: torch.Tensor | None, centre: torch.Tensor,
               spacing: torch.Tensor, weights: torch.Tensor, s_mean: torch.Tensor,
               s_var: torch.Tensor) -> None:
        """Writes grid state for the runs in ``mask`` (all when None), in place."""
        sp, m_, v_ = _spacing(f), f.lin_mean[:, 0], f.lin_cov[:, 0, 0]
        if mask is None:
            self.pending.zero_()
            f.centre.copy_(centre)
            sp.copy_(spacing)
            f.weights.copy_(weights)
            m_.copy_(s_mean)
            v_.copy_(s_var)
        else:
            m1, m3 = mask[:, None], mask[:, None, None]
            self.pending.masked_fill_(m1, 0.0)
            f.centre.copy_(torch.where(m1, centre, f.centre))
            sp.copy_(torch.where(m1, spacing, sp))
            f.weights.copy_(torch.where(m3, weights, f.weights))
            m_.copy_(torch.where(m3, s_mean, m_))
            v_.copy_(torch.where(mask, s_var, v_))

    # ------------------------------------------------------------------ predict
    def predict(self, f: LatticeFilter, *, Q: torch.Tensor | float,
                shift: torch.Tensor | None = None,
                scalar_q: float | torch.Tensor = 0.0) -> torch.Tensor:
        """Time update ``s ← s + shift + w``, ``w ~ N(0, diag(Q))``; scalar part ``+ scalar_q``.

        Args:
            f: The filter.
            Q: Process noise of the grid state: ``(2, 2)``, ``(N, 2, 2)`` (only the
                diagonal is used: the convolution is separable), ``(N, 2)`` variances, or
                a float (both axes).
            shift: ``(N, 2)`` known displacement (moves the grid centre), or None.
            scalar_q: Process-noise variance of the scalar part, float or ``(N,)``.

        Returns:
            ``(N,)`` bool, runs moved to a new grid (sized for the predicted density)
            before the convolution.
        """
        n, dt, dev = f.n_runs, f.dtype, f.device
        q = torch.as_tensor(Q, dtype=dt, device=dev)
        if q.ndim >= 2 and q.shape[-1] == 2 and q.shape[-2] == 2:
            q = torch.diagonal(q, dim1=-2, dim2=-1)
        q = _batch(q, (n, 2), "Q", dt, dev)
        if bool((q < 0).any()) or not bool(torch.isfinite(q).all()):
            raise NeuralMapError("PointMassFilter.predict: Q must be finite and >= 0.")
        if shift is not None:
            f.centre.add_(_batch(shift, (n, 2), "shift", dt, dev))
        if self.config.adaptive:
            regridded = self.regrid(f, extra_cov=q)
        else:
            regridded = torch.zeros(n, dtype=torch.bool, device=dev)
        sq = _batch(scalar_q, (n,), "scalar_q", dt, dev)
        self.pending.add_(q)
        sigma_cells = self.pending.sqrt() / _spacing(f)  # (N, 2)
        due = (sigma_cells >= DIFFUSE_MIN_CELLS).any(1)
        m_, v_ = f.lin_mean[:, 0], f.lin_cov[:, 0, 0]
        if bool(due.all()):
            w, m, v = self._diffuse(f.weights, m_, v_, sigma_cells, self._chans)
            f.weights.copy_(w)
            m_.copy_(m)
            v_.copy_(v)
            self.pending.zero_()
        elif bool(due.any()):
            idx = due.nonzero().reshape(-1)
            w, m, v = self._diffuse(f.weights.index_select(0, idx), m_.index_select(0, idx),
                                    v_.index_select(0, idx), sigma_cells.index_select(0, idx),
                                    None)
            f.weights.index_copy_(0, idx, w)
            m_.index_copy_(0, idx, m)
            v_.index_copy_(0, idx, v)
            self.pending.masked_fill_(due[:, None], 0.0)
        v_.add_(sq)
        return regridded

    @staticmethod
    def _diffuse(w: torch.Tensor, m: torch.Tensor, v: torch.Tensor, sigma_cells: torch.Tensor,
                 buf: torch.Tensor | None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Convolves masses ``(M, G, G)`` with per-run Gaussians of ``sigma_cells (M, 2)``
        cells and mixes the scalar part (module docstring); returns new ``w, m, v``."""
        n, g = w.shape[0], w.shape[-1]
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

    # ------------------------------------------------------------------ adaptive grid
    def _sample_old(self, f: LatticeFilter, chans: torch.Tensor, halfw: torch.Tensor,
                    spacing: torch.Tensor, anchor: torch.Tensor,
                    affine: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Bilinear samples of the old grid's channels at ``anchor + A (s − centre)``.

        ``s`` runs over the new grid (spacing ``spacing``); returns the clamped mass
        channel ``(N, G, G)`` and all channels ``(N, C, G, G)``.
        """
        n, g, off = f.n_runs, f.cells, f.offsets
        dx = (spacing[:, 0:1] * off)[:, None, :].expand(n, g, g)
        dy = (spacing[:, 1:2] * off)[:, :, None].expand(n, g, g)
        a = affine[:, :, :, None, None]
        px = anchor[:, 0, None, None] + a[:, 0, 0] * dx + a[:, 0, 1] * dy
        py = anchor[:, 1, None, None] + a[:, 1, 0] * dx + a[:, 1, 1] * dy
        grid = torch.stack([(px - f.centre[:, 0, None, None]) / halfw[:, 0, None, None],
                            (py - f.centre[:, 1, None, None]) / halfw[:, 1, None, None]], -1)
        out = resample_bilinear(chans, grid, padding="zeros")
        return out[:, 0].clamp_min(0.0), out

    def regrid(self, f: LatticeFilter, candidates: torch.Tensor | None = None, *,
               extra_cov: torch.Tensor | None = None) -> torch.Tensor:
        """Moves runs whose density no longer fits their grid (rule: module docstring).

        Args:
            f: The filter.
            candidates: ``(N,)`` bool, runs allowed to move (None = all).
            extra_cov: ``(N, 2)`` variances added to the posterior's when sizing the grid
                (the process noise of the coming prediction), or None.

        Returns:
            ``(N,)`` bool, runs moved.
        """
        cfg = self.config
        mean, cov = self.mean_cov(f)
        cov = cov + self.deferred_cov(f)
        sp = _spacing(f)
        sigma = torch.diagonal(cov, dim1=1, dim2=2).clamp_min(0.0).sqrt()
        var_next = sigma**2 if extra_cov is None else sigma**2 + extra_cov
        need = cfg.span_sigma * var_next.sqrt()
        halfw = sp * f.half
        off = (mean - f.centre).abs()
        # new grids get a growth margin so that a slowly widening density does not move
        # its grid every step
        spacing = ((1.0 + cfg.grow_margin) * need.clamp_min(cfg.min_half_width)
                   / f.half).clamp_min(cfg.min_spacing)
        shrink = (need < cfg.shrink_ratio * halfw) & (spacing < sp * (1 - 1e-6))
        move = (shrink.any(1)
                | (off > cfg.recentre_fraction * halfw).any(1)
                | (off + need > halfw * (1 + 1e-6)).any(1))
        if candidates is not None:
            move = move & candidates
        if not bool(move.any()):
            return move
        if bool(move.all()):  # every run moves (a shrinking posterior): in place, no copies
            pending = self.pending.clone()  # deferred process noise stays with the run
            self._move(f, mean, cov, sigma, spacing, halfw)
            self.pending.copy_(pending)
        else:
            idx = move.nonzero().reshape(-1)
            sub = f.take(idx)
            sub.rule._move(sub, mean[idx], cov[idx], sigma[idx], spacing[idx], halfw[idx])
            for name in ("weights", "lin_mean", "lin_cov", "centre", "axes"):
                getattr(f, name).index_copy_(0, idx, getattr(sub, name))
        f.regrids.add_(move.long())
        return move

    def _move(self, f: LatticeFilter, mean: torch.Tensor, cov: torch.Tensor,
              sigma: torch.Tensor, spacing: torch.Tensor, halfw: torch.Tensor) -> None:
        """Moves every run of ``f`` to the grid ``(mean, spacing)`` (see regrid)."""
        n, dt, dev = f.n_runs, f.dtype, f.device
        w, m_old, v_old = f.weights, f.lin_mean[:, 0], f.lin_cov[:, 0, 0]
        sp_old = _spacing(f)
        chans = torch.stack([w, w * m_old], 1)
        s_m = (w * m_old).sum((1, 2))  # mixture mean and variance of the scalar part
        s_v = (v_old + (w * m_old**2).sum((1, 2)) - s_m * s_m).clamp_min(0.0)
        eye = torch.eye(2, dtype=dt, device=dev).expand(n, 2, 2)
        # pass 1: plain interpolation; pass 2: the new cells mapped by the affine map that
        # gives the interpolated density the old grid's mean and covariance exactly
        w0, out = self._sample_old(f, chans, halfw, spacing, mean, eye)
        total = w0.sum((1, 2))
        w1 = w0 / torch.where(total > 0, total, 1.0)[:, None, None]
        mu2, c2 = self.mean_cov(f, w1, mean, torch.diag_embed(spacing))
        l1 = torch.linalg.cholesky_ex(cov.double())
        l2 = torch.linalg.cholesky_ex(c2.double())
        ok_aff = (l1.info == 0) & (l2.info == 0)
        eye64 = torch.eye(2, dtype=torch.float64, device=dev)
        a = l2.L @ torch.linalg.inv(torch.where(ok_aff[:, None, None], l1.L, eye64))
        a = torch.where(ok_aff[:, None, None], a.to(dt), eye)
        mu2 = torch.where(ok_aff[:, None], mu2, mean)
        w0, out = self._sample_old(f, chans, halfw, spacing, mu2, a)
        total = w0.sum((1, 2), keepdim=True)
        live = w0 > torch.finfo(dt).tiny * 1e6
        safe = torch.where(live, w0, 1.0)
        m_new = torch.where(live, out[:, 1] / safe, s_m[:, None, None])
        interp_ok = (total.reshape(n) > 0) & (sigma >= 1.5 * sp_old).all(1)
        w_interp = w0 / torch.where(total > 0, total, 1.0)
        w_gauss = self.gaussian_weights(f, mean, cov + torch.diag_embed(sp_old**2 / 12.0),
                                        mean, spacing)
        ok3 = interp_ok[:, None, None]
        weights = torch.where(ok3, w_interp, w_gauss)
        m_new = torch.where(ok3, m_new, s_m[:, None, None].expand_as(m_new))
        # keep the run's total scalar variance: v' = total − Var_w'(m')
        mbar = (weights * m_new).sum((1, 2))
        v_new = (s_v - (weights * m_new * m_new).sum((1, 2)) + mbar * mbar).clamp_min(
            1e-6 * v_old)
        self.assign(f, None, mean, spacing, weights, m_new, v_new)

    # ------------------------------------------------------------------ diagnostics
    def gaussian_affinity(self, f: LatticeFilter,
                          index: torch.Tensor | None = None) -> torch.Tensor:
        """``(N,)`` (or ``(K,)``) Bhattacharyya coefficient between the grid posterior and
        its Gaussian fit (`neuralmap.filters.point_mass.PointMassFilter.gaussian_affinity`)."""
        sp = _spacing(f)
        mean, cov = self.mean_cov(f)
        cov = cov + self.deferred_cov(f) + torch.diag_embed(sp**2 / 12.0)
        centre, w = f.centre, f.weights
        if index is not None:
            cov, mean, centre, sp, w = (t.index_select(0, index)
                                        for t in (cov, mean, centre, sp, w))
        g = self.gaussian_weights(f, mean, cov, centre, sp)
        return (w * g).sqrt().sum((1, 2))
