"""A residual super-resolution prior: the terrain between coarse nodes, learned across tiles.

Bicubic interpolation (Keys cubic convolution, the toolkit's `GridTerrain`) is the surface a
grid map answers between its nodes. It knows nothing of terrain: ridges come out rounded,
valley floors too high. `ResidualSuperRes` keeps the bicubic surface and adds a residual
predicted by a small convolutional network from the coarse grid around each cell, trained
on *other* tiles (where the fine truth is known) so that it can be applied to a new tile
of which only the coarse nodes exist::

    h_fine = B_f(h_coarse) + s_f * R(x),   x = (h_coarse - m) / s            (1)

with ``B_f`` the bicubic upsampler by the integer factor ``f`` (`bicubic_upsample`), ``m``
and ``s`` the local mean and local RMS node-to-node difference of the coarse grid
(``window`` x ``window`` box), ``s_f`` that scale carried to the fine lattice, and ``R``
the network, whose ``f²`` output channels are the residuals of the ``f²`` sub-node
positions of each cell (pixel shuffle, Shi et al. 2016, ESPCN). Normalising by the local
relief makes one network serve 1 m LiDAR and 2 km ETOPO grids alike (terrain is roughly
self-similar across scales). The residual is zero at the coarse nodes themselves, so the
upsampled grid passes through every coarse node, as bicubic does; a network whose last
layer is zero reproduces bicubic exactly.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import torch
from torch import nn
from torch.nn import functional as F  # noqa: N812

from neuralmap.dem.tile import DemTile
from neuralmap.exceptions import NeuralMapError

__all__ = ["ResidualSuperRes", "bicubic_matrix", "bicubic_upsample", "upsample_tile"]

#: Floor of the local scale ``s`` (metres): flat ground (a lake, the sea at 0 m) gets no
#: residual instead of a division by zero.
SCALE_FLOOR_M = 1e-3


def _keys_weights(t: torch.Tensor) -> torch.Tensor:
    """Keys cubic convolution (a = -1/2) weights of nodes k-1, k, k+1, k+2 at fraction t.

    Args:
        t: ``(M,)`` fractions in ``[0, 1]``.

    Returns:
        ``(M, 4)`` weights (Keys 1981, eq. 15; the rows of `neuralmap.terrain.grid`'s
        ``_KEYS`` matrix applied to ``[t³, t², t, 1]``).
    """
    t2, t3 = t * t, t * t * t
    return torch.stack([
        -0.5 * t3 + t2 - 0.5 * t,
        1.5 * t3 - 2.5 * t2 + 1.0,
        -1.5 * t3 + 2.0 * t2 + 0.5 * t,
        0.5 * t3 - 0.5 * t2,
    ], dim=-1)


def bicubic_matrix(n: int, factor: int, *, dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """The ``(factor (n-1) + 1, n)`` matrix of bicubic upsampling along one axis.

    Fine node ``r`` sits at coarse position ``r / factor``; its value is the Keys cubic
    convolution of the four nearest coarse nodes, with the quadratic-exact boundary rule
    of `neuralmap.terrain.grid.pad_cubic` (``f[-1] = 3 f[0] - 3 f[1] + f[2]``; linear
    ``2 f[0] - f[1]`` with two nodes) folded into the matrix, so that the result equals
    `GridTerrain` (``method="bicubic"``) queried at the fine nodes.

    Args:
        n: Coarse nodes along the axis (>= 2).
        factor: Integer upsampling factor (>= 1).
        dtype: Matrix dtype.

    Returns:
        The matrix (row ``r`` holds the weights of fine node ``r``).
    """
    if n < 2 or factor < 1:
        raise NeuralMapError(f"bicubic_matrix needs n >= 2 and factor >= 1, got {n}, {factor}.")
    m = factor * (n - 1) + 1
    r = torch.arange(m, dtype=torch.float64)
    k = torch.clamp(torch.div(r, factor, rounding_mode="floor"), max=n - 2).long()
    t = r / factor - k
    w = _keys_weights(t)  # (m, 4) over padded nodes k .. k+3 = coarse k-1 .. k+2
    padded = torch.zeros(m, n + 2, dtype=torch.float64)
    padded.scatter_add_(1, k[:, None] + torch.arange(4)[None, :], w)
    # fold the ghost nodes: padded column 0 is node -1, column n+1 is node n
    if n >= 3:
        lo = torch.zeros(n, dtype=torch.float64)
        lo[:3] = torch.tensor([3.0, -3.0, 1.0], dtype=torch.float64)
    else:
        lo = torch.tensor([2.0, -1.0], dtype=torch.float64)
    hi = lo.flip(0)
    mat = padded[:, 1:-1] + padded[:, :1] * lo[None, :] + padded[:, -1:] * hi[None, :]
    return mat.to(dtype)


def bicubic_upsample(coarse: torch.Tensor, factor: int) -> torch.Tensor:
    """Bicubic (Keys) upsampling of a grid by an integer factor, both axes.

    Args:
        coarse: ``(..., H, W)`` heights (no voids), H, W >= 2.
        factor: Integer factor f >= 1.

    Returns:
        ``(..., f (H-1) + 1, f (W-1) + 1)`` heights; node ``[f i, f j]`` is coarse
        ``[i, j]`` exactly (the lattice spans the same extent).
    """
    h, w = coarse.shape[-2:]
    ay = bicubic_matrix(h, factor, dtype=coarse.dtype).to(coarse.device)
    ax = bicubic_matrix(w, factor, dtype=coarse.dtype).to(coarse.device)
    return ay @ coarse @ ax.transpose(0, 1)


def _box(x: torch.Tensor, window: int) -> torch.Tensor:
    """``window`` x ``window`` box mean of ``(B, 1, H, W)`` with replicated borders."""
    pad = window // 2
    return F.avg_pool2d(F.pad(x, (pad, pad, pad, pad), mode="replicate"), window, stride=1)


class ResidualSuperRes(nn.Module):
    """Bicubic upsampling plus a learned residual (eq. 1 of the module docstring).

    Args:
        factor: Integer upsampling factor f (2 = every other node known).
        channels: Hidden channels of the network.
        depth: 3 x 3 convolution layers (>= 2); the receptive field is ``depth`` coarse
            nodes each side.
        window: Box width (coarse nodes, odd) of the local mean and scale.
        seed: Seed of the initial weights.

    Shapes:
        ``forward``: ``(B, H, W)`` coarse heights (metres) -> ``(B, f (H-1)+1, f (W-1)+1)``.
    """

    def __init__(self, factor: int = 2, channels: int = 32, depth: int = 4, window: int = 7,
                 seed: int = 0) -> None:
        super().__init__()
        if int(factor) < 2 or int(depth) < 2 or int(channels) < 1 or int(window) % 2 != 1:
            raise NeuralMapError(
                f"ResidualSuperRes needs factor >= 2, depth >= 2, channels >= 1 and an odd "
                f"window, got factor={factor}, depth={depth}, channels={channels}, "
                f"window={window}.")
        self.factor = int(factor)
        self.window = int(window)
        generator_state = torch.random.get_rng_state()
        torch.manual_seed(int(seed))
        layers: list[nn.Module] = []
        c_in = 3  # normalised height and its two normalised differences
        for _ in range(int(depth) - 1):
            layers += [nn.Conv2d(c_in, int(channels), 3, padding=1, padding_mode="replicate"),
                       nn.GELU()]
            c_in = int(channels)
        layers.append(nn.Conv2d(c_in, self.factor**2, 3, padding=1, padding_mode="replicate"))
        self.body = nn.Sequential(*layers)
        torch.random.set_rng_state(generator_state)
        keep = torch.ones(self.factor, self.factor)
        keep[0, 0] = 0.0  # the coarse node itself: no residual
        self.register_buffer("phase_mask", keep.reshape(1, -1, 1, 1), persistent=False)

    @property
    def last_layer(self) -> nn.Conv2d:
        """The output convolution (zero it to get plain bicubic)."""
        layer = self.body[-1]
        assert isinstance(layer, nn.Conv2d)
        return layer

    def normalise(self, coarse: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Network input and local scale of ``(B, H, W)`` coarse heights.

        Returns:
            ``x`` ``(B, 3, H, W)``: ``(h - m) / s`` and the forward differences along x and
            y over ``s``; ``s`` ``(B, 1, H, W)`` metres (>= `SCALE_FLOOR_M`).
        """
        h = coarse.unsqueeze(1)
        dx = F.pad(h[..., :, 1:] - h[..., :, :-1], (0, 1, 0, 0), mode="replicate")
        dy = F.pad(h[..., 1:, :] - h[..., :-1, :], (0, 0, 0, 1), mode="replicate")
        s = torch.sqrt(_box(dx * dx + dy * dy, self.window)).clamp_min(SCALE_FLOOR_M)
        m = _box(h, self.window)
        return torch.cat([(h - m) / s, dx / s, dy / s], dim=1), s

    def residual(self, coarse: torch.Tensor) -> torch.Tensor:
        """``s_f R(x)``: the learned correction to bicubic, ``(B, f(H-1)+1, f(W-1)+1)`` m."""
        f = self.factor
        hc, wc = coarse.shape[-2:]
        x, s = self.normalise(coarse)
        phases = self.body(x) * self.phase_mask * s  # (B, f², H, W), metres
        fine = F.pixel_shuffle(phases, f)  # (B, 1, f H, f W): node [f i + a, f j + b]
        return fine[:, 0, : f * (hc - 1) + 1, : f * (wc - 1) + 1]

    def forward(self, coarse: torch.Tensor) -> torch.Tensor:
        """Fine heights (eq. 1): bicubic of ``coarse`` plus the learned residual."""
        if coarse.ndim != 3 or min(coarse.shape[-2:]) < 2:
            raise NeuralMapError(
                f"ResidualSuperRes expects (B, H, W) coarse heights with H, W >= 2, got shape "
                f"{tuple(coarse.shape)}.")
        return bicubic_upsample(coarse, self.factor) + self.residual(coarse)


