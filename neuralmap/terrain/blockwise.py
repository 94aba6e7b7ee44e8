"""BlockwiseTerrainNet: a DEM learnt as one small MLP per block, blended seamlessly.

SEEDS 004 splits the map into blocks with one 2-m-1 BP net each and a position gate that
picks the net. Here all block networks run in one batched operation (grouped ``bmm``, see
`neuralmap.terrain.grouped`); blocks overlap and are blended with a C2 partition of
unity (`neuralmap.terrain.block_layout`) so that height and slope are continuous
across block borders. Each block sees its own coordinates normalised to [-1, 1] over its
extended domain, optionally lifted by Fourier features, and predicts a normalised height
that is de-normalised with the block's own mean and standard deviation: callers always
see metres.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import nn

from neuralmap.dem.tile import DemTile
from neuralmap.exceptions import NeuralMapError
from neuralmap.terrain.activations import get_activation
from neuralmap.terrain.base import TerrainModel
from neuralmap.terrain.block_layout import BlockLayout, layout_for_tile
from neuralmap.terrain.forward_slope import blockwise_height_and_slope
from neuralmap.terrain.grouped import TileGroups

ENCODINGS = ("fourier", "none")


@dataclass(frozen=True)
class BlockwiseDefaults:
    """Default architecture of `BlockwiseTerrainNet`, the one place it is set.

    The net's constructor, `BlockwiseTerrainNet.from_tile` and the training module
    take their defaults from `NET_DEFAULTS`; a config states a value only to
    override it. These are the values ``python train.py`` fits with (``frequency_scale``
    1.0 was chosen on the jacksboro fit).

    Attributes:
        block_nodes: Core block width in node intervals.
        overlap_nodes: Blending zone width across a border, in node intervals.
        encoding: ``"fourier"`` or ``"none"``.
        n_frequencies: Fourier frequencies per block.
        frequency_scale: Std of the Gaussian frequencies, cycles per block half-width.
        hidden: Hidden width.
        depth: Hidden layers.
        activation: Activation name.
        blend: Smooth blending between blocks.
        seed: Seed of the initial weights and frequencies.
    """

    block_nodes: int = 24
    overlap_nodes: float = 4.0
    encoding: str = "fourier"
    n_frequencies: int = 16
    frequency_scale: float = 1.0
    hidden: int = 32
    depth: int = 2
    activation: str = "sine"
    blend: bool = True
    seed: int = 0


#: The default architecture (single source for the net, its trainer and the configs).
NET_DEFAULTS = BlockwiseDefaults()


class BlockwiseTerrainNet(TerrainModel):
    """Per-block MLPs ``h(x, y)`` over a map, with smooth blending between blocks.

    Build it for a tile with `from_tile`; the constructor takes the explicit
    geometry so that an exported map is rebuilt from its config alone.

    Args:
        extent: ``(xmin, xmax, ymin, ymax)`` metres covered.
        num_blocks: ``(nbx, nby)`` block grid.
        blend_width: ``(wx, wy)`` half-width of the blending zone in metres (0 = hard gate).
        encoding: ``"fourier"`` (random Fourier features of the block coordinates, plus the
            coordinates themselves) or ``"none"`` (the coordinates alone, SEEDS 004).
        n_frequencies: Number of Fourier frequencies ``F`` (feature width ``2F + 2``).
        frequency_scale: Standard deviation of the Gaussian frequencies, in cycles per
            block half-width.
        hidden: Hidden width ``m``.
        depth: Number of hidden layers (1 = the 2-m-1 net of SEEDS 004).
        activation: ``sine``, ``tanh``, ``silu`` or ``bipolar_sigmoid`` (SEEDS 004).
        blend: Blend blocks (True) or use the hard gate (False, as the paper).
        seed: Seed for the initial weights and frequencies.
        tile_info: The tile's `DemTile.describe` dict, recorded in exports.
    """

    def __init__(
        self,
        *,
        extent: tuple[float, float, float, float],
        num_blocks: tuple[int, int],
        blend_width: tuple[float, float],
        encoding: str = NET_DEFAULTS.encoding,
        n_frequencies: int = NET_DEFAULTS.n_frequencies,
        frequency_scale: float = NET_DEFAULTS.frequency_scale,
        hidden: int = NET_DEFAULTS.hidden,
        depth: int = NET_DEFAULTS.depth,
        activation: str = NET_DEFAULTS.activation,
        blend: bool = NET_DEFAULTS.blend,
        seed: int = NET_DEFAULTS.seed,
        tile_info: dict[str, Any] | None = None,
    ) -> None:
        super().__init__()
        if encoding not in ENCODINGS:
            raise NeuralMapError(
                f"unknown encoding '{encoding}' (model.encoding); choose one of {ENCODINGS}."
            )
        if hidden < 1 or depth < 1:
            raise NeuralMapError(
                f"model.hidden and model.depth must be >= 1, got hidden={hidden}, depth={depth}."
            )
        self.activation_name = activation
        self._act, self._act_derivative = get_activation(activation)
        self.layout = BlockLayout(
            extent=tuple(float(e) for e in extent),  # type: ignore[arg-type]
            num_blocks=(int(num_blocks[0]), int(num_blocks[1])),
            blend_width=(
                (float(blend_width[0]), float(blend_width[1])) if blend else (0.0, 0.0)
            ),
        )
        self.extent = self.layout.extent
        self.tile_info = dict(tile_info or {})
        self.tile_name = str(self.tile_info.get("name", ""))
        self.tile_fingerprint = str(self.tile_info.get("fingerprint", ""))
        self.encoding = encoding
        self.config: dict[str, Any] = {
            "extent": list(self.layout.extent),
            "num_blocks": list(self.layout.num_blocks),
            "blend_width": [float(blend_width[0]), float(blend_width[1])],
            "encoding": encoding,
            "n_frequencies": int(n_frequencies),
            "frequency_scale": float(frequency_scale),
            "hidden": int(hidden),
            "depth": int(depth),
            "activation": activation,
            "blend": bool(blend),
            "seed": int(seed),
            "tile_info": self.tile_info,
        }

        blocks = self.layout.count
        generator = torch.Generator().manual_seed(seed)
        if encoding == "fourier":
            # The generator's device, not a default device a caller set (Lightning's init_module).
            frequencies = torch.randn(2, n_frequencies, generator=generator,
                                      device=generator.device) * frequency_scale
            d_in = 2 * n_frequencies + 2
        else:
            frequencies = torch.zeros(2, 0, device=generator.device)
            d_in = 2
        self.register_buffer("frequencies", frequencies)
        bounds = torch.as_tensor(self.layout.block_bounds(), dtype=torch.float32)
        self.register_buffer("block_center", 0.5 * (bounds[:, 0::2] + bounds[:, 1::2]))
        self.register_buffer("block_half_width", 0.5 * (bounds[:, 1::2] - bounds[:, 0::2]))
        self.register_buffer("height_mean", torch.zeros(blocks))
        self.register_buffer("height_std", torch.ones(blocks))
        self.register_buffer("global_height_std", torch.ones(()))

        widths = [d_in] + [hidden] * depth
        self.weights = nn.ParameterList()
        self.biases = nn.ParameterList()
        for fan_in, fan_out in zip(widths[:-1], widths[1:], strict=True):
            self.weights.append(nn.Parameter(self._uniform(blocks, fan_in, fan_out, generator)))
            self.biases.append(nn.Parameter(self._uniform(blocks, fan_in, fan_out, generator)[:, 0]))
        self.out_weight = nn.Parameter(self._uniform(blocks, hidden, 1, generator)[..., 0])
        self.out_bias = nn.Parameter(torch.zeros(blocks))

    @staticmethod
    def _uniform(blocks: int, fan_in: int, fan_out: int, generator: torch.Generator) -> torch.Tensor:
        # nn.Linear's default: U(-1/sqrt(fan_in), 1/sqrt(fan_in)).
        bound = 1.0 / math.sqrt(fan_in)
        return (torch.rand(blocks, fan_in, fan_out, generator=generator, device=generator.device)
                * 2.0 - 1.0) * bound

    # ------------------------------------------------------------------ construction
    @classmethod
    def from_tile(
        cls,
        tile: DemTile,
        *,
        block_nodes: int | None = NET_DEFAULTS.block_nodes,
        overlap_nodes: float = NET_DEFAULTS.overlap_nodes,
        num_blocks: tuple[int, int] | list[int] | None = None,
        encoding: str = NET_DEFAULTS.encoding,
        n_frequencies: int = NET_DEFAULTS.n_frequencies,
        frequency_scale: float = NET_DEFAULTS.frequency_scale,
        hidden: int = NET_DEFAULTS.hidden,
        depth: int = NET_DEFAULTS.depth,
        activation: str = NET_DEFAULTS.activation,
        blend: bool = NET_DEFAULTS.blend,
        seed: int = NET_DEFAULTS.seed,
    ) -> BlockwiseTerrainNet:
        """Builds the network for a tile, blocks sized in grid nodes.

        Args:
            tile: The DEM tile to fit.
            block_nodes: Core block width in node intervals (one config serves any tile).
            overlap_nodes: Blending zone width across a border, in node intervals.
            num_blocks: ``(nbx, nby)``, overrides ``block_nodes``.
            encoding: See the class docstring.
            n_frequencies: See the class docstring.
            frequency_scale: See the class docstring.
            hidden: See the class docstring.
            depth: See the class docstring.
            activation: See the class docstring.
            blend: See the class docstring.
            seed: See the class docstring.

        Returns:
            The network with per-block height statistics set from the tile.

        Raises:
            NeuralMapError: When the tile cannot feed the requested blocks.
        """
        layout = layout_for_tile(
            tile.shape,
            tile.spacing,
            tile.extent,
            block_nodes=block_nodes,
            overlap_nodes=overlap_nodes if blend else 0.0,
            num_blocks=tuple(num_blocks) if num_blocks is not None else None,  # type: ignore[arg-type]
        )
        net = cls(
            extent=layout.extent,
            num_blocks=layout.num_blocks,
            blend_width=layout.blend_width,
            encoding=encoding,
            n_frequencies=n_frequencies,
            frequency_scale=frequency_scale,
            hidden=hidden,
            depth=depth,
            activation=activation,
            blend=blend,
            seed=seed,
            tile_info=tile.describe(),
        )
        mean, std = block_height_statistics(tile, layout)
        net.height_mean.copy_(torch.as_tensor(mean, dtype=torch.float32))
        net.height_std.copy_(torch.as_tensor(std, dtype=torch.float32))
        net.global_height_std.fill_(float(np.nanstd(tile.heights)) or 1.0)
        return net

    @property
    def height_scale(self) -> float:
        """Global standard deviation of the tile's heights (m), to scale a loss."""
        return float(self.global_height_std)

    @property
    def num_parameters(self) -> int:
        """Number of trainable parameters."""
        return sum(p.numel() for p in self.parameters())

    # ------------------------------------------------------------------ evaluation
    def _features(self, local: torch.Tensor) -> torch.Tensor:
        if self.encoding == "none":
            return local
        angle = 2.0 * math.pi * (local @ self.frequencies)
        return torch.cat([local, torch.sin(angle), torch.cos(angle)], dim=-1)

    def _pairs(
        self, flat: torch.Tensor
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, TileGroups, torch.Tensor]:
        """Pairs (point, block, weight), their tiling and block-local coordinates."""
        with torch.no_grad():
            point, block, weight_nograd = self.layout.assign(flat.detach())
        del weight_nograd
        groups = TileGroups(block, self.layout.count)
        local = (flat.index_select(0, point) - self.block_center.index_select(0, block)) / (
            self.block_half_width.index_select(0, block)
        )
        return point, block, local, groups, self._blend_weights(flat, point, block)

    def _blend_weights(
        self, flat: torch.Tensor, point: torch.Tensor, block: torch.Tensor
    ) -> torch.Tensor:
        """Differentiable blending weight of each pair (recomputed with gradients)."""
        if self.layout.blend_width == (0.0, 0.0):
            return torch.ones_like(point, dtype=flat.dtype)
        xy = flat.index_select(0, point)
        nbx = self.layout.num_blocks[0]
        weight = torch.ones_like(xy[:, 0])
        for axis, index in ((0, block % nbx), (1, torch.div(block, nbx, rounding_mode="floor"))):
            i0, w0, i1, w1 = self.layout.axis_candidates(xy[:, axis], axis)
            weight = weight * torch.where(index == i0, w0, w1)
        return weight

    def _block_outputs(self, local: torch.Tensor, groups: TileGroups) -> tuple[torch.Tensor, list[torch.Tensor]]:
        """Normalised block outputs ``(Q,)`` and the pre-activations of each layer."""
        hidden = groups.pack(self._features(local))
        pre_activations = []
        for weight, bias in zip(self.weights, self.biases, strict=True):
            a = groups.linear(hidden, weight, bias)
            pre_activations.append(a)
            hidden = self._act(a)
        out = torch.bmm(hidden, self.out_weight.index_select(0, groups.tile_block).unsqueeze(-1))
        return groups.unpack(out).squeeze(-1), pre_activations

    def forward(self, xy: torch.Tensor) -> torch.Tensor:
        """Heights at metric points.

        Args:
            xy: ``(..., 2)`` east/north metres (any float dtype; computed in the
                parameters' dtype and returned in ``xy``'s dtype).

        Returns:
            ``(...)`` heights in metres. Non-finite points (a diverged filter track) give NaN
            heights with zero gradient, as for `neuralmap.terrain.GridTerrain`.
        """
        if xy.shape[-1] != 2:
            raise NeuralMapError(f"xy must have shape (..., 2), got {tuple(xy.shape)}.")
        lead = xy.shape[:-1]
        dtype = self.out_bias.dtype
        flat, finite = self._finite_points(xy.reshape(-1, 2).to(dtype))
        point, block, local, groups, weight = self._pairs(flat)
        normalised, _ = self._block_outputs(local, groups)
        normalised = normalised + self.out_bias.index_select(0, block)
        metres = self.height_mean.index_select(0, block) + self.height_std.index_select(
            0, block
        ) * normalised
        height = torch.zeros(flat.shape[0], dtype=dtype, device=flat.device).index_add(
            0, point, weight * metres
        )
        if finite is not None:
            height = torch.where(finite, height, torch.full_like(height, float("nan")))
        return height.reshape(lead).to(xy.dtype)

    def block_heights(
        self, xy: torch.Tensor, block: torch.Tensor, *, tile_size: int | None = None
    ) -> torch.Tensor:
        """Unblended heights of given blocks at given points (one block per point).

        Used by shard-wise training (every block fits its own extended domain) and by the
        lazily loaded sharded maps, which blend the blocks of several files.

        Args:
            xy: ``(Q, 2)`` metric points (finite), in the parameters' dtype.
            block: ``(Q,)`` int64 block id of this net for each point.
            tile_size: Rows per packed tile (None = automatic; fix it for bitwise
                reproducible training across block groupings).

        Returns:
            ``(Q,)`` heights in metres of block ``block[q]``'s network at ``xy[q]``.
        """
        groups = TileGroups(block, self.layout.count, tile_size=tile_size)
        local = (xy - self.block_center.index_select(0, block)) / (
            self.block_half_width.index_select(0, block)
        )
        normalised, _ = self._block_outputs(local, groups)
        normalised = normalised + self.out_bias.index_select(0, block)
        return self.height_mean.index_select(0, block) + self.height_std.index_select(
            0, block
        ) * normalised

    def height_and_slope(self, xy: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """Heights and slopes in one forward-mode pass, without autograd.

        Equal to `forward` and the autograd gradient of its sum (see
        `neuralmap.terrain.forward_slope.blockwise_height_and_slope`).

        Args:
            xy: ``(..., 2)`` east/north metres.

        Returns:
            ``(height (...), slope (..., 2))`` in ``xy``'s dtype.
        """
        return blockwise_height_and_slope(self, xy)

    def _finite_points(self, flat: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
        """Replaces non-finite points by a block centre; returns the finite mask (or None).

        The block assignment indexes blocks by ``floor`` of the coordinates, which a NaN
        would turn into an invalid index; the caller puts NaN back in the output.
        """
        finite = torch.isfinite(flat).all(-1)
        if bool(finite.all()):
            return flat, None
        centre = self.block_center[0].to(flat.dtype).expand_as(flat)
        return torch.where(finite.unsqueeze(-1), flat, centre), finite

    def analytic_slope(self, xy: torch.Tensor) -> torch.Tensor:
        """Terrain slope from the closed-form input gradient, SEEDS 004 eq. (8).

        For one block, ``N(u) = mu + sigma (sum_j w2_j f(a_j) + b2)`` with
        ``a = W1 u + b1`` and ``u = (x - c) / r``, so
        ``dN/dx = (sigma / r_x) sum_j w2_j f'(a_j) W1_xj`` (the sum over the m hidden
        paths of eq. 8). With blending, ``d/dx sum_b w_b N_b = sum_b (w_b dN_b/dx + N_b
        dw_b/dx)``; the weight derivative is taken by autograd on the scalar weight only.

        Only for ``encoding="none"`` and ``depth=1`` (the 2-m-1 BP net).

        Args:
            xy: ``(..., 2)`` metres.

        Returns:
            ``(..., 2)`` slope ``(dh/dx, dh/dy)``.
        """
        if self.encoding != "none" or len(self.weights) != 1:
            raise NeuralMapError(
                "analytic_slope (SEEDS 004 eq. 8) exists for the 2-m-1 BP preset only "
                "(encoding='none', depth=1); use neuralmap.linearize.AutogradLinearizer."
            )
        lead = xy.shape[:-1]
        dtype = self.out_bias.dtype
        flat, finite = self._finite_points(xy.reshape(-1, 2).to(dtype).detach())
        with torch.no_grad():
            point, block, _ = self.layout.assign(flat)
            groups = TileGroups(block, self.layout.count)
            half = self.block_half_width.index_select(0, block)
            local = (flat.index_select(0, point) - self.block_center.index_select(0, block)) / half
            tiles = groups.pack(local)
            a = groups.linear(tiles, self.weights[0], self.biases[0])  # (tiles, T, m)
            w_in = self.weights[0].index_select(0, groups.tile_block)  # (tiles, 2, m)
            w_out = self.out_weight.index_select(0, groups.tile_block)  # (tiles, m)
            # eq. (8): sum over hidden paths of w2_j f'(a_j) W1_ij, per input i.
            path = self._act_derivative(a) * w_out.unsqueeze(1)  # (tiles, T, m)
            grad_local = groups.unpack(torch.einsum("ktm,kim->kti", path, w_in))  # (Q, 2)
            normalised = groups.unpack(
                torch.einsum("ktm,km->kt", self._act(a), w_out).unsqueeze(-1)
            ).squeeze(-1) + self.out_bias.index_select(0, block)
            sigma = self.height_std.index_select(0, block)
            metres = self.height_mean.index_select(0, block) + sigma * normalised
            grad_block = sigma.unsqueeze(-1) * grad_local / half  # (Q, 2)
        weight_grad = None
        with torch.enable_grad():
            xy_w = flat.clone().requires_grad_(True)
            weight = self._blend_weights(xy_w, point, block)
            if weight.requires_grad:  # blending on: add sum_b N_b dw_b/dx
                (weight_grad,) = torch.autograd.grad((weight * metres).sum(), xy_w)
        weight = weight.detach()
        slope = torch.zeros(flat.shape[0], 2, dtype=dtype, device=flat.device).index_add(
            0, point, weight.unsqueeze(-1) * grad_block
        )
        if weight_grad is not None:
            slope = slope + weight_grad
        if finite is not None:
            slope = torch.where(finite.unsqueeze(-1), slope, torch.full_like(slope, float("nan")))
        return slope.reshape(*lead, 2).to(xy.dtype)


def block_height_statistics(tile: DemTile, layout: BlockLayout) -> tuple[np.ndarray, np.ndarray]:
    """Mean and standard deviation of the valid heights inside each block's extended domain.

    Uses summed-area tables, so the cost is one pass over the tile whatever the block count.
    Blocks with fewer than 4 valid nodes take the tile's global statistics.

    Returns:
        ``(mean, std)``, each ``(B,)`` in metres (std floored at 1 m).
    """
    heights = tile.heights
    valid = np.isfinite(heights)
    filled = np.where(valid, heights, 0.0)

    def table(a: np.ndarray) -> np.ndarray:
        out = np.zeros((a.shape[0] + 1, a.shape[1] + 1))
        out[1:, 1:] = a.cumsum(0).cumsum(1)
        return out

    count_t, sum_t, sq_t = table(valid.astype(float)), table(filled), table(filled**2)
    bounds = layout.block_bounds()
    x0, y0 = tile.origin
    dx, dy = tile.spacing
    ny, nx = tile.shape
    j0 = np.clip(np.ceil((bounds[:, 0] - x0) / dx - 1e-9), 0, nx).astype(int)
    j1 = np.clip(np.floor((bounds[:, 1] - x0) / dx + 1e-9) + 1, 0, nx).astype(int)
    i0 = np.clip(np.ceil((bounds[:, 2] - y0) / dy - 1e-9), 0, ny).astype(int)
    i1 = np.clip(np.floor((bounds[:, 3] - y0) / dy + 1e-9) + 1, 0, ny).astype(int)

    def box(t: np.ndarray) -> np.ndarray:
        return t[i1, j1] - t[i0, j1] - t[i1, j0] + t[i0, j0]

    n = box(count_t)
    global_mean, global_std = float(np.nanmean(heights)), float(np.nanstd(heights))
    with np.errstate(invalid="ignore", divide="ignore"):
        mean = box(sum_t) / n
        var = np.maximum(box(sq_t) / n - mean**2, 0.0)
    sparse = n < 4
    mean = np.where(sparse, global_mean, mean)
    std = np.where(sparse, global_std, np.sqrt(var))
    return mean, np.maximum(std, 1.0)
