"""Progress that reads well in a terminal and in a log file.

On a terminal (``sys.stdout.isatty()``) progress is a tqdm bar. Redirected to a file
(``python evaluate.py > log``, ``nohup``, CI) a bar's carriage-return updates turn into
megabytes of unreadable text, so `progress_bar` returns a `ProgressLines`
instead: the same small tqdm interface, printing one plain line per stage (when the
description changes and at the end) with the rate and the time left, and a heartbeat line
at most every ``interval_s`` seconds inside a long stage.
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import IO, Any

__all__ = ["ProgressLines", "ScaledUpdates", "format_duration", "is_terminal", "progress_bar",
           "progress_line", "stage_progress"]

#: Seconds between two heartbeat lines inside one stage: half the promised minute, so a
#: stage whose updates come seconds apart still prints at least once a minute (measured: at
#: 60 s a loaded R derivation went 64 s between two lines).
HEARTBEAT_S = 30.0


def is_terminal(stream: IO[str] | None = None) -> bool:
    """Whether ``stream`` (default ``sys.stdout``) is an interactive terminal."""
    stream = sys.stdout if stream is None else stream
    try:
        return bool(stream.isatty())
    except (AttributeError, ValueError):  # closed or replaced by an object without isatty
        return False


def format_duration(seconds: float | None) -> str:
    """``"12.3s"``, ``"4m05s"``, ``"2h03m"``; ``"?"`` when unknown or not finite."""
    if seconds is None or not math.isfinite(seconds) or seconds < 0:
        return "?"
    if seconds < 60:
        return f"{seconds:.1f}s"
    minutes, secs = divmod(int(round(seconds)), 60)
    if minutes < 60:
        return f"{minutes}m{secs:02d}s"
    hours, minutes = divmod(minutes, 60)
    return f"{hours}h{minutes:02d}m"


def progress_line(
    desc: str,
    done: float,
    total: float | None,
    elapsed_s: float,
    unit: str,
    extra: str = "",
    *,
    done_in_elapsed: float | None = None,
) -> str:
    """One progress line: ``desc: done/total unit (p%), rate unit/s, elapsed, time left``.

    Args:
        desc: What is running.
        done: Units done so far.
        total: Units in all (None = unknown: no percentage, no time left).
        elapsed_s: Seconds since the start.
        unit: Name of one unit (``"step"``, ``"epoch"``).
        extra: Appended after a ``" | "`` when not empty (metrics).
        done_in_elapsed: Units done within ``elapsed_s`` when fewer than ``done`` (a fit
            resumed from a checkpoint); default ``done``. Rate and time left use it.

    Returns:
        The line, without a newline.
    """
    here = done if done_in_elapsed is None else done_in_elapsed
    rate = here / elapsed_s if elapsed_s > 0 else float("nan")
    count = f"{done:g}/{total:g} {unit}" if total else f"{done:g} {unit}"
    if total:
        count += f" ({100.0 * done / total:.0f}%)"
    left = max(total - done, 0.0) / rate if total and rate > 0 else None
    rate_text = f"{rate:.3g} {unit}/s" if math.isfinite(rate) else f"? {unit}/s"
    line = (f"{desc}: {count}, {rate_text}, {format_duration(elapsed_s)} elapsed, "
            f"{format_duration(left)} left")
    return f"{line} | {extra}" if extra else line


class ProgressLines:
    """A tqdm stand-in for logs: one line per stage, no carriage returns.

    Supports the part of tqdm's interface the toolkit uses: ``update(n)``,
    ``set_description(desc)``, ``close()``, ``n``, ``total`` and use as a context manager.
    A line is printed when the description changes (the stage that ended), at
    `close` (the last stage and the total) and at most every ``interval_s`` seconds
    within a stage. Rate and time left are over the whole bar.

    Args:
        total: Units in all (None = unknown).
        desc: Description of the first stage.
        unit: Name of one unit.
        stream: Where lines go (default ``sys.stdout`` at each print).
        interval_s: Seconds between heartbeat lines inside one stage.
    """

    def __init__(self, total: float | None = None, desc: str = "", unit: str = "it", *,
                 stream: IO[str] | None = None, interval_s: float = HEARTBEAT_S) -> None:
        self.total = total
        self.desc = desc
        self.unit = unit
        self.n = 0
        self.stream = stream
        self.interval_s = float(interval_s)
        self._start = time.perf_counter()
        self._last_line = self._start
        self._stage_start_n = 0
        self._closed = False

    def _emit(self, desc: str) -> None:
        now = time.perf_counter()
        stream = sys.stdout if self.stream is None else self.stream
        print(progress_line(desc or "progress", self.n, self.total, now - self._start,
                            self.unit), file=stream, flush=True)
        self._last_line = now

    def update(self, n: float = 1) -> None:
        """Advances by ``n`` units; prints a heartbeat line when one is due."""
        self.n += n
        if time.perf_counter() - self._last_line >= self.interval_s:
            self._emit(self.desc)

    def set_description(self, desc: str, refresh: bool = True) -> None:  # noqa: ARG002
        """Starts a new stage; the line of the stage that ended is printed first."""
        if desc != self.desc and self.n > self._stage_start_n:
            self._emit(self.desc)
        self.desc = desc
        self._stage_start_n = self.n

    def close(self) -> None:
        """Prints the last line (once)."""
        if not self._closed:
            self._closed = True
            self._emit(self.desc)

    def __enter__(self) -> ProgressLines:
        return self

    def __exit__(self, *exc: Any) -> None:
        self.close()


class ScaledUpdates:
    """A bar-like object whose ``update(n)`` reports ``n * scale`` to a callback.

    Lets a loop that advances a bar one unit per step (``run_filter``) feed a stage's
    fraction callback (``progress(fraction)``).

    Args:
        callback: Called with each update's share (e.g. a bar's ``update``).
        scale: Share of one unit.
    """

    def __init__(self, callback: Callable[[float], Any], scale: float) -> None:
        self.callback = callback
        self.scale = float(scale)

    def update(self, n: float = 1) -> None:
        """Reports ``n`` units."""
        self.callback(n * self.scale)


@contextmanager
def stage_progress(desc: str, total: float, unit: str, *, enabled: bool = True
                   ) -> Iterator[Callable[[float], None] | None]:
    """A bar (or log lines) for one stage, as a callback of the fraction of it done.

    Library loops take ``progress: Callable[[float], None] | None`` and call it with the
    share of their work each step finishes (`neuralmap.nav.navigator.Navigator.replay`,
    the PCRB, the noise derivation); a study wraps each stage in this: the bar counts ``total`` units of
    ``unit`` (steps, runs), prints a heartbeat line at least every `HEARTBEAT_S`
    seconds while the stage runs when stdout is not a terminal, and its last line when
    the stage ends.

    Args:
        desc: What runs (the line's prefix).
        total: Units in the whole stage (a fraction f is ``f * total`` units).
        unit: Name of one unit.
        enabled: False yields None (no output; the loops stay silent).

    Yields:
        The fraction callback, or None when disabled.
    """
    if not enabled:
        yield None
        return
    bar = progress_bar(total=total, desc=desc, unit=unit)
    try:
        yield lambda fraction: bar.update(fraction * total)
    finally:
        bar.close()


def progress_bar(total: float | None = None, desc: str = "", unit: str = "it") -> Any:
    """A tqdm bar on a terminal, `ProgressLines` when stdout is not one.

    Args:
        total: Units in all.
        desc: Description.
        unit: Name of one unit.

    Returns:
        An object with tqdm's ``update``, ``set_description`` and ``close``.
    """
    if is_terminal():
        from tqdm.auto import tqdm

        return tqdm(total=total, desc=desc, unit=unit)
    return ProgressLines(total=total, desc=desc, unit=unit, interval_s=HEARTBEAT_S)
