"""The study layer's entry point: console script, bad input, interrupts, concurrent runs."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import threading
from pathlib import Path

import pytest
import torch

from neuralmap.io import next_version_dir
from neuralmap.studies import cli
from neuralmap.studies.registry import STUDIES

REPO_ROOT = Path(__file__).resolve().parents[2]
TINY = REPO_ROOT / "configs" / "tan_tiny.yaml"


@pytest.fixture(scope="module")
def tiny_map(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """An (untrained) neural map of the tiny scenario's tile: enough for the plumbing."""
    from neuralmap.lab.scenario import load_scenario, scenario_tile
    from neuralmap.terrain.blockwise import BlockwiseTerrainNet
    from neuralmap.terrain.export import save_map

    torch.manual_seed(0)
    tile = scenario_tile(load_scenario("tiny"))
    path = tmp_path_factory.mktemp("maps") / "neural_map.pt"
    save_map(BlockwiseTerrainNet.from_tile(tile, hidden=8, n_frequencies=4), path)
    return path


def test_console_script_runs_from_outside_the_checkout(tmp_path: Path, tiny_map: Path) -> None:
    """Configs and scenarios come from package data: any working directory works."""
    script = shutil.which("neuralmap-evaluate")
    command = [script] if script else [sys.executable, "-m", "neuralmap.studies.cli"]
    config = tmp_path / "tiny.yaml"
    shutil.copy(TINY, config)
    result = subprocess.run(
        [*command, "--config", str(config), "--map", str(tiny_map), "--n_runs", "4",
         "--methods", "[neural,bilinear]", "--tensorboard", "false"],
        cwd=tmp_path, capture_output=True, text=True, timeout=300,
    )
    assert result.returncode == 0, result.stderr
    out_dir = tmp_path / "runs" / "evaluate_tiny" / "version_0"
    assert result.stdout.strip().splitlines()[-1] == "results written to runs/evaluate_tiny/version_0"
    assert (out_dir / "report.md").is_file() and (out_dir / "results.json").is_file()


def test_help_lists_the_studies(capsys: pytest.CaptureFixture[str]) -> None:
    assert cli.main(["--help"]) == 0
    out = capsys.readouterr().out
    assert "--n_runs" in out and "--divergence_sigma" in out
    assert set(STUDIES) >= {"tan"}


def test_unknown_study_and_bad_config_files(tmp_path: Path, capsys) -> None:  # noqa: ANN001
    config = tmp_path / "x.yaml"
    config.write_text("study: kriging\n")
    assert cli.main(["--config", str(config)]) == 2
    assert "unknown study 'kriging'" in capsys.readouterr().err
    config.write_text("")
    assert cli.main(["--config", str(config)]) == 2
    assert "empty" in capsys.readouterr().err
    assert cli.main(["--config", str(tmp_path / "missing.yaml")]) == 2
    assert "file not found" in capsys.readouterr().err


def test_yaml_exponents_without_sign_are_numbers(tmp_path: Path) -> None:
    config = tmp_path / "c.yaml"
    config.write_text(TINY.read_text() + "neural_fit_variance: 1e2\npcrb_factor: 5e0\n")
    parsed = cli.parse_config(["--config", str(config)])
    assert parsed.neural_fit_variance == 100.0 and parsed.pcrb_factor == 5.0


def test_runs_dir_that_is_a_file_fails_before_any_work(tmp_path: Path, tiny_map: Path,
                                                       capsys, monkeypatch) -> None:  # noqa: ANN001
    blocker = tmp_path / "runs"
    blocker.write_text("not a folder")
    ran = []
    monkeypatch.setattr("neuralmap.studies.tan.run", lambda *a: ran.append(a))
    code = cli.main(["--config", str(TINY), "--map", str(tiny_map), "--runs_dir", str(blocker)])
    assert code == 2 and not ran
    assert "is a file, not a folder" in capsys.readouterr().err


