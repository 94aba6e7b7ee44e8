"""Every shipped study config writes TensorBoard events."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

CONFIGS = sorted(p for p in (Path(__file__).resolve().parents[2] / "configs").glob("*.yaml")
                 if "study" in (yaml.safe_load(p.read_text()) or {}))


def test_the_study_configs_are_found() -> None:
    assert {p.stem for p in CONFIGS} >= {"tan", "acquisition", "acquisition_tiny", "tan_scale",
                                         "gnss_ins", "map_size", "learned", "wind"}


@pytest.mark.parametrize("path", CONFIGS, ids=lambda p: p.stem)
def test_study_config_writes_tensorboard_events(path: Path) -> None:
    assert yaml.safe_load(path.read_text()).get("tensorboard", True) is True, path.name
