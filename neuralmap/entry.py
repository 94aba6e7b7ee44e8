"""Console-script entry points, light to import (only the standard library at the top).

``neuralmap-evaluate``: Ctrl-C while torch and the studies are still importing (the first
seconds) exits 130 with one line, like Ctrl-C during a study, instead of a traceback.
"""

from __future__ import annotations

import sys


def evaluate(args: list[str] | None = None) -> int:
    """Imports the evaluate CLI (:func:`neuralmap.studies.cli.main`) and runs it.

    Returns:
        Its exit code; 130 when interrupted while importing.
    """
    try:
        from neuralmap.studies.cli import main
    except KeyboardInterrupt:
        print("evaluate.py: interrupted; nothing was written.", file=sys.stderr)
        return 130
    return main(args)
