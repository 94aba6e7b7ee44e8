"""The latent-map file: header, decoder weights, range-coded latents, CRC32.

Layout (all integers little-endian; sizes in bytes)::

    offset  size   field
    0       8      magic b"NMLATENT"
    8       2      format version (uint16): 2, 3 with the context entropy model, 4 with
                   per-zone steps and scales (`.zones`)
    10      4      header length J (uint32)
    14      J      header, zlib-compressed UTF-8 JSON (format 1: uncompressed): {"tile_info": DemTile.describe(), "levels": L,
                   "hidden": H, "basis": "pyramid" | "wavelet", "wavelet": "cdf97",
                   "ranges": [[min, max] per latent array], "metrics": {...},
                   format 3: "entropy": "context", "context_hidden": H_c;
                   format 4: "regions": R (the zone grid side), "region_scales":
                   [b_step, b_scale] (the zone codes' Laplace scales)}
    ..      8 S    float32 quantisation steps Delta_b, Laplace scales b_b (S latent arrays)
    ..      4 C    float32 feature scales (C synthesis channels)
    ..      4(C+1) float32 linear synthesis weights w and bias b_0
    ..      2 H(C+2) float16 MLP weights A (H x C, row-major), biases a, output weights v
    ..      2 P    format 3 only: float16 context-MLP weights (P = `parameter_count(H_c)`)
    ..      4      format 4 only: number of zone-code words V (uint32)
    ..      4 V    format 4 only: range-coded zone codes, the (G, R R) step codes then
                   the scale codes, Laplace(0, b_step / b_scale) on [-32, 32] (`.zones`)
    ..      4      number of range-coder words W (uint32)
    ..      4 W    uint32 words of the range coder (constriction): format 2, latent arrays
                   in storage order, each in C order with its Laplace(0, b) on [min, max];
                   format 3, subbands in decoding order, each in wavefront order with the
                   context model's Laplace(mu, b) per symbol (`.context_model`); format 4
                   as 2 or 3 with the zone scales ``b_s 2^(c_r / 4)`` (factorized) or
                   ``log b`` offsets ``(c_r / 4) ln 2`` (context), and the decoded latents
                   ``q Delta_s 2^(k_r / 4)``
    end-4   4      CRC32 (zlib) of every byte before it

The basis (`basis`) fixes ``S``, ``C`` and the latent
shapes from the tile shape and ``L``: the pyramid ``S = C = L`` levels (format 1, which
had no ``basis`` key, reads as the pyramid), the wavelet ``S = 3 L + 1`` subbands, ``C = 1``. The file on disk is the map's
stored size; `read_latent_map` checks the magic, version, length and CRC before
decoding, so a truncated or corrupted file is refused with a clear error.

The header keys of format 4 are ``"regions"`` and ``"region_scales"``, as the files written
before the zones got their name have them: `ZONE_KEY` and `ZONE_SCALES_KEY` map them to and
from the zones (`.zones.ZoneCodes`), so every file written before reads as it did.
"""

from __future__ import annotations

import json
import os
import struct
import zlib
from pathlib import Path
from typing import Any

import numpy as np

from neuralmap.exceptions import NeuralMapError
from neuralmap.io import atomic_write_bytes
from neuralmap.terrain.latent.basis import basis_from_header
from neuralmap.terrain.latent.context_model import (
    CodingModel,
    decode_context,
    encode_context,
    parameter_count,
)
from neuralmap.terrain.latent.entropy import (
    decode_levels,
    decode_located,
    encode_levels,
    encode_located,
    symbol_range,
)
from neuralmap.terrain.latent.map import LatentTerrainMap
from neuralmap.terrain.latent.zones import (
    ZoneCodes,
    band_groups,
    code_scales,
    decode_codes,
    encode_codes,
)

MAGIC = b"NMLATENT"
FORMAT_VERSION = 4
#: Version written for factorized maps (readers before the context model read them).
FACTORIZED_VERSION = 2
#: Version written for context maps without zones.
CONTEXT_VERSION = 3
#: Format-4 header key of the zone grid side ``R`` (its name in every file written).
ZONE_KEY = "regions"
#: Format-4 header key of the zone codes' two Laplace scales (step codes, scale codes).
ZONE_SCALES_KEY = "region_scales"
_FIXED = len(MAGIC) + 2 + 4


def is_latent_file(path: str | os.PathLike[str]) -> bool:
    """Whether ``path`` is a file that starts with the latent-map magic bytes."""
    try:
        with open(path, "rb") as handle:
            return handle.read(len(MAGIC)) == MAGIC
    except (OSError, TypeError):
        return False


