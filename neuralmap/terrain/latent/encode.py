"""Encoding a tile into a latent-grid map without Lightning (benchmarks, tests, scripts).

The training recipe (shared with the Lightning module
`LatentFitModule`): Adam with a cosine learning
rate; the rounding relaxed by additive noise for the first ``1 - ste_fraction`` of the
steps, then straight-through rounding (Cool-chic's annealing from noise to the true
quantiser, so the last steps optimise what is stored). With ``relaxation="soft"`` the first
phase is C3's soft rounding plus noise, its sharpness annealed from `SOFT_ALPHA` [0] to [1]
(`soft_alpha`). With ``zones=R`` the per-zone step and scale codes (`.zones`) are chosen
by RDO when straight-through rounding starts (`zones_due`), so the last phase trains the
latents under the zones' steps. The final symbols are rounded, or chosen by
rate-distortion-optimised quantisation (`.rdoq`, ``rdoq=True``).
"""

from __future__ import annotations

import math
from typing import Any

import torch

from neuralmap.dem.tile import DemTile
from neuralmap.exceptions import NeuralMapError
from neuralmap.terrain.latent.latent_grid import LatentGrid, export_map
from neuralmap.terrain.latent.map import LatentTerrainMap
from neuralmap.terrain.latent.objective import RateDistortion

#: Soft-rounding sharpness at the start and at the end of the soft phase.
SOFT_ALPHA = (1.0, 12.0)
#: First-phase relaxations (``model.relaxation``).
RELAXATIONS = ("noise", "soft")


def quantizer_at(step: int, total: int, ste_fraction: float, relaxation: str = "noise") -> str:
    """The relaxation used at ``step`` of ``total``: ``relaxation``, then ``"ste"``."""
    return "ste" if step >= math.ceil((1.0 - ste_fraction) * total) else relaxation


def soft_alpha(step: int, total: int, ste_fraction: float) -> float:
    """Soft-rounding sharpness at ``step``: geometric from `SOFT_ALPHA` [0] to [1] over the
    first ``1 - ste_fraction`` of the steps."""
    span = max(1.0, math.ceil((1.0 - ste_fraction) * total))
    frac = min(1.0, step / span)
    return SOFT_ALPHA[0] * (SOFT_ALPHA[1] / SOFT_ALPHA[0]) ** frac


def zones_due(step: int, total: int, ste_fraction: float) -> bool:
    """Whether the zone codes are chosen at ``step``: the first straight-through step."""
    return step == math.ceil((1.0 - ste_fraction) * total)


def rdoq_rate_weight(rate_weight: float, between_weight: float) -> float:
    """``lambda`` of RDOQ for the objective ``D_nodes + mu D_between + lambda R``.

    RDOQ's distortion counts the node error only; a latent's error shows about as much
    between the nodes, so ``D_nodes + mu D_between ~ (1 + mu) D_nodes`` and the node-only
    trade-off is ``lambda / (1 + mu)``.
    """
    return float(rate_weight) / (1.0 + float(between_weight))


def make_optimizer(grid: LatentGrid, lr: float, total: int
                   ) -> tuple[torch.optim.Optimizer, torch.optim.lr_scheduler.LRScheduler]:
    """Adam over every parameter with a cosine decay to 0.1 ``lr`` over ``total`` steps."""
    optimizer = torch.optim.Adam(grid.parameters(), lr=lr)
    scheduler = torch.optim.lr_scheduler.CosineAnnealingLR(optimizer, T_max=max(1, total),
                                                           eta_min=0.1 * lr)
    return optimizer, scheduler


def fit_latent_map(
    tile: DemTile,
    *,
    rate_weight: float,
    steps: int = 1500,
    levels: int = 6,
    hidden: int = 0,
    lr: float = 0.01,
    init_step: float = 1.0,
    between_weight: float = 0.5,
    between_points: int = 8192,
    ste_fraction: float = 0.2,
    init_sweeps: int = 12,
    seed: int = 0,
    exact_start: bool = True,
    basis: str = "wavelet",
    wavelet: str = "cdf97",
    entropy: str = "factorized",
    context_hidden: int = 12,
    relaxation: str = "noise",
    rdoq: bool = False,
    zones: int = 0,
    zones_always: bool = False,
) -> tuple[LatentTerrainMap, dict[str, Any]]:
    """Fits a latent-grid map to ``tile`` and returns it as its file stores it.

    Args:
        tile: The DEM tile.
        rate_weight: ``lambda`` of `RateDistortion` (m² per bit per node).
        steps: Adam steps.
        levels: Latent levels.
        hidden: MLP hidden units.
        lr: Peak learning rate.
        init_step: Initial quantisation step (m).
        between_weight: Weight of the between-node term.
        between_points: Between-node points per step.
        ste_fraction: Final fraction of steps with straight-through rounding.
        init_sweeps: Correction sweeps of the Laplacian-pyramid start.
        seed: Seed of the MLP and of the between-node points.
        exact_start: Start from latents that reproduce every node (`LatentGrid`).
        basis: Latent basis, ``"pyramid"`` or ``"wavelet"`` (`.basis`).
        wavelet: Wavelet of the wavelet basis.
        entropy: ``"factorized"`` or ``"context"`` (`.context_model`).
        context_hidden: Hidden units of the context MLP.
        relaxation: First-phase relaxation, ``"noise"`` or ``"soft"``.
        rdoq: Choose the final symbols by RDOQ (`.rdoq`) instead of rounding.
        zones: Side ``R`` of the grid of zones with their own steps and entropy scales
            (`.zones`; 0 = one step per subband).
        zones_always: Store the zones even where they do not lower the exact
            ``SSE + lambda' bits`` (default: dropped then, `.latent_grid.zones_pay`).

    Returns:
        ``(map, history)`` with the last step's loss terms in ``history``.
    """
    torch.manual_seed(seed)
    objective = RateDistortion(tile, rate_weight=rate_weight, between_weight=between_weight,
                               between_points=between_points)
    grid = LatentGrid(tile, levels=levels, hidden=hidden, init_step=init_step,
                      init_sweeps=init_sweeps, seed=seed, exact_start=exact_start,
                      basis=basis, wavelet=wavelet, entropy=entropy,
                      context_hidden=context_hidden, zones=zones)
    if relaxation not in RELAXATIONS:
        raise NeuralMapError(f"latent map: relaxation must be one of {list(RELAXATIONS)}, got "
                             f"{relaxation!r}.")
    optimizer, scheduler = make_optimizer(grid, lr, steps)
    generator = torch.Generator().manual_seed(seed)
    terms = None
    node_lambda = rdoq_rate_weight(rate_weight, between_weight)
    for step in range(steps):
        if grid.zones and zones_due(step, steps, ste_fraction):
            grid.choose_zones(node_lambda)
        terms = objective(grid, quantizer_at(step, steps, ste_fraction, relaxation), generator,
                          soft_alpha(step, steps, ste_fraction))
        optimizer.zero_grad(set_to_none=True)
        terms.loss.backward()
        optimizer.step()
        scheduler.step()
    history: dict[str, Any] = {}
    if terms is not None:
        history = {key: float(getattr(terms, key).detach())
                   for key in ("loss", "node_mse", "between_mse", "bits")}
    latent_map = export_map(grid, rdoq_rate_weight=node_lambda if rdoq else None,
                            rdoq_target=(objective.heights, objective.valid),
                            zone_rate_weight=node_lambda, zones_always=zones_always)
    return latent_map, history
