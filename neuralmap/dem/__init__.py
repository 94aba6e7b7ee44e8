"""DEM tiles: the grid container, file readers, sample tiles and synthetic terrain."""

from neuralmap.dem.load import load_tile
from neuralmap.dem.mosaic import load_mosaic, write_mosaic
from neuralmap.dem.readers import PLAUSIBLE_HEIGHT_M, SAMPLE_NAMES, SUPPORTED_EXTENSIONS
from neuralmap.dem.synthetic import synthetic_tile
from neuralmap.dem.tile import DemTile, GeoReference, ProjectedReference

__all__ = [
    "PLAUSIBLE_HEIGHT_M",
    "SAMPLE_NAMES",
    "SUPPORTED_EXTENSIONS",
    "DemTile",
    "GeoReference",
    "ProjectedReference",
    "load_mosaic",
    "load_tile",
    "write_mosaic",
    "synthetic_tile",
]
