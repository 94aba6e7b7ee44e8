"""Map refinement from flights: fit the map correction to altimeter residuals, filter in the loop.

Maximises ``Σ_flights Σ_k ℓ_k(c) − Σ_nodes c²/(2 σ_prior²)`` over the correction offsets
``c`` (`MapCorrection`): ``ℓ_k`` is the innovation
log-likelihood of the TAN filter flying the corrected map
(`tan_log_likelihood`, Q and R fixed), so the filter's
own position estimate decides where each residual lands on the map. The prior keeps the
refined map at the original DEM fit where the flights do not inform it (unflown areas do
not drift: their offsets only feel the prior). Long flights use truncated BPTT windows.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.learning.flights import FlightBatch
from neuralmap.learning.likelihood import tan_log_likelihood
from neuralmap.learning.map_correction import CorrectedLinearizer, MapCorrection

__all__ = ["RefineResult", "refine_map"]


@dataclass
class RefineResult:
    """What `refine_map` returns.

    Attributes:
        correction: The fitted offsets.
        linearizer: The refined map's linearizer.
        history: Per epoch ``{"epoch", "nll_per_update", "prior", "max_abs_offset_m"}``.
    """

    correction: MapCorrection
    linearizer: CorrectedLinearizer
    history: list[dict[str, float]] = field(default_factory=list)


def refine_map(
    flights: FlightBatch,
    base_linearizer: Any,
    *,
    extent: tuple[float, float, float, float],
    F: torch.Tensor,
    Q: torch.Tensor,
    R: torch.Tensor | float,
    P0: torch.Tensor,
    spacing_m: float = 500.0,
    prior_sigma_m: float = 10.0,
    epochs: int = 20,
    lr: float = 1.0,
    tbptt_steps: int | None = 50,
    batch_size: int | None = None,
    seed: int = 0,
) -> RefineResult:
    """Fits a map correction to the flights (see the module docstring).

    Args:
        flights: Refinement flights.
        base_linearizer: Linearizer of the map to refine.
        extent: Map extent (the correction grid covers it).
        F, Q, P0: ``(5, 5)`` filter matrices; R: base measurement variance, m².
        spacing_m: Correction grid spacing, m.
        prior_sigma_m: σ of the prior on each offset (how far the DEM fit may be wrong), m.
        epochs: Passes over the flights.
        lr: Adam learning rate, m per step.
        tbptt_steps: Truncation window; None = whole flights.
        batch_size: Flights per step (None = all).
        seed: Shuffling seed.

    Raises:
        NeuralMapError: Non-positive spacing, prior σ, epochs or window.
    """
    if not prior_sigma_m > 0 or epochs < 1 or (tbptt_steps is not None and tbptt_steps < 1):
        raise NeuralMapError(
            f"refine_map: prior_sigma_m must be > 0, epochs >= 1 and tbptt_steps >= 1, got "
            f"{prior_sigma_m}, {epochs}, {tbptt_steps}.")
    correction = MapCorrection(extent, spacing_m=spacing_m)
    linearizer = CorrectedLinearizer(base_linearizer, correction)
    R_t = torch.as_tensor(R, dtype=P0.dtype)
    opt = torch.optim.Adam(correction.parameters(), lr=lr)
    window = tbptt_steps or flights.n_steps
    batch = batch_size or flights.n_flights
    gen = torch.Generator().manual_seed(seed)
    result = RefineResult(correction, linearizer)
    total_updates = max(int(flights.measured[:, 1:].sum()), 1)
    for epoch in range(1, epochs + 1):
        order = torch.randperm(flights.n_flights, generator=gen)
        nll_sum, n_sum, prior_val = 0.0, 0, 0.0
        for first in range(0, flights.n_flights, batch):
            part = flights.subset(order[first:first + batch])
            share = part.measured[:, 1:].sum().item() / total_updates
            state = None
            n_windows = max((part.n_steps + window - 1) // window, 1)
            for start in range(1, part.n_steps + 1, window):
                stop = min(start + window, part.n_steps + 1)
                run = tan_log_likelihood(part, linearizer, F=F, Q=Q, R=R_t, P0=P0,
                                         state=state, start=start, stop=stop, extent=extent)
                n_upd = int(run.n_updates.sum())
                prior = 0.5 * correction.offsets.square().sum() / prior_sigma_m**2
                # the prior's share of this window, so one epoch carries the prior once
                loss = (-run.log_likelihood.sum() + prior * share / n_windows) / total_updates
                opt.zero_grad()
                loss.backward()
                opt.step()
                nll_sum += float(-run.log_likelihood.sum().detach())
                n_sum += n_upd
                prior_val = float(prior.detach())
                state = run.state.detach()
        result.history.append({
            "epoch": float(epoch), "nll_per_update": nll_sum / max(n_sum, 1),
            "prior": prior_val, "max_abs_offset_m": float(correction.offsets.detach().abs().max()),
        })
    return result
