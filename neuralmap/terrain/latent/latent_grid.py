"""The trainable latent grid: continuous latents, learned quantisation, rate and distortion.

Cool-chic-style training state of a latent-grid map (Ladune et al. 2023; C3, Kim et al.
2024): per latent array ``l`` (a pyramid level or a wavelet subband, `.basis`)
continuous latents ``z_l`` (metres), a learned quantisation step ``Delta_l`` and a Laplace
scale ``b_l`` of the factorized entropy model, plus the
`Synthesis`. The stored latents are the symbols
``q_l = round(z_l / Delta_l)`` and the decoded latents ``q_l Delta_l``. During training the
rounding is relaxed, either by additive noise ``z / Delta + u``, ``u ~ U(-1/2, 1/2)``, or by
straight-through rounding (forward rounds, backward is the identity); the rate is
`laplace_bits` of the relaxed symbols under the factorized model, or under the context
model (`.context_model`, ``entropy="context"``, wavelet basis), which can also be trained
with soft rounding (``"soft"``: C3's ``s_a(s_a(y) + u)``, Agustsson & Theis 2020, with the
sharpness ``a`` annealed by the caller).
"""

from __future__ import annotations

import warnings
from typing import Any

import numpy as np
import torch
from torch import nn

from neuralmap.dem.tile import DemTile
from neuralmap.exceptions import NeuralMapError
from neuralmap.terrain.grid import fill_voids_nearest
from neuralmap.terrain.latent.basis import LatentBasis, make_basis
from neuralmap.terrain.latent.bspline import (
    bspline_weights,
    cell_position,
    interpolating_coefficients,
    node_values,
)
from neuralmap.terrain.latent.context_model import ContextModel
from neuralmap.terrain.latent.entropy import laplace_bits
from neuralmap.terrain.latent.pyramid import laplacian_init, level_shapes, node_lattice
from neuralmap.terrain.latent.synthesis import Synthesis
from neuralmap.terrain.latent.zones import (
    ZoneCodes,
    active_groups,
    band_groups,
    check_zones,
    choose_step_codes,
)

#: Relaxations of the rounding during training.
QUANTIZERS = ("noise", "ste", "round", "soft")
#: Entropy models of the latents (``model.entropy``).
ENTROPY_MODELS = ("factorized", "context")


def soft_round(y: torch.Tensor, alpha: float) -> torch.Tensor:
    """Soft rounding ``s_a(y) = floor(y) + 1/2 + tanh(a r) / (2 tanh(a / 2))``,
    ``r = y - floor(y) - 1/2`` (Agustsson & Theis 2020, eq. 3): the identity as ``a -> 0``,
    rounding as ``a -> inf``; differentiable (``floor`` has zero gradient)."""
    m = torch.floor(y) + 0.5
    return m + torch.tanh(alpha * (y - m)) / (2.0 * torch.tanh(torch.tensor(alpha / 2.0)))


def check_entropy(entropy: str, basis: str) -> str:
    """The entropy model name, or a clear error (unknown, or context without wavelets)."""
    if entropy not in ENTROPY_MODELS:
        raise NeuralMapError(f"latent map: unknown entropy model {entropy!r} (model.entropy); "
                             f"use one of {list(ENTROPY_MODELS)}.")
    if entropy == "context" and basis != "wavelet":
        raise NeuralMapError("latent map: model.entropy: context needs model.basis: wavelet "
                             f"(got basis {basis!r}).")
    return entropy


