"""``--data.spacing`` means one thing in every train.py mode: one number or ``[dx, dy]``."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import yaml

from neuralmap.dem import synthetic_tile
from neuralmap.exceptions import NeuralMapError
from neuralmap.training.cli import main
from neuralmap.training.datamodule import DemDataModule
from neuralmap.training.latent_datamodule import LatentDataModule

CONFIGS = Path(__file__).resolve().parents[2] / "configs"


@pytest.fixture(scope="module")
def tile_path(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("tile") / "plain.npy"  # a file without a spacing
    np.save(path, synthetic_tile((24, 20), spacing=1.0, seed=2).heights)
    return path


@pytest.mark.parametrize("spacing, expected", [(30.0, (30.0, 30.0)),
                                               ([30.0, 40.0], (30.0, 40.0))])
def test_both_data_modules_read_spacing_alike(tile_path: Path, spacing: object,
                                              expected: tuple[float, float]) -> None:
    assert DemDataModule(str(tile_path), spacing=spacing).tile.spacing == expected
    assert LatentDataModule(str(tile_path), spacing=spacing).tile.spacing == expected


@pytest.mark.parametrize("mode", [[], ["latent", "--config", str(CONFIGS / "latent_map.yaml")]])
def test_both_modes_parse_a_two_value_spacing(mode: list[str], tile_path: Path,
                                              capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as exit_info:
        main([*mode, "--data.path", str(tile_path), "--data.spacing", "[30,40]",
              "--print_config"])
    assert exit_info.value.code in (0, None)
    printed = yaml.safe_load(capsys.readouterr().out)
    assert printed["data"]["spacing"] == [30.0, 40.0]


def test_three_spacing_values_name_the_option() -> None:
    with pytest.raises(NeuralMapError, match=r"--data.spacing \[1.0, 2.0, 3.0\].*\[dx, dy\]"):
        LatentDataModule("jacksboro", spacing=[1.0, 2.0, 3.0])
