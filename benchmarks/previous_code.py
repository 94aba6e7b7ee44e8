"""Loads a module as it was at an earlier commit, so a benchmark can time the old code
against the new one in the same run."""

from __future__ import annotations

import importlib.util
import subprocess
import sys
import tempfile
from pathlib import Path
from types import ModuleType

REPO_ROOT = Path(__file__).resolve().parents[1]


def load_previous(commit: str, path: str, name: str) -> ModuleType | None:
    """The module at ``path`` (relative to the repository) as of ``commit``.

    Args:
        commit: A commit of this repository.
        path: The module's file, e.g. ``"neuralmap/ins/log_run.py"``.
        name: The name to import it under (registered in ``sys.modules``).

    Returns:
        The imported module, or None when git or the commit is not available (a copy of
        the sources without history).
    """
    try:
        source = subprocess.run(["git", "-C", str(REPO_ROOT), "show", f"{commit}:{path}"],
                                check=True, capture_output=True, text=True).stdout
    except (OSError, subprocess.CalledProcessError):
        return None
    file = Path(tempfile.mkdtemp()) / f"{name}.py"
    file.write_text(source)
    spec = importlib.util.spec_from_file_location(name, file)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module
