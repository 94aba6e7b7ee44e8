"""Files shipped with the package: configs and scenarios (``importlib.resources``).

The YAML configs live in the repository's ``configs/`` folder and install as package data
(``neuralmap/configs``), so a non-editable ``pip install .`` can still run
``load_scenario("jacksboro")`` or ``neuralmap-evaluate`` from any folder.
"""

from __future__ import annotations

from importlib import resources
from pathlib import Path

__all__ = ["config_dir", "config_file"]


def config_dir() -> Path:
    """The shipped ``configs`` folder (inside the installed package)."""
    return Path(str(resources.files("neuralmap") / "configs"))


def config_file(name: str) -> Path:
    """A shipped config by file name, e.g. ``"tan.yaml"`` or ``"scenarios/jacksboro.yaml"``."""
    return config_dir() / name
