"""Autograd linearisation of any terrain model (SEEDS 004: H = [-dN/dx, -dN/dy, 1, 0, 0])."""

from __future__ import annotations

import torch
from torch import nn

from neuralmap.exceptions import NeuralMapError
from neuralmap.linearize.base import Linearization, Linearizer
from neuralmap.linearize.checks import check_nonnegative, check_points
from neuralmap.linearize.region_variance import RegionReport, region_miss_variance
from neuralmap.terrain.base import TerrainModel


class AutogradLinearizer(Linearizer):
    """Height from the terrain model, slope by reverse-mode autograd.

    A `TerrainModel` evaluates every point independently,
    so the gradient of the *summed* heights with respect to ``xy`` is the per-point slope:
    one forward and one backward pass for the whole batch (faster than
    ``torch.func.vmap(jacrev(...))``, same numbers). For the BP net this equals the analytic
    gradient of SEEDS 004 eq. (8).

    The variance is the constant ``fit_variance`` (the map's fit error, treated as white
    noise and added to R: 6 m^2 in SEEDS 004).

    Works when the caller runs under ``torch.no_grad()`` (grad is enabled locally).

    Args:
        terrain: Any module mapping ``(..., 2)`` metres to ``(...)`` heights, differentiable
            in its input.
        create_graph: Keep the graph: height and slope stay differentiable with respect to
            the terrain's parameters and to ``xy`` (when ``xy`` requires grad), so a loss on
            the filter output back-propagates through the linearisation. Off: outputs are
            detached.
        fit_variance: Map fit-error variance in m^2 (>= 0), returned as the variance.
        region_variance: Also add the linearisation-error variance over the position
            uncertainty: ``E[(h(p + d) - h(p) - slope . d)^2]`` for ``d ~ N(0, pos_cov)``,
            the tangent plane's miss over the region the estimate may be in (the neural-map
            analogue of the plane-fit residual over Ω_adp, SEEDS 000). Computed with the
            3 x 3 Gauss-Hermite rule (nodes 0, ±sqrt(3); weights 2/3, 1/6 per axis; exact
            for a quadratic terrain): 8 extra height evaluations per point, no gradients.
            Needs ``pos_cov``. Nodes outside a `TerrainModel`'s extent are not used
            (mirrored or dropped with renormalised weights) and a covariance that is not
            positive definite gets an eigen-clamped square root; see
            `neuralmap.linearize.region_variance`. What was done per sample is kept in
            `region_report` after each call.

    Attributes:
        region_report: The `RegionReport` of the last region-variance evaluation
            (``None`` before the first one).

    Raises:
        NeuralMapError: ``terrain`` is not an ``nn.Module`` or ``fit_variance`` is negative.
    """

    def __init__(
        self,
        terrain: nn.Module,
        *,
        create_graph: bool = False,
        fit_variance: float = 0.0,
        region_variance: bool = False,
    ) -> None:
        super().__init__()
        if not isinstance(terrain, nn.Module):
            raise NeuralMapError(
                f"AutogradLinearizer: terrain must be a torch.nn.Module (a TerrainModel), got "
                f"{type(terrain).__name__}. Load a map with neuralmap.terrain.load_map(path)."
            )
        self.terrain = terrain
        self.create_graph = bool(create_graph)
        self.fit_variance = check_nonnegative(fit_variance, "fit_variance", "AutogradLinearizer")
        self.region_variance = bool(region_variance)
        self.region_report: RegionReport | None = None

    def extra_repr(self) -> str:
        """Short description for ``print(linearizer)``."""
        return (
            f"create_graph={self.create_graph}, fit_variance={self.fit_variance}, "
            f"region_variance={self.region_variance}"
        )

    def forward(self, xy: torch.Tensor, pos_cov: torch.Tensor | None = None) -> Linearization:
        """Linearises the terrain model at ``xy``.

        Args:
            xy: ``(N, 2)`` metric points.
            pos_cov: ``(N, 2, 2)`` horizontal covariance; used when ``region_variance``.

        Returns:
            `Linearization`: height ``(N,)``, slope ``(N, 2)``, variance ``(N,)``,
            in ``xy``'s dtype.

        Raises:
            NeuralMapError: The terrain output is not ``(N,)`` or not differentiable in xy.
        """
        xy = check_points(xy, "AutogradLinearizer")
        with torch.enable_grad():
            if self.create_graph and xy.requires_grad:
                points = xy
            else:
                points = xy.detach().requires_grad_(True)
            height = self.terrain(points)
            if not isinstance(height, torch.Tensor) or height.shape != xy.shape[:1]:
                got = tuple(height.shape) if isinstance(height, torch.Tensor) else type(height)
                raise NeuralMapError(
                    f"AutogradLinearizer: the terrain model must map (N, 2) points to (N,) "
                    f"heights, got {got} for N = {xy.shape[0]}."
                )
            if not height.requires_grad:
                raise NeuralMapError(
                    "AutogradLinearizer: the terrain output does not depend differentiably on "
                    "xy (no autograd graph). Use a TerrainModel built from torch ops, or a "
                    "classical linearizer for grids."
                )
            (slope,) = torch.autograd.grad(
                height.sum(), points, create_graph=self.create_graph, allow_unused=True
            )
        if slope is None:  # constant terrain
            slope = torch.zeros_like(points)
        if not self.create_graph:
            height = height.detach()
            slope = slope.detach()
        height = height.to(xy.dtype)
        slope = slope.to(xy.dtype)
        variance = torch.full_like(height.detach(), self.fit_variance)
        if self.region_variance:
            if pos_cov is None:
                raise NeuralMapError(
                    "AutogradLinearizer(region_variance=True) needs pos_cov (N, 2, 2), the "
                    "filter's horizontal position covariance."
                )
            variance = variance + self._region_variance(
                xy.detach(), pos_cov.detach().to(xy.dtype), height.detach(), slope.detach()
            )
        return Linearization(height, slope, variance)

    @torch.no_grad()
    def _region_variance(
        self, xy: torch.Tensor, pos_cov: torch.Tensor, height: torch.Tensor, slope: torch.Tensor
    ) -> torch.Tensor:
        """``(N,)`` mean squared miss of the tangent plane over ``N(xy, pos_cov)``."""
        n = xy.shape[0]
        if pos_cov.shape != (n, 2, 2):
            raise NeuralMapError(
                f"AutogradLinearizer: pos_cov must be (N, 2, 2) = ({n}, 2, 2), got "
                f"{tuple(pos_cov.shape)}."
            )
        on_map = self.terrain.contains if isinstance(self.terrain, TerrainModel) else None
        variance, self.region_report = region_miss_variance(
            self.terrain, xy=xy, pos_cov=pos_cov, height=height, slope=slope, on_map=on_map
        )
        return variance
