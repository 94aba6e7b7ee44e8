"""Biorthogonal wavelet transforms by lifting: CDF 9/7 and 5/3, any size, symmetric borders.

The critically sampled basis of latent-grid maps: the latents are the subbands of a 2-D
dyadic (Mallat) wavelet transform of the map's cubic B-spline coefficient grid, so the map
stores as many numbers as the grid has coefficients, and the inverse transform gives that
grid back (run once at load). Lifting (Daubechies & Sweldens 1998) factorises the filter
bank into predict / update steps on the even (``s``) and odd (``d``) samples of an axis:

``d += a_1 (s[i] + s[i+1])``, ``s += a_2 (d[i-1] + d[i])``, ... then ``s *= g_s``, ``d *= g_d``

with CDF 9/7 ``a = (-1.586134342, -0.05298011854, 0.8829110762, 0.4435068522)`` (the
JPEG 2000 irreversible filter, whose analysis taps have low-pass DC gain 1 after
``s /= K``, ``d *= K``, ``K = 1.230174105``) and LeGall / CDF 5/3 ``a = (-1/2, 1/4)`` (the
JPEG 2000 reversible filter, here in floating point). The gains ``g`` scale both to
low-pass DC gain and high-pass Nyquist gain ``sqrt 2`` (``g_s = sqrt 2 / K``,
``g_d = K / sqrt 2``), the near-orthonormal normalisation, so that equal quantisation steps
in every subband add about equal squared error. Borders use whole-sample symmetric
extension (``x[-k] = x[k]``, ``x[n-1+k] = x[n-1-k]``), which for odd-length symmetric
filters is the same as lifting with mirrored neighbours, so any length, odd or even, is
transformed without padding: an axis of ``n`` samples gives ``ceil(n/2)`` low-pass and
``floor(n/2)`` high-pass coefficients. Inverse = the steps undone in reverse order, so the
reconstruction is perfect to float rounding whatever the lifting constants.

Subbands of ``J`` levels, finest first: ``[HL_1, LH_1, HH_1, ..., HL_J, LH_J, HH_J, LL_J]``
(``HL``: high-pass along x, low-pass along y). All operations are vectorised tensor ops
(one Python step per level and lifting step, none per coefficient) and differentiable.
"""

from __future__ import annotations

import math

import torch

from neuralmap.exceptions import NeuralMapError

_K97 = 1.230174104914001
#: Lifting constants and the final low- / high-pass gains ``(g_s, g_d)`` of each wavelet.
WAVELETS: dict[str, tuple[tuple[float, ...], tuple[float, float]]] = {
    "cdf97": ((-1.586134342059924, -0.052980118572961, 0.882911075530934,
               0.443506852043971), (math.sqrt(2.0) / _K97, _K97 / math.sqrt(2.0))),
    "cdf53": ((-0.5, 0.25), (math.sqrt(2.0), 1.0 / math.sqrt(2.0))),
}
#: Orientation names of the three detail subbands of a level, in storage order.
ORIENTATIONS = ("HL", "LH", "HH")


def check_wavelet(name: str) -> str:
    """The wavelet name, or a clear error listing the known ones."""
    if name not in WAVELETS:
        raise NeuralMapError(
            f"latent map: unknown wavelet {name!r} (model.wavelet); use one of "
            f"{sorted(WAVELETS)}."
        )
    return name


def _right_s(s: torch.Tensor, n: int) -> torch.Tensor:
    """``s[i+1]`` for every odd sample ``d[i]`` (mirrored: ``x[n] = x[n-2]`` for even ``n``)."""
    return torch.cat([s[..., 1:], s[..., -1:]], dim=-1) if n % 2 == 0 else s[..., 1:]


def _left_right_d(d: torch.Tensor, n: int) -> tuple[torch.Tensor, torch.Tensor]:
    """``d[i-1]`` and ``d[i]`` for every even sample ``s[i]`` (mirrored borders)."""
    left = torch.cat([d[..., :1], d[..., :-1]], dim=-1)
    if n % 2 == 1:  # the last even sample x[n-1] has x[n] = x[n-2] on its right
        left = torch.cat([left, d[..., -1:]], dim=-1)
        right = torch.cat([d, d[..., -1:]], dim=-1)
    else:
        right = d
    return left, right


