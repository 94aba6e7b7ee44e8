"""The EKF bank (Gaussian sum; SITAN-style parallel EKFs) as a navigation method.

Each vehicle's prior is split into a ``per_axis × per_axis`` moment-matched lattice of
Gaussian components over the horizontal error (`neuralmap.filters.ekf_bank.lattice_prior`),
each run by its own TAN EKF step (`neuralmap.tan.ekf_step.tan_filter_step`, the same
linearisations as ``ekf``), each weighted by the likelihood of its innovation, pruned and
merged (`neuralmap.filters.ekf_bank.GaussianSumEKF`). The estimate is the mixture's mean
and covariance; the reported innovation and NIS are the heaviest component's.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.filters.ekf_bank import GaussianSumEKF, lattice_prior
from neuralmap.tan.ekf_step import tan_filter_step
from neuralmap.tan.method import Innovation, MethodContext, NavigationMethod
from neuralmap.tan.methods.ekf import build_linearizer
from neuralmap.tan.model import N_STATES
from neuralmap.tan.registry import register_method

__all__ = ["EkfBank", "EkfBankOptions"]


@dataclass
class EkfBankOptions:
    """Options of the EKF bank.

    Attributes:
        linearizer: As `neuralmap.tan.methods.ekf.EkfOptions.linearizer`.
        per_axis: Components per axis (K = per_axis²; 1 = one EKF at the prior mean).
        span_sigma: Half-width of the components' lattice, prior σ.
        prune: Relative weight under which a component is pruned.
        merge: Squared Mahalanobis distance under which components merge (0 = never).
        dtype: ``float64`` (default) or ``float32``.
    """

    linearizer: Any = "neural"
    per_axis: int = 7
    span_sigma: float = 2.5
    prune: float = 1e-4
    merge: float = 1.0
    dtype: str = "float64"

    def validate(self, where: str = "ekf_bank") -> EkfBankOptions:
        """Checks ranges; raises `NeuralMapError` naming the option."""
        from neuralmap.linearize.factory import LINEARIZER_NAMES

        if isinstance(self.linearizer, str) and self.linearizer not in LINEARIZER_NAMES:
            raise NeuralMapError(f"{where}.linearizer must be one of "
                                 f"{', '.join(LINEARIZER_NAMES)}, got {self.linearizer!r}.")
        if isinstance(self.per_axis, bool) or not isinstance(self.per_axis, int) or (
                self.per_axis < 1):
            raise NeuralMapError(f"{where}.per_axis must be an integer >= 1 (components per "
                                 f"axis), got {self.per_axis!r}.")
        if not self.span_sigma > 0 or not 0.0 <= self.prune < 1.0 or not self.merge >= 0.0:
            raise NeuralMapError(f"{where}: span_sigma must be > 0, prune in [0, 1) and merge "
                                 f">= 0, got {self.span_sigma!r}, {self.prune!r}, "
                                 f"{self.merge!r}.")
        if self.dtype not in ("float32", "float64"):
            raise NeuralMapError(f"{where}.dtype must be 'float32' or 'float64', got "
                                 f"{self.dtype!r}.")
        return self


@register_method("ekf_bank")
class EkfBank(NavigationMethod):
    """The EKF bank over N vehicles (module docstring)."""

    Options = EkfBankOptions

    def __init__(self, context: MethodContext, options: EkfBankOptions) -> None:
        super().__init__(context, options)
        self.dtype = torch.float32 if options.dtype == "float32" else torch.float64
        model, dev, n = context.model, context.device, context.n_vehicles
        self.linearizer = build_linearizer(context, options.linearizer, self.name)
        self.R = context.R_altimeter if context.noise_table is not None else context.R
        kw = {"dtype": self.dtype, "device": dev}
        self._nominal = (model.transition(**kw), model.process_noise(**kw))
        self._pending: tuple[torch.Tensor, torch.Tensor] | None = None
        means, covs, logw = self._components(torch.zeros(n, N_STATES, **kw),
                                             model.filter_prior(**kw))
        self.bank = GaussianSumEKF(means, covs, log_weights=logw, prune_threshold=options.prune,
                                   merge_distance=options.merge, dtype=self.dtype)
        self.k = self.bank.n_components

    def _components(self, mean: torch.Tensor, cov: torch.Tensor
                    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        o = self.options
        return lattice_prior(mean, cov, per_axis=o.per_axis, span_sigma=o.span_sigma)

    def predict(self, dt: float) -> None:
        """Deferred to the update, as the EKF's."""
        model = self.context.model
        kw = {"dtype": self.dtype, "device": self.context.device}
        self._pending = (self._nominal if dt == model.dt else
                         (model.transition(dt, **kw), model.process_noise(dt, **kw)))

    def _flush(self) -> None:
        if self._pending is not None:
            F, Q = self._pending
            self._pending = None
            self.bank.ekf.predict(F, Q)

    def update(self, ins: torch.Tensor, clearance: torch.Tensor, mask: torch.Tensor, *,
               gate: float = math.inf, quality: torch.Tensor | None = None) -> Innovation:
        n, k = self.context.n_vehicles, self.k
        if self._pending is None:
            return Innovation.none(n, self.context.device)
        F, Q = self._pending
        self._pending = None
        bank = self.bank
        use = bank.alive & mask.repeat_interleave(k, 0)
        clearance = torch.where(mask, clearance, math.nan).to(self.dtype)
        diag = tan_filter_step(bank.ekf, ins.to(self.dtype).repeat_interleave(k, 0),
                               clearance.repeat_interleave(k, 0), self.linearizer, F=F, Q=Q,
                               R=self.R, extent=self.context.extent, mask=use)
        self.cell_updates += int(use.sum())
        bank.reweight(diag.residual, diag.S, diag.updated)
        best = bank.log_weights.argmax(1) + torch.arange(n, device=mask.device) * k
        applied = diag.updated[best] & mask
        nan = torch.tensor(math.nan, dtype=torch.float64, device=mask.device)
        return Innovation(innovation=torch.where(applied, diag.residual[best].double(), nan),
                          nis=torch.where(applied, diag.nis[best].double(), nan),
                          applied=applied, gated=torch.zeros_like(applied),
                          on_map=diag.on_map[best])

    def estimate(self) -> tuple[torch.Tensor, torch.Tensor]:
        self._flush()
        mean, cov = self.bank.mixture()
        return mean.double(), cov.double()

    def load(self, mask: torch.Tensor, mean: torch.Tensor, cov: torch.Tensor) -> None:
        """Vehicles ``mask`` restart as a fresh bank split from ``N(mean, cov)``."""
        self._flush()
        means, covs, logw = self._components(mean.to(self.dtype), cov.to(self.dtype))
        b, k = self.bank, self.k
        rows = mask.repeat_interleave(k, 0)
        b.ekf.reset(rows, means.reshape(-1, N_STATES), covs.reshape(-1, N_STATES, N_STATES))
        b.log_weights = torch.where(mask[:, None], logw, b.log_weights)

    def healthy(self) -> torch.Tensor:
        return self.bank.alive.reshape(self.context.n_vehicles, self.k).any(1)
