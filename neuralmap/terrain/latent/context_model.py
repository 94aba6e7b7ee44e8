"""Context (autoregressive) entropy model of the wavelet subbands, and its wavefront coder.

Cool-chic's auto-regressive module (ARM; Ladune et al. 2023, C3: Kim et al. 2024) applied to
wavelet subbands, as EBCOT / ECECOW-style context coding does for JPEG 2000: the symbol
``q`` at ``(i, j)`` of subband ``s`` has a discretised Laplace density with location ``mu``
and scale ``b`` predicted by one small MLP shared by every subband,

``(mu, t) = MLP(x)``,  ``b = exp(t + beta_s)``,
``P(q) = F_b(q - mu + 1/2) - F_b(q - mu - 1/2)``  (Laplace CDF ``F_b``),

from ``x`` = 13 context values ``c`` and their log-magnitudes ``plog2(1 + |c|)`` (26
inputs; ``plog2`` the piecewise-linear log2 of `plog2`, exact in floating point), all in
units of the subband's own quantisation step ``Delta_s``:

* 6 causal neighbours in the same subband: ``(i, j-1), (i-1, j), (i-1, j-1), (i-1, j+1),
  (i, j-2), (i-2, j)`` (zero outside the subband);
* 5 co-located coefficients of the parent, the same orientation one level coarser (the
  coarsest detail subbands' parent is ``LL``), at ``(i // 2, j // 2)`` and its 4
  neighbours, times ``Delta_parent / Delta_s``;
* 2 co-located siblings of the same level already decoded (``LH`` sees ``HL``; ``HH``
  sees ``HL`` and ``LH``), times their step ratio.

``beta_s`` is the subband's learned scale offset (the factorized model's ``log b_s``; the
MLP's output layer starts at zero, so training starts from the factorized model). The MLP's
weights are stored in the file as float16 (`parameter_count` values, counted in the map's
bytes).

Decoding order: ``LL``, then level ``J`` .. 1, ``HL``, ``LH``, ``HH`` each. Inside a
subband the causal neighbours of ``(i, j)`` all lie on earlier wavefronts ``t = 2 i + j``,
so a subband decodes in ``2 (H - 1) + W`` vectorised steps (one MLP evaluation and one
range-decoder call per wavefront, none per symbol).

Bit-exactness between encoder and decoder: the coding path (`coding_parameters`) uses only
elementwise float64 operations (products, sums, ``max``, in a fixed order: no matrix
product, whose blocking depends on the batch size), and rounds ``mu`` to 1/64 and ``t + beta``
to 1/16 before a table look-up of ``b``, so the encoder (all symbols at once) and the decoder
(one wavefront at a time) compute the same parameters bit for bit.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from neuralmap.exceptions import NeuralMapError
from neuralmap.terrain.latent.entropy import laplace_bits

#: Causal neighbour offsets ``(di, dj)`` in the same subband (all on earlier wavefronts).
CAUSAL = ((0, -1), (-1, 0), (-1, -1), (-1, 1), (0, -2), (-2, 0))
#: Offsets around the co-located parent coefficient.
PARENT = ((0, 0), (-1, 0), (1, 0), (0, -1), (0, 1))
#: Context values per symbol (causal + parent + 2 siblings); the MLP sees them and |them|.
N_CONTEXT = len(CAUSAL) + len(PARENT) + 2
N_INPUTS = 2 * N_CONTEXT
#: Range of ``log b`` (step units) and the grids the coding path rounds to.
LOG_SCALE_RANGE = (-3.0, 10.0)
MU_GRID = 64.0
LOG_SCALE_GRID = 16.0
_PAD = 2  # zero padding of a subband for its causal neighbours


def plog2(v: np.ndarray | torch.Tensor) -> np.ndarray | torch.Tensor:
    """Piecewise-linear ``log2 v`` for ``v >= 1``: ``(e - 2) + v 2^(1 - e)`` with
    ``v = m 2^e``, ``m in [1/2, 1)`` (exact at powers of two; every operation exact, so the
    encoder and decoder agree bit for bit). Differentiable in ``v`` for tensors."""
    if isinstance(v, torch.Tensor):
        _, e = torch.frexp(v.detach())
        return (e - 2).to(v.dtype) + torch.ldexp(v, (1 - e).to(v.dtype))
    _, e = np.frexp(v)
    return (e - 2).astype(np.float64) + np.ldexp(v, 1 - e)


def parameter_count(hidden: int) -> int:
    """Weights of the context MLP: ``N_INPUTS x H + H + H x 2 + 2``."""
    return N_INPUTS * hidden + hidden + 2 * hidden + 2


@dataclass(frozen=True)
class SubbandLinks:
    """Where the context of each wavelet subband comes from (storage indices).

    Attributes:
        order: Decoding order of the subbands (``LL`` first, coarse to fine).
        parent: Parent subband of each subband (``-1`` for ``LL``).
        same_level: Whether the parent is at the same resolution (``LL`` of the coarsest
            level) instead of half of it.
        siblings: Already-decoded siblings of each subband (same level).
    """

    order: tuple[int, ...]
    parent: tuple[int, ...]
    same_level: tuple[bool, ...]
    siblings: tuple[tuple[int, ...], ...]


def subband_links(levels: int) -> SubbandLinks:
    """The context links of a ``levels``-level transform, storage order
    ``[HL_1, LH_1, HH_1, .., HL_J, LH_J, HH_J, LL_J]`` (`.wavelet`)."""
    ll = 3 * levels
    order = [ll] + [3 * (j - 1) + o for j in range(levels, 0, -1) for o in range(3)]
    parent, same, sibs = [], [], []
    for b in range(ll + 1):
        if b == ll:
            parent.append(-1), same.append(True), sibs.append(())
            continue
        j, o = b // 3 + 1, b % 3
        parent.append(3 * j + o if j < levels else ll)
        same.append(j == levels)
        sibs.append(tuple(3 * (j - 1) + k for k in range(o)))
    return SubbandLinks(tuple(order), tuple(parent), tuple(same), tuple(sibs))


def _colocated(n_child: int, n_parent: int, same_level: bool) -> np.ndarray:
    """Parent index of every child row (or column), clipped into the parent."""
    idx = np.arange(n_child) if same_level else np.arange(n_child) // 2
    return np.minimum(idx, n_parent - 1)


def wavefronts(shape: tuple[int, int]) -> list[tuple[np.ndarray, np.ndarray]]:
    """``(rows, cols)`` of every wavefront ``t = 2 i + j`` of an ``(H, W)`` subband, in order."""
    h, w = shape
    out = []
    for t in range(2 * (h - 1) + w):
        i = np.arange(max(0, (t - w + 2) // 2), min(h - 1, t // 2) + 1)
        j = t - 2 * i
        keep = (j >= 0) & (j < w)
        if keep.any():
            out.append((i[keep], j[keep]))
    return out


def wavefront_order(shape: tuple[int, int]) -> np.ndarray:
    """Flat (C-order) indices of an ``(H, W)`` subband in decoding order."""
    if shape[0] * shape[1] == 0:
        return np.zeros(0, np.int64)
    return np.concatenate([i * shape[1] + j for i, j in wavefronts(shape)])


class ContextGather:
    """Index tables that gather the context of every symbol of every subband.

    Args:
        shapes: Subband shapes in storage order.
        levels: Wavelet levels ``J``.
    """

    def __init__(self, shapes: list[tuple[int, int]], levels: int) -> None:
        if len(shapes) != 3 * levels + 1:
            raise NeuralMapError(
                f"latent map: the context model needs the wavelet basis' 3 J + 1 subbands, got "
                f"{len(shapes)} latent arrays for J = {levels} (model.entropy: context needs "
                "model.basis: wavelet).")
        self.shapes = [tuple(int(n) for n in s) for s in shapes]
        self.links = subband_links(levels)
        self.parent_rows: list[np.ndarray | None] = []
        self.parent_cols: list[np.ndarray | None] = []
        for b, (h, w) in enumerate(self.shapes):
            p = self.links.parent[b]
            if p < 0:
                self.parent_rows.append(None), self.parent_cols.append(None)
                continue
            same = self.links.same_level[b]
            self.parent_rows.append(_colocated(h, self.shapes[p][0], same))
            self.parent_cols.append(_colocated(w, self.shapes[p][1], same))

    def gather(self, padded: list, band: int, rows: np.ndarray, cols: np.ndarray,
               ratios: list) -> list:
        """The ``N_CONTEXT`` context columns of the symbols ``(rows, cols)`` of ``band``.

        Args:
            padded: Every subband zero-padded by ``_PAD`` on each side (numpy arrays or
                tensors; only already-decoded entries are read).
            band: Storage index of the subband.
            rows, cols: ``(N,)`` positions in it.
            ratios: Step ratios ``Delta_other / Delta_band`` per storage index (float or
                0-d tensor), used for the parent and siblings.

        Returns:
            ``N_CONTEXT`` arrays ``(N,)`` in the order of the module docstring.
        """
        own = padded[band]
        cols_out = [own[rows + _PAD + di, cols + _PAD + dj] for di, dj in CAUSAL]
        p = self.links.parent[band]
        if p < 0:
            zero = own[rows + _PAD, cols + _PAD] * 0.0
            cols_out += [zero] * (len(PARENT) + 2)
            return cols_out
        pr, pc = self.parent_rows[band][rows], self.parent_cols[band][cols]
        par = padded[p]
        cols_out += [par[pr + _PAD + di, pc + _PAD + dj] * ratios[p] for di, dj in PARENT]
        sibs = self.links.siblings[band]
        for k in range(2):
            if k < len(sibs):
                s = sibs[k]
                sr = np.minimum(rows, self.shapes[s][0] - 1)
                sc = np.minimum(cols, self.shapes[s][1] - 1)
                cols_out.append(padded[s][sr + _PAD, sc + _PAD] * ratios[s])
            else:
                cols_out.append(own[rows + _PAD, cols + _PAD] * 0.0)
        return cols_out


class ContextModel(nn.Module):
    """The context MLP (training form, float32, differentiable).

    Args:
        shapes: Subband shapes in storage order.
        levels: Wavelet levels ``J``.
        hidden: Hidden units ``H`` of the MLP (ReLU).
        seed: Seed of the first layer's initial weights.
    """

    def __init__(self, shapes: list[tuple[int, int]], levels: int, hidden: int = 12,
                 seed: int = 0) -> None:
        super().__init__()
        if int(hidden) < 1:
            raise NeuralMapError(f"latent map: context_hidden must be >= 1, got {hidden}.")
        self.hidden = int(hidden)
        self.gatherer = ContextGather(shapes, levels)
        gen = torch.Generator().manual_seed(int(seed) + 17)
        self.w1 = nn.Parameter(torch.randn(N_INPUTS, hidden, generator=gen) / N_INPUTS**0.5)
        self.b1 = nn.Parameter(torch.zeros(hidden))
        self.w2 = nn.Parameter(torch.zeros(hidden, 2))
        self.b2 = nn.Parameter(torch.zeros(2))
        self._all = [(np.repeat(np.arange(h), w), np.tile(np.arange(w), h))
                     for h, w in self.gatherer.shapes]

    def parameter_vector(self) -> torch.Tensor:
        """Weights in storage order ``w1, b1, w2, b2`` (`parameter_count` values)."""
        return torch.cat([p.reshape(-1) for p in (self.w1, self.b1, self.w2, self.b2)])

    def load_parameter_vector(self, vector: torch.Tensor) -> None:
        """Inverse of `parameter_vector`."""
        load_into(self, vector)

    def parameters_of(self, symbols: list[torch.Tensor], steps: torch.Tensor,
                      log_scales: torch.Tensor, offsets: list[torch.Tensor] | None = None
                      ) -> list[tuple[torch.Tensor, torch.Tensor]]:
        """``(mu, b)`` of every symbol of every subband (storage order, C-order flat).

        Args:
            symbols: Relaxed or integer symbols per subband (step units), ``(H_s, W_s)``.
            steps: ``(S,)`` quantisation steps.
            log_scales: ``(S,)`` scale offsets ``beta_s``.
            offsets: Per subband ``(H_s W_s,)`` per-zone offsets of ``log b``
                (`.zones`), or None.

        Returns:
            Per subband ``(mu (H_s W_s,), b (H_s W_s,))``.
        """
        padded = [nn.functional.pad(y, (_PAD, _PAD, _PAD, _PAD)) for y in symbols]
        out = []
        for band, (rows, cols) in enumerate(self._all):
            if rows.size == 0:
                empty = symbols[band].reshape(-1)
                out.append((empty, empty))
                continue
            ratios = [steps[k] / steps[band] for k in range(len(symbols))]
            ctx = torch.stack(self.gatherer.gather(padded, band, rows, cols, ratios), dim=-1)
            x = torch.cat([ctx, plog2(1.0 + ctx.abs())], dim=-1)
            h = torch.relu(x @ self.w1 + self.b1)
            o = h @ self.w2 + self.b2
            t = o[:, 1] + log_scales[band]
            if offsets is not None:
                t = t + offsets[band]
            log_b = t.clamp(*LOG_SCALE_RANGE)
            out.append((o[:, 0], log_b.exp()))
        return out

    def bits(self, symbols: list[torch.Tensor], steps: torch.Tensor,
             log_scales: torch.Tensor, offsets: list[torch.Tensor] | None = None
             ) -> torch.Tensor:
        """Total rate (bits) of the (relaxed) symbols under the context model."""
        total = steps.new_zeros(())
        for y, (mu, b) in zip(symbols, self.parameters_of(symbols, steps, log_scales, offsets),
                              strict=True):
            if y.numel():
                total = total + laplace_bits(y.reshape(-1) - mu, b).sum()
        return total


def load_into(model: ContextModel, vector: torch.Tensor) -> None:
    """Copies a `parameter_vector` into ``model``."""
    h = model.hidden
    sizes = [N_INPUTS * h, h, 2 * h, 2]
    parts = torch.split(torch.as_tensor(vector, dtype=torch.float32), sizes)
    with torch.no_grad():
        model.w1.copy_(parts[0].view(N_INPUTS, h))
        model.b1.copy_(parts[1])
        model.w2.copy_(parts[2].view(h, 2))
        model.b2.copy_(parts[3])


# ---------------------------------------------------------------------- coding path (numpy)
_LOG_TABLE_LO = int(round(LOG_SCALE_RANGE[0] * LOG_SCALE_GRID))
_LOG_TABLE_HI = int(round(LOG_SCALE_RANGE[1] * LOG_SCALE_GRID))
_SCALE_TABLE = np.exp(np.arange(_LOG_TABLE_LO, _LOG_TABLE_HI + 1, dtype=np.float64)
                      / LOG_SCALE_GRID)


class CodingModel:
    """The stored context model in its bit-exact coding form (float64, elementwise only).

    Args:
        vector: ``(parameter_count(H),)`` stored weights (float16 values, as read back).
        hidden: ``H``.
        shapes: Subband shapes in storage order.
        levels: Wavelet levels ``J``.
        steps: ``(S,)`` stored quantisation steps (float32 values).
        scales: ``(S,)`` stored scale offsets ``exp(beta_s)`` (float32 values).
        offsets: Per subband ``(H_s, W_s)`` per-zone offsets of ``log b`` (float64,
            `.zones.ZoneCodes.log_scale_offsets`), or None.
    """

    def __init__(self, vector: np.ndarray, hidden: int, shapes: list[tuple[int, int]],
                 levels: int, steps: np.ndarray, scales: np.ndarray,
                 offsets: list[np.ndarray] | None = None) -> None:
        v = np.asarray(vector, np.float64)
        h = int(hidden)
        if v.size != parameter_count(h):
            raise NeuralMapError(
                f"latent map: {v.size} context weights do not fit a {h}-unit context MLP "
                f"({parameter_count(h)} expected); the file is damaged.")
        self.w1 = v[: N_INPUTS * h].reshape(N_INPUTS, h)
        self.b1 = v[N_INPUTS * h : N_INPUTS * h + h]
        self.w2 = v[N_INPUTS * h + h : N_INPUTS * h + 3 * h].reshape(h, 2)
        self.b2 = v[N_INPUTS * h + 3 * h :]
        self.gatherer = ContextGather(shapes, levels)
        st = np.asarray(steps, np.float64)
        self.ratios = [[float(st[k] / st[b]) for k in range(st.size)] for b in range(st.size)]
        self.log_offsets = np.log(np.asarray(scales, np.float64))
        self.offsets = (None if offsets is None
                        else [np.asarray(o, np.float64) for o in offsets])

    def mlp(self, ctx: list[np.ndarray], band: int, rows: np.ndarray | None = None,
            cols: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """``(mu, b)`` on the coding grids from the context columns (elementwise, fixed order;
        ``rows, cols`` locate the symbols for the per-zone offsets)."""
        x = ctx + [plog2(1.0 + np.abs(c)) for c in ctx]
        h = np.broadcast_to(self.b1, (x[0].size, self.b1.size)).copy()
        for k, col in enumerate(x):
            h += col[:, None] * self.w1[k]
        np.maximum(h, 0.0, out=h)
        mu = np.full(h.shape[0], self.b2[0])
        t = np.full(h.shape[0], self.b2[1])
        for k in range(h.shape[1]):
            mu += h[:, k] * self.w2[k, 0]
            t += h[:, k] * self.w2[k, 1]
        t += self.log_offsets[band]
        if self.offsets is not None:
            t += self.offsets[band][rows, cols]
        mu = np.round(mu * MU_GRID) / MU_GRID
        idx = np.clip(np.round(t * LOG_SCALE_GRID), _LOG_TABLE_LO, _LOG_TABLE_HI).astype(np.int64)
        return mu, _SCALE_TABLE[idx - _LOG_TABLE_LO]

    def padded(self, symbols: list[np.ndarray]) -> list[np.ndarray]:
        return [np.pad(np.asarray(s, np.float64), _PAD) for s in symbols]

    def all_parameters(self, symbols: list[np.ndarray]) -> list[tuple[np.ndarray, np.ndarray]]:
        """``(mu, b)`` of every symbol (C-order flat per subband), all at once (encoder)."""
        padded = self.padded(symbols)
        out = []
        for band, (h, w) in enumerate(self.gatherer.shapes):
            rows, cols = np.repeat(np.arange(h), w), np.tile(np.arange(w), h)
            ctx = self.gatherer.gather(padded, band, rows, cols, self.ratios[band])
            out.append(self.mlp(ctx, band, rows, cols) if rows.size
                       else (np.zeros(0), np.ones(0)))
        return out


def _laplace_cdf(x: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Zero-mean Laplace CDF ``F_b(x)`` (float64)."""
    return np.where(x < 0, 0.5 * np.exp(np.minimum(x, 0.0) / b),
                    1.0 - 0.5 * np.exp(-np.maximum(x, 0.0) / b))


