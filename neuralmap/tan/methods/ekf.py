"""The TAN EKF (SEEDS 004) with any linearisation and any robust/adaptive update policy.

The 5-state error-state EKF (`neuralmap.tan.ekf_step.tan_filter_step`: predict, linearise
the map at ``p̂ = p_ins − δp̂⁻`` with the horizontal covariance, update with ``R = R_base +
the linearisation variance``), over N vehicles in one `neuralmap.filters.ekf.BatchedEKF`.
The linearisation is a `neuralmap.linearize` method by name (``bilinear``, ``nine_point``,
``neural`` = autograd on any map, ...) or a `Linearizer` object; the policy a
`neuralmap.filters.policies.registry` name (``ekf`` = none, ``raf``, ``igg3``, ``huber``,
``chi2``, ``quality_raf``, ...) or a policy object. A model with more states than the five
(``n_states``, ``jacobian``: the AR map-error states of `neuralmap.tan.augmented`) runs the
augmented filter; the estimate is its navigation block.

``ekf`` starts wherever the prior is (a cold start: one hypothesis, linearised at the prior
mean); ``point_mass_ekf`` (`PointMassEkf`) is the same filter started by the point-mass
acquisition grid, the toolkit's recommended EKF.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.filters.stats import symmetrize
from neuralmap.tan.ekf_step import tan_filter_step
from neuralmap.tan.method import Innovation, MethodContext, NavigationMethod
from neuralmap.tan.model import N_STATES
from neuralmap.tan.registry import register_method

__all__ = ["EkfMethod", "EkfOptions", "PointMassEkf", "build_linearizer"]


@dataclass
class EkfOptions:
    """Options of the EKF methods.

    Attributes:
        linearizer: A `neuralmap.linearize.factory.LINEARIZER_NAMES` name, or a
            `neuralmap.linearize.base.Linearizer` object (Python only: e.g. one with a
            measured noise table). ``neural`` (default) and ``neural_region`` linearise the
            map itself by autograd, whatever the map; the others read the DEM (a grid map,
            or the tile passed to the Navigator).
        policy: A `neuralmap.filters.policies.registry.POLICY_NAMES` name (``ekf`` = the
            plain update) or a policy object (Python only).
        policy_args: Options of a policy given by name.
        dtype: ``float64`` (default) or ``float32``.
    """

    linearizer: Any = "neural"
    policy: Any = "ekf"
    policy_args: dict[str, Any] = field(default_factory=dict)
    dtype: str = "float64"

    def validate(self, where: str = "ekf") -> EkfOptions:
        """Checks the names (lists the valid ones) and the policy's arguments."""
        from neuralmap.filters.policies.registry import POLICY_NAMES
        from neuralmap.linearize.factory import LINEARIZER_NAMES

        if isinstance(self.linearizer, str) and self.linearizer not in LINEARIZER_NAMES:
            raise NeuralMapError(f"{where}.linearizer must be one of "
                                 f"{', '.join(LINEARIZER_NAMES)}, got {self.linearizer!r}.")
        if not isinstance(self.linearizer, str) and not callable(self.linearizer):
            raise NeuralMapError(f"{where}.linearizer must be a linearisation name or a "
                                 f"Linearizer, got {type(self.linearizer).__name__}.")
        if isinstance(self.policy, str) and self.policy not in POLICY_NAMES:
            raise NeuralMapError(f"{where}.policy must be one of {', '.join(POLICY_NAMES)}, "
                                 f"got {self.policy!r}.")
        if not isinstance(self.policy_args, dict):
            raise NeuralMapError(f"{where}.policy_args must be a mapping of option: value, "
                                 f"got {self.policy_args!r}.")
        if self.dtype not in ("float32", "float64"):
            raise NeuralMapError(f"{where}.dtype must be 'float32' or 'float64', got "
                                 f"{self.dtype!r}.")
        if isinstance(self.policy, str):
            from neuralmap.filters.policies.registry import make_policy

            make_policy(self.policy, self.policy_args, where=f"{where}.policy")  # args checked
        return self


