"""One experiment-name rule for the trainers and the studies."""

from __future__ import annotations

import pytest

from neuralmap.exceptions import NeuralMapError
from neuralmap.io import check_experiment_name
from neuralmap.studies.tan import TanStudyConfig


@pytest.mark.parametrize("name", ["", ".", "..", "../up", "a/b", "a\\b", ".hidden"])
def test_the_same_names_are_refused_everywhere(name: str) -> None:
    with pytest.raises(NeuralMapError, match="plain folder name inside --runs_dir") as direct:
        check_experiment_name(name)
    with pytest.raises(NeuralMapError) as study:
        TanStudyConfig(experiment=name).validate()
    assert str(study.value) == str(direct.value)
    import neuralmap.training.cli as training_cli

    assert training_cli.check_experiment_name is check_experiment_name  # one rule


def test_plain_names_pass() -> None:
    for name in ("evaluate", "fit-2", "tan_outliers_tiny", "a.b"):
        assert check_experiment_name(name) == name