def coding_model(latent_map: LatentTerrainMap, symbols: list[np.ndarray] | None = None,
                 zones: ZoneCodes | None = None) -> CodingModel:
    """The context model of a context map in its coding form (zone offsets included)."""
    assert latent_map.context is not None
    syms = latent_map.symbols if symbols is None else symbols
    shapes = [tuple(s.shape) for s in syms]
    zones = latent_map.zones if zones is None else zones
    stored = np.asarray(latent_map.context, "<f2").astype(np.float32)
    offsets = None if zones is None else zones.log_scale_offsets(shapes)
    return CodingModel(stored, latent_map.context_hidden, shapes, latent_map.levels,
                       latent_map.steps, latent_map.scales, offsets)


def symbol_models(latent_map: LatentTerrainMap, symbols: list[np.ndarray] | None = None,
                  zones: ZoneCodes | None = None) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per latent array ``(mu, b)`` (flat, C order) of every symbol under the map's entropy
    model as the coder uses it: factorized ``(0, b_s)`` (times the zone scales), or the
    context model's (`.context_model.CodingModel.all_parameters`)."""
    syms = latent_map.symbols if symbols is None else symbols
    zones = latent_map.zones if zones is None else zones
    if latent_map.context is not None:
        return coding_model(latent_map, syms, zones).all_parameters(syms)
    shapes = [tuple(s.shape) for s in syms]
    maps = (zones.scale_maps(shapes) if zones is not None
            else [np.ones(sh) for sh in shapes])
    return [(np.zeros(int(np.prod(sh))), float(b) * m.ravel())
            for sh, b, m in zip(shapes, latent_map.scales.astype(np.float64), maps, strict=True)]


def encode_latent_map(latent_map: LatentTerrainMap) -> bytes:
    """The file bytes of a latent map (see the module docstring for the layout)."""
    levels, hidden = latent_map.levels, latent_map.hidden
    ranges = [list(symbol_range(s)) for s in latent_map.symbols]
    header = {
        # unset fields (None) are left out: every reader takes them with .get
        "tile_info": {k: v for k, v in latent_map.tile_info.items() if v is not None},
        "levels": levels,
        "hidden": hidden,
        **latent_map.basis.describe(),
        "ranges": ranges,
        "metrics": latent_map.metrics,
    }
    context, zones = latent_map.context, latent_map.zones
    if context is not None:
        header["entropy"] = "context"
        header["context_hidden"] = latent_map.context_hidden
    zone_bytes = b""
    if zones is not None:
        scales = code_scales(zones)
        header[ZONE_KEY] = zones.zones
        header[ZONE_SCALES_KEY] = list(scales)
        zone_words = encode_codes(zones, scales)
        zone_bytes = struct.pack("<I", zone_words.size) + zone_words.astype("<u4").tobytes()
    header_bytes = zlib.compress(
        json.dumps(header, separators=(",", ":"), allow_nan=False).encode(), 9)
    synth = latent_map.synthesis_vector
    channels = latent_map.basis.channels
    linear = synth[: channels + 1]
    mlp = synth[channels + 1 :]
    context_bytes = b""
    tuples = [(int(lo), int(hi)) for lo, hi in ranges]
    if context is None and zones is None:
        words = encode_levels(latent_map.symbols, [float(b) for b in latent_map.scales])
    elif context is None:
        words = encode_located(latent_map.symbols, symbol_models(latent_map), tuples)
    else:
        context_bytes = np.asarray(context, "<f2").tobytes()
        words = encode_context(coding_model(latent_map), latent_map.symbols, tuples)
    version = (FORMAT_VERSION if zones is not None
               else FACTORIZED_VERSION if context is None else CONTEXT_VERSION)
    parts = [
        MAGIC,
        struct.pack("<HI", version, len(header_bytes)),
        header_bytes,
        np.concatenate([latent_map.steps, latent_map.scales, latent_map.feature_scale])
        .astype("<f4").tobytes(),
        np.asarray(linear, "<f4").tobytes(),
        np.asarray(mlp, "<f2").tobytes(),
        context_bytes,
        zone_bytes,
        struct.pack("<I", words.size),
        words.astype("<u4").tobytes(),
    ]
    body = b"".join(parts)
    return body + struct.pack("<I", zlib.crc32(body))


def stored_latent_map(latent_map: LatentTerrainMap) -> LatentTerrainMap:
    """The map exactly as the file stores it (MLP weights rounded to float16)."""
    return decode_latent_map(encode_latent_map(latent_map), where="<memory>")


def write_latent_map(latent_map: LatentTerrainMap, path: str | os.PathLike[str]) -> Path:
    """Writes the map's bitstream atomically; returns the path."""
    return atomic_write_bytes(Path(path), encode_latent_map(latent_map))


def _damaged(where: str, what: str) -> NeuralMapError:
    return NeuralMapError(
        f"{where}: latent map file is damaged ({what}). Export it again with "
        "`python train.py latent --config configs/latent_map.yaml`."
    )


