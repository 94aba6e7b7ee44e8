"""Temporary minimal readers (full version being written)."""

from __future__ import annotations

from pathlib import Path

from neuralmap.dem.synthetic import synthetic_tile
from neuralmap.dem.tile import DemTile
from neuralmap.exceptions import NeuralMapError

SAMPLE_NAMES = ("jacksboro", "synthetic")
SUPPORTED_EXTENSIONS = (".npz", ".npy", ".hgt", ".asc", ".tif", ".tiff")


def load_tile(
    name_or_path: str | Path,
    *,
    spacing: float | tuple[float, float] | None = None,
    origin: tuple[float, float] | None = None,
    name: str | None = None,
) -> DemTile:
    """Loads a sample tile or a DEM file (placeholder: synthetic only)."""
    if str(name_or_path) == "synthetic":
        return synthetic_tile()
    raise NeuralMapError(f"not yet: {name_or_path}")
