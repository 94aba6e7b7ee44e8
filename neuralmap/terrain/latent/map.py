"""LatentTerrainMap: a decoded latent-grid neural map as a `TerrainModel`.

Built from what the bitstream stores (integer symbols, quantisation steps, synthesis
weights), it turns the latents into node-lattice B-spline coefficients once
(`lattice`: the pyramid's levels refined
exactly, or the inverse wavelet transform) and folds the linear parts
of the synthesis into ``K = 1 + H`` coefficient channels
(`folded`). A query is then one 4 x 4
gather of ``K``-vectors, the cubic B-spline weights, and ``H`` ``tanh``:

``h = b + g_0 + sum_k v_k tanh(g_k + a_k)``,  ``dh/dx = dg_0/dx + sum_k v_k (1 - tanh^2) dg_k/dx``

with ``g = sum_ab w_a(v) w_b(u) C[i + a, j + b, :]`` (forward-mode chain rule through the
kernel and the MLP, no autograd). The map is C² inside the extent (cubic B-spline,
smooth ``tanh``), so height and slope are continuous across cells. Nothing is sampled on
a grid: the coefficient grid *is* the stored map, re-expressed in one spline basis.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.terrain.latent.basis import LatentBasis, make_basis
from neuralmap.terrain.latent.bspline import bspline_matrix, cell_position
from neuralmap.terrain.latent.evaluated import EvaluatedTerrain
from neuralmap.terrain.latent.synthesis import Synthesis
from neuralmap.terrain.latent.zones import ZoneCodes


def _horner(r: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """``r[:, 0] t^3 + r[:, 1] t^2 + r[:, 2] t + r[:, 3]`` for ``r (M, 4, K)``, ``t (M, 1)``."""
    out = torch.addcmul(r[:, 1], r[:, 0], t)
    out = torch.addcmul(r[:, 2], out, t)
    return torch.addcmul(r[:, 3], out, t)


def _horner_derivative(r: torch.Tensor, t: torch.Tensor) -> torch.Tensor:
    """``d/dt`` of `_horner`: ``3 r[:, 0] t^2 + 2 r[:, 1] t + r[:, 2]``."""
    out = torch.addcmul(r[:, 1], r[:, 0], 1.5 * t)
    return torch.addcmul(r[:, 2], out, 2.0 * t)


def polynomial_table(coeffs: torch.Tensor, shape: tuple[int, int]) -> torch.Tensor:
    """The spline of every cell as bicubic polynomial coefficients (exact piecewise form).

    On cell ``(i, j)``, ``g_k(tu, tv) = sum_cd P[c, d, k] tv^(3-c) tu^(3-d)`` with
    ``P[c, d] = sum_ab S[a, c] S[b, d] C[i + a, j + b]`` and ``S`` the B-spline weight rows
    over ``[t^3, t^2, t, 1]`` (the pp-form of the same spline, as scipy's ``PPoly``).

    Args:
        coeffs: ``(ny + 2, nx + 2, K)`` node-lattice coefficients (float64).
        shape: ``(ny, nx)`` nodes.

    Returns:
        ``((ny - 1) (nx - 1), 4 * 4 * K)`` rows laid out ``[d (tu power), c (tv power), k]``.
    """
    ny, nx = shape
    s = bspline_matrix(coeffs)[:4]  # (a, c)
    table = coeffs.new_zeros(ny - 1, nx - 1, 4, 4, coeffs.shape[-1])  # (i, j, d, c, k)
    for a in range(4):
        for b in range(4):
            patch = coeffs[a : a + ny - 1, b : b + nx - 1]  # (i, j, K)
            weight = s[b][:, None] * s[a][None, :]  # (d, c)
            table += weight[None, None, :, :, None] * patch[:, :, None, None, :]
    return table.reshape((ny - 1) * (nx - 1), -1)


class LatentTerrainMap(EvaluatedTerrain):
    """A latent-grid neural map decoded from its stored form.

    Points outside `extent` are clamped to the border (height of the nearest border
    point, zero slope across the border), like `GridTerrain`.

    Args:
        symbols: Integer latents per latent array, shapes `LatentBasis.shapes`.
        steps: ``(S,)`` quantisation steps (metres).
        scales: ``(S,)`` Laplace scales of the entropy model (step units).
        synthesis: ``(C + 1 + H C + 2 H,)`` synthesis parameters over ``C`` feature
            channels (`Synthesis.parameter_vector` order).
        feature_scale: ``(C,)`` feature scales of the synthesis.
        hidden: MLP hidden units ``H``.
        tile_info: `DemTile.describe` of the tile the map was fitted to.
        metrics: Fit metrics (stored in the file header).
        dtype: dtype of the coefficient buffer (float32 for speed; ``.double()`` works).
        basis: The latent basis (default: the pyramid of ``len(symbols)`` levels).
        context: ``(parameter_count(context_hidden),)`` weights of the context entropy
            model (`.context_model`), or None for the factorized model.
        context_hidden: Hidden units of the context MLP (0 without it).
        zones: Per-zone step and scale codes (`.zones`), or None (one step per latent
            array).

    Raises:
        NeuralMapError: Inconsistent shapes.
    """

    coeffs: torch.Tensor
    inner_bias: torch.Tensor
    outer: torch.Tensor

    def __init__(
        self,
        symbols: list[np.ndarray],
        steps: np.ndarray,
        scales: np.ndarray,
        synthesis: np.ndarray,
        feature_scale: np.ndarray,
        *,
        hidden: int,
        tile_info: dict[str, Any],
        metrics: dict[str, Any] | None = None,
        dtype: torch.dtype = torch.float32,
        basis: LatentBasis | None = None,
        context: np.ndarray | None = None,
        context_hidden: int = 0,
        zones: ZoneCodes | None = None,
    ) -> None:
        super().__init__()
        self.tile_info = dict(tile_info)
        self.tile_name = str(self.tile_info.get("name", ""))
        self.tile_fingerprint = str(self.tile_info.get("fingerprint", ""))
        self.shape = tuple(int(n) for n in self.tile_info["shape"])
        self.spacing = tuple(float(s) for s in self.tile_info["spacing"])
        self.origin = tuple(float(o) for o in self.tile_info["origin"])
        ny, nx = self.shape
        self.extent = (self.origin[0], self.origin[0] + (nx - 1) * self.spacing[0],
                       self.origin[1], self.origin[1] + (ny - 1) * self.spacing[1])
        self.basis = basis if basis is not None else make_basis(
            "pyramid", len(symbols), self.shape)  # type: ignore[arg-type]
        self.levels = self.basis.levels
        self.hidden = int(hidden)
        self.metrics: dict[str, Any] = dict(metrics or {})
        expected = self.basis.shapes(self.shape)  # type: ignore[arg-type]
        got = [tuple(s.shape) for s in symbols]
        if got != expected:
            raise NeuralMapError(
                f"latent map: latent shapes {got} do not fit a {ny} x {nx} tile (expected "
                f"{expected}); the file is damaged."
            )
        self.context = None if context is None else np.asarray(context, np.float32).copy()
        self.context_hidden = int(context_hidden) if context is not None else 0
        self.entropy = "factorized" if context is None else "context"
        self.symbols = [np.ascontiguousarray(s, dtype=np.int32) for s in symbols]
        self.zones = zones
        if zones is not None and len(zones.groups) != len(symbols):
            raise NeuralMapError(
                f"latent map: zone codes for {len(zones.groups)} latent arrays, the map "
                f"has {len(symbols)}; the file is damaged.")
        self.steps = np.asarray(steps, np.float32).copy()
        self.scales = np.asarray(scales, np.float32).copy()
        self.feature_scale = np.asarray(feature_scale, np.float32).copy()
        self.synthesis_vector = np.asarray(synthesis, np.float32).copy()
        synth = Synthesis(self.basis.channels, self.hidden, torch.from_numpy(self.feature_scale))
        synth.load_parameter_vector(torch.from_numpy(self.synthesis_vector))
        mix, bias, inner_bias, outer = synth.folded()
        lattice = self.basis.lattice(self.decoded_latents, self.shape)  # type: ignore[arg-type]
        coeffs = torch.einsum("lyx,lk->yxk", lattice, mix)  # (ny + 2, nx + 2, K)
        self.register_buffer("coeffs", coeffs.reshape(-1, coeffs.shape[-1]).to(dtype).contiguous())
        self.register_buffer("bias", bias.to(dtype))
        self.register_buffer("inner_bias", inner_bias.to(dtype))
        self.register_buffer("outer", outer.to(dtype))
        table = polynomial_table(coeffs, self.shape)  # type: ignore[arg-type]
        self.register_buffer("poly", table.to(dtype).contiguous(), persistent=False)

    def extra_repr(self) -> str:
        """Short description for ``print(model)``."""
        return (f"tile={self.tile_name!r}, shape={self.shape}, basis={self.basis.name}, "
                f"levels={self.levels}, entropy={self.entropy}, "
                f"zones={0 if self.zones is None else self.zones.zones}, "
                f"hidden={self.hidden}")

    @property
    def decoded_latents(self) -> list[torch.Tensor]:
        """Decoded latents ``q_b Delta_b`` per latent array (float64, storage order), times
        the zone step multipliers ``2^(k_r / 4)`` with zones (`.zones`)."""
        out = [torch.from_numpy(s).double() * float(d)
               for s, d in zip(self.symbols, self.steps, strict=True)]
        if self.zones is None:
            return out
        maps = self.zones.step_maps([tuple(s.shape) for s in self.symbols])
        return [q * torch.from_numpy(m) for q, m in zip(out, maps, strict=True)]

    def _query_dtype(self) -> torch.dtype:
        return self.coeffs.dtype

    def _evaluate(self, xy: torch.Tensor, *, with_slope: bool
                  ) -> tuple[torch.Tensor, torch.Tensor | None]:
        """Heights ``(M,)`` and optional slopes ``(M, 2)`` of ``(M, 2)`` points.

        One row of the piecewise-polynomial table per point (`polynomial_table`),
        then Horner's rule in ``tu`` and ``tv`` over all channels at once (differentiable
        in ``xy``).
        """
        ny, nx = self.shape
        (x0, y0), (dx, dy) = self.origin, self.spacing
        u = (xy[:, 0] - x0) * (1.0 / dx)
        v = (xy[:, 1] - y0) * (1.0 / dy)
        j, tu, in_u = cell_position(u, nx - 1)
        i, tv, in_v = cell_position(v, ny - 1)
        k = self.coeffs.shape[1]
        dt = xy.dtype
        rows = self.poly.index_select(0, i * (nx - 1) + j).to(dt).view(-1, 4, 4 * k)
        tu, tv = tu.unsqueeze(-1), tv.unsqueeze(-1)
        # Horner in tu over d, for every (c, k) at once: (M, 4 K), then in tv over c
        r0 = _horner(rows, tu).view(-1, 4, k)
        val = _horner(r0, tv)  # (M, K)
        if with_slope:
            gu = _horner(_horner_derivative(rows, tu).view(-1, 4, k), tv)
            gv = _horner_derivative(r0, tv)
        height = val[:, 0] + self.bias.to(dt)
        if self.hidden:
            outer = self.outer.to(dt)
            z = torch.tanh(val[:, 1:] + self.inner_bias.to(dt))
            height = height + z @ outer
        if not with_slope:
            return height, None
        gx, gy = gu[:, 0], gv[:, 0]
        if self.hidden:
            w = (1.0 - z * z) * outer
            gx = gx + (gu[:, 1:] * w).sum(-1)
            gy = gy + (gv[:, 1:] * w).sum(-1)
        slope = torch.stack([gx * (1.0 / dx) * in_u, gy * (1.0 / dy) * in_v], dim=-1)
        return height, slope

    def node_heights(self) -> torch.Tensor:
        """``(ny, nx)`` heights at the tile's nodes (float64 decode, for metrics)."""
        synth = Synthesis(self.basis.channels, self.hidden, torch.from_numpy(self.feature_scale))
        synth.load_parameter_vector(torch.from_numpy(self.synthesis_vector))
        from neuralmap.terrain.latent.bspline import node_values

        feats = node_values(self.basis.lattice(self.decoded_latents, self.shape))  # type: ignore[arg-type]
        with torch.no_grad():
            return synth.double()(feats.permute(1, 2, 0))