def gather_features(lattice: torch.Tensor, u: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """Spline features of a node-lattice coefficient grid at fractional node positions.

    Args:
        lattice: ``(C, ny + 2, nx + 2)`` coefficients (`node_lattice`).
        u: ``(M,)`` east positions in node intervals.
        v: ``(M,)`` north positions in node intervals.

    Returns:
        ``(M, C)`` features, differentiable in the coefficients and positions.
    """
    c, py, px = lattice.shape
    j, tu, _ = cell_position(u, px - 3)
    i, tv, _ = cell_position(v, py - 3)
    wx = bspline_weights(tu, derivative=False)  # (4, M)
    wy = bspline_weights(tv, derivative=False)
    offsets = (torch.arange(4)[:, None] * px + torch.arange(4)[None, :]).reshape(16)
    index = (i * px + j)[:, None] + offsets  # (M, 16)
    flat = lattice.reshape(c, -1)
    vals = flat[:, index.reshape(-1)].view(c, -1, 4, 4)  # (C, M, a, b)
    weights = wy.T[:, :, None] * wx.T[:, None, :]  # (M, a, b)
    return (vals * weights).sum((-1, -2)).T


def node_operator(nodes: int, scale: int, count: int) -> torch.Tensor:
    """Sparse ``(nodes, count)`` matrix of a level's B-splines at the nodes of one axis.

    Entry ``(n, k)`` is ``B(n / scale - (k - 1))`` (at most 4 non-zeros per row).
    """
    n = torch.arange(nodes, dtype=torch.float64)[:, None]
    k = torch.arange(count, dtype=torch.float64)[None, :]
    a = (n / scale - (k - 1)).abs()
    dense = torch.where(a < 1, 2.0 / 3.0 - a**2 + a**3 / 2,
                        torch.where(a < 2, (2 - a).clamp(min=0) ** 3 / 6, torch.zeros_like(a)))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # "sparse CSR support is in beta"
        return dense.float().to_sparse_csr()


def exact_finest(heights: torch.Tensor, latents: list[torch.Tensor],
                 shape: tuple[int, int]) -> torch.Tensor:
    """Minimum-norm finest-level correction that makes ``latents`` reproduce the nodes.

    Solves ``A_y c A_x^T = r`` for ``c`` with ``r`` the node residual of ``latents`` and
    ``A`` the finest level's B-spline node operators (`node_operator`), through their
    pseudo-inverses (float64; ``O(n^3)`` per axis).

    Args:
        heights: ``(ny, nx)`` node heights (float64, mean removed as for the start).
        latents: Level coefficient grids, finest first.
        shape: ``(ny, nx)``.

    Returns:
        The finest level's ``(ny + 2, nx + 2)`` correction (float64).
    """
    ny, nx = shape
    residual = heights - node_values(node_lattice(latents, shape)).sum(0)
    a_y = node_operator(ny, 1, ny + 2).to_dense().double()
    a_x = node_operator(nx, 1, nx + 2).to_dense().double()
    return torch.linalg.pinv(a_y) @ residual @ torch.linalg.pinv(a_x).T


def node_gains(basis: LatentBasis, shape: tuple[int, int]) -> torch.Tensor:
    """``(S,)`` squared node response ``G_b`` of one unit latent in each latent array.

    ``G_b = sum_nodes h^2`` for a unit coefficient at the centre of array ``b`` (float64
    decode); a quantisation error of variance ``s^2`` there adds ``G_b s^2`` to the summed
    squared node error, so steps ``Delta_b = Delta / sqrt(G_b)`` weigh every array alike.
    """
    shapes = basis.shapes(shape)
    gains = []
    for b, (my, mx) in enumerate(shapes):
        unit = [torch.zeros(sh, dtype=torch.float64) for sh in shapes]
        unit[b][my // 2, mx // 2] = 1.0
        gains.append(float((node_values(basis.lattice(unit, shape)) ** 2).sum()))
    return torch.tensor(gains, dtype=torch.float64).clamp(min=1e-6)


#: Buffer names in checkpoints written before the zones got their name -> the names now.
OLD_BUFFERS = {"region_step_codes": "zone_step_codes", "region_scale_codes": "zone_scale_codes",
               "regions_chosen": "zones_chosen"}

class LatentGrid(nn.Module):
    """Trainable latents (wavelet subbands or pyramid levels) + entropy model + synthesis.

    Args:
        tile: The DEM tile (voids are filled nearest for the start and masked in the loss).
        levels: Wavelet levels ``J`` (``3 J + 1`` subbands) or pyramid levels ``L`` (knot
            spacing ``2^l`` nodes).
        hidden: MLP hidden units (0 = linear synthesis only).
        init_step: Initial quantisation step, metres: every pyramid level's, or the node
            error scale of the wavelet subbands' steps ``init_step / sqrt(G_b)``
            (`node_gains`).
        init_sweeps: Pyramid basis: correction sweeps per level of the Laplacian-pyramid start (12 brings
            the start to 0.07 m node RMSE on jacksboro, 3.9 m on topobathy; 2 left 1.1 m
            and 41 m, which 1000 Adam steps did not recover on topobathy).
        seed: Seed of the MLP's initial weights.
        exact_start: Add to the finest level the minimum-norm coefficients that make the
            start reproduce every node exactly (least squares through the B-spline node
            operators, ``A_y c A_x^T = r``); without it the start keeps the residual the
            sweeps leave (3.9 m node RMSE on topobathy, a floor Adam did not get under).
            Pyramid basis only.
        basis: ``"pyramid"`` (overcomplete B-spline levels) or ``"wavelet"`` (the subbands
            of a ``levels``-level wavelet transform of the B-spline coefficient grid,
            started exactly from the coefficients that interpolate the nodes,
            `interpolating_coefficients`).
        wavelet: ``"cdf97"`` or ``"cdf53"`` (wavelet basis).
        entropy: ``"factorized"`` (one Laplace per latent array) or ``"context"`` (the
            context MLP of `.context_model`; wavelet basis only).
        context_hidden: Hidden units of the context MLP.
        zones: Side ``R`` of the grid of zones with their own step and entropy scale
            (`.zones`; 0 = one step per latent array). The codes start at 0 and are
            chosen by `choose_zones` (the fit does so when straight-through rounding
            starts).

    Raises:
        NeuralMapError: Unknown basis, wavelet or entropy model, ``zones`` out of range, ``levels`` < 1 or too many for the
            tile, ``hidden`` < 0, ``init_step`` <= 0.
    """

    def __init__(self, tile: DemTile, *, levels: int = 6, hidden: int = 0,
                 init_step: float = 1.0, init_sweeps: int = 12, seed: int = 0,
                 exact_start: bool = True, basis: str = "wavelet",
                 wavelet: str = "cdf97", entropy: str = "factorized",
                 context_hidden: int = 12, zones: int = 0) -> None:
        super().__init__()
        self.zones = check_zones(zones)
        ny, nx = tile.shape
        self.basis = make_basis(basis, levels, (int(ny), int(nx)), wavelet=wavelet)
        if int(hidden) < 0:
            raise NeuralMapError(f"latent map: hidden must be >= 0, got {hidden}.")
        if not init_step > 0:
            raise NeuralMapError(f"latent map: init_step must be > 0 metres, got {init_step}.")
        self.shape = (int(ny), int(nx))
        self.levels = int(levels)
        self.hidden = int(hidden)
        self.tile_info = tile.describe()
        filled = torch.as_tensor(fill_voids_nearest(tile.heights, tile.spacing))
        mean = float(filled.mean())
        if self.basis.name == "pyramid":
            init = laplacian_init(filled - mean, self.levels, sweeps=max(1, int(init_sweeps)))
            if exact_start:
                init[0] = init[0] + exact_finest(filled - mean, init, self.shape)
            step = torch.full((len(init),), float(init_step))
        else:
            init = self.basis.analyse(interpolating_coefficients(filled - mean))
            step = (float(init_step) / node_gains(self.basis, self.shape).sqrt()).float()
        node_feats = node_values(self.basis.lattice(init, self.shape))
        scale = node_feats.reshape(self.basis.channels, -1).std(dim=1).clamp(min=1e-3)
        self.latents = nn.ParameterList([nn.Parameter(z.float()) for z in init])
        self.log_step = nn.Parameter(step.log())
        spread = torch.stack([z.float().abs().mean() for z in init]).clamp(min=1e-3) / step
        self.log_scale = nn.Parameter(spread.clamp(min=0.05).log())
        self.synthesis = Synthesis(self.basis.channels, self.hidden, scale.float(), bias=mean,
                                   seed=seed)
        # pyramid node-evaluation operators (sparse, not state): features_l = A_y c_l A_x^T
        shapes = level_shapes(self.shape, self.levels) if self.basis.name == "pyramid" else []
        self.entropy = check_entropy(entropy, self.basis.name)
        self.context: ContextModel | None = None
        if self.entropy == "context":
            self.context = ContextModel(self.basis.shapes(self.shape), self.levels,
                                        hidden=context_hidden, seed=seed)
        self._node_ops = [
            (node_operator(ny, 2**level, shapes[level][0]),
             node_operator(nx, 2**level, shapes[level][1]))
            for level in range(len(shapes))
        ]
        # zone codes (buffers, so a checkpoint keeps them): (G, R²) step and scale codes
        self.groups = band_groups(self.basis.name, len(init))
        n_groups, n_zone = max(self.groups) + 1, max(1, self.zones) ** 2
        self.register_buffer("zone_step_codes", torch.zeros(n_groups, n_zone, dtype=torch.int64))
        self.register_buffer("zone_scale_codes", torch.zeros(n_groups, n_zone, dtype=torch.int64))
        self.register_buffer("zones_chosen", torch.zeros((), dtype=torch.bool))
        self._zone_cache: tuple | None = None

    def _load_from_state_dict(self, state_dict: dict[str, Any], prefix: str, *args: Any,
                              **kwargs: Any) -> None:
        """Also reads checkpoints written before the zones got their name: their buffers
        ``region_step_codes``, ``region_scale_codes``, ``regions_chosen`` (`OLD_BUFFERS`)
        load into the zone buffers."""
        for old, new in OLD_BUFFERS.items():
            if prefix + old in state_dict and prefix + new not in state_dict:
                state_dict[prefix + new] = state_dict.pop(prefix + old)
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    # ------------------------------------------------------------------ zones
    @property
    def zone_codes(self) -> ZoneCodes | None:
        """The zone codes (None without zones)."""
        if not self.zones:
            return None
        shapes = [tuple(z.shape) for z in self.latents]
        return ZoneCodes(self.zones, self.zone_step_codes.numpy().copy(),
                         self.zone_scale_codes.numpy().copy(), tuple(self.groups),
                         active_groups(shapes, self.groups, self.zones))

    def set_zones(self, codes: ZoneCodes) -> None:
        """Stores chosen zone codes."""
        self.zone_step_codes.copy_(torch.as_tensor(codes.step_codes))
        self.zone_scale_codes.copy_(torch.as_tensor(codes.scale_codes))
        self.zones_chosen.fill_(True)
        self._zone_cache = None

    def zone_maps(self, codes: ZoneCodes | None = None
                    ) -> tuple[list[torch.Tensor], list[torch.Tensor]] | None:
        """Per array ``(H, W)`` step multipliers and scale terms (factorized: scale
        multipliers; context: ``log b`` offsets, flat), float32, of ``codes`` (default: the
        grid's once chosen); None without zones or before they are chosen."""
        if codes is None:
            codes = self.zone_codes if bool(self.zones_chosen) else None
        if codes is None:
            return None
        key = (codes.step_codes.tobytes(), codes.scale_codes.tobytes())
        if self._zone_cache is None or self._zone_cache[0] != key:
            shapes = [tuple(z.shape) for z in self.latents]
            steps = [torch.from_numpy(m).float() for m in codes.step_maps(shapes)]
            if self.context is None:
                scale = [torch.from_numpy(m).float() for m in codes.scale_maps(shapes)]
            else:
                scale = [torch.from_numpy(m).float().reshape(-1)
                         for m in codes.log_scale_offsets(shapes)]
            self._zone_cache = (key, (steps, scale))
        return self._zone_cache[1]

    def choose_zones(self, rate_weight: float, *, store: bool = True) -> ZoneCodes | None:
        """Chooses every zone's step code (and a first scale code) by RDO from the
        current latents (`.zones.choose_step_codes`) at ``lambda'`` = ``rate_weight`` (m²
        per bit, RDOQ's), stores and returns them. The context model keeps scale codes 0
        (its MLP predicts the local scale); they are chosen again on the final symbols.
        ``store=False`` returns them without storing."""
        if not self.zones:
            return None
        with torch.no_grad():
            latents = [z.detach().double().numpy() for z in self.latents]
            w2 = float(self.synthesis.linear.detach().double().pow(2).mean())
            codes = choose_step_codes(latents, self.steps.double().numpy(),
                                      self.scales.double().numpy(),
                                      node_gains(self.basis, self.shape).numpy(), w2,
                                      float(rate_weight), self.zones, self.groups)
        if self.context is not None:
            codes = codes.with_scale_codes(np.zeros_like(codes.scale_codes))
        if store:
            self.set_zones(codes)
        return codes

    # ------------------------------------------------------------------ quantisation
    @property
    def steps(self) -> torch.Tensor:
        """``(L,)`` quantisation steps ``Delta_l`` (metres)."""
        return self.log_step.exp()

    @property
    def scales(self) -> torch.Tensor:
        """``(L,)`` Laplace scales ``b_l`` (quantisation-step units)."""
        return self.log_scale.exp()

    def relaxed(self, quantizer: str, alpha: float = 8.0
                ) -> tuple[list[torch.Tensor], torch.Tensor]:
        """Decoded latents and total rate under a relaxation of the rounding.

        Args:
            quantizer: ``"noise"`` (additive uniform noise), ``"ste"`` (straight-through
                rounding), ``"round"`` (hard rounding, no gradient to the latents) or
                ``"soft"`` (rate at ``s_a(y) + u``, decoded ``s_a(s_a(y) + u)``, C3).
            alpha: Sharpness ``a`` of the soft rounding.

        Returns:
            ``(decoded latents (metres, finest first), rate in bits (scalar))``.
        """
        if quantizer not in QUANTIZERS:
            raise NeuralMapError(f"latent map: quantizer must be one of {QUANTIZERS}, got "
                                 f"{quantizer!r}.")
        decoded, relaxed, bits = [], [], []
        steps, scales = self.steps, self.scales
        maps = self.zone_maps()
        for level, z in enumerate(self.latents):
            step = steps[level] if maps is None else steps[level] * maps[0][level]
            y = z / step
            out = None
            if quantizer == "noise":
                y = y + (torch.rand_like(y) - 0.5)
            elif quantizer == "ste":
                y = y + (torch.round(y) - y).detach()
            elif quantizer == "soft":
                y = soft_round(y, alpha) + (torch.rand_like(y) - 0.5)
                out = soft_round(y, alpha)
            else:
                y = torch.round(y).detach()
            decoded.append((y if out is None else out) * step)
            relaxed.append(y)
            if self.context is None:
                scale = scales[level] if maps is None else scales[level] * maps[1][level]
                bits.append(laplace_bits(y, scale).sum())
        if self.context is not None:
            return decoded, self.context.bits(relaxed, steps, self.log_scale,
                                              None if maps is None else maps[1])
        return decoded, torch.stack(bits).sum()

    def symbols(self, codes: ZoneCodes | None = None) -> list[np.ndarray]:
        """The integer symbols ``round(z_l / Delta_l)`` per latent array (int32; with
        zones ``Delta_l`` times the zone's step multiplier, of ``codes`` or the grid's)."""
        maps = self.zone_maps(codes)
        with torch.no_grad():
            return [torch.round(z / (s if maps is None else s * maps[0][k])).to(torch.int32)
                    .numpy() for k, (z, s) in enumerate(zip(self.latents, self.steps,
                                                            strict=True))]

    # ------------------------------------------------------------------ decoding
    def node_features(self, decoded: list[torch.Tensor]) -> torch.Tensor:
        """``(ny, nx, C)`` features at every node: pyramid ``A_y c_l A_x^T`` per level
        (sparse banded B-spline operators; equal to refining to the node lattice), wavelet
        the node values of the inverse-transformed coefficient grid."""
        if self.basis.name != "pyramid":
            return node_values(self.basis.lattice(decoded, self.shape)).permute(1, 2, 0)
        feats = []
        for (op_y, op_x), c in zip(self._node_ops, decoded, strict=True):
            t = torch.sparse.mm(op_y, c.to(op_y.dtype))  # (ny, kx)
            feats.append(torch.sparse.mm(op_x, t.T.contiguous()))  # (nx, ny)
        return torch.stack(feats, dim=-1).transpose(0, 1)

    def node_heights(self, decoded: list[torch.Tensor]) -> torch.Tensor:
        """``(ny, nx)`` heights at every node from decoded latents."""
        return self.synthesis(self.node_features(decoded))

    def point_heights(self, decoded: list[torch.Tensor], uv: torch.Tensor) -> torch.Tensor:
        """``(M,)`` heights at fractional node positions ``uv (M, 2)`` (east, north)."""
        if self.basis.name != "pyramid":
            lattice = self.basis.lattice(decoded, self.shape)
            return self.synthesis(gather_features(lattice, uv[:, 0], uv[:, 1]))
        feats = [gather_features(c.unsqueeze(0), uv[:, 0] / 2**level, uv[:, 1] / 2**level)
                 for level, c in enumerate(decoded)]
        return self.synthesis(torch.cat(feats, dim=-1))

    def config(self) -> dict[str, Any]:
        """Constructor-level description stored in the bitstream header."""
        return {"levels": self.levels, "hidden": self.hidden, "shape": list(self.shape),
                **self.basis.describe(), "entropy": self.entropy,
                "level_shapes": [list(s) for s in self.basis.shapes(self.shape)]}


def stored_context(grid: LatentGrid) -> np.ndarray | None:
    """The context MLP's weights as the file stores them (float16 values), or None."""
    if grid.context is None:
        return None
    with torch.no_grad():
        return grid.context.parameter_vector().numpy().astype(np.float16).astype(np.float32)


def coding_parameters(grid: LatentGrid, symbols: list[np.ndarray],
                      codes: ZoneCodes | None = None) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per latent array ``(mu, b)`` (flat) of ``symbols`` under the grid's entropy model as
    the file codes it (factorized ``(0, b_s)`` times the zone scales, or the context
    model in its coding form), with zone codes ``codes`` (default: the grid's)."""
    from neuralmap.terrain.latent.context_model import CodingModel

    codes = grid.zone_codes if codes is None else codes
    shapes = [tuple(s.shape) for s in symbols]
    with torch.no_grad():
        steps = grid.steps.numpy().astype(np.float32)
        scales = grid.scales.numpy().astype(np.float32)
    vector = stored_context(grid)
    if vector is None:
        maps = codes.scale_maps(shapes) if codes is not None else [np.ones(sh) for sh in shapes]
        return [(np.zeros(int(np.prod(sh))), float(b) * m.ravel())
                for sh, b, m in zip(shapes, scales.astype(np.float64), maps, strict=True)]
    assert grid.context is not None
    offsets = None if codes is None else codes.log_scale_offsets(shapes)
    model = CodingModel(vector, grid.context.hidden, shapes, grid.levels, steps, scales,
                        offsets)
    return model.all_parameters(symbols)


def _ranges(sym: list[np.ndarray]) -> list[tuple[int, int]]:
    return [(min(0, int(s.min())), max(0, int(s.max()))) if s.size else (0, 0) for s in sym]


def rdoq_symbols(grid: LatentGrid, rate_weight: float, heights: torch.Tensor,
                 valid: torch.Tensor | None = None, codes: ZoneCodes | None = None
                 ) -> tuple[list[np.ndarray], dict]:
    """RDOQ symbols of a trained grid (`.rdoq`) under its entropy model as stored (and its
    zone steps and scales, `.zones`).

    Args:
        grid: The trained grid.
        rate_weight: ``lambda`` of the node-only trade-off (m² per bit per node).
        heights: ``(ny, nx)`` target node heights (voids filled).
        valid: ``(ny, nx)`` bool mask of the nodes that count (default: all).
        codes: Zone codes (default: the grid's once chosen).

    Returns:
        ``(symbols, info)`` as `rdoq` (``J`` in summed m²: ``n`` times the objective).
    """
    from neuralmap.terrain.latent.context_model import symbol_bits
    from neuralmap.terrain.latent.rdoq import rdoq

    shapes = grid.basis.shapes(grid.shape)
    if codes is None and bool(grid.zones_chosen):
        codes = grid.zone_codes
    step_maps = (codes.step_maps(shapes) if codes is not None
                 else [np.ones(sh) for sh in shapes])
    with torch.no_grad():
        steps = grid.steps.numpy().astype(np.float32)
        w = float(grid.synthesis.linear.detach().double().pow(2).mean())
    gains = node_gains(grid.basis, grid.shape).numpy() * w
    # SSE of a one-step change of each symbol: G_s w^2 (Delta_s m_r)^2
    curvature = [g * (float(d) * m) ** 2 for g, d, m in zip(gains, steps, step_maps, strict=True)]
    step_tensors = [float(d) * torch.from_numpy(m).float()
                    for d, m in zip(steps, step_maps, strict=True)]
    target = torch.as_tensor(heights, dtype=torch.float32)
    mask = (torch.ones_like(target, dtype=torch.bool) if valid is None
            else torch.as_tensor(valid, dtype=torch.bool))

    def bits_of(sym: list[np.ndarray]) -> list:
        params = coding_parameters(grid, sym, codes)
        return [(lambda c, mu=mu, b=b, r=r: symbol_bits(c, mu, b, *r).reshape(c.shape))
                for (mu, b), r in zip(params, _ranges(sym), strict=True)]

    def distortion_of(sym: list[np.ndarray]) -> tuple[float, list[np.ndarray]]:
        with torch.enable_grad():  # also inside validation's no_grad
            q = [torch.from_numpy(s.astype(np.float32)).requires_grad_(True) for s in sym]
            decoded = [qi * d for qi, d in zip(q, step_tensors, strict=True)]
            err = grid.node_heights(decoded) - target
            sse = (err[mask] ** 2).sum()
            grads = torch.autograd.grad(sse, q)
        return float(sse.detach()), [g.double().numpy() for g in grads]

    return rdoq(grid.symbols(codes), curvature, rate_weight, bits_of, distortion_of)


def refine_zones(grid: LatentGrid, symbols: list[np.ndarray], codes: ZoneCodes
                 ) -> ZoneCodes:
    """``codes`` with the scale codes chosen again on the final ``symbols`` (exact code
    length, `.zones.refine_scale_codes`)."""
    from neuralmap.terrain.latent.zones import refine_scale_codes

    return refine_scale_codes(codes, symbols, coding_parameters(grid, symbols, codes),
                              _ranges(symbols))


def exact_objective(grid: LatentGrid, symbols: list[np.ndarray], codes: ZoneCodes,
                    rate_weight: float, heights: torch.Tensor, valid: torch.Tensor) -> float:
    """``SSE_nodes + lambda' bits`` of ``symbols`` under ``codes`` (m²): the decoded nodes
    against ``heights`` at ``valid``, the ideal code length of the symbols (coder form)."""
    from neuralmap.terrain.latent.context_model import symbol_bits

    shapes = [tuple(s.shape) for s in symbols]
    with torch.no_grad():
        steps = grid.steps.numpy().astype(np.float32)
        decoded = [torch.from_numpy(s.astype(np.float32)) * float(d) * torch.from_numpy(m).float()
                   for s, d, m in zip(symbols, steps, codes.step_maps(shapes), strict=True)]
        err = grid.node_heights(decoded) - torch.as_tensor(heights, dtype=torch.float32)
        sse = float((err[torch.as_tensor(valid, dtype=torch.bool)].double() ** 2).sum())
    bits = sum(float(symbol_bits(s, mu, b, *r).sum()) for s, (mu, b), r in
               zip(symbols, coding_parameters(grid, symbols, codes), _ranges(symbols),
                   strict=True) if s.size)
    return sse + float(rate_weight) * bits


def zones_pay(grid: LatentGrid, symbols: list[np.ndarray], codes: ZoneCodes,
              plain: list[np.ndarray], rate_weight: float, heights: torch.Tensor,
              valid: torch.Tensor) -> bool:
    """Whether the symbols under the zones' steps with their codes (range-coded words, the
    count and about 32 header bytes) have a lower `exact_objective` than the uniform-step
    ``plain`` symbols."""
    from neuralmap.terrain.latent.zones import code_scales, encode_codes

    zero = ZoneCodes(codes.zones, np.zeros_like(codes.step_codes),
                     np.zeros_like(codes.scale_codes), codes.groups, codes.active)
    code_bits = 32.0 * encode_codes(codes, code_scales(codes)).size + 8.0 * (4 + 32)
    j_zones = (exact_objective(grid, symbols, codes, rate_weight, heights, valid)
               + float(rate_weight) * code_bits)
    return j_zones < exact_objective(grid, plain, zero, rate_weight, heights, valid)


def export_map(grid: LatentGrid, metrics: dict[str, Any] | None = None, *,
               rdoq_rate_weight: float | None = None,
               rdoq_target: tuple[torch.Tensor, torch.Tensor] | None = None,
               zone_rate_weight: float | None = None,
               zones_always: bool = False) -> Any:
    """The `LatentTerrainMap` of a trained grid,
    exactly as its file stores it (symbols rounded, MLP weights in float16).

    Args:
        grid: The trained grid.
        metrics: Stored in the file header.
        rdoq_rate_weight: When given, the symbols are chosen by RDOQ at this ``lambda``
            (`rdoq_symbols`) instead of rounded.
        rdoq_target: ``(heights (ny, nx), valid (ny, nx))`` node targets of RDOQ (needed
            with ``rdoq_rate_weight``; `RateDistortion.heights` / ``.valid``).
        zone_rate_weight: ``lambda'`` of the zone-code choice when the fit did not
            choose them (`LatentGrid.choose_zones`); default ``rdoq_rate_weight``.
            With zones the scale codes are chosen again on the final symbols.
        zones_always: Keep the zones even where they do not pay. By default, with
            ``rdoq_target`` and a ``lambda'``, the map is stored without zones (format 2
            / 3) when the exact ``SSE_nodes + lambda' bits`` of the uniform-step symbols,
            zone codes' bits excluded, is no larger than the zoned one's with them
            (`zones_pay`): small maps, where about a hundred codes are a tenth of the
            file.

    Raises:
        NeuralMapError: ``rdoq_rate_weight`` without ``rdoq_target``.
    """
    if rdoq_rate_weight is not None and rdoq_target is None:
        raise NeuralMapError("export_map: RDOQ needs the node targets (rdoq_target).")
    from neuralmap.terrain.latent.bitstream import stored_latent_map
    from neuralmap.terrain.latent.map import LatentTerrainMap

    codes = None  # the grid is left as it is (a validation export does not change the fit)
    if grid.zones and bool(grid.zones_chosen):
        codes = grid.zone_codes
    elif grid.zones:
        lam = zone_rate_weight if zone_rate_weight is not None else rdoq_rate_weight
        if lam is None:
            raise NeuralMapError(
                "export_map: the zone codes were not chosen during the fit; pass "
                "zone_rate_weight (lambda', m² per bit) or rdoq_rate_weight.")
        codes = grid.choose_zones(lam, store=False)
    if codes is not None:
        codes = refine_zones(grid, grid.symbols(codes), codes)
    symbols = (grid.symbols(codes) if rdoq_rate_weight is None or rdoq_target is None
               else rdoq_symbols(grid, rdoq_rate_weight, *rdoq_target, codes=codes)[0])
    if codes is not None:
        codes = refine_zones(grid, symbols, codes)
        lam = zone_rate_weight if zone_rate_weight is not None else rdoq_rate_weight
        if not zones_always and rdoq_target is not None and lam is not None:
            zero = ZoneCodes(codes.zones, np.zeros_like(codes.step_codes),
                             np.zeros_like(codes.scale_codes), codes.groups, codes.active)
            plain = (grid.symbols(zero) if rdoq_rate_weight is None
                     else rdoq_symbols(grid, rdoq_rate_weight, *rdoq_target, codes=zero)[0])
            if not zones_pay(grid, symbols, codes, plain, lam, *rdoq_target):
                codes, symbols = None, plain
    with torch.no_grad():
        latent_map = LatentTerrainMap(
            symbols, grid.steps.numpy(), grid.scales.numpy(),
            grid.synthesis.parameter_vector().numpy(),
            grid.synthesis.feature_scale.numpy(), hidden=grid.hidden,
            tile_info=grid.tile_info, metrics=metrics, basis=grid.basis,
            context=stored_context(grid),
            context_hidden=grid.context.hidden if grid.context is not None else 0,
            zones=codes,
        )
    return stored_latent_map(latent_map)
