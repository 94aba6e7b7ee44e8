"""Quality-based measurement noise: paper 003's robust factor ρ ≥ 1 from quality indicators.

Paper 003 inflates the measurement noise by a factor built from observation-quality
indicators (for GNSS: PDOP, ambiguity-fix success rate, satellite count, the solution's
own σ) through membership functions with quantisation parameters κ, η, ζ, θ ∈ [0.1, 0.5],
``R_k = ρ · diag(σ_r², σ_v²)``, and tunes R *before* the adaptive-factor test. The
printed membership functions are lost; the reconstruction implemented here:

* each indicator j has a "good" level ``g_j`` and a "bad" level ``b_j`` (either order:
  for a fix ratio or a satellite count the bad level is the smaller one) and a
  piecewise-linear membership ``μ_j(q) = clip((q − g_j) / (b_j − g_j), 0, cap_j)``:
  0 at or beyond the good level, 1 at the bad level, growing linearly up to ``cap_j``;
* ``ρ = 1 + Σ_j w_j μ_j`` with the quantisation parameters ``w_j`` (κ, η, ζ, θ):
  ρ = 1 for a clean epoch, ``1 + Σ w_j`` when every indicator sits at its bad level
  (1.4–3 for w in [0.1, 0.5] and four indicators: the paper's "2–3 times" range), more
  for worse epochs (bounded by the caps);
* ``R ← ρ R`` for every component of the sample;
* a *flag* indicator (``reject=True``: lock lost, no fix) rejects the sample's
  measurement outright when its membership reaches 1.

For TAN the same mechanism reads the radar-altimeter quality: terrain roughness in the
beam footprint, height above ground, and the lock flag (`QualityR.altimeter`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.filters.policy import Adaptation, FilterPolicy, UpdateContext

__all__ = ["QualityIndicator", "QualityR", "quality_factor", "quality_membership"]


def quality_membership(
    value: torch.Tensor, good: float, bad: float, cap: float = 4.0
) -> torch.Tensor:
    """Membership ``μ = clip((q − good) / (bad − good), 0, cap)`` of an indicator.

    Args:
        value: ``(...)`` indicator values.
        good: Level at or beyond which the measurement is clean (μ = 0).
        bad: Level at which μ = 1 (on either side of ``good``).
        cap: Largest membership.

    Returns:
        ``(...)`` memberships in ``[0, cap]``.
    """
    if not (math.isfinite(good) and math.isfinite(bad)) or good == bad:
        raise NeuralMapError(
            f"quality_membership: 'good' = {good!r} and 'bad' = {bad!r} must be finite and "
            "differ."
        )
    return ((value - good) / (bad - good)).clamp(0.0, cap)


def quality_factor(memberships: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """Robust factor ``ρ = 1 + Σ_j w_j μ_j`` (≥ 1).

    Args:
        memberships: ``(N, K)`` memberships.
        weights: ``(K,)`` quantisation parameters (κ, η, ζ, θ, ...), ≥ 0.

    Returns:
        ``(N,)`` factors.
    """
    return 1.0 + (memberships * weights.to(memberships)).sum(-1)


@dataclass(frozen=True)
class QualityIndicator:
    """One observation-quality indicator of `QualityR`.

    Attributes:
        name: Indicator name (``"pdop"``, ``"fix_ratio"``, ``"roughness_m"``, ...).
        good: Clean level (membership 0 at or beyond it).
        bad: Level of membership 1 (either side of ``good``).
        weight: Quantisation parameter (κ, η, ζ, θ: 0.1–0.5 in paper 003), ≥ 0.
        cap: Largest membership (default 4).
        reject: A flag indicator: membership ≥ 1 rejects the measurement (weight unused).
    """

    name: str
    good: float
    bad: float
    weight: float = 0.3
    cap: float = 4.0
    reject: bool = False

    def validate(self, where: str) -> None:
        """Raises NeuralMapError on unusable levels, weight or cap."""
        if not (math.isfinite(self.good) and math.isfinite(self.bad)) or self.good == self.bad:
            raise NeuralMapError(
                f"{where}: indicator {self.name!r} needs finite, different 'good' and 'bad' "
                f"levels, got good = {self.good!r}, bad = {self.bad!r}."
            )
        if not 0.0 <= self.weight < math.inf:
            raise NeuralMapError(
                f"{where}: indicator {self.name!r} has weight {self.weight!r}; quantisation "
                "parameters must be finite and >= 0 (0.1–0.5 in the paper)."
            )
        if not 0.0 < self.cap < math.inf:
            raise NeuralMapError(f"{where}: indicator {self.name!r} has cap {self.cap!r} <= 0.")


class QualityR(FilterPolicy):
    """Inflates R by ``ρ = 1 + Σ w_j μ_j(q_j)`` from per-epoch quality indicators.

    Call `set_quality` with the epoch's indicators before every update (they are
    consumed by the update, so a stale epoch cannot be reused silently).

    Args:
        indicators: The indicators, in the column order of `set_quality`.

    Reports ``rho`` ``(N,)``, ``membership`` ``(N, K)`` and ``rejected`` ``(N,)``.

    Raises:
        NeuralMapError: No indicators, duplicate names, bad levels/weights.
    """

    name = "quality"

    def __init__(self, indicators: Sequence[QualityIndicator]) -> None:
        indicators = list(indicators)
        if not indicators:
            raise NeuralMapError("QualityR: give at least one QualityIndicator.")
        names = [ind.name for ind in indicators]
        if len(set(names)) != len(names):
            raise NeuralMapError(f"QualityR: indicator names must be unique, got {names}.")
        for ind in indicators:
            ind.validate("QualityR")
        self.indicators = indicators
        self._values: torch.Tensor | None = None

    @classmethod
    def gnss(
        cls,
        kappa: float = 0.3,
        eta: float = 0.3,
        zeta: float = 0.3,
        theta: float = 0.3,
        *,
        pdop: tuple[float, float] = (2.0, 6.0),
        fix_ratio: tuple[float, float] = (0.95, 0.5),
        satellites: tuple[float, float] = (10.0, 4.0),
        sigma_m: tuple[float, float] = (0.05, 0.5),
    ) -> QualityR:
        """Paper 003's GNSS indicators: PDOP (κ), fix ratio (η), satellites (ζ), σ (θ).

        Columns of `set_quality`: ``pdop``, ``fix_ratio``, ``satellites``,
        ``sigma_m`` (the solution's reported position σ); each ``(good, bad)`` pair sets
        the membership levels.
        """
        return cls([
            QualityIndicator("pdop", *pdop, weight=kappa),
            QualityIndicator("fix_ratio", *fix_ratio, weight=eta),
            QualityIndicator("satellites", *satellites, weight=zeta),
            QualityIndicator("sigma_m", *sigma_m, weight=theta),
        ])

    @classmethod
    def altimeter(
        cls,
        kappa: float = 0.5,
        eta: float = 0.2,
        *,
        roughness_m: tuple[float, float] = (2.0, 15.0),
        height_agl_m: tuple[float, float] = (300.0, 3000.0),
    ) -> QualityR:
        """Radar-altimeter quality for TAN: roughness in the beam (κ), height (η), lock.

        Columns of `set_quality`: ``roughness_m`` (terrain height spread in the
        beam footprint), ``height_agl_m`` (height above ground), ``lock`` (1 = locked,
        0 = loss of lock: the measurement is rejected).
        """
        return cls([
            QualityIndicator("roughness_m", *roughness_m, weight=kappa),
            QualityIndicator("height_agl_m", *height_agl_m, weight=eta),
            QualityIndicator("lock", 1.0, 0.0, weight=0.0, reject=True),
        ])

    @property
    def names(self) -> list[str]:
        """Indicator names (the column order of `set_quality`)."""
        return [ind.name for ind in self.indicators]

    def reset(self) -> None:
        """Drops indicators that were set but not used."""
        self._values = None

    def set_quality(self, values: torch.Tensor | Mapping[str, torch.Tensor]) -> None:
        """The indicators of the next update.

        Args:
            values: ``(N, K)`` tensor (columns in `names` order) or a mapping from
                every indicator name to an ``(N,)`` tensor.

        Raises:
            NeuralMapError: Missing/unknown names, wrong number of columns or lengths.
        """
        where = "QualityR.set_quality"
        K = len(self.indicators)
        if isinstance(values, Mapping):
            missing = [n for n in self.names if n not in values]
            extra = [n for n in values if n not in self.names]
            if missing or extra:
                raise NeuralMapError(
                    f"{where}: indicators must be exactly {self.names}; missing {missing}, "
                    f"unknown {extra}."
                )
            cols = [torch.as_tensor(values[n]) for n in self.names]
            shapes = {n: tuple(c.shape) for n, c in zip(self.names, cols, strict=True)}
            lengths = set(shapes.values())
            if len(lengths) != 1 or any(c.ndim != 1 for c in cols):
                raise NeuralMapError(
                    f"{where}: every indicator must be an (N,) tensor of the same length, got "
                    f"shapes {shapes}."
                )
            t = torch.stack([c.to(torch.float64) if not c.is_floating_point() else c
                             for c in cols], dim=-1)
        else:
            t = torch.as_tensor(values)
            if t.ndim != 2 or t.shape[1] != K:
                raise NeuralMapError(
                    f"{where}: expected (N, K) = (N, {K}) indicators (columns {self.names}), "
                    f"got shape {tuple(t.shape)}."
                )
        self._values = t

    def adapt(self, context: UpdateContext) -> Adaptation:
        """``R ← ρ R``; flag indicators reject; consumes the indicators."""
        where = "QualityR"
        if self._values is None:
            raise NeuralMapError(
                f"{where}: no quality indicators for this update; call "
                "policy.set_quality(values) before every update."
            )
        values, self._values = self._values, None
        batch, m = context.residual.shape
        if values.shape[0] != batch:
            raise NeuralMapError(
                f"{where}: indicators hold {values.shape[0]} samples but the filter has "
                f"{batch}; pass (N, {len(self.indicators)}) with N = {batch}."
            )
        values = values.to(dtype=context.R.dtype, device=context.R.device)
        bad = ~torch.isfinite(values).all(-1) & context.mask
        if bool(bad.any()):
            i = int(torch.nonzero(bad)[0, 0])
            raise NeuralMapError(
                f"{where}: non-finite quality indicator at sample {i}: {values[i].tolist()}; "
                "mask samples without indicators instead."
            )
        values = torch.where(context.mask.unsqueeze(-1), values, 0.0)
        mu = torch.stack([
            quality_membership(values[:, j], ind.good, ind.bad, ind.cap)
            for j, ind in enumerate(self.indicators)
        ], dim=-1)
        weights = torch.tensor([0.0 if ind.reject else ind.weight for ind in self.indicators],
                               dtype=mu.dtype, device=mu.device)
        rho = torch.where(context.mask, quality_factor(mu, weights), 1.0)
        flags = [j for j, ind in enumerate(self.indicators) if ind.reject]
        rejected = torch.zeros(batch, dtype=torch.bool, device=mu.device)
        for j in flags:
            rejected = rejected | (mu[:, j] >= 1.0)
        rejected = rejected & context.mask
        info = {"rho": rho, "membership": mu, "rejected": rejected}
        R = context.R * rho.reshape(-1, 1, 1)
        keep = None
        if flags and bool(rejected.any()):
            keep = (~rejected).unsqueeze(-1).expand(batch, m)
        return Adaptation(R=R, keep=keep, info=info)
