"""No silent stage: every long stage of ``python evaluate.py`` prints heartbeat lines to a log.

The clock is faked (every ``time.perf_counter`` call advances it 7 s), so each stage looks
minutes long while the tiny run takes seconds; stdout is captured (not a terminal), so the
progress is plain lines (`neuralmap.progress.ProgressLines`).
"""

from __future__ import annotations

import io
import re
from pathlib import Path

import pytest

import neuralmap.progress as progress
from neuralmap.progress import ProgressLines, ScaledUpdates, stage_progress

REPO_ROOT = Path(__file__).resolve().parents[2]
TINY_CONFIG = REPO_ROOT / "configs" / "tan_tiny.yaml"
#: A progress line: "<desc>: <done>/<total> <unit> (<p>%), <rate>, <elapsed> elapsed, ..."
LINE = re.compile(r"^(?P<desc>.+?): [\d.]+/[\d.]+ \w+ \(\d+%\), .* elapsed, ")


def _fake_clock(monkeypatch: pytest.MonkeyPatch, step_s: float) -> list[float]:
    now = [0.0]

    def tick() -> float:
        now[0] += step_s
        return now[0]

    monkeypatch.setattr(progress.time, "perf_counter", tick)
    return now


def test_stage_progress_turns_fractions_into_units(monkeypatch: pytest.MonkeyPatch,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    _fake_clock(monkeypatch, 25.0)
    with stage_progress("tracker", 40, "step") as report:
        assert report is not None
        feed = ScaledUpdates(report, 1.0 / 40)
        for _ in range(40):
            feed.update(1)
    lines = capsys.readouterr().out.splitlines()
    assert len(lines) >= 10 and all(LINE.match(line) for line in lines)  # a line per ~60 s
    assert lines[-1].startswith("tracker: 40/40 step (100%)")
    with stage_progress("off", 10, "step", enabled=False) as report:
        assert report is None
    assert capsys.readouterr().out == ""


def test_heartbeat_interval_is_read_when_the_bar_is_made(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(progress, "is_terminal", lambda stream=None: False)
    monkeypatch.setattr(progress, "HEARTBEAT_S", 5.0)
    bar = progress.progress_bar(10, "x")
    assert isinstance(bar, ProgressLines) and bar.interval_s == 5.0
    bar.stream = io.StringIO()
    bar.close()


def test_every_long_tan_stage_prints_heartbeats_to_a_log(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
        capsys: pytest.CaptureFixture[str]) -> None:
    import neuralmap.lab.pcrb as pcrb
    from neuralmap.studies import cli

    # the PCRB evaluates its slopes in chunks; the tiny run has one chunk of the default size
    monkeypatch.setattr(pcrb, "SLOPE_CHUNK", 32)
    now = _fake_clock(monkeypatch, 7.0)
    code = cli.main(["--config", str(TINY_CONFIG), "--runs_dir", str(tmp_path),
                     "--methods", "[bilinear,point_mass_ekf,point_mass_tracker]",
                     "--n_runs", "4", "--noise_pilot_runs", "8", "--noise_iterations", "1",
                     "--progress", "true", "--tensorboard", "false"])
    out = capsys.readouterr().out
    assert code == 0, out
    assert now[0] > 600.0  # the faked run "took" minutes
    descs = [m.group("desc") for m in map(LINE.match, out.splitlines()) if m]
    for stage in ("R derivation", "Monte Carlo", "point_mass_tracker", "point_mass_ekf",
                  "PCRB"):
        hits = [d for d in descs if d.startswith(stage)]
        # a heartbeat inside the stage and its closing line at least
        assert len(hits) >= 2, f"stage {stage!r} printed {len(hits)} progress lines:\n{out}"