def symbol_bits(sym: np.ndarray, mu: np.ndarray, b: np.ndarray, lo: int, hi: int) -> np.ndarray:
    """``-log2 P(q)`` of integer symbols under the discretised Laplace on ``[lo, hi]``.

    The coder's form (constriction's quantised Laplace): ``P(q) = F(q + 1/2) - F(q - 1/2)``
    with ``F(x) = F_b(x - mu)``, the two end symbols taking the tails
    (``P(lo) = F(lo + 1/2)``, ``P(hi) = 1 - F(hi - 1/2)``).
    """
    q = np.asarray(sym, np.float64).ravel()
    upper = np.where(q >= hi, 1.0, _laplace_cdf(q + 0.5 - mu, b))
    lower = np.where(q <= lo, 0.0, _laplace_cdf(q - 0.5 - mu, b))
    if lo == hi:
        return np.zeros_like(q)
    return -np.log2(np.maximum(upper - lower, 2.0**-24))


def ideal_context_bits(model: CodingModel, symbols: list[np.ndarray],
                       ranges: list[tuple[int, int]]) -> float:
    """Total ``-log2 P`` of integer symbols under the coding-form context model
    (`symbol_bits` per subband): the ideal code length of `encode_context`."""
    total = 0.0
    for sym, (mu, b), (lo, hi) in zip(symbols, model.all_parameters(symbols), ranges,
                                      strict=True):
        if sym.size:
            total += float(symbol_bits(sym, mu, b, lo, hi).sum())
    return total


