"""Height and slope of a blockwise neural map in one forward-mode pass (no autograd).

Reverse-mode autograd evaluates the network, records a graph and runs it backwards; for
the two inputs ``(x, y)`` of a terrain map, forward mode is cheaper: the two tangents
``dh/dx`` and ``dh/dy`` ride along the forward pass as two extra rows of every tile, so a
layer is still one ``bmm`` (three times taller) and nothing is recorded. For a layer
``a = W h + b``, ``z = f(a)``: ``da/dx = W dh/dx`` and ``dz/dx = f'(a) da/dx``. This is the
chain rule of SEEDS 004 eq. (8) carried through any depth and through the Fourier
features, ``d sin(2 pi F^T u)/du = 2 pi F cos(2 pi F^T u)``. The blending weights (products
of quintic smoothsteps) are differentiated in closed form, so
``dh/dx = sum_b (w_b dN_b/dx + N_b dw_b/dx)`` exactly as autograd of the forward pass.

Measured on one CPU thread (``benchmarks/bench_map_size.py``, jacksboro compact maps) it is
*not* faster than reverse-mode autograd (0.6-0.8x): the three-times-taller ``bmm`` costs
about what the backward pass does. Its use is a graph-free, exact slope (e.g. under
``no_grad``); for grid-speed queries bake the map (`neuralmap.terrain.bake`).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from typing import Protocol

import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.terrain.block_layout import BlockLayout
from neuralmap.terrain.grouped import TileGroups


class BlockwiseParameters(Protocol):
    """What the forward-mode pass reads of a blockwise map
    (`neuralmap.terrain.blockwise.BlockwiseTerrainNet` provides it; declared here so
    this module needs no import of the network's module)."""

    layout: BlockLayout
    encoding: str
    frequencies: torch.Tensor
    weights: Sequence[torch.Tensor]
    biases: Sequence[torch.Tensor]
    out_weight: torch.Tensor
    out_bias: torch.Tensor
    block_center: torch.Tensor
    block_half_width: torch.Tensor
    height_mean: torch.Tensor
    height_std: torch.Tensor
    _act: Callable[[torch.Tensor], torch.Tensor]
    _act_derivative: Callable[[torch.Tensor], torch.Tensor]

    def _finite_points(self, flat: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor | None]:
        ...



def _axis_weights(
    layout: BlockLayout, u: torch.Tensor, axis: int
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Blocks along one axis, their weights and the weights' derivative.

    Same blocks and weights as `BlockLayout.axis_candidates`; adds
    ``d w_neighbour / du`` (and ``d w_own / du = -d w_neighbour / du``).

    Returns:
        ``(i0, w0, i1, w1, dw1)``, each ``(P,)``.
    """
    i0, w0, i1, w1 = layout.axis_candidates(u, axis)
    half = layout.blend_width[axis]
    if half <= 0:
        return i0, w0, i1, w1, torch.zeros_like(w1)
    lo = layout.extent[2 * axis]
    core = layout.core_size[axis]
    s = (u - lo) / core
    own = s.floor().clamp(0, layout.num_blocks[axis] - 1)
    upper = (s - own) >= 0.5
    border = torch.where(upper, (own + 1.0) * core, own * core) + lo
    t = (u - (border - half)) / (2.0 * half)
    inside = (t > 0.0) & (t < 1.0)
    tc = t.clamp(0.0, 1.0)
    ds = 30.0 * tc * tc * (1.0 - tc) * (1.0 - tc) / (2.0 * half)  # d smoothstep / du
    dw1 = torch.where(upper, ds, -ds) * (inside & (w1 > 0)).to(u.dtype)
    return i0, w0, i1, w1, dw1


def _assign_with_derivatives(
    layout: BlockLayout, xy: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """Point-block pairs with their blending weight and its gradient.

    Returns:
        ``(point (Q,), block (Q,), weight (Q,), weight_grad (Q, 2))``.
    """
    ix0, wx0, ix1, wx1, dwx1 = _axis_weights(layout, xy[:, 0], 0)
    iy0, wy0, iy1, wy1, dwy1 = _axis_weights(layout, xy[:, 1], 1)
    nbx = layout.num_blocks[0]
    block = torch.stack([iy0 * nbx + ix0, iy0 * nbx + ix1, iy1 * nbx + ix0, iy1 * nbx + ix1], 1)
    wx = torch.stack([wx0, wx1, wx0, wx1], 1)
    wy = torch.stack([wy0, wy0, wy1, wy1], 1)
    dwx = torch.stack([-dwx1, dwx1, -dwx1, dwx1], 1)
    dwy = torch.stack([-dwy1, -dwy1, dwy1, dwy1], 1)
    weight = wx * wy
    keep = weight > 0
    point = torch.arange(xy.shape[0], device=xy.device).unsqueeze(1).expand(-1, 4)
    grad = torch.stack([dwx * wy, wx * dwy], -1)
    return point[keep], block[keep], weight[keep], grad[keep]


def blockwise_height_and_slope(
    net: BlockwiseParameters, xy: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor]:
    """Heights and slopes of a blockwise map
    (`BlockwiseTerrainNet`) by forward-mode
    differentiation.

    Equal (to float rounding) to ``net(xy)`` and to the autograd gradient of its sum; no
    graph is recorded, so it is the fast path for filters and benchmarks.

    Args:
        net: The blockwise neural map (any depth, ``"fourier"`` or ``"none"`` encoding,
            blended or hard-gated).
        xy: ``(..., 2)`` east/north metres.

    Returns:
        ``(height (...), slope (..., 2))`` in ``xy``'s dtype (computed in the parameters'
        dtype), metres and metres per metre.

    Raises:
        NeuralMapError: ``xy`` not shaped ``(..., 2)``.
    """
    if not isinstance(xy, torch.Tensor) or xy.ndim < 1 or xy.shape[-1] != 2:
        shape = tuple(xy.shape) if isinstance(xy, torch.Tensor) else type(xy).__name__
        raise NeuralMapError(f"height_and_slope: xy must have shape (..., 2), got {shape}.")
    lead = xy.shape[:-1]
    dtype = net.out_bias.dtype
    with torch.no_grad():
        flat, finite = net._finite_points(xy.reshape(-1, 2).to(dtype))
        point, block, weight, weight_grad = _assign_with_derivatives(net.layout, flat)
        groups = TileGroups(block, net.layout.count)
        half = net.block_half_width.index_select(0, block)  # (Q, 2)
        local = (flat.index_select(0, point) - net.block_center.index_select(0, block)) / half
        tiles = groups.pack(local)  # (K, T, 2)
        k, t = tiles.shape[0], tiles.shape[1]
        nf = net.frequencies.shape[1] if net.encoding == "fourier" else 0
        # rows [0, T): values; [T, 2T): d/du_x; [2T, 3T): d/du_y (written in place, no cat)
        hidden = tiles.new_zeros(k, 3 * t, 2 + 2 * nf)
        hidden[:, :t, :2] = tiles
        hidden[:, t : 2 * t, 0] = 1.0
        hidden[:, 2 * t :, 1] = 1.0
        if nf:
            freq = net.frequencies * (2.0 * math.pi)  # (2, F)
            angle = tiles @ freq
            sin = torch.sin(angle, out=hidden[:, :t, 2 : 2 + nf])
            cos = torch.cos(angle, out=hidden[:, :t, 2 + nf :])
            for i in range(2):
                rows = slice((i + 1) * t, (i + 2) * t)
                torch.mul(cos, freq[i], out=hidden[:, rows, 2 : 2 + nf])
                torch.mul(sin, -freq[i], out=hidden[:, rows, 2 + nf :])
        for w, b in zip(net.weights, net.biases, strict=True):
            a = torch.bmm(hidden, w.index_select(0, groups.tile_block))
            value = a[:, :t].add_(b.index_select(0, groups.tile_block).unsqueeze(1))
            out = torch.empty_like(a)
            out[:, :t] = net._act(value)
            deriv = net._act_derivative(value).unsqueeze(1)
            width = a.shape[-1]  # named, not -1: zero tiles (no points) must still reshape
            torch.mul(a[:, t:].view(k, 2, t, width), deriv,
                      out=out[:, t:].view(k, 2, t, width))
            hidden = out
        w_out = net.out_weight.index_select(0, groups.tile_block).unsqueeze(-1)
        res = torch.bmm(hidden, w_out)  # (K, 3T, 1)
        normalised = groups.unpack(res[:, :t]).squeeze(-1) + net.out_bias.index_select(0, block)
        grad_local = torch.cat(
            [groups.unpack(res[:, t : 2 * t]), groups.unpack(res[:, 2 * t :])], -1
        )  # (Q, 2)
        sigma = net.height_std.index_select(0, block)
        metres = net.height_mean.index_select(0, block) + sigma * normalised
        grad_block = grad_local * (sigma.unsqueeze(-1) / half)
        n = flat.shape[0]
        height = torch.zeros(n, dtype=dtype, device=flat.device).index_add_(
            0, point, weight * metres
        )
        pair_slope = grad_block.mul_(weight.unsqueeze(-1)).add_(
            weight_grad * metres.unsqueeze(-1)
        )
        slope = torch.zeros(n, 2, dtype=dtype, device=flat.device).index_add_(
            0, point, pair_slope
        )
        if finite is not None:  # non-finite points: NaN height and slope, as forward()
            height = torch.where(finite, height, torch.full_like(height, float("nan")))
            slope = torch.where(finite.unsqueeze(-1), slope, torch.full_like(slope, float("nan")))
    return height.reshape(lead).to(xy.dtype), slope.reshape(*lead, 2).to(xy.dtype)