def analysis_1d(x: torch.Tensor, wavelet: str) -> tuple[torch.Tensor, torch.Tensor]:
    """One analysis level along the last axis.

    Args:
        x: ``(..., n)`` samples, ``n >= 2``.
        wavelet: A key of `WAVELETS`.

    Returns:
        ``(low (..., ceil(n/2)), high (..., floor(n/2)))``.
    """
    n = x.shape[-1]
    steps, (gs, gd) = WAVELETS[wavelet]
    s, d = x[..., 0::2], x[..., 1::2]
    for idx, a in enumerate(steps):
        if idx % 2 == 0:
            d = d + a * (s[..., : d.shape[-1]] + _right_s(s, n))
        else:
            left, right = _left_right_d(d, n)
            s = s + a * (left + right)
    return s * gs, d * gd


def synthesis_1d(s: torch.Tensor, d: torch.Tensor, wavelet: str) -> torch.Tensor:
    """Inverse of `analysis_1d`: ``(..., n)`` samples from ``low`` and ``high``."""
    n = s.shape[-1] + d.shape[-1]
    steps, (gs, gd) = WAVELETS[wavelet]
    s, d = s * (1.0 / gs), d * (1.0 / gd)
    for idx in range(len(steps) - 1, -1, -1):
        a = steps[idx]
        if idx % 2 == 0:
            d = d - a * (s[..., : d.shape[-1]] + _right_s(s, n))
        else:
            left, right = _left_right_d(d, n)
            s = s - a * (left + right)
    pairs = torch.stack([s[..., : d.shape[-1]], d], dim=-1).flatten(-2)
    return torch.cat([pairs, s[..., d.shape[-1]:]], dim=-1) if n % 2 else pairs


def subband_shapes(shape: tuple[int, int], levels: int) -> list[tuple[int, int]]:
    """Shapes of the ``3 J + 1`` subbands of a ``shape`` array, finest first (module order)."""
    ny, nx = shape
    out: list[tuple[int, int]] = []
    for _ in range(levels):
        ly, hy, lx, hx = (ny + 1) // 2, ny // 2, (nx + 1) // 2, nx // 2
        out += [(ly, hx), (hy, lx), (hy, hx)]
        ny, nx = ly, lx
    return out + [(ny, nx)]


def check_levels(shape: tuple[int, int], levels: int) -> int:
    """``levels`` if every level's input has >= 2 samples per axis, else a clear error."""
    ny, nx = shape
    ok = int(levels) >= 1
    for _ in range(int(levels)):
        ok = ok and ny >= 2 and nx >= 2
        ny, nx = (ny + 1) // 2, (nx + 1) // 2
    if not ok:
        raise NeuralMapError(
            f"latent map: a wavelet of {levels} levels does not fit a {shape[0]} x {shape[1]} "
            "coefficient grid (each level halves it and needs >= 2 samples per axis); use "
            "fewer model.levels."
        )
    return int(levels)


def forward_2d(x: torch.Tensor, levels: int, wavelet: str = "cdf97") -> list[torch.Tensor]:
    """``J``-level 2-D analysis of ``x (ny, nx)`` into subbands, finest first."""
    check_wavelet(wavelet)
    check_levels(tuple(x.shape), levels)  # type: ignore[arg-type]
    bands: list[torch.Tensor] = []
    low = x
    for _ in range(levels):
        lo_x, hi_x = analysis_1d(low, wavelet)  # along x
        ll, lh = analysis_1d(lo_x.transpose(-1, -2), wavelet)  # along y
        hl, hh = analysis_1d(hi_x.transpose(-1, -2), wavelet)
        bands += [hl.transpose(-1, -2), lh.transpose(-1, -2), hh.transpose(-1, -2)]
        low = ll.transpose(-1, -2)
    return bands + [low]


def inverse_2d(bands: list[torch.Tensor], wavelet: str = "cdf97") -> torch.Tensor:
    """Inverse of `forward_2d` (differentiable in every subband)."""
    check_wavelet(wavelet)
    levels = (len(bands) - 1) // 3
    low = bands[-1]
    for level in range(levels - 1, -1, -1):
        hl, lh, hh = bands[3 * level : 3 * level + 3]
        lo_x = synthesis_1d(low.transpose(-1, -2), lh.transpose(-1, -2), wavelet)
        hi_x = synthesis_1d(hl.transpose(-1, -2), hh.transpose(-1, -2), wavelet)
        low = synthesis_1d(lo_x.transpose(-1, -2), hi_x.transpose(-1, -2), wavelet)
    return low
