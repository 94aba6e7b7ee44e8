"""Batched point-mass filter: grid Bayes over a 2-D state, a scalar Kalman part per cell.

The acquisition configuration of the one lattice filter
(`neuralmap.filters.lattice.filter.LatticeFilter`; Bergman, Ljung and Gustafsson's
point-mass filter, the convolution form of the prediction of Matoušek, Duník et al.) for
N independent runs at once. Each run carries

* a regular ``G × G`` grid over the 2-D state ``s = (s_x, s_y)`` (in terrain navigation the
  horizontal INS error), centred at ``centre (N, 2)`` with per-axis spacing
  ``spacing (N, 2)`` (the lattice's ``axes = diag(spacing)``); cell ``(i, j)`` (row ``i``
  along y, column ``j`` along x) sits at ``centre + spacing · (j − h, i − h)``,
  ``h = (G − 1) / 2``;
* normalised cell masses ``w (N, G, G)`` (the discrete posterior, Dirac convention);
* a Rao-Blackwellised scalar Gaussian per cell, ``a | cell ij ~ N(m_ij, v)`` (the altitude
  error), entering the measurement linearly: the lattice filter's linear part with
  ``nz = 1``, ``E = 0``, ``F = 1``, ``c = 1`` (``scalar_mean`` is ``lin_mean[:, 0]``,
  ``scalar_var`` is ``lin_cov[:, 0, 0]``). ``v`` is one number per run: with a common ``R``
  the scalar Kalman variance update does not depend on the cell, and the moment-matched
  prediction keeps the run's total variance ``v + Var_w(m)`` exact.

Measurement model (one scalar per run and step)::

    y = g(s) + a + e,      e ~ N(0, R)  (optionally a Gaussian + uniform mixture)

where ``g`` is given per cell by the caller (``predicted (N, G, G)``, or a callable mapping
the cell coordinates ``(N, G, G, 2)`` to it): the filter knows nothing of what ``g`` is.
Update per cell (the lattice filter's): ``ν = y − g − m``, ``S = v + R``,
``log w += −½ ν²/S``, ``m += v ν / S``, ``v ← v R / S`` — the marginalised likelihood of
the Rao-Blackwellised point-mass filter, in the log domain; a run whose likelihood is zero
(or not finite) in every cell keeps its prior weights, counted in
`PointMassFilter.recoveries` — never NaN.

Prediction and the adaptive grid are the ``fixed`` / ``adaptive`` lattice rule
(`neuralmap.filters.lattice.grid_rule.GridLattice`: deferred diffusion by separable
convolution, re-centring and re-sizing as the posterior moves and shrinks).
"""

from __future__ import annotations

from collections.abc import Callable

import torch

from neuralmap.filters.lattice.filter import LatticeFilter, LatticeUpdate
from neuralmap.filters.lattice.grid_rule import DIFFUSE_MIN_CELLS, GridLattice, PointMassConfig
from neuralmap.filters.lattice.kernels import BANDED_MIN_HALF_LEN, convolve_axis, gaussian_kernels
from neuralmap.filters.lattice.kernels import toeplitz_kernels as toeplitz_kernels

# the kernels are those of `neuralmap.filters.lattice.kernels` (re-exported here)
__all__ = ["BANDED_MIN_HALF_LEN", "DIFFUSE_MIN_CELLS", "PointMassConfig", "PointMassFilter",
           "PointMassUpdate", "convolve_axis", "gaussian_kernels", "toeplitz_kernels"]

#: Per-run results of `PointMassFilter.update` (the lattice filter's; ``nis``,
#: ``innovation`` and ``widened`` are None on the grid).
PointMassUpdate = LatticeUpdate


