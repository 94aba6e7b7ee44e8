"""Per-zone quantisation steps and entropy scales of the latents (non-stationary rate).

One step per subband codes flat and rough parts of a tile alike. Here every latent array is
cut into an ``R x R`` grid of *zones* (the same spatial grid in every array, so a zone
covers the same ground in every subband), and each zone ``r`` of each *group* ``g`` (a
wavelet level's three detail subbands share one group, ``LL`` has its own; a pyramid level
is one group) carries two small integer codes:

* a step code ``k``: the zone's quantisation step is ``Delta_s 2^(k / 4)``;
* a scale code ``c``: the entropy model's scale there is ``b_s 2^(c / 4)`` (factorized
  model), or ``log b`` of the context model is offset by ``(c / 4) ln 2``.

(A *region* elsewhere in the toolkit is a large area of many tiles; a zone is a part of
one map's latent arrays. The file format keeps its original header keys, ``"regions"`` and
``"region_scales"``, `.bitstream`.)

The step codes are chosen by rate-distortion optimisation from the continuous latents
``z`` (`choose_step_codes`), with the same ``lambda'`` (m² per bit) as RDOQ: for each zone
and candidate ``k``, the symbols ``q = round(z / (Delta_s 2^(k/4)))`` give

``D_r(k) = w^2 sum_{s in g} G_s sum_{i in r} (z_i - q_i Delta_s 2^(k/4))^2``  (summed node
error, m²; ``G_s`` the node gain of a unit latent, ``w`` the synthesis weight),

``R_r(k) = min_c sum_{s in g} sum_{i in r} -log2 P(q_i | b_s 2^(c/4))`` bits, in closed form
from three sums per zone (zeros, non-zeros, ``sum |q|``; discretised Laplace, `.entropy`),

and ``k_r = argmin_k D_r(k) + lambda' R_r(k)`` (ties to the smallest ``|k|``). Under MSE at
high rate a uniform step is optimal; at low rate (coefficients near or under the step,
which is where flat ground sits) the optimal entropy-coded step depends on the local
variance (Sullivan 1996), and the scale code lets a flat zone's zeros cost almost nothing.
Once the symbols are final the scale codes are chosen again exactly under the coder's
model (`refine_scale_codes`).

The codes are range coded (a discretised Laplace on ``[-32, 32]`` per kind, scale in the
header; `encode_codes`) in a stream of their own before the latents (format 4,
`.bitstream`). Decoding builds the per-coefficient step and scale maps by one index look-up
per array (`ZoneCodes.step_maps`), no loop over zones or coefficients.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from neuralmap.exceptions import NeuralMapError

#: Codes per octave of the step and scale multipliers (``2^(code / CODES_PER_OCTAVE)``).
CODES_PER_OCTAVE = 4
#: Range of the stored codes (both kinds).
CODE_RANGE = (-32, 32)
#: Candidate step codes of the RDO (step x 1/2 .. x 4).
STEP_CANDIDATES = tuple(range(-4, 9))
#: Candidate scale codes (scale x 2^-8 .. x 2^4).
SCALE_CANDIDATES = tuple(range(-32, 17))
#: Largest zone grid side.
MAX_ZONES = 64
#: A group carries codes only when every array in it has at least this many coefficients
#: per zone (and >= R rows and columns); smaller groups keep code 0, uncoded.
MIN_PER_ZONE = 16
#: Price of a code's magnitude in the choice, bits per unit (about what the range coder of
#: the codes charges: a Laplace of scale ~5 code units), so a saturated choice that saves
#: next to nothing is not taken.
CODE_BITS = 0.3


def check_zones(zones: int) -> int:
    """The zone grid side ``R`` (0 = one step per subband), or a clear error."""
    if not (isinstance(zones, (int, np.integer)) and 0 <= int(zones) <= MAX_ZONES):
        raise NeuralMapError(
            f"latent map: model.zones must be an integer in 0..{MAX_ZONES} (the side R of "
            f"the R x R grid of zones with their own step and entropy scale; 0 = one step "
            f"per subband), got {zones!r}.")
    return int(zones)


def band_groups(basis_name: str, count: int) -> list[int]:
    """Group of every latent array: a wavelet level's ``HL, LH, HH`` share one, ``LL`` its
    own (storage order ``[HL_1, LH_1, HH_1, .., LL_J]``); a pyramid level is one group."""
    if basis_name == "wavelet":
        return [b // 3 for b in range(count)]
    return list(range(count))


def zone_index(shape: tuple[int, int], zones: int) -> np.ndarray:
    """``(H, W)`` int64 zone of every coefficient of an array: ``(i R // H) R + j R // W``."""
    h, w = shape
    rows = (np.arange(h) * zones) // max(h, 1)
    cols = (np.arange(w) * zones) // max(w, 1)
    return rows[:, None] * zones + cols[None, :]


def multiplier(codes: np.ndarray) -> np.ndarray:
    """``2^(code / CODES_PER_OCTAVE)`` (float64)."""
    return np.exp2(np.asarray(codes, np.float64) / CODES_PER_OCTAVE)


@dataclass(frozen=True)
class ZoneCodes:
    """The zone grid of a map and its codes.

    Attributes:
        zones: Grid side ``R``.
        step_codes: ``(G, R * R)`` int step codes ``k``.
        scale_codes: ``(G, R * R)`` int scale codes ``c``.
        groups: Group of every latent array (`band_groups`).
        active: Per group, whether it carries codes (`active_groups`); the codes of an
            inactive group are 0 and not stored.
    """

    zones: int
    step_codes: np.ndarray
    scale_codes: np.ndarray
    groups: tuple[int, ...]
    active: tuple[bool, ...]

    def _maps(self, codes: np.ndarray, shapes: list[tuple[int, int]]) -> list[np.ndarray]:
        return [np.asarray(codes, np.int64)[g][zone_index(tuple(s), self.zones)]
                for g, s in zip(self.groups, shapes, strict=True)]

    def step_maps(self, shapes: list[tuple[int, int]]) -> list[np.ndarray]:
        """Per array ``(H, W)`` step multipliers ``2^(k / 4)`` (float64)."""
        return [multiplier(m) for m in self._maps(self.step_codes, shapes)]

    def scale_maps(self, shapes: list[tuple[int, int]]) -> list[np.ndarray]:
        """Per array ``(H, W)`` scale multipliers ``2^(c / 4)`` (float64)."""
        return [multiplier(m) for m in self._maps(self.scale_codes, shapes)]

    def log_scale_offsets(self, shapes: list[tuple[int, int]]) -> list[np.ndarray]:
        """Per array ``(H, W)`` offsets ``(c / 4) ln 2`` of the context model's ``log b``."""
        return [m.astype(np.float64) * (math.log(2.0) / CODES_PER_OCTAVE)
                for m in self._maps(self.scale_codes, shapes)]

    def with_scale_codes(self, scale_codes: np.ndarray) -> ZoneCodes:
        codes = np.asarray(scale_codes, np.int64) * np.asarray(self.active)[:, None]
        return ZoneCodes(self.zones, self.step_codes, codes, self.groups, self.active)

    def describe(self) -> dict[str, float]:
        """Summary for logs: spread of the step and scale codes."""
        return {"zones": float(self.zones),
                "step_code_min": float(self.step_codes.min()),
                "step_code_max": float(self.step_codes.max()),
                "scale_code_min": float(self.scale_codes.min()),
                "scale_code_max": float(self.scale_codes.max())}


def active_groups(shapes: list[tuple[int, int]], groups: list[int], zones: int
                  ) -> tuple[bool, ...]:
    """Whether each group carries codes: every array of it has ``>= R`` rows and columns
    and ``>= MIN_PER_ZONE`` coefficients per zone (fixed by the shapes, not stored)."""
    out = [True] * (max(groups) + 1)
    for g, (h, w) in zip(groups, shapes, strict=True):
        if h < zones or w < zones or h * w < MIN_PER_ZONE * zones * zones:
            out[g] = False
    return tuple(out)


# ------------------------------------------------------------------ rate of zone statistics
def _laplace_zone_bits(n0: np.ndarray, n1: np.ndarray, sum_m: np.ndarray,
                         b: np.ndarray) -> np.ndarray:
    """Bits of a zone's symbols under a zero-mean discretised Laplace of scale ``b``
    (`.entropy.laplace_bits`, exact) from ``n0`` zeros, ``n1`` non-zeros and ``sum |q|``:

    ``n0 (-log2(1 - e^{-1/(2b)})) + n1 (-log2(1/2 (1 - e^{-1/b}))) + (sum|q| - n1/2)/(b ln 2)``.
    """
    p0 = -np.expm1(-0.5 / b)
    p1 = 0.5 * -np.expm1(-1.0 / b)
    return (-n0 * np.log2(np.maximum(p0, 1e-300)) - n1 * np.log2(np.maximum(p1, 1e-300))
            + (sum_m - 0.5 * n1) / (b * math.log(2.0)))


def choose_step_codes(latents: list[np.ndarray], steps: np.ndarray, scales: np.ndarray,
                      gains: np.ndarray, weight2: float, rate_weight: float, zones: int,
                      groups: list[int]) -> ZoneCodes:
    """RDO choice of every zone's step code (and a first scale code), see the module
    docstring.

    Args:
        latents: Continuous latents ``z`` per array (metres), ``(H_s, W_s)``.
        steps: ``(S,)`` subband steps ``Delta_s`` (m).
        scales: ``(S,)`` subband Laplace scales ``b_s`` (step units).
        gains: ``(S,)`` node gains ``G_s`` (`.latent_grid.node_gains`).
        weight2: ``w^2``, the squared linear synthesis weight.
        rate_weight: ``lambda'`` (m² per bit).
        zones: Grid side ``R``.
        groups: Group of every array.

    Returns:
        The codes (scale codes: the rate-minimising ones at the chosen steps).
    """
    n_groups, n_zone = max(groups) + 1, zones * zones
    ks = np.asarray(STEP_CANDIDATES, np.float64)
    cs = np.asarray(SCALE_CANDIDATES, np.float64)
    dist = np.zeros((n_groups, ks.size, n_zone))
    # bits per (group, k, zone, c): summed over the group's arrays
    bits = np.zeros((n_groups, ks.size, n_zone, cs.size))
    for b, z in enumerate(latents):
        z = np.asarray(z, np.float64)
        if z.size == 0:
            continue
        g, idx = groups[b], zone_index(z.shape, zones).ravel()
        flat = z.ravel()
        delta = float(steps[b]) * multiplier(ks)  # (K,)
        q = np.round(flat[None, :] / delta[:, None])  # (K, N)
        err2 = (flat[None, :] - q * delta[:, None]) ** 2
        m = np.abs(q)
        offs = (np.arange(ks.size)[:, None] * n_zone + idx[None, :]).ravel()
        size = ks.size * n_zone
        dist[g] += (float(gains[b]) * weight2
                    * np.bincount(offs, err2.ravel(), size)).reshape(ks.size, n_zone)
        n1 = np.bincount(offs, (m > 0).ravel().astype(np.float64), size).reshape(ks.size, n_zone)
        total = np.bincount(offs, minlength=size).astype(np.float64).reshape(ks.size, n_zone)
        sum_m = np.bincount(offs, m.ravel(), size).reshape(ks.size, n_zone)
        scale = float(scales[b]) * multiplier(cs)  # (C,)
        bits[g] += _laplace_zone_bits((total - n1)[..., None], n1[..., None],
                                        sum_m[..., None], scale[None, None, :])
    bits = bits + CODE_BITS * np.abs(cs)  # the scale code's own price
    best_c = np.argmin(bits, axis=-1)  # (G, K, R²)
    rate = np.take_along_axis(bits, best_c[..., None], -1)[..., 0]
    rate = rate + CODE_BITS * np.abs(ks)[None, :, None]  # the step code's own price
    cost = dist + float(rate_weight) * rate  # (G, K, R²)
    # ties go to the smallest |k|: candidates ordered by |k|, argmin takes the first
    order = np.argsort(np.abs(ks), kind="stable")
    pick = order[np.argmin(cost[:, order, :], axis=1)]  # (G, R²)
    active = active_groups([tuple(np.shape(z)) for z in latents], groups, zones)
    on = np.asarray(active)[:, None]
    step_codes = ks[pick].astype(np.int64) * on
    scale_codes = cs[np.take_along_axis(best_c, pick[:, None, :], 1)[:, 0, :]].astype(np.int64)
    return ZoneCodes(zones, step_codes, scale_codes * on, tuple(groups), active)


def refine_scale_codes(codes: ZoneCodes, symbols: list[np.ndarray],
                       params: list[tuple[np.ndarray, np.ndarray]],
                       ranges: list[tuple[int, int]]) -> ZoneCodes:
    """The scale codes that minimise the coder's ideal code length of the final symbols.

    Args:
        codes: Current codes.
        symbols: Final integer symbols per array.
        params: Per array ``(mu, b)`` flat C-order of the coder under ``codes``
            (`.bitstream.symbol_models`).
        ranges: ``(lo, hi)`` symbol range per array.

    Returns:
        ``codes`` with each zone's scale code replaced by its best candidate.
    """
    from neuralmap.terrain.latent.context_model import symbol_bits

    n_groups, n_zone = codes.scale_codes.shape
    cs = np.asarray(SCALE_CANDIDATES, np.int64)
    bits = np.zeros((n_groups, n_zone, cs.size))
    shapes = [tuple(s.shape) for s in symbols]
    current = codes._maps(codes.scale_codes, shapes)
    for b, (sym, (mu, scale), (lo, hi)) in enumerate(zip(symbols, params, ranges, strict=True)):
        if sym.size == 0 or lo == hi:
            continue
        g, idx = codes.groups[b], zone_index(sym.shape, codes.zones).ravel()
        base = scale / multiplier(current[b].ravel())  # b without the zone's offset
        for k, c in enumerate(cs):
            cost = symbol_bits(sym, mu, base * multiplier(c), lo, hi)
            bits[g, :, k] += np.bincount(idx, cost, n_zone)
    bits += CODE_BITS * np.abs(cs)
    order = np.argsort(np.abs(cs), kind="stable")
    best = cs[order][np.argmin(bits[:, :, order], axis=-1)]
    return codes.with_scale_codes(best)


# ------------------------------------------------------------------ coding of the codes
def code_scales(codes: ZoneCodes) -> tuple[float, float]:
    """Laplace scales (code units) of the two code kinds, as stored (2 decimals, >= 0.1)."""
    out = []
    on = np.asarray(codes.active, bool)
    for c in (codes.step_codes, codes.scale_codes):
        c = np.asarray(c)[on]
        mean_abs = float(np.abs(c).mean()) if c.size else 0.0
        out.append(max(0.1, round(mean_abs, 2)))
    return out[0], out[1]


def encode_codes(codes: ZoneCodes, scales: tuple[float, float]) -> np.ndarray:
    """Range codes the step codes, then the scale codes (C order), each under a
    discretised Laplace(0, scale) on `CODE_RANGE`. Returns ``(W,)`` uint32 words."""
    from neuralmap.terrain.latent.entropy import constriction_module

    constriction = constriction_module()
    encoder = constriction.stream.queue.RangeEncoder()
    lo, hi = CODE_RANGE
    on = np.asarray(codes.active, bool)
    for c, scale in zip((codes.step_codes, codes.scale_codes), scales, strict=True):
        flat = np.ascontiguousarray(np.asarray(c)[on], np.int32).ravel()
        if flat.size == 0:
            continue
        if flat.min() < lo or flat.max() > hi:
            raise NeuralMapError(f"latent map: zone codes outside {CODE_RANGE}.")
        encoder.encode(flat, constriction.stream.model.QuantizedLaplace(lo, hi, 0.0, scale))
    return np.asarray(encoder.get_compressed(), dtype=np.uint32)


def decode_codes(words: np.ndarray, zones: int, groups: list[int],
                 scales: tuple[float, float], shapes: list[tuple[int, int]]) -> ZoneCodes:
    """Inverse of `encode_codes` (``shapes``: the latent arrays', for `active_groups`).

    Raises:
        NeuralMapError: The words do not decode (damaged payload).
    """
    from neuralmap.terrain.latent.entropy import constriction_module

    constriction = constriction_module()
    decoder = constriction.stream.queue.RangeDecoder(np.ascontiguousarray(words, np.uint32))
    n_groups, n_zone = max(groups) + 1, zones * zones
    active = active_groups(shapes, groups, zones)
    on = np.asarray(active, bool)
    lo, hi = CODE_RANGE
    out = []
    for scale in scales:
        codes = np.zeros((n_groups, n_zone), np.int64)
        if on.any():
            try:
                values = decoder.decode(constriction.stream.model.QuantizedLaplace(
                    lo, hi, 0.0, float(scale)), int(on.sum()) * n_zone)
            except Exception as exc:  # noqa: BLE001 - constriction raises its own types
                raise NeuralMapError(f"latent zone codes do not decode "
                                     f"({type(exc).__name__}); the file is damaged.") from None
            codes[on] = np.asarray(values, np.int64).reshape(-1, n_zone)
        out.append(codes)
    return ZoneCodes(zones, out[0], out[1], tuple(groups), active)
