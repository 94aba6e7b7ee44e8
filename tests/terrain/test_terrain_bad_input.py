"""Neural maps at non-finite points and damaged map files: NaN out or a clear NeuralMapError."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from neuralmap.dem import synthetic_tile
from neuralmap.exceptions import NeuralMapError
from neuralmap.linearize import AutogradLinearizer
from neuralmap.terrain.blockwise import BlockwiseTerrainNet
from neuralmap.terrain.export import load_map, save_map
from neuralmap.terrain.grid import GridTerrain


@pytest.fixture(scope="module")
def tile():
    return synthetic_tile((48, 48), spacing=30.0, seed=2)


@pytest.mark.parametrize("encoding, depth", [("fourier", 2), ("none", 1)])
def test_nan_positions_give_nan_heights_like_the_grid(tile, encoding: str, depth: int) -> None:
    net = BlockwiseTerrainNet.from_tile(tile, block_nodes=16, hidden=8, n_frequencies=4,
                                        encoding=encoding, depth=depth).double()
    good = torch.tensor([[100.0, 200.0], [900.0, 1200.0]], dtype=torch.float64)
    bad = torch.tensor([[float("nan"), 5.0], [3.0, float("inf")]], dtype=torch.float64)
    xy = torch.cat([good[:1], bad[:1], good[1:], bad[1:]])
    height = net(xy)  # was: RuntimeError from bincount
    assert torch.isnan(height[[1, 3]]).all()
    torch.testing.assert_close(height[[0, 2]], net(good), rtol=0, atol=0)
    assert torch.isnan(GridTerrain(tile)(bad[:1])).all()  # the same convention for NaN
    lin = AutogradLinearizer(net)(xy)
    assert torch.isnan(lin.height[[1, 3]]).all()
    torch.testing.assert_close(lin.slope[[0, 2]], AutogradLinearizer(net)(good).slope)
    if encoding == "none":
        slope = net.analytic_slope(xy)
        assert torch.isnan(slope[[1, 3]]).all()
        torch.testing.assert_close(slope[[0, 2]], net.analytic_slope(good))


def test_load_map_of_none_or_a_number() -> None:
    for bad in (None, 3):
        with pytest.raises(NeuralMapError, match="path must be the path of a neural_map.pt"):
            load_map(bad)  # type: ignore[arg-type]


def test_map_with_valid_header_but_bad_config(tile, tmp_path: Path) -> None:
    net = BlockwiseTerrainNet.from_tile(tile, block_nodes=16, hidden=8, n_frequencies=4)
    path = save_map(net, tmp_path / "neural_map.pt")
    payload = torch.load(path, weights_only=True)
    payload["config"]["hidden"] = 12  # weights no longer fit
    torch.save(payload, tmp_path / "edited.pt")
    with pytest.raises(NeuralMapError, match="do not build") as info:
        load_map(tmp_path / "edited.pt")
    assert "Traceback" not in str(info.value)
    payload["config"]["no_such_option"] = 1
    torch.save(payload, tmp_path / "edited2.pt")
    with pytest.raises(NeuralMapError, match="edited2.pt"):
        load_map(tmp_path / "edited2.pt")
    payload["config"] = {"activation": "nope"}
    torch.save(payload, tmp_path / "edited3.pt")
    with pytest.raises(NeuralMapError, match="edited3.pt"):
        load_map(tmp_path / "edited3.pt")


@pytest.mark.parametrize("where", ["weight", "quantised scale", "sharded shard"])
def test_map_with_non_finite_parameters_is_refused(tile, tmp_path: Path, where: str) -> None:
    """A NaN weight or scale makes every run fail numerically: refuse it at load time."""
    net = BlockwiseTerrainNet.from_tile(tile, block_nodes=16, hidden=8, n_frequencies=4)
    if where == "quantised scale":
        path = save_map(net, tmp_path / "neural_map.pt", quantization="int8_tensor")
        payload = torch.load(path, weights_only=True)
        name, entry = next((k, v) for k, v in payload["quantization"]["tensors"].items()
                           if "scale" in v)
        entry["scale"] = torch.full_like(torch.as_tensor(entry["scale"]), float("nan"))
        torch.save(payload, path)
        expected = name
    else:
        name = next(k for k, v in net.state_dict().items() if v.is_floating_point()
                    and v.numel() > 1 and "weight" in k)
        with torch.no_grad():
            net.state_dict()[name].view(-1)[0] = float("nan")
        path = save_map(net, tmp_path / "neural_map.pt")
        expected = name
    if where == "sharded shard":
        from neuralmap.terrain.sharded import write_shard_index

        index = write_shard_index(tmp_path / "map_index.json", layout=net.layout,
                                  shard_blocks=net.layout.num_blocks, files=[path.name])
        with pytest.raises(NeuralMapError, match="non-finite") as info:
            load_map(index)(torch.tensor([[100.0, 200.0]]))
    else:
        with pytest.raises(NeuralMapError, match="non-finite") as info:
            load_map(path)
    assert expected in str(info.value) and "Train the map again" in str(info.value)
