"""Rate-distortion-optimised quantisation (RDOQ) of a latent map's final symbols.

Rounding to the nearest integer minimises the distortion of each symbol, not the map's
``J = D + lambda R``. RDOQ (as in HEVC encoders and trellis-quantised JPEG 2000) picks, per
symbol, among ``round(y)``, one step towards zero and ``0`` the one with the least

``n J_i = g_s Delta_s^2 (q - y)^2 + lambda bits(q)``

(``y`` the continuous latent in step units, ``g_s`` the squared node response of one unit
latent of subband ``s`` times the squared linear synthesis weight: `node_gains`; ``n`` the
node count, ``lambda`` the objective's rate weight in m² per bit per node). Under the
context model ``bits(q)`` is taken with the contexts of the current symbols, so a pass is
accepted only if the whole map's ``J`` (summed distortion estimate plus the exact ideal
code length) goes down, and passes repeat until it does not. Where the model predicts a
small scale (flat ground, calm sea) a non-zero symbol is dear and is zeroed; where it
predicts a large one (rough relief) rounding is kept: a dead zone that follows the
terrain, the non-stationary part of the rate allocation.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

#: ``bits(symbols) -> per subband, a function giving -log2 P of candidate symbol arrays``.
BitsOf = Callable[[list[np.ndarray]], list[Callable[[np.ndarray], np.ndarray]]]


def rdoq(y: list[np.ndarray], gains: np.ndarray, steps: np.ndarray, rate_weight: float,
         bits_of: BitsOf, *, passes: int = 3) -> tuple[list[np.ndarray], dict[str, float]]:
    """RDOQ of the symbols of continuous latents ``y`` (step units).

    Args:
        y: Continuous latents per subband (step units), any shapes.
        gains: ``(S,)`` distortion gains ``g_s`` (m² of summed squared node error per m²).
        steps: ``(S,)`` quantisation steps ``Delta_s`` (m).
        rate_weight: ``lambda`` (m² per bit per node).
        bits_of: Given the current symbols, per subband a function of a candidate array
            (same shape) returning its bits elementwise under the current contexts.
        passes: Most passes.

    Returns:
        ``(symbols (int32 per subband), {"j_round", "j_rdoq", "passes"})`` with ``J`` in
        summed m² (``n`` times the objective's ``D + lambda R``, distortion estimated).
    """
    w = [float(g) * float(d) ** 2 for g, d in zip(gains, steps, strict=True)]

    def total(sym: list[np.ndarray]) -> float:
        dist = sum(wi * float(((s - yi) ** 2).sum()) for wi, s, yi in zip(w, sym, y, strict=True))
        rate = sum(float(f(s).sum()) for f, s in zip(bits_of(sym), sym, strict=True))
        return dist + rate_weight * rate

    sym = [np.round(yi).astype(np.int32) for yi in y]
    best = j_round = total(sym)
    done = 0
    for _ in range(passes):
        fns = bits_of(sym)
        trial = []
        for wi, s, yi, f in zip(w, sym, y, fns, strict=True):
            cands = [s, (s - np.sign(s)).astype(np.int32), np.zeros_like(s)]
            cost = np.stack([wi * (c - yi) ** 2 + rate_weight * f(c) for c in cands])
            pick = np.argmin(cost, axis=0)
            trial.append(np.choose(pick, cands).astype(np.int32))
        j = total(trial)
        if not j < best:
            break
        sym, best, done = trial, j, done + 1
    return sym, {"j_round": j_round, "j_rdoq": best, "passes": float(done)}
