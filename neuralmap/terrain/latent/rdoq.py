"""Rate-distortion-optimised quantisation (RDOQ) of a latent map's final symbols.

Rounding each latent to the nearest integer minimises neither the map's node error (after
straight-through training a latent sits anywhere in its rounding cell) nor ``D + lambda R``.
RDOQ (as in HEVC encoders and trellis-quantised JPEG 2000) moves symbols by one step or to
``0`` where that lowers

``J = SSE_nodes + lambda' bits``  (summed squared node error, m²; ``lambda'`` in m² per bit),

each symbol's change ``dq`` priced to second order, exactly for a linear synthesis:

``dSSE_i = g_i dq + G_s Delta_s^2 dq^2``,  ``g_i = dSSE / dq_i``

(``g`` by one backward pass through the synthesis, ``G_s`` the squared node response of a
unit latent of subband ``s`` times the squared synthesis weight, `node_gains`), and
``bits`` under the entropy model with the contexts of the current symbols. Changes made
together interact, so a pass is kept only if the whole map's exact ``J`` (decoded nodes,
ideal code length) goes down; otherwise only the half of its changes with the largest
predicted gains is tried, and so on. Where the model predicts a small scale (flat ground,
calm sea) a non-zero symbol is dear and goes to zero; where it predicts a large one (rough
relief) it stays: a dead zone that follows the terrain.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

#: ``bits_of(symbols)``: per subband, a function of a candidate array giving its bits
#: elementwise under the contexts of ``symbols``.
BitsOf = Callable[[list[np.ndarray]], list[Callable[[np.ndarray], np.ndarray]]]
#: ``distortion_of(symbols)``: ``(SSE, [dSSE/dq per subband])``.
DistortionOf = Callable[[list[np.ndarray]], tuple[float, list[np.ndarray]]]


def rdoq(symbols: list[np.ndarray], curvature: list[np.ndarray] | np.ndarray,
         rate_weight: float,
         bits_of: BitsOf, distortion_of: DistortionOf, *, passes: int = 4,
         halvings: int = 4) -> tuple[list[np.ndarray], dict[str, float]]:
    """RDOQ starting from ``symbols`` (the rounded latents).

    Args:
        symbols: Integer symbols per subband.
        curvature: Per subband ``G_s Delta_s^2``, the SSE of a one-step change (m²): a
            float, or an array of the subband's shape (per-zone steps, `.zones`).
        rate_weight: ``lambda'`` (m² per bit).
        bits_of: See `BitsOf`.
        distortion_of: See `DistortionOf`.
        passes: Most accepted passes.
        halvings: Most halvings of a pass's change set before giving up.

    Returns:
        ``(symbols (int32), {"j_round", "j_rdoq", "passes"})`` with the exact ``J`` (m²).
    """
    def total(sym: list[np.ndarray]) -> tuple[float, list[np.ndarray]]:
        sse, grads = distortion_of(sym)
        rate = sum(float(f(s).sum()) for f, s in zip(bits_of(sym), sym, strict=True))
        return sse + rate_weight * rate, grads

    sym = [np.asarray(s, np.int32) for s in symbols]
    best, grads = total(sym)
    j_round, done = best, 0
    for _ in range(passes):
        fns = bits_of(sym)
        picks, gains = [], []
        for c2, s, g, f in zip(curvature, sym, grads, fns, strict=True):
            c2 = np.asarray(c2, np.float64)
            base = rate_weight * f(s)
            cands = [s, s - 1, s + 1, np.zeros_like(s)]
            cost = np.stack([g * (c - s) + c2 * (c - s) ** 2 + rate_weight * f(c) - base
                             for c in cands])
            pick = np.argmin(cost, axis=0)
            picks.append(np.choose(pick, cands).astype(np.int32))
            gains.append(-np.min(cost, axis=0))
        order = np.sort(np.concatenate([x.ravel() for x in gains]))[::-1]
        moved = int((order > 0).sum())
        improved = False
        for _ in range(halvings + 1):
            if moved == 0:
                break
            cut = order[moved - 1]
            trial = [np.where(gn >= cut, p, s) if moved < order.size else p
                     for gn, p, s in zip(gains, picks, sym, strict=True)]
            j, g_new = total(trial)
            if j < best:
                sym, best, grads, improved = trial, j, g_new, True
                break
            moved //= 2
        if not improved:
            break
        done += 1
    return sym, {"j_round": j_round, "j_rdoq": best, "passes": float(done)}