def build_linearizer(context: MethodContext, linearizer: Any, method: str) -> Any:
    """The map linearisation of an EKF method: a `neuralmap.linearize` method by name on the
    context's map (``neural``/``neural_region`` by autograd on any map; the DEM methods on
    the context's tile or a grid map's heights), or a given `Linearizer` object; wrapped in
    the context's measured noise table when there is one.

    Raises:
        NeuralMapError: A DEM method on a map that is not a grid, without the tile.
    """
    from neuralmap.linearize.factory import make_linearizer

    if not isinstance(linearizer, str):
        lin = linearizer
    elif linearizer in ("neural", "neural_region"):
        lin = make_linearizer(linearizer, tile=None, terrain=context.terrain)
    else:
        lin = make_linearizer(linearizer, tile=_dem_tile(context, linearizer, method))
    if context.noise_table is not None:
        from neuralmap.linearize.measured_noise import MeasuredNoiseLinearizer

        lin = MeasuredNoiseLinearizer(lin, context.noise_table)
    if isinstance(lin, torch.nn.Module):
        lin.to(context.device)
    return lin


def _dem_tile(context: MethodContext, linearizer: str, method: str) -> Any:
    """The DEM tile a DEM-reading linearisation needs: the context's, or a grid map's."""
    from neuralmap.dem.tile import DemTile

    if context.tile is not None:
        return context.tile
    terrain = context.terrain
    heights = getattr(terrain, "heights", None)
    if heights is None or getattr(terrain, "origin", None) is None:
        raise NeuralMapError(
            f"method {method!r}: the linearisation {linearizer!r} reads the DEM itself; pass "
            "tile=<the DemTile> or use a grid map, or choose the linearisation 'neural' "
            "(autograd on any map) or the default point_mass_tracker.")
    return DemTile(heights=heights.detach().double().cpu().numpy(),
                   spacing=tuple(terrain.spacing), origin=tuple(terrain.origin),
                   name=getattr(terrain, "tile_name", "") or "map")


