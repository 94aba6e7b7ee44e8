"""Plain progress lines for logs: the format, the stage lines, the bar/line choice."""

from __future__ import annotations

import io

import pytest

import neuralmap.progress as progress
from neuralmap.progress import ProgressLines, format_duration, progress_bar, progress_line


def test_format_duration() -> None:
    assert [format_duration(s) for s in (0.04, 12.34, 65, 3600 + 180, None, float("inf"), -1)] \
        == ["0.0s", "12.3s", "1m05s", "1h03m", "?", "?", "?"]


def test_progress_line_rate_and_time_left() -> None:
    line = progress_line("Monte Carlo [neural]", 300, 1200, 3.0, "step", "rmse 1.2")
    assert line == ("Monte Carlo [neural]: 300/1200 step (25%), 100 step/s, 3.0s elapsed, "
                    "9.0s left | rmse 1.2")
    # resumed: 10 of 20 epochs done, 5 of them in 10 s -> 0.5 epoch/s, 20 s left
    line = progress_line("train", 10, 20, 10.0, "epoch", done_in_elapsed=5)
    assert line == "train: 10/20 epoch (50%), 0.5 epoch/s, 10.0s elapsed, 20.0s left"
    assert progress_line("x", 3, None, 0.0, "it") == "x: 3 it, ? it/s, 0.0s elapsed, ? left"


def test_progress_lines_one_line_per_stage(monkeypatch: pytest.MonkeyPatch) -> None:
    now = [0.0]
    monkeypatch.setattr(progress.time, "perf_counter", lambda: now[0])
    out = io.StringIO()
    bar = ProgressLines(total=40, desc="MC [a]", unit="step", stream=out)
    for _ in range(20):
        now[0] += 0.05
        bar.update(1)
    bar.set_description("MC [b]")
    for _ in range(20):
        now[0] += 0.05
        bar.update(1)
    bar.close()
    bar.close()  # only once
    lines = out.getvalue().splitlines()
    assert "\r" not in out.getvalue()
    assert lines == ["MC [a]: 20/40 step (50%), 20 step/s, 1.0s elapsed, 1.0s left",
                     "MC [b]: 40/40 step (100%), 20 step/s, 2.0s elapsed, 0.0s left"]


def test_heartbeat_line_inside_a_long_stage(monkeypatch: pytest.MonkeyPatch) -> None:
    now = [0.0]
    monkeypatch.setattr(progress.time, "perf_counter", lambda: now[0])
    out = io.StringIO()
    bar = ProgressLines(total=100, desc="s", unit="step", stream=out, interval_s=60.0)
    for _ in range(100):
        now[0] += 1.0
        bar.update(1)
    assert len(out.getvalue().splitlines()) == 1  # at 60 s


def test_progress_bar_is_tqdm_on_a_terminal_only(monkeypatch: pytest.MonkeyPatch) -> None:
    from tqdm.auto import tqdm

    assert not progress.is_terminal(io.StringIO())
    monkeypatch.setattr(progress, "is_terminal", lambda stream=None: False)
    assert isinstance(progress_bar(10, "x"), ProgressLines)
    monkeypatch.setattr(progress, "is_terminal", lambda stream=None: True)
    bar = progress_bar(10, "x")
    assert isinstance(bar, tqdm)
    bar.close()
