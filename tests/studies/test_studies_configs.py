"""Study configs: each config class names its own study, the shipped YAMLs list only what
differs from the defaults, and defaults shared with lower layers agree."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import pytest

from neuralmap.io import load_yaml
from neuralmap.studies.registry import STUDIES, get_study

CONFIGS = Path(__file__).resolve().parents[2] / "configs"


@pytest.mark.parametrize("name", sorted(STUDIES))
def test_config_class_names_its_study(name: str) -> None:
    """MapSizeStudyConfig, TanOutliersConfig and TanScaleConfig inherited ``study="tan"``:
    a run from Python wrote ``"study": "tan"``."""
    config_cls, _, _ = get_study(name)
    assert config_cls().study == name
    assert config_cls().seed == 0  # a fixed default seed: a rerun reproduces the report


def _study_yamls() -> list[Path]:
    out = []
    for path in sorted(CONFIGS.glob("*.yaml")):
        data = load_yaml(path.read_text())
        if isinstance(data, dict) and data.get("study") in STUDIES:
            out.append(path)
    return out


@pytest.mark.parametrize("path", _study_yamls(), ids=lambda p: p.name)
def test_yaml_lists_only_what_differs_from_the_defaults(path: Path) -> None:
    data = load_yaml(path.read_text())
    config_cls, _, spec = get_study(data["study"])
    defaults = dataclasses.asdict(config_cls())
    same = sorted(k for k, v in data.items() if k != "study" and k in defaults
                  and (v == defaults[k] or (isinstance(v, list)
                                           and isinstance(defaults[k], (list, tuple))
                                           and v == list(defaults[k]))))
    assert not same, f"{path.name} repeats defaults: {same}"
    unknown = sorted(set(data) - set(defaults))
    assert not unknown, f"{path.name}: unknown keys {unknown}"
    if path.name == spec.default_config:  # the shipped config is the defaults
        assert set(data) == {"study"}, path.name


def test_wind_defaults_agree_with_the_simulator_and_the_shipped_filters() -> None:
    from neuralmap.studies.wind import DEFAULT_FILTERS, WindStudyConfig
    from neuralmap.wind.simulator import WindSimConfig

    assert WindStudyConfig().shear_direction_deg == WindSimConfig().shear_direction_deg
    assert len(WindStudyConfig().filters) == len(DEFAULT_FILTERS) == 7
