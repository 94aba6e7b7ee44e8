"""Console-script entry points, light to import (only the standard library at the top).

``neuralmap-evaluate`` and ``python evaluate.py``, ``neuralmap-export``, ``neuralmap-gins``
and ``neuralmap-navigate``: Ctrl-C while torch and the package are still importing (the first
seconds) exits 130 with one line, like Ctrl-C during the run, instead of a traceback. A
``KeyboardInterrupt`` raised inside an import is not enough: an extension module
interrupted half-way (numpy) leaves a half-initialised module behind, and the next import
fails with an unrelated ``AttributeError``. So during the imports SIGINT ends the process
at once; nothing has been written yet. `parse_error_message` turns a parse error of these
commands' jsonargparse parsers into their one ``error:`` line.
"""

from __future__ import annotations

import importlib
import os
import re
import signal
import sys
from collections.abc import Callable, Iterator, Mapping
from contextlib import contextmanager
from typing import Any

MESSAGE = "evaluate.py: interrupted; nothing was written."


@contextmanager
def interrupt_exits(message: str = MESSAGE) -> Iterator[None]:
    """While the block runs, SIGINT prints ``message`` to stderr and exits 130 at once."""

    def on_interrupt(signum: int, frame: Any) -> None:  # noqa: ARG001
        sys.stderr.write(message + "\n")
        sys.stderr.flush()
        os._exit(130)  # no cleanup to run: nothing is open or written while importing

    previous: Callable[..., Any] | int | None = signal.getsignal(signal.SIGINT)
    signal.signal(signal.SIGINT, on_interrupt)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous if previous is not None else signal.SIG_DFL)


def evaluate(args: list[str] | None = None) -> int:
    """Imports the evaluate CLI (`neuralmap.studies.cli.main`) and runs it.

    Returns:
        Its exit code; 130 when interrupted while importing (a SIGINT there ends the process
        with that code; a ``KeyboardInterrupt`` raised by an import returns it).
    """
    try:
        with interrupt_exits():
            from neuralmap.studies.cli import main
    except KeyboardInterrupt:
        print(MESSAGE, file=sys.stderr)
        return 130
    return main(args)


#: Exit status of an interrupted command (128 + SIGINT), as a shell reports Ctrl-C.
EXIT_INTERRUPTED = 130


def interrupted_line(prog: str) -> str:
    """The one line an interrupted command prints."""
    return f"{prog}: interrupted; nothing was written (earlier outputs are unchanged)."


def _console(prog: str, module: str, args: list[str] | None) -> int:
    """Imports ``module`` with Ctrl-C ending the process in one line (`interrupt_exits`),
    then runs its ``main(args)``; returns its exit code."""
    try:
        with interrupt_exits(interrupted_line(prog)):
            main = importlib.import_module(module).main
    except KeyboardInterrupt:
        print(interrupted_line(prog), file=sys.stderr)
        return EXIT_INTERRUPTED
    code = main(args)
    return code if isinstance(code, int) else 0


def export(args: list[str] | None = None) -> int:
    """``neuralmap-export`` (`neuralmap.terrain.export_cli.main`), Ctrl-C-safe while
    importing."""
    return _console("neuralmap-export", "neuralmap.terrain.export_cli", args)


def gins(args: list[str] | None = None) -> int:
    """``neuralmap-gins`` (`neuralmap.ins.gins_cli.main`), Ctrl-C-safe while importing."""
    return _console("neuralmap-gins", "neuralmap.ins.gins_cli", args)


def navigate(args: list[str] | None = None) -> int:
    """``neuralmap-navigate`` (`neuralmap.flights.cli.main`), Ctrl-C-safe while importing."""
    return _console("neuralmap-navigate", "neuralmap.flights.cli", args)


_PARSER_KEY = re.compile(r'Parser key "([\w.]+)"')
_GIVEN = re.compile(r"(?:Given value|Got value): (.*)$")


def parse_error_message(exc: BaseException, prog: str,
                        expected: Mapping[str, str] | None = None) -> str:
    """A jsonargparse parse error as one line: the option as typed (``--max_gap``, not
    ``Parser key "max_gap"``), the value given, what is valid (``expected[key]`` when
    the option has an entry) and where to read every option.

    Args:
        exc: The parser's ``ArgumentError``.
        prog: The command, for the ``--help`` hint.
        expected: Option key -> the valid values in words (``"a number of seconds > 0"``).
    """
    text = str(exc)
    key = _PARSER_KEY.search(text)
    given = _GIVEN.search(text.strip().splitlines()[-1]) if text.strip() else None
    if key is not None and expected and key.group(1) in expected:
        value = f"{given.group(1)!r}" if given else "the value given"
        return (f"--{key.group(1)}: {value} is not valid; expected "
                f"{expected[key.group(1)]}. Run {prog} --help for every option.")
    line = " ".join(text.split())
    line = _PARSER_KEY.sub(lambda m: f"--{m.group(1)}", line)
    return f"{line}. Run {prog} --help for every option and its type."
