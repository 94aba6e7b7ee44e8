"""Mean-point selection ("平均选点", SEEDS 000 LCK = 2): a plane through group mean points."""

from __future__ import annotations

import torch

from neuralmap.dem.tile import DemTile
from neuralmap.linearize.window import ADAPTIVE_MAX_SIGMA_M, WindowPlaneLinearizer


class MeanPointLinearizer(WindowPlaneLinearizer):
    """Plane through the mean points of the halves of the window (method of group averages).

    Our reading of SEEDS 000's "mean point selection" (LCK = 2), which the paper groups with
    the fits that make the *algebraic sum* of the deviations zero rather than the sum of
    squares minimal: the window Omega = ``6 sigma_x x 6 sigma_y`` (SEEDS 000's region) is
    sampled on the ``n x n`` pattern and split into an east and a west half (and a north
    and a south half). Each half is replaced by its mean point (mean position, mean
    height); the slope along x is the central difference of the two mean points,

    ``h_x = (mean(h | xi > 0) - mean(h | xi < 0)) / (mean(x | xi > 0) - mean(x | xi < 0))``,

    likewise ``h_y``, and the plane passes through the mean point of the whole window, so
    its deviations sum to zero over each half. (With odd ``n`` the centre column/row
    belongs to neither half.) Exact on a plane; on a quadratic it gives the gradient at the
    centre, like the least-squares plane, because the pattern is symmetric.
    Variance = residual variance of the samples about that plane, ``sum(r^2) / (n^2 - 3)``.

    The paper uses it with the adaptive window, hence the default ``sigma="adaptive"``.

    Args:
        tile: The DEM tile.
        sigma: ``"adaptive"`` (default), or a fixed sigma in metres / ``(sigma_x, sigma_y)``.
        n_samples: Samples per axis; see ``WindowPlaneLinearizer``.
        min_sigma: Lower clamp of the adaptive sigma (default: grid spacing).
        max_sigma: Upper clamp of the adaptive sigma, metres.
        interpolation: DEM interpolant sampled, ``"bilinear"`` or ``"bicubic"``.
        dtype: Dtype of the height buffer.
    """

    def __init__(
        self,
        tile: DemTile,
        *,
        sigma: float | tuple[float, float] | str = "adaptive",
        n_samples: int | None = None,
        min_sigma: float | tuple[float, float] | None = None,
        max_sigma: float = ADAPTIVE_MAX_SIGMA_M,
        interpolation: str = "bilinear",
        dtype: torch.dtype = torch.float64,
    ) -> None:
        super().__init__(
            tile,
            sigma=sigma,
            n_samples=n_samples,
            min_sigma=min_sigma,
            max_sigma=max_sigma,
            interpolation=interpolation,
            dtype=dtype,
        )

    def make_solver(self, pattern: torch.Tensor, design: torch.Tensor) -> torch.Tensor:
        """Group-average rule, shape ``(3, n^2)``: window mean, then half-mean differences."""
        rows = [torch.full((pattern.shape[0],), 1.0 / pattern.shape[0], dtype=torch.float64)]
        for axis in (0, 1):
            coord = pattern[:, axis]
            pos = (coord > 0).double()
            neg = (coord < 0).double()
            pos, neg = pos / pos.sum(), neg / neg.sum()
            spread = (pos * coord).sum() - (neg * coord).sum()
            rows.append((pos - neg) / spread)
        return torch.stack(rows)
