"""Maximum-likelihood noise learning through the TAN filter (gradient ascent, TBPTT).

``θ* = argmax Σ_flights Σ_k ℓ_k(θ)`` over the parameters of Q and R
(`NoiseModel`), with ``ℓ_k`` the innovation
log-likelihood of `tan_log_likelihood`. Long flights
use truncated back-propagation through time: the flights are cut into windows of
``tbptt_steps`` steps, one optimiser step per window, the filter state carried (detached)
from one window to the next. The loss is the negative log-likelihood per applied update,
so the learning rate does not depend on the number of flights.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.learning.flights import FlightBatch
from neuralmap.learning.likelihood import tan_log_likelihood
from neuralmap.learning.noise_model import NoiseModel

__all__ = ["NoiseFitResult", "fit_noise", "make_optimizer", "nees_summary"]


@dataclass
class NoiseFitResult:
    """History of a noise fit.

    Attributes:
        history: Per epoch ``{"epoch", "log_likelihood_per_update", "Q_diag", "R",
            "nees"}`` (the likelihood of the whole flights at the epoch's start values,
            evaluated without truncation).
        noise: The fitted model.
    """

    noise: NoiseModel
    history: list[dict[str, Any]] = field(default_factory=list)


def make_optimizer(name: str, params: Any, lr: float) -> torch.optim.Optimizer:
    """``adam`` or ``sgd`` by name (a clear error otherwise)."""
    if name == "adam":
        return torch.optim.Adam(params, lr=lr)
    if name == "sgd":
        return torch.optim.SGD(params, lr=lr, momentum=0.9)
    raise NeuralMapError(f"optimizer {name!r} is unknown; use 'adam' or 'sgd'.")


def nees_summary(nees: torch.Tensor | None) -> float:
    """Time-and-run average NEES (finite entries) — 5 for a consistent 5-state filter."""
    if nees is None or nees.numel() == 0:
        return float("nan")
    finite = torch.isfinite(nees)
    return float(nees[finite].mean()) if bool(finite.any()) else float("nan")


def evaluate_noise(flights: FlightBatch, linearizer: Any, noise: NoiseModel, *,
                   F: torch.Tensor, P0: torch.Tensor) -> dict[str, Any]:
    """Whole-flight log-likelihood per update, NEES and the parameter values (no grad)."""
    with torch.no_grad():
        run = tan_log_likelihood(flights, linearizer, F=F, Q=noise.Q(), R=noise.R(), P0=P0)
    n_upd = max(int(run.n_updates.sum()), 1)
    return {"log_likelihood_per_update": float(run.log_likelihood.sum()) / n_upd,
            "nees": nees_summary(run.nees), "n_updates": n_upd,
            "skipped_off_map": run.skipped_off_map, **noise.values()}


def fit_noise(
    flights: FlightBatch,
    linearizer: Any,
    noise: NoiseModel,
    *,
    F: torch.Tensor,
    P0: torch.Tensor,
    epochs: int = 50,
    lr: float = 0.05,
    optimizer: str = "adam",
    tbptt_steps: int | None = None,
    batch_size: int | None = None,
    seed: int = 0,
    eval_flights: int | None = None,
    lr_min_ratio: float = 1.0,
    callback: Callable[[int, dict[str, Any]], None] | None = None,
) -> NoiseFitResult:
    """Fits Q and R by maximising the innovation log-likelihood of the flights.

    Args:
        flights: Training flights.
        linearizer: Map linearisation method.
        noise: Start values (changed in place).
        F: ``(5, 5)`` Φ. P0: ``(5, 5)`` prior covariance (fixed).
        epochs: Passes over the flights (≥ 1).
        lr: Learning rate (on the log-parameters).
        optimizer: ``adam`` or ``sgd``.
        tbptt_steps: Window length of truncated BPTT; None = whole flights.
        batch_size: Flights per optimiser step (None = all); shuffled per epoch.
        seed: Shuffling seed.
        eval_flights: Flights (the first ones) of the per-epoch evaluation; None = all.
        lr_min_ratio: Cosine decay of the learning rate over all optimiser steps down to
            ``lr · lr_min_ratio`` (1 = constant rate; minibatch and window noise makes a
            constant rate wander around the optimum by about ``lr`` in log-parameter).
        callback: Called as ``callback(epoch, record)`` after each epoch's evaluation.

    Returns:
        `NoiseFitResult` (history has ``epochs + 1`` records: the start and every
        epoch).

    Raises:
        NeuralMapError: epochs < 1, tbptt_steps < 1, batch_size < 1, unknown optimiser.
    """
    if epochs < 1:
        raise NeuralMapError(f"fit_noise: epochs must be >= 1, got {epochs}.")
    if tbptt_steps is not None and tbptt_steps < 1:
        raise NeuralMapError(f"fit_noise: tbptt_steps must be >= 1 (or None), got {tbptt_steps}.")
    if batch_size is not None and batch_size < 1:
        raise NeuralMapError(f"fit_noise: batch_size must be >= 1 (or None), got {batch_size}.")
    if not 0.0 < lr_min_ratio <= 1.0:
        raise NeuralMapError(f"fit_noise: lr_min_ratio must be in (0, 1], got {lr_min_ratio}.")
    opt = make_optimizer(optimizer, noise.parameters(), lr)
    window = tbptt_steps or flights.n_steps
    batch = batch_size or flights.n_flights
    n_opt_steps = epochs * -(-flights.n_flights // batch) * -(-flights.n_steps // window)
    schedule = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=max(n_opt_steps, 1),
                                                          eta_min=lr * lr_min_ratio)
    gen = torch.Generator().manual_seed(seed)
    result = NoiseFitResult(noise)

    probe = flights if eval_flights is None else flights.subset(slice(0, eval_flights))

    def record(epoch: int) -> None:
        rec = {"epoch": epoch, **evaluate_noise(probe, linearizer, noise, F=F, P0=P0)}
        result.history.append(rec)
        if callback is not None:
            callback(epoch, rec)

    record(0)
    for epoch in range(1, epochs + 1):
        order = torch.randperm(flights.n_flights, generator=gen)
        for first in range(0, flights.n_flights, batch):
            part = flights.subset(order[first:first + batch].to(flights.ins_pos.device))
            state = None
            for start in range(1, part.n_steps + 1, window):
                stop = min(start + window, part.n_steps + 1)
                opt.zero_grad()
                run = tan_log_likelihood(part, linearizer, F=F, Q=noise.Q(), R=noise.R(),
                                         P0=P0, state=state, start=start, stop=stop)
                n_upd = int(run.n_updates.sum())
                if n_upd > 0:
                    (-run.log_likelihood.sum() / n_upd).backward()
                    opt.step()
                schedule.step()
                state = run.state.detach()
        record(epoch)
    return result
