"""``python train.py noise --config configs/learn_noise.yaml``: the noise-learning mode."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from neuralmap.lab.scenario import load_scenario
from neuralmap.training.cli import main

REPO_ROOT = Path(__file__).resolve().parents[2]


def test_mode_is_the_first_word(capsys: pytest.CaptureFixture[str]) -> None:
    """The first word picks the mode; an unknown one is a clear error."""
    with pytest.raises(SystemExit) as exit_info:
        main(["weights", "--config", str(REPO_ROOT / "configs" / "learn_noise.yaml")])
    assert exit_info.value.code == 2
    assert "mode 'weights' is unknown" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exit_info:
        main(["noise", "--config", str(REPO_ROOT / "configs" / "learn_noise.yaml"),
              "--print_config"])
    assert exit_info.value.code == 0
    printed = capsys.readouterr().out
    assert "scenario: jacksboro" in printed and "q_kind: log_diagonal" in printed


@pytest.mark.slow
def test_tiny_noise_learning_writes_a_scenario_evaluate_can_use(tmp_path: Path) -> None:
    torch.manual_seed(0)
    path = main(["noise", "--config", str(REPO_ROOT / "configs" / "learn_noise_tiny.yaml"),
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
        main(["noise", "--config", str(REPO_ROOT / "configs" / "learn_noise_tiny.yaml"),
              "--runs_dir", str(tmp_path), "--model.q_kind", "cholesky"])
    assert exit_info.value.code == 2
    assert "q_kind" in capsys.readouterr().err


@pytest.fixture(scope="module")
def tiny_log(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Four simulated flights of the tiny scenario (dt = 1 s) as a CSV flight log."""
    from neuralmap.lab.scenario import scenario_tile
    from neuralmap.lab.simulator import simulate
    from neuralmap.learning.flight_log import write_flight_log
    from neuralmap.learning.flights import FlightBatch

    tiny = load_scenario("tiny")
    flights = FlightBatch.from_truth(simulate(tiny, scenario_tile(tiny), n_runs=4, seed=0))
    return write_flight_log(tmp_path_factory.mktemp("log") / "tiny.csv", flights)


def _edited_log(src: Path, dst: Path, edit) -> Path:  # noqa: ANN001
    import csv

    rows = list(csv.DictReader(src.open(encoding="utf-8")))
    for row in rows:
        edit(row)
    with dst.open("w", newline="", encoding="utf-8") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(rows[0]))
        writer.writeheader()
        writer.writerows(rows)
    return dst


@pytest.mark.parametrize("case", ["half_step", "radar_empty", "off_tile", "other_dt",
                                  "other_tile"])
def test_flight_logs_that_cannot_teach_anything_exit_2_and_leave_no_run_folder(
    case: str, tiny_log: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str],
) -> None:
    import dataclasses

    from neuralmap.lab.scenario import save_scenario

    tiny = load_scenario("tiny")
    log, extra, expect = tiny_log, [], ""
    if case == "half_step":  # the same rows stamped every 0.5 s
        log = _edited_log(tiny_log, tmp_path / "log.csv",
                          lambda r: r.update(time=str(0.5 * float(r["time"]))))
        expect = "the flights step 0.5 s but scenario 'tiny' has dt = 1 s"
    elif case == "radar_empty":
        log = _edited_log(tiny_log, tmp_path / "log.csv", lambda r: r.update(radar=""))
        expect = "no altimeter reading in any flight"
    elif case == "off_tile":
        log = _edited_log(tiny_log, tmp_path / "log.csv",
                          lambda r: r.update(ins_x=str(float(r["ins_x"]) + 1e5)))
        expect = "no altimeter reading lies on the tile"
    else:  # the filter flies another world than the flights'
        other = dataclasses.replace(
            tiny, name="other", **({"dt": 2.0} if case == "other_dt" else
                                   {"tile_options": {**tiny.tile_options, "seed": 9}}))
        path = save_scenario(other, tmp_path / "other.yaml")
        extra = ["--model.scenario", str(path)]
        expect = "time step" if case == "other_dt" else "uses tile"
    runs = tmp_path / "runs"
    with pytest.raises(SystemExit) as exit_info:
        main(["noise", "--config", str(REPO_ROOT / "configs" / "learn_noise_tiny.yaml"),
              "--runs_dir", str(runs), "--data.log_path", str(log), "--data.n_val_flights", "1",
              "--trainer.max_epochs", "1", *extra])
    err = capsys.readouterr().err
    assert exit_info.value.code == 2, err[-2000:]
    assert "error:" in err and expect in err and "Traceback" not in err
    assert not list(runs.glob("*/version_*"))  # no folder holding only an event file


def test_a_good_flight_log_is_learned_from(tiny_log: Path, tmp_path: Path) -> None:
    """The checks above refuse nothing usable: the tiny log (dt 1 s, on the tile) trains."""
    path = main(["noise", "--config", str(REPO_ROOT / "configs" / "learn_noise_tiny.yaml"),
                 "--runs_dir", str(tmp_path), "--data.log_path", str(tiny_log),
                 "--data.n_val_flights", "1", "--trainer.max_epochs", "1"])
    assert path is not None and path.is_file() and path.name == "learned_scenario.yaml"
    assert load_scenario(path).dt == 1.0