@register_method("ekf")
class EkfMethod(NavigationMethod):
    """The TAN EKF over N vehicles: one linearisation, one update policy (module docstring).

    Raises:
        NeuralMapError: A linearisation that cannot be built on this map (a DEM method on a
            map that is not a grid, without the tile).
    """

    Options = EkfOptions

    def __init__(self, context: MethodContext, options: EkfOptions) -> None:
        from neuralmap.filters.ekf import BatchedEKF

        super().__init__(context, options)
        self.dtype = torch.float32 if options.dtype == "float32" else torch.float64
        model, dev = context.model, context.device
        self.n_states = int(getattr(model, "n_states", N_STATES))
        self.jacobian = model.jacobian if self.n_states > N_STATES else None
        self.prior = model.filter_prior(dtype=self.dtype, device=dev)
        self.ekf = BatchedEKF(torch.zeros(context.n_vehicles, self.n_states, dtype=self.dtype,
                                          device=dev), self.prior)
        self.linearizer = build_linearizer(context, options.linearizer, self.name)
        # a measured noise table carries the map's error: R is then the altimeter's alone
        self.R = (context.R_altimeter if context.noise_table is not None else context.R)
        if self.n_states > N_STATES:
            self.R = float(model.base_R)
        self.policy = self._policy()
        self._nominal = (model.transition(dtype=self.dtype, device=dev),
                         model.process_noise(dtype=self.dtype, device=dev))
        self._pending: tuple[torch.Tensor, torch.Tensor] | None = None

    # ------------------------------------------------------------------ set-up
    def _policy(self) -> Any:
        from neuralmap.filters.policies.compose import quality_members
        from neuralmap.filters.policies.registry import make_policy

        policy = self.options.policy
        if isinstance(policy, str):
            policy = make_policy(policy, self.options.policy_args, where=f"{self.name}.policy")
        if policy is not None:
            policy.reset()
        self._quality = quality_members(policy)
        return policy

    # ------------------------------------------------------------------ the protocol
    def predict(self, dt: float) -> None:
        """Defers the prediction to the update (the EKF step predicts, then linearises at
        the predicted estimate); `estimate` applies a pending one."""
        model = self.context.model
        if dt == model.dt:
            self._pending = self._nominal
        else:
            kw = {"dtype": self.dtype, "device": self.context.device}
            self._pending = (model.transition(dt, **kw), model.process_noise(dt, **kw))

    def _flush(self) -> None:
        if self._pending is not None:
            F, Q = self._pending
            self._pending = None
            if self.policy is None:
                self.ekf.predict(F, Q)
            else:
                self.ekf.predict(F, Q, policy=self.policy)

    def update(self, ins: torch.Tensor, clearance: torch.Tensor, mask: torch.Tensor, *,
               gate: float = math.inf, quality: torch.Tensor | None = None) -> Innovation:
        """The EKF step (predict, linearise, update) for every vehicle, updating ``mask``;
        spikes are the policy's to handle (``gate`` is not used)."""
        if self._pending is None:
            return Innovation.none(self.context.n_vehicles, self.context.device)
        if self._quality:
            if quality is None:
                raise NeuralMapError(
                    f"method {self.name!r}: the policy {self.options.policy!r} reads the "
                    "altimeter's quality record; pass quality= to Navigator.step, or choose a "
                    "policy without 'quality' (raf, igg3, huber, chi2, ...).")
            for member in self._quality:
                member.set_quality(quality)
        F, Q = self._pending
        self._pending = None
        clearance = torch.where(mask, clearance, math.nan).to(self.dtype)
        diag = tan_filter_step(self.ekf, ins.to(self.dtype), clearance, self.linearizer, F=F,
                               Q=Q, R=self.R, extent=self.context.extent,
                               mask=None if bool(mask.all()) else mask, policy=self.policy,
                               jacobian=self.jacobian)
        if self.ekf.x.requires_grad or self.ekf.P.requires_grad:  # a graph-keeping map
            self.ekf.x, self.ekf.P = self.ekf.x.detach(), self.ekf.P.detach()
        applied = diag.updated.detach() & mask
        self.cell_updates += int(applied.sum())
        nan = torch.tensor(math.nan, dtype=torch.float64, device=applied.device)
        return Innovation(innovation=torch.where(applied, diag.residual.detach().double(), nan),
                          nis=torch.where(applied, diag.nis.detach().double(), nan),
                          applied=applied, gated=torch.zeros_like(applied),
                          on_map=diag.on_map)

    def estimate(self) -> tuple[torch.Tensor, torch.Tensor]:
        self._flush()
        x, P = self.ekf.x[:, :N_STATES], self.ekf.P[:, :N_STATES, :N_STATES]
        return x.double(), P.double()

    def load(self, mask: torch.Tensor, mean: torch.Tensor, cov: torch.Tensor) -> None:
        self._flush()
        n, k = mean.shape[0], self.n_states
        if k > N_STATES:  # the extra states restart from their prior
            full_m = torch.zeros(n, k, dtype=mean.dtype, device=mean.device)
            full_m[:, :N_STATES] = mean
            full_c = self.prior.to(cov.dtype).expand(n, k, k).clone()
            full_c[:, :N_STATES, :N_STATES] = cov
            mean, cov = full_m, full_c
        self.ekf.reset(mask, mean.to(self.dtype), symmetrize(cov.to(self.dtype)))

    def healthy(self) -> torch.Tensor:
        return self.ekf.healthy.clone()


@register_method("point_mass_ekf")
class PointMassEkf(EkfMethod):
    """The EKF started by the point-mass acquisition grid: every vehicle acquires on the
    grid first (and again after a lost lock), the EKF takes over once the grid posterior is
    unimodal and small (the Navigator's hand-off rule)."""

    Options = EkfOptions
    acquisition = "always"
