"""Fit evaluation: height and slope errors of a terrain model against its DEM tile.

Used per epoch on the validation nodes (through `FitAccumulator`) and once at the
end of a fit on every valid node (`evaluate_fit`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import torch

from neuralmap.dem.tile import DemTile
from neuralmap.terrain.base import TerrainModel
from neuralmap.terrain.grid import GridTerrain


def height_and_slope(
    model: TerrainModel, xy: torch.Tensor, *, chunk: int = 65536
) -> tuple[torch.Tensor, torch.Tensor]:
    """Heights and autograd slopes of a terrain model, also inside ``inference_mode``.

    Args:
        model: Any `TerrainModel` differentiable in ``xy``.
        xy: ``(N, 2)`` metric points.
        chunk: Points per autograd pass.

    Returns:
        ``(height (N,), slope (N, 2))`` detached, in the model's output dtype;
        ``slope = (dh/dx, dh/dy)`` in metres per metre.
    """
    if xy.ndim != 2 or xy.shape[-1] != 2:
        raise ValueError(f"xy must have shape (N, 2), got {tuple(xy.shape)}")
    heights, slopes = [], []
    with torch.inference_mode(False), torch.enable_grad():
        for part in torch.split(xy, chunk):
            # clone() leaves inference mode: a normal tensor that autograd can track.
            point = part.clone().requires_grad_(True)
            height = model(point)
            (slope,) = torch.autograd.grad(height.sum(), point)
            heights.append(height.detach())
            slopes.append(slope.detach())
    if not heights:
        return xy.new_zeros(0), xy.new_zeros(0, 2)
    return torch.cat(heights), torch.cat(slopes)


@dataclass
class FitAccumulator:
    """Streaming sums for RMSE, max |error|, mean error and slope RMSE over chunks.

    Errors are ``model - DEM``. The slope RMSE is the RMS of the slope-error vector norm,
    ``sqrt(mean(|grad N - grad h|^2))`` in m/m, against the bicubic DEM slopes.
    """

    n: float = 0.0
    sum_err: float = 0.0
    sum_sq: float = 0.0
    max_abs: float = 0.0
    slope_sum_sq: float = 0.0
    slope_ref_sum_sq: float = 0.0
    slope_max: float = 0.0

    def update(
        self,
        pred: torch.Tensor,
        target: torch.Tensor,
        slope_pred: torch.Tensor,
        slope_ref: torch.Tensor,
    ) -> None:
        """Adds one chunk: ``pred``/``target`` ``(N,)`` m, slopes ``(N, 2)`` m/m."""
        if pred.numel() == 0:
            return
        err = (pred - target).double()
        slope_err = (slope_pred - slope_ref).double().square().sum(-1)
        self.n += err.numel()
        self.sum_err += float(err.sum())
        self.sum_sq += float(err.square().sum())
        self.max_abs = max(self.max_abs, float(err.abs().max()))
        self.slope_sum_sq += float(slope_err.sum())
        self.slope_ref_sum_sq += float(slope_ref.double().square().sum())
        self.slope_max = max(self.slope_max, float(slope_err.sqrt().max()))

    def as_tensor(self) -> torch.Tensor:
        """``(7,)`` float64 state, for all-reduce across ranks (sums; maxima separately)."""
        return torch.tensor(
            [self.n, self.sum_err, self.sum_sq, self.max_abs, self.slope_sum_sq,
             self.slope_ref_sum_sq, self.slope_max],
            dtype=torch.float64,
        )

    @classmethod
    def from_tensors(cls, sums: torch.Tensor, maxima: torch.Tensor) -> FitAccumulator:
        """Rebuilds the state from all-reduced sums and maxima of `as_tensor`."""
        s, m = sums.tolist(), maxima.tolist()
        return cls(n=s[0], sum_err=s[1], sum_sq=s[2], max_abs=m[3], slope_sum_sq=s[4],
                   slope_ref_sum_sq=s[5], slope_max=m[6])

    def metrics(self) -> dict[str, float]:
        """``rmse_m``, ``max_abs_m``, ``mean_m``, ``std_m``, ``slope_rmse``, ``slope_max``,
        ``dem_slope_rms`` (RMS slope norm of the DEM, for scale), ``n_nodes``."""
        n = max(self.n, 1.0)
        mean = self.sum_err / n
        return {
            "rmse_m": math.sqrt(self.sum_sq / n),
            "max_abs_m": self.max_abs,
            "mean_m": mean,
            "std_m": math.sqrt(max(self.sum_sq / n - mean * mean, 0.0)),
            "slope_rmse": math.sqrt(self.slope_sum_sq / n),
            "slope_max": self.slope_max,
            "dem_slope_rms": math.sqrt(self.slope_ref_sum_sq / n),
            "n_nodes": int(self.n),
        }


def residual_autocorrelation(
    residual: np.ndarray, max_lag: int
) -> tuple[np.ndarray, np.ndarray, int, int]:
    """Sample autocorrelation of a gridded fit error along rows (x) and columns (y).

    ``r(k) = [sum e_i e_{i+k} / n_k] / [sum e_i^2 / n_0]`` over all pairs of valid nodes
    ``k`` apart on the same row (x) or column (y), after removing the mean. For white
    errors ``|r(k)| < 1.96 / sqrt(n_0)`` at 95 % (the whiteness check of SEEDS 004
    fig. 3d and SEEDS 000 step 2).

    Args:
        residual: ``(ny, nx)`` errors, NaN at voids.
        max_lag: Largest lag in nodes (clipped to the grid size - 1).

    Returns:
        ``(acf_x (Lx + 1,), acf_y (Ly + 1,), n_x, n_y)``: autocorrelations for lags
        ``0..L`` (``acf[0] = 1``) and the number of valid nodes used.
    """
    valid = np.isfinite(residual)
    n0 = int(valid.sum())
    if n0 == 0:
        return np.ones(1), np.ones(1), 0, 0
    e = np.where(valid, residual - residual[valid].mean(), 0.0)
    var = float((e**2).sum() / n0) or 1.0
    w = valid.astype(np.float64)

    def along(axis: int) -> np.ndarray:
        lags = min(max_lag, residual.shape[axis] - 1)
        out = np.ones(lags + 1)
        for k in range(1, lags + 1):  # a few dozen lags, each vectorised over the grid
            if axis == 1:
                prod, cnt = e[:, :-k] * e[:, k:], w[:, :-k] * w[:, k:]
            else:
                prod, cnt = e[:-k] * e[k:], w[:-k] * w[k:]
            pairs = cnt.sum()
            out[k] = prod.sum() / pairs / var if pairs > 0 else np.nan
        return out

    return along(1), along(0), n0, n0


@dataclass
class FitEvaluation:
    """Result of `evaluate_fit`.

    Attributes:
        fitted: ``(ny, nx)`` model heights at every node (voids included), metres.
        residual: ``(ny, nx)`` model minus DEM at valid nodes, NaN at voids, metres.
        acf_x: Residual autocorrelation along rows for lags ``0..L``.
        acf_y: Residual autocorrelation along columns.
        metrics: Scalars (see `FitAccumulator.metrics`, plus ``n_void``,
            ``acf_x_lag1``, ``acf_y_lag1`` and the off-node errors of
            `offnode_error`: ``offnode_rmse_m``, ``offnode_max_abs_m``,
            ``offnode_slope_rmse``).
    """

    fitted: np.ndarray
    residual: np.ndarray
    acf_x: np.ndarray
    acf_y: np.ndarray
    metrics: dict[str, float] = field(default_factory=dict)


def offnode_error(
    model: TerrainModel, tile: DemTile, *, n_points: int = 20000, seed: int = 0,
    chunk: int = 65536,
) -> dict[str, float]:
    """The model against the bicubic DEM at seeded random points between the nodes.

    Points are uniform over the cells with four valid corners
    (`OffNodeSampler`); the reference is the Keys
    bicubic interpolant of the DEM, the surface a grid map answers there.

    Returns:
        ``offnode_rmse_m``, ``offnode_max_abs_m`` (m) and ``offnode_slope_rmse`` (m/m, RMS
        norm of the slope error); NaN when the tile has no valid cell.
    """
    from neuralmap.exceptions import NeuralMapError
    from neuralmap.training.offnode import OffNodeSampler

    try:
        sampler = OffNodeSampler(tile)
    except NeuralMapError:
        nan = float("nan")
        return {"offnode_rmse_m": nan, "offnode_max_abs_m": nan, "offnode_slope_rmse": nan}
    param = next(iter(model.parameters()), None)
    device = param.device if param is not None else torch.device("cpu")
    dtype = param.dtype if param is not None else torch.float64
    xy, ref_h, ref_s = sampler.sample(n_points, torch.Generator().manual_seed(int(seed)),
                                      dtype=torch.float64)
    was_training = model.training
    model.eval()
    try:
        height, slope = height_and_slope(model, xy.to(device, dtype), chunk=chunk)
    finally:
        model.train(was_training)
    err = height.double().cpu() - ref_h
    slope_err = (slope.double().cpu() - ref_s).square().sum(-1)
    return {"offnode_rmse_m": float(err.square().mean().sqrt()),
            "offnode_max_abs_m": float(err.abs().max()),
            "offnode_slope_rmse": float(slope_err.mean().sqrt())}


def evaluate_fit(
    model: TerrainModel,
    tile: DemTile,
    *,
    slope_ref: torch.Tensor | None = None,
    chunk: int = 65536,
    max_lag: int = 40,
    offnode_points: int = 20000,
) -> FitEvaluation:
    """Evaluates a terrain model on every valid node of its tile.

    Height errors are ``model(x, y) - h`` at the nodes; slope errors compare the model's
    autograd slope with the bicubic DEM slope (`GridTerrain`, Keys a = -1/2).

    Args:
        model: The fitted terrain model.
        tile: The DEM tile it was fitted to.
        slope_ref: Optional precomputed ``(n_valid, 2)`` reference slopes at the valid
            nodes in row-major order (as `DemDataModule.all_slopes`).
        chunk: Points per evaluation pass.
        max_lag: Largest autocorrelation lag in nodes.
        offnode_points: Random points between the nodes for `offnode_error`
            (0 skips it).

    Returns:
        The `FitEvaluation`.
    """
    ny, nx = tile.shape
    valid = tile.valid_mask
    param = next(iter(model.parameters()), None)
    device = param.device if param is not None else torch.device("cpu")
    dtype = param.dtype if param is not None else torch.float32
    xy = torch.as_tensor(tile.node_xy().reshape(-1, 2), dtype=dtype, device=device)
    was_training = model.training
    model.eval()
    try:
        heights, slopes = height_and_slope(model, xy, chunk=chunk)
    finally:
        model.train(was_training)
    valid_flat = torch.as_tensor(valid.reshape(-1), device=device)
    if slope_ref is None:
        grid = GridTerrain(tile, method="bicubic", dtype=torch.float64)
        slope_ref = torch.cat(
            [grid.height_and_slope(p)[1] for p in torch.split(xy[valid_flat].double().cpu(), chunk)]
        )
    acc = FitAccumulator()
    target = torch.as_tensor(tile.heights.reshape(-1)[valid.reshape(-1)], device=device)
    acc.update(
        heights[valid_flat].double(), target.double(), slopes[valid_flat].double(),
        slope_ref.to(device).double(),
    )
    fitted = heights.double().cpu().numpy().reshape(ny, nx)
    residual = np.where(valid, fitted - tile.heights, np.nan)
    acf_x, acf_y, _, _ = residual_autocorrelation(residual, max_lag)
    metrics: dict[str, float] = dict(acc.metrics())
    metrics["n_void"] = int(tile.n_void)
    metrics["acf_x_lag1"] = float(acf_x[1]) if acf_x.size > 1 else float("nan")
    metrics["acf_y_lag1"] = float(acf_y[1]) if acf_y.size > 1 else float("nan")
    if offnode_points > 0:
        metrics.update(offnode_error(model, tile, n_points=offnode_points, chunk=chunk))
    return FitEvaluation(fitted=fitted, residual=residual, acf_x=acf_x, acf_y=acf_y,
                         metrics=metrics)
