"""The navigation-method protocol: what every TAN filter offers the `Navigator`.

A navigation method estimates the 5-state INS error ``δX = [δx, δy, δh, δv_x, δv_y]``
(INS − truth, `neuralmap.tan.model`) of N vehicles at once (batch first) from the radar
altimeter, on one map. The `Navigator` (`neuralmap.nav.navigator`) runs the integrity state
machine around it — acquisition, hand-off, lost lock, re-acquisition, off-map and
no-measurement epochs, protection levels — and asks the method for four things only:

* `NavigationMethod.predict` over an interval ``Δt`` (the model's ``Φ(Δt)``, ``Q(Δt)``);
* `NavigationMethod.update` with the clearances (and, for policies that read it, the
  altimeter's quality record) of the rows in a mask, returning an `Innovation`;
* `NavigationMethod.estimate`: the mean ``(N, 5)`` and covariance ``(N, 5, 5)``;
* `NavigationMethod.load` / `NavigationMethod.drop`: rows (re)start from a Gaussian, or
  leave (the pipeline holds them elsewhere, e.g. on the acquisition grid).

A method is one class with a declared options dataclass (`NavigationMethod.Options`, read
from the navigator config's section of the method's name straight into it) and one
registry line (`neuralmap.tan.registry.register_method`); the Navigator, the
``neuralmap-navigate`` command and every study that flies TAN then fly it by name.

Measurement, every method (SEEDS 004): ``y = h_ins − clearance = t(p_ins − δp) + δh − v``,
``v ~ N(0, R)``, ``R`` the context's (altimeter + the map's error variance).
"""

from __future__ import annotations

import abc
from dataclasses import dataclass
from typing import Any, ClassVar

import torch

from neuralmap.tan.model import TanModel

__all__ = ["ACQUISITION_RULES", "Innovation", "MethodContext", "NavigationMethod"]

#: When the Navigator starts (and re-starts after a lost lock) a method's vehicles on the
#: point-mass acquisition grid: ``never``, ``wide`` (a prior whose horizontal σ exceeds the
#: config's ``acquisition.above_sigma_m``) or ``always``.
ACQUISITION_RULES = ("never", "wide", "always")


@dataclass(frozen=True)
class MethodContext:
    """What a navigation method is built from (the `Navigator` fills it).

    Attributes:
        terrain: The map, any `neuralmap.terrain.base.TerrainModel` (``forward(xy (..., 2))
            -> (...)`` heights) with an ``extent``.
        extent: Map extent ``(xmin, xmax, ymin, ymax)``, m.
        model: The TAN model (`TanModel`: ``P0``, ``Q`` per period, ``Φ(Δt)``, the altitude
            error model).
        R: Measurement variance ``σ_alt² + σ_map²``, m² (a method may add its own
            linearisation variance).
        R_altimeter: The altimeter's part ``σ_alt²`` of it, m² (a method whose own noise
            model covers the map's error, e.g. a measured noise table, uses this).
        n_vehicles: N, the batch of every tensor.
        device: Where the state lives.
        tile: The DEM tile behind a grid map (for EKF linearisations that read the DEM), or
            None.
        noise_table: A measured linearisation-noise table (EKF methods;
            `neuralmap.linearize.measured_noise.NoiseTable`), or None.
    """

    terrain: Any
    extent: tuple[float, float, float, float]
    model: TanModel
    R: float
    R_altimeter: float
    n_vehicles: int
    device: torch.device
    tile: Any = None
    noise_table: Any = None


@dataclass
class Innovation:
    """What `NavigationMethod.update` reports per vehicle (``(N,)`` each).

    Attributes:
        innovation: The measurement residual of the update (predicted minus measured
            clearance), m; NaN where not updated.
        nis: Its normalised square ``ν² / S`` (the predictive NIS of a point-mass method);
            NaN where not updated and not gated.
        applied: bool, the update was applied.
        gated: bool, the clearance was refused by the spike gate (its ``nis`` is the
            predictive NIS that refused it).
        on_map: bool, the estimate the method linearised at (or any of its cells) lies on
            the map.
    """

    innovation: torch.Tensor
    nis: torch.Tensor
    applied: torch.Tensor
    gated: torch.Tensor
    on_map: torch.Tensor

    @classmethod
    def none(cls, n: int, device: torch.device) -> Innovation:
        """No update for any of ``n`` vehicles."""
        nan = torch.full((n,), float("nan"), dtype=torch.float64, device=device)
        no = torch.zeros(n, dtype=torch.bool, device=device)
        return cls(innovation=nan, nis=nan.clone(), applied=no, gated=no.clone(),
                   on_map=~no)


