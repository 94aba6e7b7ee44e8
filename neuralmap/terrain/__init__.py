"""Terrain models behind one interface ``forward(xy) -> height``: grids and neural maps."""

from neuralmap.terrain.base import TerrainModel
from neuralmap.terrain.blockwise import BlockwiseTerrainNet
from neuralmap.terrain.export import load_map, save_map
from neuralmap.terrain.grid import GridTerrain

__all__ = ["BlockwiseTerrainNet", "GridTerrain", "TerrainModel", "load_map", "save_map"]