class PointMassFilter(LatticeFilter):
    """N point-mass filters over a 2-D state with a Rao-Blackwellised scalar, in lock-step:
    the lattice filter with the grid rule (``fixed`` or ``adaptive``) and the scalar model.

    Args:
        mean: ``(N, 2)`` prior mean of the grid state.
        cov: ``(2, 2)`` or ``(N, 2, 2)`` prior covariance (symmetric positive definite).
        scalar_mean: Prior mean of the scalar part, float or ``(N,)``.
        scalar_var: Prior variance of the scalar part (> 0), float or ``(N,)``.
        config: Grid options (`PointMassConfig`).
        dtype: float32 or float64 (default float64).

    Attributes:
        weights: ``(N, G, G)`` normalised cell masses (rows along y, columns along x).
        scalar_mean: ``(N, G, G)`` per-cell mean of the scalar part (``lin_mean[:, 0]``).
        scalar_var: ``(N,)`` conditional variance of the scalar part (``lin_cov[:, 0, 0]``).
        centre: ``(N, 2)`` grid centres.
        spacing: ``(N, 2)`` grid spacing per axis (the diagonal of ``axes``).
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
        from neuralmap.exceptions import NeuralMapError

        config = (config or PointMassConfig()).validate()
        if dtype not in (torch.float32, torch.float64):
            raise NeuralMapError(f"PointMassFilter: dtype must be float32 or float64, got {dtype}.")
        mean = torch.as_tensor(mean)
        if mean.ndim != 2 or mean.shape[1] != 2 or mean.shape[0] < 1:
            raise NeuralMapError(
                f"PointMassFilter: mean must have shape (N, 2), got {tuple(mean.shape)}."
            )
        n, dev = mean.shape[0], mean.device
        kw = {"dtype": dtype, "device": dev}
        super().__init__(GridLattice(config, n, dtype, dev), n, E=torch.zeros(2, 1, **kw),
                         F=torch.ones(1, 1, **kw), c=torch.ones(1, **kw), dtype=dtype,
                         device=dev, name="PointMassFilter")
        self.config = config
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
        self.rule.reset(self, mean, cov, scalar_mean, scalar_var, mask)

    # ------------------------------------------------------------------ views
    @property
    def scalar_mean(self) -> torch.Tensor:
        """``(N, G, G)`` per-cell mean of the scalar part (a view of ``lin_mean``)."""
        return self.lin_mean[:, 0]

    @property
    def scalar_var(self) -> torch.Tensor:
        """``(N,)`` conditional variance of the scalar part (a view of ``lin_cov``)."""
        return self.lin_cov[:, 0, 0]

    @property
    def spacing(self) -> torch.Tensor:
        """``(N, 2)`` grid spacing per axis (a view of the diagonal of ``axes``)."""
        return torch.diagonal(self.axes, dim1=1, dim2=2)

    @property
    def _pending(self) -> torch.Tensor:
        """``(N, 2)`` process noise not yet convolved into the masses (the rule's)."""
        return self.rule.pending

    def mean(self) -> torch.Tensor:
        """``(N, 2)`` posterior mean ``Σ w s``."""
        return self.rule.mean_cov(self)[0]

    def cov(self) -> torch.Tensor:
        """``(N, 2, 2)`` posterior covariance ``Σ w (s − s̄)(s − s̄)ᵀ`` plus the process
        noise not yet applied to the grid (see `DIFFUSE_MIN_CELLS`); symmetric."""
        return self.rule.mean_cov(self)[1] + self.rule.deferred_cov(self)

    def scalar_moments(self) -> tuple[torch.Tensor, torch.Tensor]:
        """Mixture mean and variance ``(N,)`` of the scalar part over the grid."""
        w, m_ = self.weights, self.scalar_mean
        m = (w * m_).sum((1, 2))
        v = self.scalar_var + (w * m_**2).sum((1, 2)) - m * m
        return m, v.clamp_min(0.0)

    def _gaussian_weights(self, mean: torch.Tensor, cov: torch.Tensor, centre: torch.Tensor,
                          spacing: torch.Tensor) -> torch.Tensor:
        """Normalised masses of ``N(mean, cov)`` on the grid ``(centre, spacing)``."""
        return self.rule.gaussian_weights(self, mean, cov, centre, spacing)

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
        return self.rule.gaussian_affinity(self, index)

    # ------------------------------------------------------------------ predict / update
    def predict(
        self,
        *,
        Q: torch.Tensor | float,
        shift: torch.Tensor | None = None,
        scalar_q: float | torch.Tensor = 0.0,
    ) -> torch.Tensor:
        """Time update ``s ← s + shift + w``, ``w ~ N(0, diag(Q))``; scalar part ``+ scalar_q``
        (`GridLattice.predict`).

        Args:
            Q: Process noise of the grid state: ``(2, 2)``, ``(N, 2, 2)`` (only the
                diagonal is used: the convolution is separable), ``(N, 2)`` variances, or
                a float (both axes).
            shift: ``(N, 2)`` known displacement (moves the grid centre), or None.
            scalar_q: Process-noise variance of the scalar part, float or ``(N,)``.

        Returns:
            ``(N,)`` bool, runs moved to a new grid before the convolution.
        """
        return self.rule.predict(self, Q=Q, shift=shift, scalar_q=scalar_q)

    def update(
        self,
        measurement: torch.Tensor,
        predicted: torch.Tensor | Callable[[torch.Tensor], torch.Tensor],
        *,
        R: float | torch.Tensor,
        mask: torch.Tensor | None = None,
        cell_variance: torch.Tensor | None = None,
    ) -> PointMassUpdate:
        """Measurement update ``y = g(s) + a + e`` in every cell (`LatticeFilter.update`).

        Args:
            measurement: ``(N,)`` measurement ``y`` (NaN = no measurement for that run).
            predicted: ``(N, G, G)`` ``g`` at every cell, or a callable taking the cell
                coordinates ``(N, G, G, 2)`` (`points`) and returning it. Non-finite
                cells get zero likelihood.
            R: Measurement noise variance (> 0), float or ``(N,)``.
            mask: ``(N,)`` bool, runs to update (None = all).
            cell_variance: ``(N, G, G)`` extra variance of ``g`` within each cell (the
                spread of the model over the cell's area), or None: added to ``S`` in the
                likelihood of that cell only ("likelihood flattening").

        Returns:
            `PointMassUpdate`.
        """
        return super().update(measurement, predicted, R=R, mask=mask,
                              cell_variance=cell_variance)

    def regrid(self, candidates: torch.Tensor | None = None, *,
               extra_cov: torch.Tensor | None = None) -> torch.Tensor:
        """Moves runs whose density no longer fits their grid (`GridLattice.regrid`).

        Args:
            candidates: ``(N,)`` bool, runs allowed to move (None = all).
            extra_cov: ``(N, 2)`` variances added to the posterior's when sizing the grid
                (the process noise of the coming prediction), or None.

        Returns:
            ``(N,)`` bool, runs moved.
        """
        return self.rule.regrid(self, candidates, extra_cov=extra_cov)