class NavigationMethod(abc.ABC):
    """The declared interface of a navigation method (module docstring).

    Subclasses set `Options` (a dataclass of the method's options, defaults = the shipped
    ones) and `acquisition`, implement the abstract methods, and register with
    `neuralmap.tan.registry.register_method`.

    Args:
        context: `MethodContext`.
        options: An instance of `Options` (validated by the config before).

    Attributes:
        name: The registry name (set by `register_method`).
        Options: The options dataclass.
        acquisition: One of `ACQUISITION_RULES`.
        cell_updates: Likelihood evaluations done so far (cells × vehicles for a lattice,
            components for a bank, vehicles for an EKF), for throughput figures.
    """

    name: ClassVar[str] = ""
    Options: ClassVar[type] = type(None)
    acquisition: ClassVar[str] = "never"

    def __init__(self, context: MethodContext, options: Any) -> None:
        self.context = context
        self.options = options
        self.cell_updates = 0

    @abc.abstractmethod
    def predict(self, dt: float) -> None:
        """Time update of every vehicle over ``dt`` s (``Φ(Δt)``, ``Q(Δt)`` of the model)."""

    @abc.abstractmethod
    def update(self, ins: torch.Tensor, clearance: torch.Tensor, mask: torch.Tensor, *,
               gate: float = float("inf"), quality: torch.Tensor | None = None) -> Innovation:
        """Measurement update of the vehicles in ``mask``.

        Args:
            ins: ``(N, 3)`` INS position ``x, y, h`` (map frame, m), float64.
            clearance: ``(N,)`` radar clearance, m (finite where ``mask``).
            mask: ``(N,)`` bool, the vehicles to update.
            gate: Spike gate: a method that gates leaves out a clearance whose predictive
                NIS exceeds it (reported ``gated``); ``inf`` = off.
            quality: ``(N, q)`` the altimeter's quality record, for policies that read it,
                or None.

        Returns:
            `Innovation`.
        """

    @abc.abstractmethod
    def estimate(self) -> tuple[torch.Tensor, torch.Tensor]:
        """The estimate ``(mean (N, 5), cov (N, 5, 5))`` of ``δX``, float64."""

    @abc.abstractmethod
    def load(self, mask: torch.Tensor, mean: torch.Tensor, cov: torch.Tensor) -> None:
        """Vehicles ``mask (N,)`` (re)start from ``N(mean (N, 5), cov (N, 5, 5))`` (rows
        outside the mask are ignored)."""

    def drop(self, mask: torch.Tensor) -> None:  # noqa: B027 - optional, a no-op by default
        """Vehicles ``mask (N,)`` leave the method (held elsewhere): it may stop spending on
        them. Their next `load` restarts them."""

    def protection_level(self, risk: float, gaussian: torch.Tensor,
                         mean: torch.Tensor) -> torch.Tensor:
        """``(N,)`` horizontal protection level at ``risk``, m, given the Gaussian one of the
        method's own covariance (`neuralmap.nav.integrity`) and the estimate ``mean (N, 5)``
        (`estimate`'s): a method whose posterior is not Gaussian (a point-mass lattice)
        answers from its own mass; the default is the Gaussian level."""
        return gaussian

    def counters(self) -> dict[str, torch.Tensor]:
        """The method's own per-vehicle counters ``(N,)`` (e.g. a lattice's recoveries),
        reported beside the Navigator's; none by default."""
        return {}

    def healthy(self) -> torch.Tensor:
        """``(N,)`` bool: the filter is numerically healthy (finite, positive definite)."""
        return torch.ones(self.context.n_vehicles, dtype=torch.bool,
                          device=self.context.device)
