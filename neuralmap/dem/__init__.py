"""DEM tiles: the grid container, file readers, sample tiles and synthetic terrain."""

from neuralmap.dem.readers import SAMPLE_NAMES, SUPPORTED_EXTENSIONS, load_tile
from neuralmap.dem.synthetic import synthetic_tile
from neuralmap.dem.tile import DemTile, GeoReference

__all__ = [
    "SAMPLE_NAMES",
    "SUPPORTED_EXTENSIONS",
    "DemTile",
    "GeoReference",
    "load_tile",
    "synthetic_tile",
]
