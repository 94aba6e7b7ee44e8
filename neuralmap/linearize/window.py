"""Plane fits over the window Omega = 6 sigma_x x 6 sigma_y around the estimate (SEEDS 000).

The window Omega around the estimate (SEEDS 000 calls it the region) is sampled on a fixed
``n x n`` pattern of bilinear DEM samples, scaled to the window, so every estimate has the
same number of samples and the whole batch is one tensor operation. In the pattern's
normalised coordinates ``(xi, eta) in [-3, 3]^2`` the design ``[1, xi, eta]`` is the same
for every estimate, so any linear plane-fit rule is a constant ``(3, n^2)`` matrix applied
to the ``(n^2, N)`` samples: the fit is closed-form and batched.
"""

from __future__ import annotations

import math

import torch

from neuralmap.dem.tile import DemTile
from neuralmap.exceptions import NeuralMapError
from neuralmap.linearize.base import Linearization, Linearizer
from neuralmap.linearize.checks import check_points, check_pos_cov
from neuralmap.terrain.grid import INTERPOLATIONS, GridTerrain

#: Fixed window sigmas of SEEDS 000 (Omega = 6 sigma x 6 sigma): Omega_max, _mean, _min.
SIGMA_MAX_M = 400.0
SIGMA_MEAN_M = 240.0
SIGMA_MIN_M = 80.0

#: Default upper clamp of the adaptive sigma, metres.
ADAPTIVE_MAX_SIGMA_M = 1000.0
#: Default pattern size for the adaptive window.
ADAPTIVE_N_SAMPLES = 15
_AUTO_N_RANGE = (5, 33)


def sample_pattern(n: int) -> torch.Tensor:
    """Cell-centred ``n x n`` sample pattern over ``[-3, 3]^2`` (units of sigma).

    Symmetric about 0 on both axes, so the least-squares plane of a quadratic has exactly
    the quadratic's gradient at the centre.

    Args:
        n: Samples per axis (>= 2).

    Returns:
        ``(n * n, 2)`` float64 ``(xi, eta)``; ``xi`` varies fastest.
    """
    ticks = -3.0 + (torch.arange(n, dtype=torch.float64) + 0.5) * (6.0 / n)
    eta, xi = torch.meshgrid(ticks, ticks, indexing="ij")
    return torch.stack([xi.reshape(-1), eta.reshape(-1)], dim=-1)


