"""Measurement noise of a linearisation method from measured statistics (not hand constants).

The altimeter innovation of the TAN EKF (SEEDS 004) at the estimate ``p̂`` with horizontal
error ``d = p − p̂ ~ N(0, P)`` carries, besides the altimeter noise, the method's miss

``e(d) = t(p̂ + d) − h(p̂) − slope(p̂) · d``

where ``t`` is the true terrain and ``h``, ``slope`` are what the method returns at
``p̂`` (SEEDS 000: ``m_k = −m1 − m2 − m_d − m_r``: ``e`` holds the DEM/map error ``m_d``
and the linearisation error ``m2`` together). Its second moment ``v(σ) = E[e²]`` over the
map and over ``d ~ N(0, σ² I)`` is measured here by Monte Carlo against the truth terrain
(`measure_linearization_noise`): at ``σ = 0`` it is the map's mean squared error,
and it grows with ``σ`` as the tangent plane misses the terrain over the position
uncertainty (the slope variance over the current covariance). In flight the errors
``d`` are not ``N(0, P)`` while the filter converges (a few runs lag behind their own
covariance); `neuralmap.lab.noise_calibration` re-measures ``v(σ)`` on pilot flights
and replaces the table's ``variance_m2`` where it has enough samples.

`MeasuredNoiseLinearizer` wraps any method and returns, instead of the method's own
variance, the table's variance at the filter's current ``σ = sqrt(tr P_xy / 2)``
(piecewise linear in σ, constant beyond the table's ends).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.linearize.base import Linearization, Linearizer
from neuralmap.linearize.checks import check_points

__all__ = [
    "DEFAULT_NOISE_SIGMAS_M",
    "fit_offset_scale",
    "MeasuredNoiseLinearizer",
    "NoiseTable",
    "interpolate_table",
    "position_sigma",
    "measure_linearization_noise",
    "noise_sigmas",
]

#: Position σ (m, per axis) at which the noise is measured: map error (0) to acquisition.
DEFAULT_NOISE_SIGMAS_M: tuple[float, ...] = (
    0.0, 2.5, 5.0, 10.0, 15.0, 20.0, 30.0, 40.0, 60.0, 80.0, 100.0, 150.0, 200.0, 300.0,
)


def noise_sigmas(prior_sigma_m: float) -> tuple[float, ...]:
    """The σ nodes of a noise table for a flight whose prior horizontal σ is
    ``prior_sigma_m``: `DEFAULT_NOISE_SIGMAS_M` (made for a 100 m prior: up to 3× it) scaled
    down with a smaller prior, so that a small tile (a UAV with a 10 m prior) keeps its
    sampling margin inside the map; unchanged for priors of 100 m or more."""
    scale = min(1.0, float(prior_sigma_m) / 100.0)
    return tuple(s * scale for s in DEFAULT_NOISE_SIGMAS_M)


@dataclass(frozen=True)
class NoiseTable:
    """A method's measured miss statistics as a function of the position σ.

    Attributes:
        sigmas_m: ``(K,)`` increasing per-axis position σ, m (the first is usually 0).
        map_mse_m2: ``(K,)`` ``E[e²]`` over the map with ``d ~ N(0, σ² I)`` (map error +
            linearisation error), m².
        map_mean_m: ``(K,)`` ``E[e]`` over the map, m.
        variance_m2: ``(K,)`` offset ``a(σ)`` of the R term the filter gets, m²:
            ``map_mse_m2``, or the in-flight value where ``flight_samples`` is large enough
            (`neuralmap.lab.noise_calibration.calibrate_noise`).
        scale: ``(K,)`` weight ``b(σ)`` of the method's own variance ``u`` (its local
            roughness measure: cell twist, plane-fit residual, region miss): the R term is
            ``a(σ) + b(σ) u``, fitted by least squares of ``e²`` on ``u`` (zeros: ``a`` alone).
        flight_samples: ``(K,)`` weight of the pilot-flight samples behind each node (0 =
            the map value is used).
        n_points: Map points of the measurement.
        draws: Position errors ``d`` drawn per point and σ.
        seed: Seed of the points and draws.
    """

    sigmas_m: tuple[float, ...]
    map_mse_m2: tuple[float, ...]
    map_mean_m: tuple[float, ...]
    variance_m2: tuple[float, ...]
    flight_samples: tuple[float, ...]
    n_points: int
    draws: int
    seed: int
    scale: tuple[float, ...] = ()

    def __post_init__(self) -> None:
        if not self.scale:
            object.__setattr__(self, "scale", (0.0,) * len(self.sigmas_m))

    def to_dict(self) -> dict[str, Any]:
        """Plain-JSON form for results.json."""
        return {"sigmas_m": list(self.sigmas_m), "map_mse_m2": list(self.map_mse_m2),
                "map_mean_m": list(self.map_mean_m), "variance_m2": list(self.variance_m2),
                "flight_samples": list(self.flight_samples), "n_points": self.n_points,
                "draws": self.draws, "seed": self.seed, "scale": list(self.scale)}


def position_sigma(cov: torch.Tensor) -> torch.Tensor:
    """The per-axis position σ a noise table is read at: ``sqrt(tr(cov) / 2)``.

    Args:
        cov: ``(N, 2, 2)`` horizontal covariance, m².

    Returns:
        ``(N,)`` σ, m (NaN for a non-finite covariance).
    """
    return (0.5 * (cov[:, 0, 0] + cov[:, 1, 1])).clamp(min=0.0).sqrt()


def interpolate_table(sigmas: torch.Tensor, values: torch.Tensor, sigma: torch.Tensor
                      ) -> torch.Tensor:
    """Piecewise-linear ``values(sigma)`` on the increasing nodes ``sigmas``, constant
    beyond both ends.

    Args:
        sigmas: ``(K,)`` increasing nodes (K >= 1).
        values: ``(K,)`` values at the nodes.
        sigma: ``(N,)`` query points.

    Returns:
        ``(N,)`` interpolated values (NaN where ``sigma`` is NaN).
    """
    if sigmas.numel() == 1:
        return values.expand_as(sigma).clone()
    s = sigma.clamp(min=float(sigmas[0]), max=float(sigmas[-1]))
    idx = torch.bucketize(s, sigmas).clamp(1, sigmas.numel() - 1)
    lo, hi = sigmas[idx - 1], sigmas[idx]
    w = (s - lo) / (hi - lo)
    out = values[idx - 1] + w * (values[idx] - values[idx - 1])
    return torch.where(torch.isnan(sigma), torch.full_like(out, float("nan")), out)


def _uniform_points(extent: tuple[float, float, float, float], margin: float, n: int,
                    gen: torch.Generator) -> torch.Tensor:
    xmin, xmax, ymin, ymax = extent
    if xmax - xmin <= 2 * margin or ymax - ymin <= 2 * margin:
        raise NeuralMapError(
            f"measure_linearization_noise: the map extent {extent} is smaller than twice the "
            f"margin {margin:g} m (4 x the largest sigma); measure at smaller "
            "sigmas or on a larger tile."
        )
    u = torch.rand(n, 2, generator=gen, dtype=torch.float64)
    return torch.stack([xmin + margin + u[:, 0] * (xmax - xmin - 2 * margin),
                        ymin + margin + u[:, 1] * (ymax - ymin - 2 * margin)], dim=-1)


def fit_offset_scale(e2: torch.Tensor, u: torch.Tensor, w: torch.Tensor | None = None
                     ) -> tuple[float, float]:
    """Weighted least squares ``e² ≈ a + b u`` with ``a, b >= 0`` and the mean kept.

    ``b = max(cov(e², u) / var(u), 0)`` (0 when ``u`` has no spread), ``a = mean(e²) − b
    mean(u)``; when that is negative, ``a = 0`` and ``b = mean(e²) / mean(u)``. Either way
    ``a + b mean(u) = mean(e²)``.

    Returns:
        ``(a, b)``.
    """
    e2, u = e2.double(), u.double()
    w = torch.ones_like(e2) if w is None else w.double()
    total = float(w.sum())
    if not total > 0:
        return 0.0, 0.0
    mean_e, mean_u = float((w * e2).sum()) / total, float((w * u).sum()) / total
    var_u = float((w * (u - mean_u).square()).sum()) / total
    cov = float((w * (u - mean_u) * (e2 - mean_e)).sum()) / total
    b = max(cov / var_u, 0.0) if var_u > 1e-12 * max(mean_u * mean_u, 1e-300) else 0.0
    a = mean_e - b * mean_u
    if a < 0.0:
        a, b = 0.0, (mean_e / mean_u if mean_u > 0 else 0.0)
    return a, b


def _miss(linearizer: Linearizer, truth: Any, p: torch.Tensor, sigma: float,
          d: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(M, J)`` miss ``t(p + d) − h(p) − slope(p) · d`` with the method run at ``σ² I``,
    and ``(M,)`` the method's own variance there."""
    m = p.shape[0]
    cov = torch.eye(2, dtype=p.dtype).expand(m, 2, 2) * (sigma * sigma)
    lin = linearizer(p, cov)
    height = lin.height.detach().double()
    slope = lin.slope.detach().double()
    with torch.no_grad():
        t = truth((p.unsqueeze(1) + d).reshape(-1, 2)).double().reshape(d.shape[:2])
    miss = t - height.unsqueeze(1) - (slope.unsqueeze(1) * d).sum(-1)
    return miss, lin.variance.detach().double()