def test_interrupt_leaves_nothing_behind(tmp_path: Path, tiny_map: Path, capsys,
                                         monkeypatch) -> None:  # noqa: ANN001
    def interrupted(config, outputs) -> None:  # noqa: ANN001
        (outputs.dir / "half.png").write_bytes(b"partial")
        raise KeyboardInterrupt

    monkeypatch.setattr("neuralmap.studies.tan.run", interrupted)
    runs = tmp_path / "runs"
    code = cli.main(["--config", str(TINY), "--map", str(tiny_map), "--runs_dir", str(runs)])
    assert code == 130 and "interrupted" in capsys.readouterr().err
    leftovers = [p for p in runs.rglob("*")] if runs.exists() else []
    assert not [p for p in leftovers if p.is_file() or p.name.startswith(".tmp-version")]


def test_sigterm_cleans_the_staging_folder(tmp_path: Path, tiny_map: Path, capsys,
                                           monkeypatch) -> None:  # noqa: ANN001
    """``kill <pid>`` (SIGTERM) used to end the process at once, leaving the hidden
    staging folder behind."""
    import os
    import signal

    def killed(config, outputs) -> None:  # noqa: ANN001
        (outputs.dir / "half.png").write_bytes(b"partial")
        os.kill(os.getpid(), signal.SIGTERM)

    monkeypatch.setattr("neuralmap.studies.tan.run", killed)
    runs = tmp_path / "runs"
    before = signal.getsignal(signal.SIGTERM)
    code = cli.main(["--config", str(TINY), "--map", str(tiny_map), "--runs_dir", str(runs)])
    assert code == 130 and "interrupted" in capsys.readouterr().err
    assert not list(runs.rglob(".tmp-version*"))
    assert signal.getsignal(signal.SIGTERM) is before  # restored


def test_staging_folder_of_a_killed_run_is_removed_by_the_next(
        tmp_path: Path, tiny_map: Path, capsys, monkeypatch) -> None:  # noqa: ANN001
    """A SIGKILLed study cannot clean up: the next run into the experiment does."""
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    root = tmp_path / "runs" / "evaluate_tiny"
    stale = root / f".tmp-version_{dead.pid}_abc123"
    (stale / "sub").mkdir(parents=True)
    (stale / "half.png").write_bytes(b"partial")
    alive = root / f".tmp-version_{os.getpid()}_live"  # a running study's: kept
    alive.mkdir()

    def quick(config, outputs) -> None:  # noqa: ANN001
        outputs.add_text("done")

    monkeypatch.setattr("neuralmap.studies.tan.run", quick)
    code = cli.main(["--config", str(TINY), "--map", str(tiny_map),
                     "--runs_dir", str(tmp_path / "runs"), "--tensorboard", "false"])
    assert code == 0, capsys.readouterr().err
    assert not stale.exists() and alive.is_dir()
    assert "tan: seed 0" in capsys.readouterr().out  # the seed is printed


def test_ctrl_c_while_importing_is_an_interrupt(tmp_path: Path) -> None:
    """Ctrl-C in the first second (torch still importing) printed a traceback."""
    import signal
    import time

    proc = subprocess.Popen([sys.executable, str(REPO_ROOT / "evaluate.py"), "--help"],
                            cwd=tmp_path, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                            text=True)
    time.sleep(0.3)
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=120)
    if proc.returncode == 0:  # --help finished before the signal: nothing to check
        pytest.skip("the command finished before the signal")
    assert proc.returncode == 130, err
    assert "Traceback" not in err and "interrupted" in err


