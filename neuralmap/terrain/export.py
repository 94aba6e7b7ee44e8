"""Export and load neural maps as plain ``nn.Module`` files (no Lightning needed)."""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.io import atomic_write_torch
from neuralmap.terrain.blockwise import BlockwiseTerrainNet
from neuralmap.terrain.quantize import check_scheme, dequantize_state, quantize_state
from neuralmap.terrain.sharded import ShardedTerrainMap, is_sharded_index

FORMAT = "neuralmap-terrain-map"
#: Version 2 adds the optional ``quantization`` entry; unquantised files stay version 1.
FORMAT_VERSION = 2
_CLASSES: dict[str, type[BlockwiseTerrainNet]] = {"BlockwiseTerrainNet": BlockwiseTerrainNet}


def save_map(
    model: BlockwiseTerrainNet,
    path: str | os.PathLike[str],
    *,
    metrics: dict[str, Any] | None = None,
    extra: dict[str, Any] | None = None,
    quantization: str | None = None,
) -> Path:
    """Writes a neural map atomically (temporary file, then rename).

    The file records the model class, its constructor config (including the tile it was
    fitted to: name, fingerprint, extent), the float state dict and optional metrics.
    With ``quantization`` the parameters are stored in that compact form instead
    (`neuralmap.terrain.quantize`; buffers stay float32) and `load_map`
    dequantises them; the file size is then the map's stored size.

    Args:
        model: The fitted network.
        path: Destination, conventionally ``runs/<experiment>/<version>/neural_map.pt``.
        metrics: Final fit metrics (JSON-like), stored for reports.
        extra: Any further JSON-like information (e.g. the training config).
        quantization: ``None`` (float32) or a scheme of
            `neuralmap.terrain.quantize.QUANT_SCHEMES` (``"fp16"``, ``"int8_tensor"``,
            ``"int8_block"``, ``"int8_channel"``).

    Returns:
        The path written.

    Raises:
        NeuralMapError: Unknown quantisation scheme.
    """
    path = Path(path)
    # clone: a parameter that is a view (e.g. a bias sliced from a larger init tensor) would
    # otherwise drag its whole storage into the file.
    state = {k: v.detach().cpu().clone() for k, v in model.state_dict().items()}
    payload: dict[str, Any] = {
        "format": FORMAT,
        "format_version": 1,
        "class": type(model).__name__,
        "config": model.config,
        "state_dict": state,
        "metrics": dict(metrics or {}),
        "extra": dict(extra or {}),
    }
    if quantization is not None:
        quantized = quantize_state(model, check_scheme(quantization))
        for name in quantized["tensors"]:
            state.pop(name, None)
        payload["quantization"] = quantized
        payload["format_version"] = FORMAT_VERSION
    return atomic_write_torch(path, payload)


def load_map_payload(path: str | os.PathLike[str]) -> dict[str, Any]:
    """Reads and checks an exported map file; returns its raw payload dict.

    Raises:
        NeuralMapError: If the file is missing or is not a neuralmap export.
    """
    if not isinstance(path, (str, os.PathLike)):
        raise NeuralMapError(
            f"load_map: path must be the path of a neural_map.pt file, got "
            f"{type(path).__name__} {path!r}. `python train.py` prints the path on its last line."
        )
    path = Path(path)
    if not path.is_file():
        raise NeuralMapError(
            f"map file not found: {path}. Train one with `python train.py` (it prints the "
            "path of neural_map.pt on its last line) or pass an existing file."
        )
    try:
        payload = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # noqa: BLE001 - any unpickling failure means "not our format"
        raise NeuralMapError(
            f"{path} is not a neuralmap map export (could not be read as one: "
            f"{type(exc).__name__}). Use the neural_map.pt written by `python train.py`."
        ) from None
    if not isinstance(payload, dict) or payload.get("format") != FORMAT:
        raise NeuralMapError(
            f"{path} is not a neuralmap map export (no '{FORMAT}' header); a Lightning "
            "checkpoint (.ckpt) or another torch file is not a map. Use the neural_map.pt "
            "written by `python train.py`."
        )
    if payload.get("format_version", 0) > FORMAT_VERSION:
        raise NeuralMapError(
            f"{path} was written by a newer neuralmap (format version "
            f"{payload['format_version']} > {FORMAT_VERSION}); upgrade neuralmap."
        )
    if payload.get("class") not in _CLASSES:
        raise NeuralMapError(
            f"{path}: unknown map class {payload.get('class')!r}; known: {sorted(_CLASSES)}."
        )
    return payload