class WindowPlaneLinearizer(Linearizer):
    """Base class: a plane fitted by a linear rule to samples of the window around ``xy``.

    Subclasses provide `make_solver` (the rule). The height is the bilinear DEM
    height at the estimate (the map look-up ``h_d(x^, y^)`` of SEEDS 000 eq. 4); the plane
    gives the slope; the variance is the plane-fit residual variance
    ``sum(r^2) / (n^2 - 3)`` over the samples. Samples and height come from the bilinear
    DEM (``interpolation="bicubic"`` samples the bicubic surface instead, on which a fit of a
    quadratic terrain is exact).

    The window Omega around the estimate (SEEDS 000 calls it the region) spans
    ``6 sigma_x x 6 sigma_y``. Its size: ``sigma`` fixed (a number, or
    ``(sigma_x, sigma_y)``) or ``"adaptive"``: ``sigma_x, sigma_y = sqrt(diag(pos_cov))``,
    clamped to ``[min_sigma, max_sigma]`` (default ``min_sigma`` = the grid spacing per
    axis, so the window always spans at least 6 cells; default ``max_sigma`` = 1000 m).
    The adaptive window is axis-aligned: the position cross-covariance is not used.
    Non-finite covariances give ``max_sigma``.

    Samples that fall outside the tile take the border heights (GridTerrain clamps); flag
    off-map estimates with ``linearizer.grid.contains(xy)``.

    Args:
        tile: The DEM tile.
        sigma: Window half-width / 3 in metres, ``(sigma_x, sigma_y)``, or ``"adaptive"``.
        n_samples: Samples per axis (``n x n`` in all). ``None``: for a fixed sigma, enough
            for a sample spacing no coarser than the grid spacing, clamped to [5, 33]; for
            the adaptive window, 15.
        min_sigma: Lower clamp of the adaptive sigma (m, or per axis); ``None`` = spacing.
        max_sigma: Upper clamp of the adaptive sigma (m).
        interpolation: DEM interpolant sampled: ``"bilinear"`` (default) or ``"bicubic"``.
        dtype: Dtype of the height buffer (outputs use ``xy``'s dtype).

    Raises:
        NeuralMapError: Bad ``sigma``, ``n_samples`` or clamps.
    """

    pattern: torch.Tensor
    design: torch.Tensor
    solver: torch.Tensor

    def __init__(
        self,
        tile: DemTile,
        *,
        sigma: float | tuple[float, float] | str = SIGMA_MAX_M,
        n_samples: int | None = None,
        min_sigma: float | tuple[float, float] | None = None,
        max_sigma: float = ADAPTIVE_MAX_SIGMA_M,
        interpolation: str = "bilinear",
        dtype: torch.dtype = torch.float64,
    ) -> None:
        super().__init__()
        who = type(self).__name__
        if interpolation not in INTERPOLATIONS:
            raise NeuralMapError(
                f"{who}: interpolation must be one of {', '.join(INTERPOLATIONS)}, got "
                f"{interpolation!r}."
            )
        self.grid = GridTerrain(tile, method=interpolation, dtype=dtype)
        self.adaptive = isinstance(sigma, str)
        if self.adaptive:
            if sigma != "adaptive":
                raise NeuralMapError(
                    f"{who}: sigma must be a positive number of metres, a pair "
                    f"(sigma_x, sigma_y), or 'adaptive'; got {sigma!r}."
                )
            self.sigma = None
            lo = tile.spacing if min_sigma is None else _pair(min_sigma, "min_sigma", who)
            hi = _pair(max_sigma, "max_sigma", who)
            if any(h < low for h, low in zip(hi, lo, strict=True)):
                raise NeuralMapError(
                    f"{who}: max_sigma {hi} must be >= min_sigma {lo} (metres)."
                )
            self.sigma_bounds = (tuple(lo), tuple(hi))
        else:
            self.sigma = _pair(sigma, "sigma", who)
            self.sigma_bounds = None
        if n_samples is None:
            if self.adaptive:
                n_samples = ADAPTIVE_N_SAMPLES
            else:
                need = max(6.0 * s / d for s, d in zip(self.sigma, tile.spacing, strict=True))
                n_samples = min(max(math.ceil(need) + 1, _AUTO_N_RANGE[0]), _AUTO_N_RANGE[1])
        if isinstance(n_samples, bool) or not isinstance(n_samples, int) or n_samples < 2:
            raise NeuralMapError(
                f"{who}: n_samples must be an integer >= 2 (samples per axis), got "
                f"{n_samples!r}."
            )
        self.n_samples = n_samples
        pattern = sample_pattern(n_samples)
        design = torch.cat([torch.ones(n_samples**2, 1, dtype=torch.float64), pattern], dim=1)
        solver = self.make_solver(pattern, design)
        self.register_buffer("pattern", pattern.to(dtype), persistent=False)
        self.register_buffer("design", design.to(dtype), persistent=False)
        self.register_buffer("solver", solver.to(dtype), persistent=False)

    def make_solver(self, pattern: torch.Tensor, design: torch.Tensor) -> torch.Tensor:
        """The fit rule: ``(3, n^2)`` matrix mapping samples to ``(c0, c_xi, c_eta)``.

        Args:
            pattern: ``(n^2, 2)`` normalised sample positions.
            design: ``(n^2, 3)`` design matrix ``[1, xi, eta]``.

        Returns:
            ``(3, n^2)`` float64 matrix.
        """
        raise NotImplementedError

    def extra_repr(self) -> str:
        """Short description for ``print(linearizer)``."""
        sigma = "adaptive" if self.adaptive else self.sigma
        return (
            f"sigma={sigma}, n_samples={self.n_samples}, bounds={self.sigma_bounds}, "
            f"interpolation={self.grid.method!r}"
        )

    def window_sigma(self, xy: torch.Tensor, pos_cov: torch.Tensor | None) -> torch.Tensor:
        """Per-estimate ``(sigma_x, sigma_y)`` of the window, ``(N, 2)`` metres.

        Args:
            xy: ``(N, 2)`` metric points.
            pos_cov: ``(N, 2, 2)`` position covariance (required when adaptive).

        Returns:
            ``(N, 2)`` sigmas in ``xy``'s dtype.
        """
        n = xy.shape[0]
        if not self.adaptive:
            assert self.sigma is not None
            return torch.tensor(self.sigma, dtype=xy.dtype, device=xy.device).expand(n, 2)
        pos_cov = check_pos_cov(pos_cov, n, type(self).__name__)
        assert self.sigma_bounds is not None
        lo, hi = (torch.tensor(b, dtype=xy.dtype, device=xy.device) for b in self.sigma_bounds)
        var = torch.diagonal(pos_cov.detach(), dim1=-2, dim2=-1).to(xy.dtype)
        sigma = torch.nan_to_num(var.clamp(min=0.0).sqrt(), nan=float("inf"))
        return torch.minimum(torch.maximum(sigma, lo), hi)

    def forward(self, xy: torch.Tensor, pos_cov: torch.Tensor | None = None) -> Linearization:
        """Fits the plane over the window around each estimate.

        Args:
            xy: ``(N, 2)`` metric points.
            pos_cov: ``(N, 2, 2)`` horizontal position covariance (m^2); required when
                ``sigma="adaptive"``, ignored otherwise.

        Returns:
            `Linearization` with shapes ``(N,)``, ``(N, 2)``, ``(N,)``.
        """
        xy = check_points(xy, type(self).__name__)
        dt = xy.dtype
        with torch.no_grad():
            xy = xy.detach()
            sigma = self.window_sigma(xy, pos_cov)  # (N, 2)
            points = torch.addcmul(xy, self.pattern.to(dt).unsqueeze(1), sigma)  # (n^2, N, 2)
            samples = self.grid(points)  # (n^2, N)
            coef = self.solver.to(dt) @ samples  # (3, N)
            resid = samples - self.design.to(dt) @ coef
            variance = resid.square().sum(0) / (self.n_samples**2 - 3)
            slope = torch.stack([coef[1], coef[2]], dim=-1) / sigma
            height = self.grid(xy)
        return Linearization(height, slope, variance)


def _pair(value: float | tuple[float, float], name: str, who: str) -> tuple[float, float]:
    """A positive finite length, or a pair of them, as ``(x, y)``."""
    try:
        pair = tuple(float(v) for v in (value if isinstance(value, (tuple, list)) else (value,)))
    except (TypeError, ValueError):
        pair = ()
    if len(pair) == 1:
        pair = pair * 2
    if len(pair) != 2 or not all(math.isfinite(v) and v > 0 for v in pair):
        raise NeuralMapError(
            f"{who}: {name} must be a positive finite length in metres or a pair "
            f"(x, y) of them, got {value!r}."
        )
    return pair  # type: ignore[return-value]