def upsample_tile(tile: DemTile, prior: ResidualSuperRes | None, factor: int = 2) -> DemTile:
    """A fine tile from a coarse one: bicubic (``prior=None``) or the learned prior.

    Args:
        tile: Coarse tile without voids.
        prior: Trained prior (its factor is used), or ``None`` for plain bicubic.
        factor: Factor when ``prior`` is ``None``.

    Returns:
        Tile of ``f (H-1) + 1`` x ``f (W-1) + 1`` nodes at ``spacing / f``, same origin
        (wrap it in `GridTerrain` to navigate on it).

    Raises:
        NeuralMapError: Voids in the tile.
    """
    if not tile.valid_mask.all():
        raise NeuralMapError(
            f"tile '{tile.name}' has {int((~tile.valid_mask).sum())} void node(s); upsampling "
            "needs a complete coarse grid (fill or crop the voids first).")
    coarse = torch.as_tensor(np.asarray(tile.heights, dtype=np.float64))
    if prior is None:
        fine = bicubic_upsample(coarse, int(factor))
    else:
        factor = prior.factor
        with torch.no_grad():
            param = next(prior.parameters())
            fine = prior(coarse[None].to(param.dtype))[0].to(torch.float64)
    spacing = (tile.spacing[0] / factor, tile.spacing[1] / factor)
    return dataclasses.replace(tile, heights=fine.numpy(), spacing=spacing,
                               name=f"{tile.name}_x{factor}",
                               meta={**tile.meta, "upsampled": "bicubic" if prior is None
                                     else "residual super-resolution prior",
                                     "factor": factor})
