"""``train.py``'s mode: the first word, else the configs' ``learn:`` key read by the
jsonargparse pre-parser (`neuralmap.training.cli.mode_parser`), else ``map``."""

from __future__ import annotations

from pathlib import Path

import pytest

from neuralmap.training.cli import config_learn, config_mode, main

CONFIGS = Path(__file__).resolve().parents[2] / "configs"


def test_learn_key_picks_the_mode(tmp_path: Path) -> None:
    latent = str(CONFIGS / "latent_map.yaml")
    assert config_mode(["--config", latent]) == "latent"
    assert config_mode([f"--config={latent}"]) == "latent"
    assert config_mode(["-c", latent, "--trainer.max_epochs", "2"]) == "latent"
    assert config_mode(["--config", str(CONFIGS / "train.yaml")]) == "map"
    assert config_learn(["--config", str(CONFIGS / "train.yaml")]) is None
    assert config_mode([]) == "map"
    # layered configs: the last file that names a mode wins (jsonargparse's order)
    noise = tmp_path / "noise.yaml"
    noise.write_text("learn: noise\n")
    assert config_mode(["--config", latent, "--config", str(noise)]) == "noise"
    assert config_mode(["--config", str(noise), "--config", str(CONFIGS / "train.yaml")]) == "noise"
    # a missing or broken file is left to the mode's own parser, which reports it
    broken = tmp_path / "broken.yaml"
    broken.write_text("trainer: [1\n")
    assert config_mode(["--config", str(tmp_path / "missing.yaml")]) == "map"
    assert config_mode(["--config", str(broken)]) == "map"


def test_bad_learn_key_is_one_error_line(tmp_path: Path,
                                         capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "bad.yaml"
    bad.write_text("learn: latnet\ntrainer: {max_epochs: 2}\n")
    with pytest.raises(SystemExit) as exit_info:
        main(["--config", str(bad)])
    assert exit_info.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [f"error: {bad}: learn: 'latnet' is not a train.py mode; use one of map, "
                   "noise, region, latent."]


def test_mode_word_that_contradicts_the_config_is_refused(
    capsys: pytest.CaptureFixture[str],
) -> None:
    with pytest.raises(SystemExit) as exit_info:
        main(["noise", "--config", str(CONFIGS / "latent_map.yaml")])
    assert exit_info.value.code == 2
    assert "the config is written for `learn: latent`" in capsys.readouterr().err


def test_config_without_mode_word_runs_its_mode(capsys: pytest.CaptureFixture[str]) -> None:
    """``train.py --config configs/latent_map.yaml --print_config`` goes to the latent CLI."""
    with pytest.raises(SystemExit) as exit_info:
        main(["--config", str(CONFIGS / "latent_map.yaml"), "--print_config"])
    assert exit_info.value.code == 0
    printed = capsys.readouterr().out
    assert "learn: latent" in printed and "rate_weight: 3.0" in printed
