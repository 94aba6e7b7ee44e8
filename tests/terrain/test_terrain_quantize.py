"""Quantised neural maps: export -> load_map round trip within the quantisation bound."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest
import torch

from neuralmap.dem.synthetic import synthetic_tile
from neuralmap.dem.tile import DemTile
from neuralmap.exceptions import NeuralMapError
from neuralmap.terrain.blockwise import BlockwiseTerrainNet
from neuralmap.terrain.export import load_map, load_map_payload, save_map
from neuralmap.terrain.quantize import QUANT_SCHEMES, quantize_model


@pytest.fixture(scope="module")
def tile() -> DemTile:
    return synthetic_tile((49, 61), 30.0, seed=1, relief=200.0, name="synth")


@pytest.fixture(scope="module")
def net(tile: DemTile) -> BlockwiseTerrainNet:
    torch.manual_seed(0)
    model = BlockwiseTerrainNet.from_tile(tile, block_nodes=20, n_frequencies=4, hidden=8)
    with torch.no_grad():  # spread the weights like a trained net (not the uniform init)
        for p in model.parameters():
            p.add_(0.3 * torch.randn(p.shape, generator=torch.Generator().manual_seed(p.numel())))
    return model.eval()


def _reference_dequantise(w: np.ndarray, scheme: str) -> tuple[np.ndarray, np.ndarray]:
    """Plain NumPy symmetric int8 / fp16 quantisation: (dequantised, elementwise bound)."""
    if scheme == "fp16":
        back = w.astype(np.float16).astype(np.float64)
        return back, np.abs(w) * 2.0**-11 + 2.0**-25
    if scheme == "int8_tensor" or w.ndim < 2:
        axes: tuple[int, ...] = tuple(range(w.ndim))
    elif scheme == "int8_channel" and w.ndim == 3:
        axes = (1,)
    else:
        axes = tuple(range(1, w.ndim))
    scale = np.abs(w).max(axis=axes, keepdims=True) / 127.0
    scale = np.where(scale > 0, scale, 1.0).astype(np.float32).astype(np.float64)
    back = np.clip(np.rint(w / scale), -127, 127) * scale
    return back, np.broadcast_to(scale / 2.0, w.shape) * (1 + 1e-6)


@pytest.mark.parametrize("scheme", QUANT_SCHEMES)
def test_round_trip_within_quantisation_bound(
    net: BlockwiseTerrainNet, tile: DemTile, scheme: str, tmp_path: Path
) -> None:
    path = save_map(net, tmp_path / "map.pt", quantization=scheme)
    loaded = load_map(path)
    original = dict(net.named_parameters())
    for name, p in loaded.named_parameters():
        w = original[name].detach().double().numpy()
        got = p.detach().double().numpy()
        ref, bound = _reference_dequantise(w, scheme)
        assert np.all(np.abs(got - w) <= bound), name
        np.testing.assert_allclose(got, ref, rtol=1e-6, atol=1e-7, err_msg=name)
    for name, b in net.named_buffers():  # buffers stay float32, bit for bit
        torch.testing.assert_close(dict(loaded.named_buffers())[name], b, rtol=0, atol=0)
    # the loaded file is the in-memory quantised model, and close to the float one
    xy = torch.from_numpy(tile.node_xy().reshape(-1, 2)).float()
    with torch.no_grad():
        torch.testing.assert_close(loaded(xy), quantize_model(net, scheme)(xy), rtol=0, atol=0)
        drift = (loaded(xy) - net(xy)).abs().max().item()
    assert 0.0 < drift < (0.05 if scheme == "fp16" else 5.0)


def test_quantised_files_are_smaller(tile: DemTile, tmp_path: Path) -> None:
    net = BlockwiseTerrainNet.from_tile(tile, block_nodes=20, n_frequencies=8, hidden=32)
    n_params = net.num_parameters
    size = {
        s: os.path.getsize(save_map(net, tmp_path / f"{s}.pt", quantization=s))
        for s in (None, "fp16", "int8_tensor")
    }
    assert size[None] - size["fp16"] >= 2 * n_params - 512  # 2 bytes saved per parameter
    assert size["fp16"] - size["int8_tensor"] >= n_params - 4096  # scales: 6 small records
    assert load_map_payload(tmp_path / "None.pt")["format_version"] == 1


def test_float_export_stores_no_hidden_storage(net: BlockwiseTerrainNet, tmp_path: Path) -> None:
    """Biases are views of larger init tensors: the file must hold only their own values."""
    path = save_map(net, tmp_path / "f.pt")
    stored = sum(t.numel() * t.element_size() for t in net.state_dict().values())
    assert os.path.getsize(path) < stored + 16_384


def test_missing_scale_is_a_clear_error(net: BlockwiseTerrainNet, tmp_path: Path) -> None:
    path = save_map(net, tmp_path / "q.pt", quantization="int8_channel")
    payload = torch.load(path, weights_only=True)
    del payload["quantization"]["tensors"]["weights.0"]["scale"]
    torch.save(payload, path)
    with pytest.raises(NeuralMapError, match="no 'scale'"):
        load_map(path)


def test_missing_quantised_tensor_and_bad_scheme(
    net: BlockwiseTerrainNet, tmp_path: Path
) -> None:
    path = save_map(net, tmp_path / "q.pt", quantization="int8_tensor")
    payload = torch.load(path, weights_only=True)
    del payload["quantization"]["tensors"]["out_weight"]
    torch.save(payload, path)
    with pytest.raises(NeuralMapError, match="out_weight"):
        load_map(path)
    with pytest.raises(NeuralMapError, match="quantisation scheme"):
        save_map(net, tmp_path / "x.pt", quantization="int4")