def _damaged(path: str | os.PathLike[str], payload: dict[str, Any], exc: Exception) -> NeuralMapError:
    """The error for a file whose header is ours but whose config or weights do not load."""
    first = str(exc).splitlines()[0] if str(exc) else ""
    return NeuralMapError(
        f"{path}: the header says neuralmap map, but its config or weights do not build "
        f"a {payload.get('class')} ({type(exc).__name__}: {first}). The file is damaged "
        "or was edited; export it again with `python train.py`."
    )


def load_map(path: str | os.PathLike[str]) -> BlockwiseTerrainNet:
    """Loads an exported neural map as a plain ``nn.Module`` in eval mode.

    Args:
        path: A file written by `save_map`, the ``map_index.json`` (or its
            folder) of a sharded region map: then a
            `ShardedTerrainMap` that loads shards lazily,
            or a latent-grid map bitstream (recognised by its magic bytes): then a
            `LatentTerrainMap`, or a latent tileset's ``latent_tileset.json`` (or its
            folder): then a `LatentTileset`
            that decodes its tiles lazily.

    Returns:
        The terrain model; ``.tile_name``, ``.tile_fingerprint``, ``.extent`` and
        ``.tile_info`` say which tile it was fitted to, ``.metrics`` holds the stored metrics.

    Raises:
        NeuralMapError: If the file is missing, not a neuralmap export, its stored config
            or weights do not build the model (a damaged or hand-edited file), a
            quantised file lacks values or scales, or a weight or scale is not finite.
    """
    from neuralmap.terrain.latent.tileset_index import is_tileset_index

    if isinstance(path, (str, os.PathLike)) and is_tileset_index(path):
        from neuralmap.terrain.latent.tileset import LatentTileset

        return LatentTileset(path)  # type: ignore[return-value]
    if isinstance(path, (str, os.PathLike)) and is_sharded_index(path):
        index = Path(path)
        return ShardedTerrainMap(  # type: ignore[return-value]
            index / "map_index.json" if index.is_dir() else index, load_shard=load_map_file)
    from neuralmap.terrain.latent.bitstream import is_latent_file, read_latent_map

    if isinstance(path, (str, os.PathLike)) and is_latent_file(path):  # magic b"NMLATENT"
        return read_latent_map(path)  # type: ignore[return-value]
    return load_map_file(path)


def load_map_file(path: str | os.PathLike[str]) -> BlockwiseTerrainNet:
    """Loads one map file written by `save_map` (no sharded-index dispatch).

    Raises:
        NeuralMapError: As `load_map`.
    """
    payload = load_map_payload(path)
    state = payload.get("state_dict")
    state = dict(state) if isinstance(state, dict) else state
    if "quantization" in payload and isinstance(state, dict):
        state.update(dequantize_state(payload["quantization"]))
    try:
        config = dict(payload["config"])
        model = _CLASSES[payload["class"]](**config)
    except NeuralMapError as exc:
        raise NeuralMapError(f"{path}: the stored map config is invalid ({exc}).") from None
    except (KeyError, TypeError, ValueError, RuntimeError, AttributeError, IndexError) as exc:
        raise _damaged(path, payload, exc) from None
    missing = sorted(set(model.state_dict()) - set(state)) if isinstance(state, dict) else []
    if missing:
        raise NeuralMapError(
            f"{path}: the map file lacks the tensor(s) {', '.join(missing)}; it is incomplete "
            "or damaged. Export the map again with save_map."
        )
    try:
        model.load_state_dict(state)  # type: ignore[arg-type]
    except (KeyError, TypeError, ValueError, RuntimeError, AttributeError, IndexError) as exc:
        raise _damaged(path, payload, exc) from None
    _check_finite(path, model)
    model.metrics = payload.get("metrics", {})  # type: ignore[assignment]
    model.eval()
    return model


def _check_finite(path: str | os.PathLike[str], model: torch.nn.Module) -> None:
    """Refuses a map whose weights, scales or buffers hold NaN or infinity.

    Such a map would make every filter run fail numerically, which a study would otherwise
    count as "no divergence".
    """
    bad = [name for name, value in model.state_dict().items()
           if value.is_floating_point() and not bool(torch.isfinite(value).all())]
    if bad:
        shown = ", ".join(bad[:4]) + (f" and {len(bad) - 4} more" if len(bad) > 4 else "")
        raise NeuralMapError(
            f"{path}: the map holds non-finite values (NaN or infinity) in {shown}; the fit "
            "diverged or the file was damaged. Train the map again (a lower --model.lr "
            "usually helps) and export it anew."
        )
