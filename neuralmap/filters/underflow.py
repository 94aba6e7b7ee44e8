"""``exp`` and ``log`` for grid masses without the CPU's slow path on underflow.

On this CPU build (torch 2.13, AVX-512), ``torch.exp`` of an argument near or below
``log(finfo.tiny)`` (−87.3 in float32, −708.4 in float64; ``-inf`` included) runs 3–100×
slower than of a moderate one (6.5 M float32 elements: 5 ms at −80, 15 ms at −87, 31 ms at
−87.34, 505 ms at −103), and ``torch.log(0)`` 25× slower than of a normal value
(measured: 6.5 M float32 elements, ``exp`` of uniformly drawn −200…0 in 281 ms against
24 ms here, ``log`` of zeros 54 ms against 2 ms). A point-mass grid is mostly such cells:
after a few updates nearly every cell's log-mass is far below its peak. These helpers
take the fast path for every element:

* `exp_or_zero` is ``exp(x)`` for ``x ≥`` `EXP_FLOOR` (−80 in float32, −700
  in float64; bit-identical there) and exactly 0 below: masses below ``1.8e-35`` of the
  peak in float32 (``1e-304`` in float64) are dropped;
* `log_or_neg_inf` is ``log(w)`` for ``w > 0`` (bit-identical) and ``-inf`` for
  ``w ≤ 0``.
"""

from __future__ import annotations

import math

import torch

__all__ = ["EXP_FLOOR", "exp_or_zero", "log_or_neg_inf"]

#: Smallest argument `exp_or_zero` exponentiates, per dtype (the fast path's range).
EXP_FLOOR = {torch.float32: -80.0, torch.float64: -700.0}


def exp_or_zero(x: torch.Tensor, *, out_of_place: bool = True) -> torch.Tensor:
    """``exp(x)`` with arguments below `EXP_FLOOR` mapped to exactly 0.

    Args:
        x: Any shape, float32 or float64 (NaN stays NaN).
        out_of_place: False reuses ``x``'s storage for the result (``x`` is overwritten).

    Returns:
        Tensor of ``x``'s shape and dtype.
    """
    lo = EXP_FLOOR.get(x.dtype, math.log(torch.finfo(x.dtype).tiny))
    under = x < lo
    e = x.clamp_min(lo) if out_of_place else x.clamp_min_(lo)
    return e.exp_().masked_fill_(under, 0.0)


def log_or_neg_inf(w: torch.Tensor) -> torch.Tensor:
    """``log(w)`` with ``w ≤ 0`` mapped to ``-inf`` (masses: any shape, w ≥ 0).

    Args:
        w: Any shape, float32 or float64.

    Returns:
        Tensor of ``w``'s shape and dtype.
    """
    zero = w <= 0
    return torch.where(zero, 1.0, w).log_().masked_fill_(zero, -math.inf)
