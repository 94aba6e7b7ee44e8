"""The tiny latent-map config trains through train.py end to end; bad input exits 2."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from neuralmap.dem import load_tile
from neuralmap.terrain.export import load_map
from neuralmap.terrain.latent import LatentTerrainMap
from neuralmap.training.cli import main

CONFIGS = Path(__file__).resolve().parents[2] / "configs"
BASE = ["latent", "--config", str(CONFIGS / "latent_map.yaml"), "--config", str(CONFIGS / "latent_map_tiny.yaml")]


def test_tiny_config_trains_and_exports(tmp_path: Path, capsys):
    path = main([*BASE, "--runs_dir", str(tmp_path)])
    out = capsys.readouterr().out.strip().splitlines()
    assert path is not None and out[-1] == str(path)
    assert path.name == "latent_map.nlat"
    latent_map = load_map(path)
    assert isinstance(latent_map, LatentTerrainMap)
    assert latent_map.basis.name == "wavelet"  # the config's default basis
    tile = load_tile("synthetic:40x32")
    assert latent_map.tile_fingerprint == tile.fingerprint()
    assert latent_map.metrics["rmse_m"] > 0
    h, slope = latent_map.height_and_slope(torch.tensor([[100.0, 200.0]]))
    assert torch.isfinite(h).all() and torch.isfinite(slope).all()
    events = list(path.parent.glob("events.out.tfevents.*"))
    assert events, "TensorBoard events expected in the run folder"


@pytest.mark.parametrize("lam", ["0", "-2"])
def test_nonpositive_rate_weight_is_a_clear_error(tmp_path: Path, capsys, lam: str):
    with pytest.raises(SystemExit) as exc:
        main([*BASE, "--runs_dir", str(tmp_path), "--model.rate_weight", lam])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "error: latent map: the rate weight lambda (model.rate_weight) must be" in err


def test_unknown_basis_is_a_clear_error(tmp_path: Path, capsys):
    with pytest.raises(SystemExit) as exc:
        main([*BASE, "--runs_dir", str(tmp_path), "--model.basis", "dct"])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert "error: latent map: unknown basis 'dct' (model.basis); use one of" in err
    assert "Traceback" not in err


def test_config_learn_key_picks_the_latent_mode(tmp_path: Path) -> None:
    """``train.py --config configs/latent_map.yaml`` (no mode word) runs the latent mode."""
    from neuralmap.training.cli import config_mode

    assert config_mode(["--config", str(CONFIGS / "latent_map.yaml")]) == "latent"
    assert config_mode(["--config", str(CONFIGS / "train.yaml")]) == "map"
    assert config_mode(["--config", str(tmp_path / "missing.yaml")]) == "map"


@pytest.mark.parametrize("where", ["argv", "argv=", "config"])
def test_the_old_regions_option_names_its_new_name(tmp_path: Path, capsys, where: str):
    """``--model.regions`` (and ``model: regions:`` in a config) is now ``model.zones``: a
    one-line error that names the new spelling, before anything is built."""
    extra = {"argv": ["--model.regions", "4"], "argv=": ["--model.regions=4"]}.get(where)
    if extra is None:
        config = tmp_path / "old.yaml"
        config.write_text("model:\n  regions: 4\n", encoding="utf-8")
        extra = ["--config", str(config)]
    with pytest.raises(SystemExit) as exc:
        main([*BASE, "--runs_dir", str(tmp_path), *extra])
    assert exc.value.code == 2
    err = capsys.readouterr().err
    assert err.startswith("error: ") and "model.zones" in err and "renamed" in err
    assert not list(tmp_path.glob("*/version_*"))