def measure_linearization_noise(
    linearizer: Linearizer,
    truth: Any,
    *,
    extent: tuple[float, float, float, float],
    sigmas: tuple[float, ...] = DEFAULT_NOISE_SIGMAS_M,
    n_points: int = 4000,
    draws: int = 8,
    seed: int = 0,
    local: bool = False,
    progress: Callable[[float], None] | None = None,
) -> NoiseTable:
    """Measures a method's miss ``e = t(p̂ + d) − h(p̂) − slope(p̂) · d`` against the truth.

    ``p̂`` uniform over ``extent`` shrunk by ``4 max(σ)``, ``d ~ N(0, σ² I)`` with ``draws``
    draws per point, the method run with ``pos_cov = σ² I`` (the adaptive methods use it);
    the same points and standard normals for every σ (SEEDS 000: the DEM error ``m_d`` and
    the linearisation error ``m2`` of the measurement noise, measured together).

    Args:
        linearizer: The method (``forward(xy, pos_cov) -> Linearization``).
        truth: The true terrain, ``(..., 2) -> (...)`` heights (float64).
        extent: ``(xmin, xmax, ymin, ymax)`` of the map, m.
        sigmas: Increasing per-axis σ (m, >= 0).
        n_points: Points ``p̂`` (>= 100).
        draws: Draws of ``d`` per point (>= 1).
        seed: Seed of points and draws.
        local: Fit ``e² ≈ a + b u`` on the method's own variance ``u``
            (`fit_offset_scale`, per point ``e²`` averaged over the draws); False:
            ``a = E[e²]``, ``b = 0``.
        progress: Called with the share of the work done as each σ node ends
            (`neuralmap.progress.stage_progress`); None = silent.

    Returns:
        `NoiseTable` (``variance_m2`` = ``a``, ``scale`` = ``b``).

    Raises:
        NeuralMapError: Bad sigmas, counts or an extent too small for them.
    """
    sig = [float(s) for s in sigmas]
    if not sig or any(not (s >= 0 and math.isfinite(s)) for s in sig) or any(
            b <= a for a, b in zip(sig, sig[1:], strict=False)):
        raise NeuralMapError(
            f"measure_linearization_noise: sigmas must be finite, >= 0 and strictly increasing "
            f"(metres), got {sigmas!r}.")
    if n_points < 100 or draws < 1:
        raise NeuralMapError(
            f"measure_linearization_noise: need n_points >= 100 and draws >= 1; got {n_points}, "
            f"{draws}.")
    gen = torch.Generator().manual_seed(int(seed) + 0x4E0)
    p = _uniform_points(extent, 4.0 * sig[-1], n_points, gen)
    z = torch.randn(n_points, draws, 2, generator=gen, dtype=torch.float64)
    param = next(iter(linearizer.parameters()), None)
    dtype = param.dtype if param is not None else torch.float64
    mse, mean, offset, scale = [], [], [], []
    for s in sig:
        e, u = _miss(linearizer, truth, p.to(dtype), s, (z * s).to(dtype))
        ok = torch.isfinite(e).all(dim=1) & torch.isfinite(u)
        e, u = e[ok].double(), u[ok]
        mse.append(float(e.square().mean()) if e.numel() else 0.0)
        mean.append(float(e.mean()) if e.numel() else 0.0)
        a, b = fit_offset_scale(e.square().mean(dim=1), u) if local and e.numel() else (
            mse[-1], 0.0)
        offset.append(a)
        scale.append(b)
        if progress is not None:
            progress(1.0 / len(sig))
    return NoiseTable(tuple(sig), tuple(mse), tuple(mean), tuple(offset), (0.0,) * len(sig),
                      int(n_points), int(draws), int(seed), tuple(scale))


