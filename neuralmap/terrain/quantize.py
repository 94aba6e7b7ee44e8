"""Post-training weight quantisation of neural maps, for compact map files.

Only the network parameters (weights and biases of every block MLP) are quantised; the
small buffers (Fourier frequencies, block geometry, per-block height mean and standard
deviation) stay float32, since a height mean in fp16 would already be off by 0.25 m at
500 m. Schemes:

* ``"fp16"``: IEEE half precision; ``|w - w_q| <= 2^-11 |w|`` (normal range).
* ``"int8_tensor"``: symmetric int8 with one float32 scale per tensor,
  ``s = max |w| / 127``, ``w_q = s round(w / s)``; ``|w - w_q| <= s / 2``.
* ``"int8_block"``: one scale per block (the leading axis of every parameter).
* ``"int8_channel"``: one scale per block and output unit (the last axis of a weight
  matrix ``(B, d_in, d_out)``); vectors ``(B, d)`` get one scale per block.

The stored form is a dict ``{"scheme": ..., "tensors": {name: {"values": ...,
"scale": ...}}}`` written into the map payload by `neuralmap.terrain.export.save_map`
and read back (dequantised to float32) by `neuralmap.terrain.export.load_map`.
"""

from __future__ import annotations

import copy
from typing import Any

import torch
from torch import nn

from neuralmap.exceptions import NeuralMapError

#: Every scheme `quantize_state` accepts.
QUANT_SCHEMES = ("fp16", "int8_tensor", "int8_block", "int8_channel")

_INT8_MAX = 127


def check_scheme(scheme: str) -> str:
    """Returns ``scheme`` or raises a NeuralMapError listing the valid ones."""
    if scheme not in QUANT_SCHEMES:
        raise NeuralMapError(
            f"unknown quantisation scheme {scheme!r}; choose one of {', '.join(QUANT_SCHEMES)}."
        )
    return scheme


def _reduce_dims(tensor: torch.Tensor, scheme: str) -> tuple[int, ...]:
    """Axes over which one int8 scale is shared."""
    if scheme == "int8_tensor" or tensor.ndim < 2:
        return tuple(range(tensor.ndim))
    if scheme == "int8_channel" and tensor.ndim >= 3:
        return tuple(range(1, tensor.ndim - 1))
    return tuple(range(1, tensor.ndim))


def int8_scale(tensor: torch.Tensor, scheme: str) -> torch.Tensor:
    """Symmetric int8 scale ``max |w| / 127`` per group (1 where a group is all zero).

    Args:
        tensor: A float parameter.
        scheme: ``"int8_tensor"``, ``"int8_block"`` or ``"int8_channel"``.

    Returns:
        float32 scale broadcastable to ``tensor`` (kept dimensions of size 1).
    """
    dims = _reduce_dims(tensor, scheme)
    amax = tensor.detach().abs().to(torch.float32)
    if dims:
        amax = amax.amax(dim=dims, keepdim=True)
    scale = amax / _INT8_MAX
    return torch.where(scale > 0, scale, torch.ones_like(scale))


def quantize_tensor(tensor: torch.Tensor, scheme: str) -> dict[str, torch.Tensor]:
    """Quantises one tensor; returns ``{"values": ...}`` plus ``"scale"`` for int8 schemes."""
    check_scheme(scheme)
    data = tensor.detach().cpu()
    if scheme == "fp16":
        return {"values": data.to(torch.float16)}
    scale = int8_scale(data, scheme)
    values = torch.round(data.to(torch.float32) / scale).clamp_(-_INT8_MAX, _INT8_MAX)
    return {"values": values.to(torch.int8), "scale": scale}


def dequantize_tensor(entry: Any, *, name: str, scheme: str) -> torch.Tensor:
    """float32 tensor of one stored entry.

    Raises:
        NeuralMapError: A missing or inconsistent ``values`` / ``scale``.
    """
    if not isinstance(entry, dict) or not isinstance(entry.get("values"), torch.Tensor):
        raise NeuralMapError(
            f"quantised map: tensor {name!r} has no stored values; the file is damaged. "
            "Export the map again with save_map(..., quantization=...)."
        )
    values = entry["values"]
    if scheme == "fp16":
        return values.to(torch.float32)
    scale = entry.get("scale")
    if not isinstance(scale, torch.Tensor):
        raise NeuralMapError(
            f"quantised map ({scheme}): tensor {name!r} has int8 values but no 'scale'; the "
            "file is incomplete or damaged. Export the map again with "
            "save_map(..., quantization=...)."
        )
    if values.dtype != torch.int8:
        raise NeuralMapError(
            f"quantised map ({scheme}): tensor {name!r} holds {values.dtype}, expected int8."
        )
    try:
        return values.to(torch.float32) * scale.to(torch.float32)
    except RuntimeError:
        raise NeuralMapError(
            f"quantised map ({scheme}): scale of {name!r} has shape {tuple(scale.shape)}, "
            f"which does not broadcast to the values {tuple(values.shape)}."
        ) from None


def quantize_state(model: nn.Module, scheme: str) -> dict[str, Any]:
    """Quantises every parameter of ``model``.

    Args:
        model: The neural map (its ``named_parameters`` are quantised, buffers are not).
        scheme: One of `QUANT_SCHEMES`.

    Returns:
        ``{"scheme": scheme, "tensors": {name: {"values", ["scale"]}}}``.
    """
    check_scheme(scheme)
    tensors = {name: quantize_tensor(p, scheme) for name, p in model.named_parameters()}
    return {"scheme": scheme, "tensors": tensors}


def dequantize_state(quantized: Any) -> dict[str, torch.Tensor]:
    """float32 state-dict entries of a stored quantisation dict.

    Raises:
        NeuralMapError: Unknown scheme, or a tensor with missing values or scales.
    """
    if not isinstance(quantized, dict) or not isinstance(quantized.get("tensors"), dict):
        raise NeuralMapError(
            "quantised map: the 'quantization' entry has no 'tensors' dict; the file is "
            "damaged. Export the map again with save_map(..., quantization=...)."
        )
    scheme = check_scheme(quantized.get("scheme"))  # type: ignore[arg-type]
    return {
        name: dequantize_tensor(entry, name=name, scheme=scheme)
        for name, entry in quantized["tensors"].items()
    }


def quantize_model(model: nn.Module, scheme: str) -> nn.Module:
    """A copy of ``model`` whose parameters are the dequantised ``scheme`` values.

    This is exactly the model `neuralmap.terrain.export.load_map` returns for a map
    exported with ``quantization=scheme``, without the file round trip.
    """
    out = copy.deepcopy(model)
    state = dequantize_state(quantize_state(model, scheme))
    with torch.no_grad():
        for name, param in out.named_parameters():
            param.copy_(state[name].to(param.dtype))
    return out.eval()
