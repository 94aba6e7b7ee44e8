"""Console-script entry points, light to import (only the standard library at the top).

``neuralmap-evaluate`` and ``python evaluate.py``: Ctrl-C while torch and the studies are
still importing (the first seconds) exits 130 with one line, like Ctrl-C during a study,
instead of a traceback. A ``KeyboardInterrupt`` raised inside an import is not enough: an
extension module interrupted half-way (numpy) leaves a half-initialised module behind, and
the next import fails with an unrelated ``AttributeError``. So during the imports SIGINT
ends the process at once; nothing has been written yet.
"""

from __future__ import annotations

import os
import signal
import sys
from collections.abc import Callable, Iterator
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