def decode_latent_map(data: bytes, *, where: str) -> LatentTerrainMap:
    """Decodes file bytes into a `LatentTerrainMap` (checks magic, CRC, lengths).

    Raises:
        NeuralMapError: Not a latent map, newer format, checksum mismatch (truncated or
            corrupted), or inconsistent contents.
    """
    if data[: len(MAGIC)] != MAGIC:
        raise NeuralMapError(f"{where}: not a latent map file (no {MAGIC!r} magic bytes).")
    if len(data) < _FIXED + 4:
        raise _damaged(where, f"truncated: {len(data)} bytes")
    body, (crc,) = data[:-4], struct.unpack("<I", data[-4:])
    if zlib.crc32(body) != crc:
        raise NeuralMapError(
            f"{where}: checksum mismatch (CRC32 {zlib.crc32(body):08x} != stored {crc:08x}): "
            "the latent map file is truncated or corrupted. Copy it again or re-export it "
            "with `python train.py latent --config configs/latent_map.yaml`."
        )
    version, header_len = struct.unpack("<HI", body[len(MAGIC) : _FIXED])
    if version > FORMAT_VERSION:
        raise NeuralMapError(
            f"{where}: latent map format version {version} is newer than this neuralmap "
            f"reads ({FORMAT_VERSION}); upgrade neuralmap."
        )
    try:
        pos = _FIXED
        raw = body[pos : pos + header_len]
        header: dict[str, Any] = json.loads((zlib.decompress(raw) if version >= 2 else raw).decode())
        pos += header_len
        hidden = int(header["hidden"])
        info = header["tile_info"]
        basis = basis_from_header(header, tuple(info["shape"]))  # type: ignore[arg-type]
        shapes = basis.shapes(tuple(info["shape"]))  # type: ignore[arg-type]
        count, channels = len(shapes), basis.channels
        floats = np.frombuffer(body, "<f4", 2 * count + channels, pos).astype(np.float32)
        pos += 4 * (2 * count + channels)
        linear = np.frombuffer(body, "<f4", channels + 1, pos).astype(np.float32)
        pos += 4 * (channels + 1)
        n_mlp = hidden * (channels + 2)
        mlp = np.frombuffer(body, "<f2", n_mlp, pos).astype(np.float32)
        pos += 2 * n_mlp
        context, context_hidden = None, 0
        if version >= 3 and header.get("entropy") == "context":
            context_hidden = int(header["context_hidden"])
            n_ctx = parameter_count(context_hidden)
            context = np.frombuffer(body, "<f2", n_ctx, pos).astype(np.float32)
            pos += 2 * n_ctx
        zones = None
        if version >= 4 and header.get(ZONE_KEY):
            (n_zone,) = struct.unpack("<I", body[pos : pos + 4])
            pos += 4
            zone_words = np.frombuffer(body, "<u4", n_zone, pos)
            pos += 4 * n_zone
            code_sc = header[ZONE_SCALES_KEY]
            zones = decode_codes(zone_words, int(header[ZONE_KEY]),
                                   band_groups(basis.name, count),
                                   (float(code_sc[0]), float(code_sc[1])), shapes)
        (n_words,) = struct.unpack("<I", body[pos : pos + 4])
        pos += 4
        words = np.frombuffer(body, "<u4", n_words, pos)
        pos += 4 * n_words
        if pos != len(body):
            raise ValueError(f"{len(body) - pos} trailing bytes")
        ranges = [(int(lo), int(hi)) for lo, hi in header["ranges"]]
        steps, scales, feature_scale = floats[:count], floats[count : 2 * count], floats[2 * count :]
        if context is None and zones is None:
            symbols = decode_levels(words, shapes, [float(b) for b in scales], ranges)
        elif context is None:
            maps = zones.scale_maps(shapes)
            params = [(np.zeros(int(np.prod(sh))), float(b) * m.ravel())
                      for sh, b, m in zip(shapes, scales.astype(np.float64), maps, strict=True)]
            symbols = decode_located(words, shapes, params, ranges)
        else:
            offsets = None if zones is None else zones.log_scale_offsets(shapes)
            model = CodingModel(context, context_hidden, shapes, basis.levels, steps, scales,
                                offsets)
            symbols = decode_context(model, words, ranges)
    except NeuralMapError:
        raise
    except (KeyError, TypeError, ValueError, IndexError, struct.error,
            UnicodeDecodeError, zlib.error) as exc:
        raise _damaged(where, f"{type(exc).__name__}: {exc}") from None
    return LatentTerrainMap(
        symbols, steps, scales, np.concatenate([linear, mlp]), feature_scale,
        hidden=hidden, tile_info=info, metrics=header.get("metrics") or {}, basis=basis,
        context=context, context_hidden=context_hidden, zones=zones,
    )


def read_latent_map(path: str | os.PathLike[str]) -> LatentTerrainMap:
    """Loads a latent map file written by `write_latent_map` (eval mode).

    Raises:
        NeuralMapError: Missing file, or see `decode_latent_map`.
    """
    path = Path(path)
    if not path.is_file():
        raise NeuralMapError(f"latent map file not found: {path}.")
    latent_map = decode_latent_map(path.read_bytes(), where=str(path))
    latent_map.eval()
    return latent_map
