"""A terrain model evaluated by one batched kernel: height and analytic slope together.

`LatentTerrainMap` (one tile) and `LatentTileset` (a region of them) both answer a query
by one ``_evaluate`` of the flattened points — heights, and slopes in the same pass when
asked — so the input check and the two public queries live here once.
"""

from __future__ import annotations

import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.terrain.base import TerrainModel

__all__ = ["EvaluatedTerrain"]


class EvaluatedTerrain(TerrainModel):
    """A `TerrainModel` whose subclasses implement ``_evaluate`` on ``(M, 2)`` points."""

    def _evaluate(self, xy: torch.Tensor, *, with_slope: bool
                  ) -> tuple[torch.Tensor, torch.Tensor | None]:
        """Heights ``(M,)`` and, with ``with_slope``, slopes ``(M, 2)`` of ``(M, 2)`` points."""
        raise NotImplementedError

    def _query_dtype(self) -> torch.dtype:
        """The dtype integer query points are converted to."""
        return torch.float32

    def _check_xy(self, xy: torch.Tensor) -> torch.Tensor:
        if not isinstance(xy, torch.Tensor) or xy.ndim < 1 or xy.shape[-1] != 2:
            shape = tuple(xy.shape) if isinstance(xy, torch.Tensor) else type(xy).__name__
            raise NeuralMapError(
                f"{type(self).__name__}: xy must be a tensor of shape (..., 2) (east, north "
                f"metres), got {shape}."
            )
        return xy if xy.is_floating_point() else xy.to(self._query_dtype())

    def forward(self, xy: torch.Tensor) -> torch.Tensor:
        """Heights, differentiable in ``xy``.

        Args:
            xy: ``(..., 2)`` east/north metres.

        Returns:
            ``(...)`` heights in metres, dtype of ``xy``.
        """
        xy = self._check_xy(xy)
        height, _ = self._evaluate(xy.reshape(-1, 2), with_slope=False)
        return height.view(xy.shape[:-1])

    def height_and_slope(self, xy: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Heights and analytic slopes ``(dh/dx, dh/dy)`` (forward mode, no autograd).

        Args:
            xy: ``(..., 2)`` east/north metres.

        Returns:
            ``(height (...), slope (..., 2))``, metres and metres per metre.
        """
        xy = self._check_xy(xy)
        lead = xy.shape[:-1]
        with torch.no_grad():
            height, slope = self._evaluate(xy.reshape(-1, 2), with_slope=True)
        assert slope is not None
        return height.view(lead), slope.view(*lead, 2)
