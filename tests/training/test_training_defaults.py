"""One source of the network defaults: the net, its trainer and configs/train.yaml agree."""

from __future__ import annotations

import dataclasses
import inspect
from pathlib import Path

import yaml

from neuralmap.terrain.blockwise import NET_DEFAULTS, BlockwiseTerrainNet
from neuralmap.training.module import TerrainFitModule

REPO = Path(__file__).resolve().parents[2]


def _defaults(fn: object) -> dict[str, object]:
    return {
        name: p.default
        for name, p in inspect.signature(fn).parameters.items()  # type: ignore[arg-type]
        if p.default is not inspect.Parameter.empty
    }


def test_net_constructor_from_tile_and_module_share_the_defaults() -> None:
    expected = dataclasses.asdict(NET_DEFAULTS)
    module = _defaults(TerrainFitModule.__init__)
    from_tile = _defaults(BlockwiseTerrainNet.from_tile)
    init = _defaults(BlockwiseTerrainNet.__init__)
    for name, value in expected.items():
        assert module[name] == value, f"TerrainFitModule.{name}: {module[name]} != {value}"
        assert from_tile[name] == value, f"from_tile.{name}: {from_tile[name]} != {value}"
        if name in init:  # block_nodes / overlap_nodes exist only in from_tile
            assert init[name] == value, f"__init__.{name}: {init[name]} != {value}"
    # Every architecture argument of from_tile (but num_blocks) has its default in one place.
    assert set(from_tile) - {"num_blocks"} == set(expected)


def test_train_yaml_states_only_overrides_and_keeps_the_trained_values() -> None:
    config = yaml.safe_load((REPO / "configs" / "train.yaml").read_text())
    module = _defaults(TerrainFitModule.__init__)
    restated = [k for k, v in config["model"].items() if module.get(k, object()) == v]
    assert not restated, f"configs/train.yaml restates code defaults: {restated}"
    effective = {**module, **config["model"]}
    # The values `python train.py` has always fitted with (the jacksboro default map).
    assert effective["frequency_scale"] == 1.0 and effective["n_frequencies"] == 16
    assert effective["hidden"] == 32 and effective["depth"] == 2
    assert effective["block_nodes"] == 24 and effective["overlap_nodes"] == 4.0
    assert effective["lr"] == 0.01 and effective["encoding"] == "fourier"