def test_concurrent_runs_get_distinct_version_folders(tmp_path: Path) -> None:
    barrier = threading.Barrier(8)
    taken: list[Path] = []

    def reserve() -> None:
        barrier.wait()
        taken.append(next_version_dir(tmp_path / "exp"))

    threads = [threading.Thread(target=reserve) for _ in range(8)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert sorted(p.name for p in taken) == [f"version_{i}" for i in range(8)]


def test_flight_off_the_tile_exits_2_with_the_reason(tmp_path: Path, tiny_map: Path,
                                                    capsys) -> None:  # noqa: ANN001
    scenario = tmp_path / "off.yaml"
    text = (REPO_ROOT / "configs" / "scenarios" / "tiny.yaml").read_text()
    scenario.write_text(text.replace("start_xy: [500.0, 500.0]", "start_xy: [-9000.0, -9000.0]"))
    code = cli.main(["--config", str(TINY), "--map", str(tiny_map), "--scenario", str(scenario),
                     "--runs_dir", str(tmp_path / "runs"), "--methods", "[bilinear]"])
    err = capsys.readouterr().err
    assert code == 2 and "no run could be scored" in err and "start_xy" in err
    assert not (tmp_path / "runs").exists() or not any((tmp_path / "runs").rglob("*.json"))


def test_voids_under_the_flight_path_are_counted() -> None:
    from types import SimpleNamespace

    import numpy as np

    from neuralmap.dem.tile import DemTile
    from neuralmap.studies.setup import void_exposure

    heights = np.zeros((20, 20))
    heights[10, 10] = np.nan
    tile = DemTile(heights, spacing=(10.0, 10.0), name="holey")
    pos = torch.zeros(3, 4, 3, dtype=torch.float64)
    pos[..., 0] = 15.0
    pos[..., 1] = 15.0
    pos[1, 2, :2] = torch.tensor([100.0, 100.0], dtype=torch.float64)  # next to the void
    pos[2, :, :2] = torch.tensor([102.0, 104.0], dtype=torch.float64)  # over it, always
    found = void_exposure(tile, SimpleNamespace(pos=pos))
    assert found == {"samples": 5, "runs": 2}


def test_newest_map_of_the_scenarios_tile_is_preferred(tmp_path: Path, tiny_map: Path) -> None:
    """A newer map of another tile must not shadow the scenario's own map."""
    import os

    from neuralmap.dem import synthetic_tile
    from neuralmap.lab.scenario import load_scenario, scenario_tile
    from neuralmap.studies.maps import find_latest_map
    from neuralmap.terrain.blockwise import BlockwiseTerrainNet
    from neuralmap.terrain.export import save_map

    own = tmp_path / "tiny" / "version_0" / "neural_map.pt"
    own.parent.mkdir(parents=True)
    shutil.copy(tiny_map, own)
    other = tmp_path / "other" / "version_0" / "neural_map.pt"
    other_tile = synthetic_tile((40, 40), spacing=(30.0, 30.0), seed=9, name="other")
    save_map(BlockwiseTerrainNet.from_tile(other_tile, block_nodes=48, hidden=8), other)
    os.utime(own, (1000, 1000))
    os.utime(other, (2000, 2000))  # newer
    fingerprint = scenario_tile(load_scenario("tiny")).fingerprint()
    assert find_latest_map(tmp_path) == other
    assert find_latest_map(tmp_path, tile_fingerprint=fingerprint) == own
    # the map-size study's discovery: the newest map of the tile in every experiment folder
    from neuralmap.studies.maps import find_tile_maps

    assert find_tile_maps(str(tmp_path), fingerprint) == [own]
    assert find_tile_maps(str(tmp_path), other_tile.fingerprint()) == [other]


def test_empty_scenario_file_is_refused(tmp_path: Path) -> None:
    from neuralmap.exceptions import NeuralMapError
    from neuralmap.lab.scenario import load_scenario

    empty = tmp_path / "empty.yaml"
    empty.write_text("# nothing here\n")
    with pytest.raises(NeuralMapError, match="empty"):
        load_scenario(empty)
    exponent = tmp_path / "exp.yaml"
    text = (REPO_ROOT / "configs" / "scenarios" / "tiny.yaml").read_text()
    exponent.write_text(text.replace("R_m2: 9.0", "R_m2: 9e0"))
    assert load_scenario(exponent).R_m2 == 9.0


def test_console_entry_imports_nothing_heavy_and_handles_early_ctrl_c(monkeypatch,
                                                                      capsys) -> None:  # noqa: ANN001
    """``neuralmap-evaluate`` imported the whole study layer (torch) before any handler."""
    import ast
    import builtins

    from neuralmap import entry

    tree = ast.parse(Path(entry.__file__).read_text())
    top = [n for n in tree.body if isinstance(n, (ast.Import, ast.ImportFrom))]
    standard = {"__future__", "sys", "os", "re", "signal", "importlib", "contextlib",
                "collections.abc", "typing"}
    assert all((getattr(n, "module", None) or n.names[0].name) in standard for n in top)
    real_import = builtins.__import__

    def interrupted(name, *args, **kwargs):  # noqa: ANN001, ANN002, ANN003, ANN202
        if name == "neuralmap.studies.cli":
            raise KeyboardInterrupt
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", interrupted)
    assert entry.evaluate(["--help"]) == 130
    assert "interrupted" in capsys.readouterr().err