class MeasuredNoiseLinearizer(Linearizer):
    """A method whose variance is its measured noise table at the filter's position σ.

    Height and slope are the wrapped method's; the variance is
    ``a(σ) + b(σ) u`` (``a = table.variance_m2``, ``b = table.scale``, ``u`` the wrapped
    method's own variance at the point; ``b = 0`` unless the table was fitted ``local``) with ``σ = sqrt(tr(pos_cov) / 2)`` (the mean per-axis
    variance of the horizontal covariance), piecewise linear in σ and constant beyond the
    table (`interpolate_table`); without ``pos_cov`` the σ = 0 value (the map error).
    It replaces the method's own variance (which the table already contains, measured).

    Args:
        inner: The wrapped linearisation method.
        table: Its `NoiseTable` (`measure_linearization_noise`).
    """

    table_sigmas: torch.Tensor
    table_variance: torch.Tensor
    table_scale: torch.Tensor

    def __init__(self, inner: Linearizer, table: NoiseTable) -> None:
        super().__init__()
        if not isinstance(inner, torch.nn.Module):
            raise NeuralMapError(
                f"MeasuredNoiseLinearizer: inner must be a Linearizer, got {type(inner).__name__}.")
        self.inner = inner
        self.table = table
        self.register_buffer("table_sigmas", torch.tensor(table.sigmas_m, dtype=torch.float64),
                             persistent=False)
        self.register_buffer("table_variance",
                             torch.tensor(table.variance_m2, dtype=torch.float64),
                             persistent=False)
        self.register_buffer("table_scale", torch.tensor(table.scale, dtype=torch.float64),
                             persistent=False)
        self.local = any(b != 0.0 for b in table.scale)

    def __getattr__(self, name: str) -> Any:
        """The wrapped method's attributes (``terrain``, ``grid``, ``extent``...)."""
        try:
            return super().__getattr__(name)
        except AttributeError:
            inner = super().__getattr__("inner")
            return getattr(inner, name)

    def forward(self, xy: torch.Tensor, pos_cov: torch.Tensor | None = None) -> Linearization:
        """The wrapped method's height and slope, the measured variance at ``pos_cov``.

        Args:
            xy: ``(N, 2)`` metric points.
            pos_cov: ``(N, 2, 2)`` horizontal position covariance (m²) or None.

        Returns:
            `Linearization` with shapes ``(N,)``, ``(N, 2)``, ``(N,)``.
        """
        xy = check_points(xy, "MeasuredNoiseLinearizer")
        lin = self.inner(xy, pos_cov)
        dtype = lin.height.dtype
        sigmas = self.table_sigmas.to(dtype)
        values = self.table_variance.to(dtype)
        if pos_cov is None:
            sigma = torch.zeros_like(lin.height.detach())
        else:
            sigma = position_sigma(pos_cov.detach().to(dtype))
        variance = interpolate_table(sigmas, values, sigma)
        if self.local:
            own = lin.variance.detach().to(dtype)
            variance = variance + interpolate_table(sigmas, self.table_scale.to(dtype), sigma) * own
        return Linearization(lin.height, lin.slope, variance)
