"""Training the residual super-resolution prior on tiles whose fine truth is known.

Each step cuts random patches from the training grids (every grid also at its 2x and 4x
decimations, so one tile gives the prior several ground resolutions), applies one of the
eight rotations/reflections of the square, decimates each patch by the factor (keeping
nodes ``[f i, f j]``) and fits `ResidualSuperRes` to the withheld nodes::

    L = mean over withheld nodes of ((h_pred - h_true) / s_f)²                     (1)

with ``s_f`` the local scale of the coarse patch (eq. 1 of `neuralmap.terrain.superres`)
carried to the fine lattice, so that rough and flat tiles weigh alike. Adam with a cosine
schedule.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np
import torch
from torch.nn import functional as F  # noqa: N812

from neuralmap.exceptions import NeuralMapError
from neuralmap.terrain.superres import ResidualSuperRes

__all__ = ["PatchSampler", "fit_superres_prior", "prior_loss"]


class PatchSampler:
    """Random fine patches from a set of complete grids, their decimations included.

    Args:
        grids: Fine height grids ``(ny, nx)`` in metres without voids.
        factor: Decimation factor of the prior.
        patch: Coarse patch side P (fine side ``f (P-1) + 1``).
        decimations: Extra ground resolutions: each grid also enters as ``grid[::d, ::d]``
            for every ``d`` listed (those smaller than one fine patch are skipped).

    Raises:
        NeuralMapError: No grid large enough for one patch, or a grid with voids.
    """

    def __init__(self, grids: Sequence[np.ndarray], *, factor: int, patch: int,
                 decimations: Sequence[int] = (1, 2, 4)) -> None:
        self.factor = int(factor)
        self.patch = int(patch)
        self.fine = self.factor * (self.patch - 1) + 1
        self.grids: list[torch.Tensor] = []
        for grid in grids:
            arr = np.asarray(grid, dtype=np.float64)
            if not np.isfinite(arr).all():
                raise NeuralMapError("PatchSampler: a training grid has voids; fill or crop "
                                     "them first.")
            for d in decimations:
                sub = arr[:: int(d), :: int(d)]
                if min(sub.shape) >= self.fine:
                    self.grids.append(torch.as_tensor(np.ascontiguousarray(sub)))
        if not self.grids:
            raise NeuralMapError(
                f"PatchSampler: no training grid has {self.fine} x {self.fine} nodes for one "
                f"patch (factor {factor}, patch {patch}); use a smaller patch.")
        # pick grids in proportion to their patch positions
        sizes = np.array([(g.shape[0] - self.fine + 1) * (g.shape[1] - self.fine + 1)
                          for g in self.grids], dtype=np.float64)
        self.weights = torch.as_tensor(sizes / sizes.sum())

    def sample(self, n: int, generator: torch.Generator) -> torch.Tensor:
        """``(n, F, F)`` float64 fine patches (F = ``f (P-1) + 1``), randomly rotated/flipped."""
        picks = torch.multinomial(self.weights, int(n), replacement=True, generator=generator)
        out = []
        for g in picks.tolist():
            grid = self.grids[g]
            i = int(torch.randint(grid.shape[0] - self.fine + 1, (1,), generator=generator))
            j = int(torch.randint(grid.shape[1] - self.fine + 1, (1,), generator=generator))
            p = grid[i: i + self.fine, j: j + self.fine]
            k = int(torch.randint(8, (1,), generator=generator))
            p = torch.rot90(p, k % 4, dims=(0, 1))
            out.append(p.flip(1) if k >= 4 else p)
        return torch.stack(out)


def prior_loss(prior: ResidualSuperRes, fine: torch.Tensor) -> torch.Tensor:
    """Eq. (1): normalised squared error at the withheld nodes of ``(B, F, F)`` patches."""
    f = prior.factor
    coarse = fine[:, ::f, ::f]
    pred = prior(coarse)
    _, s = prior.normalise(coarse)
    s_f = F.interpolate(s, scale_factor=f, mode="nearest")[:, 0, : fine.shape[1], : fine.shape[2]]
    withheld = torch.ones_like(fine, dtype=torch.bool)
    withheld[:, ::f, ::f] = False
    err = (pred - fine) / s_f
    return (err[withheld] ** 2).mean()


def fit_superres_prior(
    grids: Sequence[np.ndarray],
    *,
    factor: int = 2,
    steps: int = 600,
    batch: int = 16,
    patch: int = 24,
    lr: float = 2e-3,
    channels: int = 32,
    depth: int = 4,
    seed: int = 0,
    progress: Callable[[float], None] | None = None,
) -> ResidualSuperRes:
    """Trains a `ResidualSuperRes` on fine grids (eq. 1), float32.

    Args:
        grids: Fine grids with known truth (the tiles the prior learns from).
        factor: Upsampling factor.
        steps: Adam steps.
        batch: Patches per step.
        patch: Coarse patch side.
        lr: Peak learning rate (cosine decay to 0).
        channels: Hidden channels.
        depth: Convolution layers.
        seed: Seed of the weights and of the patch draws.
        progress: Called with the fraction of steps done.

    Returns:
        The trained prior in eval mode.
    """
    prior = ResidualSuperRes(factor=factor, channels=channels, depth=depth, seed=seed).float()
    sampler = PatchSampler(grids, factor=factor, patch=patch)
    generator = torch.Generator().manual_seed(int(seed))
    opt = torch.optim.Adam(prior.parameters(), lr=lr)
    sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=max(int(steps), 1))
    prior.train()
    for step in range(int(steps)):
        fine = sampler.sample(batch, generator).float()
        loss = prior_loss(prior, fine)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        sched.step()
        if progress is not None and (step + 1) % 10 == 0:
            progress(10 / max(int(steps), 1))
    return prior.eval()
