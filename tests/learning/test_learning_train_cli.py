"""``python train.py --config configs/learn_noise.yaml``: the noise-learning mode of train.py."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from neuralmap.exceptions import NeuralMapError
from neuralmap.nav.scenario import load_scenario
from neuralmap.training.cli import main
from neuralmap.training.noise_cli import learn_mode

REPO_ROOT = Path(__file__).resolve().parents[2]


def test_learn_switch_keeps_the_default_map_fit() -> None:
    assert learn_mode([]) == "map"
    assert learn_mode(["--config", str(REPO_ROOT / "configs" / "train.yaml")]) == "map"
    assert learn_mode(["--config", str(REPO_ROOT / "configs" / "learn_noise.yaml")]) == "noise"
    assert learn_mode(["--learn=noise"]) == "noise"
    with pytest.raises(NeuralMapError, match="learn"):
        learn_mode(["--learn", "weights"])


@pytest.mark.slow
def test_tiny_noise_learning_writes_a_scenario_evaluate_can_use(tmp_path: Path) -> None:
    torch.manual_seed(0)
    path = main(["--config", str(REPO_ROOT / "configs" / "learn_noise_tiny.yaml"),
                 "--runs_dir", str(tmp_path), "--trainer.max_epochs", "2"])
    assert path is not None and path.name == "learned_scenario.yaml"
    learned = load_scenario(path)
    tiny = load_scenario("tiny")
    assert learned.P0_diag == tiny.P0_diag
    # moved from the mis-specified start (Q x 0.1, R x 10) toward the truth
    assert learned.R_m2 + learned.fit_variance_m2 < 10 * (tiny.R_m2 + tiny.fit_variance_m2)
    assert any(path.parent.glob("events.out.tfevents.*"))


def test_noise_mode_bad_option_exits_2(tmp_path: Path, capsys) -> None:  # noqa: ANN001
    with pytest.raises(SystemExit) as exit_info:
        main(["--config", str(REPO_ROOT / "configs" / "learn_noise_tiny.yaml"),
              "--runs_dir", str(tmp_path), "--model.q_kind", "cholesky"])
    assert exit_info.value.code == 2
    assert "q_kind" in capsys.readouterr().err