def encode_context(model: CodingModel, symbols: list[np.ndarray],
                   ranges: list[tuple[int, int]]) -> np.ndarray:
    """Range codes every subband in decoding order, each in wavefront order.

    Returns:
        ``(W,)`` uint32 compressed words.
    """
    from neuralmap.terrain.latent.entropy import constriction_module

    constriction = constriction_module()
    encoder = constriction.stream.queue.RangeEncoder()
    params = model.all_parameters(symbols)
    for band in model.gatherer.links.order:
        lo, hi = ranges[band]
        sym = np.asarray(symbols[band], np.int32)
        if sym.size == 0 or lo == hi:
            continue
        order = wavefront_order(sym.shape)
        mu, b = params[band]
        family = constriction.stream.model.QuantizedLaplace(int(lo), int(hi))
        encoder.encode(np.ascontiguousarray(sym.ravel()[order]), family,
                       np.ascontiguousarray(mu[order]), np.ascontiguousarray(b[order]))
    return np.asarray(encoder.get_compressed(), dtype=np.uint32)


def decode_context(model: CodingModel, words: np.ndarray,
                   ranges: list[tuple[int, int]]) -> list[np.ndarray]:
    """Inverse of `encode_context`: subband by subband, wavefront by wavefront.

    Raises:
        NeuralMapError: The words do not decode (damaged payload).
    """
    from neuralmap.terrain.latent.entropy import constriction_module

    constriction = constriction_module()
    decoder = constriction.stream.queue.RangeDecoder(np.ascontiguousarray(words, np.uint32))
    shapes = model.gatherer.shapes
    padded = [np.zeros((h + 2 * _PAD, w + 2 * _PAD)) for h, w in shapes]
    for band in model.gatherer.links.order:
        lo, hi = ranges[band]
        own = padded[band]
        if shapes[band][0] * shapes[band][1] == 0:
            continue
        if lo == hi:
            own[_PAD:-_PAD, _PAD:-_PAD] = lo
            continue
        family = constriction.stream.model.QuantizedLaplace(int(lo), int(hi))
        ratios = model.ratios[band]
        for rows, cols in wavefronts(shapes[band]):
            mu, b = model.mlp(model.gatherer.gather(padded, band, rows, cols, ratios), band,
                              rows, cols)
            try:
                values = decoder.decode(family, mu, b)
            except Exception as exc:  # noqa: BLE001 - constriction raises its own types
                raise NeuralMapError(
                    f"latent payload does not decode ({type(exc).__name__}); the file is "
                    "damaged.") from None
            own[rows + _PAD, cols + _PAD] = values
    return [p[_PAD:-_PAD, _PAD:-_PAD].astype(np.int32) for p in padded]
