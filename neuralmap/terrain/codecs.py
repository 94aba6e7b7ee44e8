"""Compressed DEM grids: error-bounded raster codecs as the storage baseline for neural maps.

A map stored on board is never a raw float32 grid: it is a compressed one. This module
encodes a `DemTile` with the raster codecs of ``imagecodecs``
and the SZ3 error-bounded compressor of ``pysz`` (optional extra ``neuralmap[codecs]``),
decodes the bytes again and returns the decoded
tile, so every navigation method (grid interpolation, plane fits, ...) runs on exactly what
the decoder on board would see. The stored size is the encoded payload plus a fixed
`HEADER_BYTES` header (shape, spacing, origin, quantisation offset and step, codec).

Codecs (``max_error`` = the bound on ``|decoded - stored|`` at the stored nodes, metres):

* ``"lerc"``: LERC on float32 heights with ``maxZError = max_error`` (Esri's codec for
  elevation rasters). Bound: ``max_error`` plus the float32 rounding of the heights.
* ``"jpegls"``: JPEG-LS near-lossless on heights quantised to ``uint16`` with step
  ``s = 2 max_error / (2 near + 1)`` (default ``near = 2``). Bound: ``s / 2 + near s =
  max_error``.
* ``"jpeg2k"``: JPEG 2000 lossy (irreversible wavelet) on heights quantised with step
  ``max_error / 8``; the codec is not error-bounded, so the encoder searches the target
  PSNR (bisection) for the smallest stream whose decoded maximum error is within
  ``max_error`` (checked against the heights by the encoder; lossless JPEG 2000 when no
  lossy stream is). Bound: ``max_error`` (verified, not by construction).
* ``"zstd"``: int16 + zstd: heights quantised to ``int16`` with step ``2 max_error``, row
  differences (TIFF predictor 2), zstd level 19. Bound: ``max_error``.
* ``"sz3"``: SZ3 (``pysz``, the error-bounded compressor for scientific floating-point
  data: prediction + quantisation + entropy coding) on the float64 heights with the
  absolute error bound ``max_error``. Bound: ``max_error``.

``decimation = d > 1`` first resamples the tile (bicubic) to a grid with about ``d`` times
the spacing and the same extent, compresses that grid the same way and interpolates the
decoded grid back to the original nodes (bicubic): the bound then holds at the coarse
nodes only, and the error at the original nodes is whatever the measurement says.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

from neuralmap.dem.tile import DemTile
from neuralmap.exceptions import NeuralMapError
from neuralmap.terrain.grid import GridTerrain, fill_voids_nearest

#: Every codec name `compress_grid` accepts.
GRID_CODECS = ("lerc", "jpegls", "jpeg2k", "zstd", "sz3")

#: One-line description of each codec, for reports.
CODEC_LABELS = {
    "lerc": "LERC (float32, maxZError)",
    "jpegls": "JPEG-LS near-lossless (uint16 levels)",
    "jpeg2k": "JPEG 2000 lossy (uint16 levels, PSNR searched for the bound)",
    "zstd": "int16 + zstd (row differences, level 19)",
    "sz3": "SZ3 (pysz, absolute error bound)",
}

#: Bytes counted for the grid header with every compressed grid: shape (2 x int32), spacing,
#: origin, quantisation offset and step (6 x float64), codec id and settings (8 bytes).
HEADER_BYTES = 64

_CODEC_CLASSES = {"lerc": "LERC", "jpegls": "JPEGLS", "jpeg2k": "JPEG2K", "zstd": "ZSTD"}
_UINT16_LEVELS = 65535


def _pysz() -> Any:
    """The ``pysz`` module (SZ3); else a NeuralMapError naming the extra."""
    try:
        import pysz
    except ImportError:
        raise NeuralMapError(
            "compressed grids ('sz3') need the optional package pysz: pip install "
            "'neuralmap[codecs]' (or pip install 'pysz>=1.1')."
        ) from None
    return pysz


def _imagecodecs(codec: str) -> Any:
    """The codec library of ``codec`` (``imagecodecs``, or ``pysz`` for SZ3), checked to
    provide it; else a NeuralMapError naming the extra."""
    if codec == "sz3":
        return _pysz()
    try:
        import imagecodecs
    except ImportError:
        raise NeuralMapError(
            f"compressed grids ({codec!r}) need the optional package imagecodecs: "
            "pip install 'neuralmap[codecs]' (or pip install 'imagecodecs>=2024.1')."
        ) from None
    klass = getattr(imagecodecs, _CODEC_CLASSES[codec], None)
    if klass is None or not getattr(klass, "available", False):
        raise NeuralMapError(
            f"the installed imagecodecs {getattr(imagecodecs, '__version__', '?')} was built "
            f"without the {codec!r} codec; install a full build: pip install -U "
            "'imagecodecs>=2024.1'."
        )
    return imagecodecs


@dataclass(frozen=True)
class CompressedGrid:
    """An encoded DEM grid and what the decoder makes of it.

    Attributes:
        codec: Codec name (one of `GRID_CODECS`).
        max_error: Requested maximum error at the stored nodes, metres.
        decimation: Decimation factor (1 = full resolution).
        payload: The encoded bytes (what is stored, with `HEADER_BYTES`).
        stored_shape: ``(ny, nx)`` of the encoded grid.
        step: Height quantisation step in metres (``None`` for LERC and SZ3, which take
            floats).
        offset: Height subtracted before quantisation (the tile minimum), metres.
        error_bound: Guaranteed ``max |decoded - stored heights|`` at the stored nodes.
        tile: The decoded heights at the original tile's nodes (decimated grids
            interpolated back, bicubic), as a tile with the original geometry.
        settings: Codec settings used (e.g. ``near``, the JPEG 2000 PSNR level).
        decode_s: Wall-clock seconds the decoder took for the payload (without the
            bicubic interpolation back of decimated grids).
        source_fingerprint: `DemTile.fingerprint` of the tile that was encoded.
    """

    codec: str
    max_error: float
    decimation: int
    payload: bytes
    stored_shape: tuple[int, int]
    step: float | None
    offset: float
    error_bound: float
    tile: DemTile
    settings: dict[str, Any] = field(default_factory=dict)
    decode_s: float = 0.0
    source_fingerprint: str = ""

    @property
    def nbytes(self) -> int:
        """Stored bytes: payload plus `HEADER_BYTES`."""
        return len(self.payload) + HEADER_BYTES

    @property
    def bits_per_node(self) -> float:
        """Stored bits per node of the original (full-resolution) tile."""
        ny, nx = self.tile.shape
        return 8.0 * self.nbytes / (ny * nx)

    @property
    def name(self) -> str:
        """Short label, e.g. ``"jpegls e=1 x2"``."""
        label = f"{self.codec} e={self.max_error:g}"
        return label if self.decimation == 1 else f"{label} x{self.decimation}"

    def terrain(
        self, *, method: str = "bicubic", dtype: torch.dtype = torch.float64
    ) -> GridTerrain:
        """The decoded grid as a `GridTerrain` (interpolation ``method``).

        The terrain records the *encoded* tile's name and fingerprint: it is a map of that
        tile (the filters' tile checks accept it for the original tile's scenarios).
        """
        grid = GridTerrain(self.tile, method=method, dtype=dtype)
        if self.source_fingerprint:
            grid.tile_fingerprint = self.source_fingerprint
        return grid


def _check_max_error(max_error: float) -> float:
    try:
        value = float(max_error)
    except (TypeError, ValueError):
        value = float("nan")
    if not (math.isfinite(value) and value > 0.0):
        raise NeuralMapError(
            f"compress_grid: max_error must be a finite number of metres > 0, got "
            f"{max_error!r}. Use e.g. max_error=1.0 (lossless integer DEMs: 0.5)."
        )
    return value


def _quantise(heights: np.ndarray, step: float, offset: float, codec: str) -> np.ndarray:
    """``round((h - offset) / step)`` as uint16, or a NeuralMapError when out of range."""
    levels = np.rint((heights - offset) / step)
    top = float(levels.max())
    if top > _UINT16_LEVELS:
        span = float(heights.max() - offset)
        raise NeuralMapError(
            f"compress_grid({codec!r}): a height span of {span:.1f} m at a quantisation step "
            f"of {step:g} m needs {top:.0f} levels, more than 16 bits hold; raise max_error "
            f"to at least {span / _UINT16_LEVELS * 2:.3g} m or use codec='lerc'."
        )
    return levels.astype(np.uint16)


def _encode(
    codec: str, heights: np.ndarray, max_error: float, near: int
) -> tuple[bytes, float | None, float, float, dict[str, Any]]:
    """Encodes ``(ny, nx)`` float64 heights; returns payload, step, offset, bound, settings."""
    ic = _imagecodecs(codec)
    offset = float(heights.min())
    if codec == "lerc":
        data = heights.astype(np.float32)
        payload = bytes(ic.lerc_encode(data, level=max_error))
        rounding = float(np.abs(data.astype(np.float64) - heights).max())
        return payload, None, offset, max_error + rounding, {"maxZError": max_error}
    if codec == "sz3":
        config = ic.szConfig()
        config.errorBoundMode = ic.szErrorBoundMode.ABS
        config.absErrorBound = float(max_error)
        compressed, _ = ic.sz.compress(np.ascontiguousarray(heights, dtype=np.float64), config)
        return bytes(compressed), None, offset, max_error, {"absErrorBound": max_error}
    if codec == "jpegls":
        step = 2.0 * max_error / (2 * near + 1)
        levels = _quantise(heights, step, offset, codec)
        payload = bytes(ic.jpegls_encode(levels, level=near))
        return payload, step, offset, max_error, {"near": near}
    if codec == "zstd":
        step = 2.0 * max_error
        levels = _quantise(heights, step, offset, codec).astype(np.int32) - 32768
        signed = levels.astype(np.int16)
        diffs = np.diff(signed, axis=1, prepend=np.int16(0))  # int16 wrap-around is exact
        payload = bytes(ic.zstd_encode(np.ascontiguousarray(diffs).tobytes(), level=19))
        return payload, step, offset, max_error, {"predictor": "row difference", "level": 19}
    # jpeg2k: not error-bounded; bisect the PSNR target for the smallest conforming stream.
    step = max_error / 8.0
    levels = _quantise(heights, step, offset, codec)

    def decoded_error(stream: bytes) -> float:
        back = np.asarray(ic.jpeg2k_decode(stream), dtype=np.float64) * step + offset
        return float(np.abs(back - heights).max())

    best = bytes(ic.jpeg2k_encode(levels, level=0, reversible=True))
    best_level: float | None = None
    lo, hi = 20.0, 160.0
    for _ in range(14):
        mid = 0.5 * (lo + hi)
        stream = bytes(ic.jpeg2k_encode(levels, level=mid))
        if decoded_error(stream) <= max_error:
            hi = mid
            if len(stream) < len(best):
                best, best_level = stream, mid
        else:
            lo = mid
    settings = {"psnr_level": best_level, "reversible": best_level is None}
    return best, step, offset, max_error, settings


def _decode(
    codec: str, payload: bytes, shape: tuple[int, int], step: float | None, offset: float
) -> np.ndarray:
    """Decodes a payload back to ``(ny, nx)`` float64 heights."""
    ic = _imagecodecs(codec)
    if codec == "lerc":
        return np.asarray(ic.lerc_decode(payload), dtype=np.float64)
    if codec == "sz3":
        data, _ = ic.sz.decompress(np.frombuffer(payload, dtype=np.uint8), np.float64, shape)
        return np.asarray(data, dtype=np.float64).reshape(shape)
    assert step is not None
    if codec == "jpegls":
        levels = np.asarray(ic.jpegls_decode(payload), dtype=np.float64)
    elif codec == "jpeg2k":
        levels = np.asarray(ic.jpeg2k_decode(payload), dtype=np.float64)
    else:
        diffs = np.frombuffer(ic.zstd_decode(payload), dtype=np.int16).reshape(shape)
        signed = np.cumsum(diffs, axis=1, dtype=np.int16)  # wraps back exactly
        levels = signed.astype(np.float64) + 32768.0
    return levels * step + offset


def _resample(tile: DemTile, heights: np.ndarray, decimation: int) -> tuple[DemTile, np.ndarray]:
    """Bicubic resampling to about ``decimation`` times the spacing over the same extent."""
    ny, nx = tile.shape
    my = max(1, math.ceil((ny - 1) / decimation))
    mx = max(1, math.ceil((nx - 1) / decimation))
    (x0, y0), (dx, dy) = tile.origin, tile.spacing
    spacing = ((nx - 1) * dx / mx, (ny - 1) * dy / my)
    full = DemTile(heights=heights, spacing=tile.spacing, origin=tile.origin, name=tile.name)
    grid = GridTerrain(full, method="bicubic")
    xs = x0 + np.arange(mx + 1) * spacing[0]
    ys = y0 + np.arange(my + 1) * spacing[1]
    xx, yy = np.meshgrid(xs, ys)
    xy = torch.from_numpy(np.stack([xx, yy], axis=-1))
    coarse = grid.height_and_slope(xy)[0].numpy()
    coarse_tile = DemTile(heights=coarse, spacing=spacing, origin=tile.origin, name=tile.name)
    return coarse_tile, coarse


def compress_grid(
    tile: DemTile,
    *,
    codec: str,
    max_error: float,
    decimation: int = 1,
    near: int = 2,
) -> CompressedGrid:
    """Encodes a DEM tile with an error-bounded raster codec and decodes it back.

    Voids are filled with the nearest valid node first (as `GridTerrain` does).

    Args:
        tile: The DEM tile.
        codec: One of `GRID_CODECS` (see the module docstring for each bound).
        max_error: Maximum error at the stored nodes, metres (> 0).
        decimation: Integer factor ``>= 1``; ``> 1`` stores a resampled coarser grid and
            interpolates the decoded one back to the tile's nodes (bicubic).
        near: JPEG-LS ``NEAR`` parameter (``>= 0``; only for ``"jpegls"``).

    Returns:
        The `CompressedGrid` (payload, stored bytes, decoded tile).

    Raises:
        NeuralMapError: Unknown codec, ``max_error <= 0``, a bad ``decimation`` or
            ``near``, a height span too wide for 16-bit levels, or imagecodecs missing
            (the message names the ``codecs`` extra).
    """
    if codec not in GRID_CODECS:
        raise NeuralMapError(
            f"compress_grid: unknown codec {codec!r}; choose one of {', '.join(GRID_CODECS)}."
        )
    bound = _check_max_error(max_error)
    if not (isinstance(decimation, int | np.integer) and decimation >= 1):
        raise NeuralMapError(
            f"compress_grid: decimation must be an integer >= 1, got {decimation!r}."
        )
    if not (isinstance(near, int | np.integer) and near >= 0):
        raise NeuralMapError(f"compress_grid: near must be an integer >= 0, got {near!r}.")
    if not isinstance(tile, DemTile):
        raise NeuralMapError(
            f"compress_grid: tile must be a neuralmap.dem.DemTile, got {type(tile).__name__}."
        )
    _imagecodecs(codec)
    heights = fill_voids_nearest(tile.heights, tile.spacing)
    if decimation > 1:
        coarse_tile, stored = _resample(tile, heights, int(decimation))
    else:
        coarse_tile, stored = tile, heights
    payload, step, offset, error_bound, settings = _encode(codec, stored, bound, int(near))
    started = time.perf_counter()
    decoded = _decode(codec, payload, stored.shape, step, offset)
    decode_s = time.perf_counter() - started
    if decimation > 1:
        back = DemTile(
            heights=decoded,
            spacing=coarse_tile.spacing,
            origin=coarse_tile.origin,
            name=tile.name,
        )
        xy = torch.from_numpy(tile.node_xy())
        decoded = GridTerrain(back, method="bicubic").height_and_slope(xy)[0].numpy()
    out_tile = DemTile(
        heights=decoded,
        spacing=tile.spacing,
        origin=tile.origin,
        name=tile.name,
        geo=tile.geo,
        source=f"{tile.source} decoded from {codec} (max_error={bound:g} m, x{decimation})",
        meta={"codec": codec, "max_error": bound, "decimation": int(decimation)},
    )
    return CompressedGrid(
        codec=codec,
        max_error=bound,
        decimation=int(decimation),
        payload=payload,
        stored_shape=tuple(int(n) for n in stored.shape),  # type: ignore[arg-type]
        step=step,
        offset=offset,
        error_bound=error_bound,
        tile=out_tile,
        settings=settings,
        decode_s=decode_s,
        source_fingerprint=tile.fingerprint(),
    )
