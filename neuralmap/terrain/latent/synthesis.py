"""Synthesis of a latent-grid map: linear synthesis plus a tiny MLP residual.

Per point, the ``L`` upsampled latent features ``f = (f_0 .. f_{L-1})`` (metres) give the
height

``h = b_0 + w . f + sum_k v_k tanh( (A (f / sigma))_k + a_k ) + c``

(Cool-chic's synthesis reduced to one linear layer and a one-hidden-layer residual;
``sigma`` are fixed per-level feature scales). ``tanh`` is smooth, so the map stays C¹.
Both inner maps are linear in ``f`` and ``f`` is linear in the latents, so
`Synthesis.folded` turns the synthesis into ``1 + H`` coefficient channels; the query
then needs only ``H`` ``tanh`` per point (no matrix product).
"""

from __future__ import annotations

import torch
from torch import nn


class Synthesis(nn.Module):
    """Linear synthesis + ``hidden``-unit tanh MLP residual over ``levels`` features.

    Args:
        levels: Number of latent levels ``L`` (input features).
        hidden: Hidden units ``H`` of the residual MLP (0 = linear synthesis only).
        feature_scale: ``(L,)`` fixed feature scales ``sigma`` (metres).
        bias: Initial ``b_0`` (metres; the tile's mean height).
        seed: Seed of the MLP's initial weights.
    """

    feature_scale: torch.Tensor

    def __init__(self, levels: int, hidden: int, feature_scale: torch.Tensor, *, bias: float = 0.0,
                 seed: int = 0) -> None:
        super().__init__()
        self.levels = int(levels)
        self.hidden = int(hidden)
        gen = torch.Generator().manual_seed(int(seed))
        self.register_buffer("feature_scale", torch.as_tensor(feature_scale, dtype=torch.float32))
        self.linear = nn.Parameter(torch.ones(levels))
        self.bias = nn.Parameter(torch.tensor(float(bias)))
        self.inner = nn.Parameter(torch.randn(hidden, levels, generator=gen) / levels**0.5)
        self.inner_bias = nn.Parameter(torch.zeros(hidden))
        self.outer = nn.Parameter(torch.zeros(hidden))

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        """Heights ``(...)`` from features ``(..., L)`` (metres)."""
        h = self.bias + features @ self.linear
        if self.hidden:
            a = (features / self.feature_scale) @ self.inner.T + self.inner_bias
            h = h + torch.tanh(a) @ self.outer
        return h

    def parameter_vector(self) -> torch.Tensor:
        """All learned parameters flattened in storage order: linear, bias, inner,
        inner_bias, outer (``L + 1 + H L + 2 H`` values)."""
        return torch.cat([self.linear.reshape(-1), self.bias.reshape(1), self.inner.reshape(-1),
                          self.inner_bias.reshape(-1), self.outer.reshape(-1)])

    def load_parameter_vector(self, vector: torch.Tensor) -> None:
        """Inverse of `parameter_vector`."""
        sizes = [self.levels, 1, self.hidden * self.levels, self.hidden, self.hidden]
        parts = torch.split(torch.as_tensor(vector, dtype=torch.float32), sizes)
        with torch.no_grad():
            self.linear.copy_(parts[0])
            self.bias.copy_(parts[1][0])
            self.inner.copy_(parts[2].view(self.hidden, self.levels))
            self.inner_bias.copy_(parts[3])
            self.outer.copy_(parts[4])

    def folded(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """The synthesis as channel mixing: ``(mix (L, 1 + H), bias, inner_bias, outer)``.

        Channel 0 of ``features @ mix`` is ``w . f``, channels ``1..H`` are ``A (f / sigma)``;
        then ``h = bias + ch_0 + outer . tanh(ch_{1..} + inner_bias)`` (float64).
        """
        d = torch.float64
        mix = torch.cat([self.linear.detach().to(d)[:, None],
                         (self.inner.detach().to(d) / self.feature_scale.to(d)).T], dim=1)
        return (mix, self.bias.detach().to(d), self.inner_bias.detach().to(d),
                self.outer.detach().to(d))
